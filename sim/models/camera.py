"""Camera landmark errors: perception, recognition, distance and bearing (seeds/000 eq. 5–14).

Source: seeds/000_b0d2d08e12d78625.txt, "Cameras". The extracted formulas are garbled; the
reading below is argued in docs/models.md §Camera. Symbols: ``a`` = viewing angle, the angle
between the landmark's facing direction and the direction from the landmark to the robot
(0 = seen head-on); ``d`` = distance robot–landmark.

Perception (miss) probability, eq. 5–8, the multiplicative reading (docs/models.md "Seed readings
decided on purpose" argues it against the additive one)::

    P_miss(a, d) = min(1, 4 a^2 / a_max^2 + p_perc * g(d))      for d_min <= d <= d_max     (5)+(8)
    g(d) = b^((d - d_max) / d_max)                                                          (6)
    P_miss = 1                                                  for d < d_min or d > d_max

``d_min``/``d_max`` are the camera's ``min_range_m``/``max_range_m`` (the same keys of
``[sensors.camera]`` bound the field of view). ``b`` = ``distance_base`` (2 in the seed:
"exponential at base 2"; Figure 4 compares bases). ``g`` is the seed's distance function: it
"grows with increasing distance and reaches its maximum (1) at the maximum sight distance" and
scales the base rate ``p_perc``. Eq. 7, extracted as ``2^((d^2 - d_max^2) / (2 d_max))``, is
the square-root-free approximation of an exponent in ``d - d_max`` (``d - d_max = (d^2 -
d_max^2) / (d + d_max)`` and ``d + d_max = 2 d_max`` at ``d = d_max``: the ``2 d_max`` of its
denominator), and is 1 at ``d_max``; so eq. 6's extracted ``d_min`` is read as ``d_max``. Eq. 7
itself is a speed trick with no effect on the distribution; it is not used. ``P_miss = p_perc``
at 0° and ``d_max``, ``p_perc / b`` next to the camera; the angle term reaches 1 at
``a = a_max / 2`` (``a_max`` is the full opening of the landmark's viewing cone); below ``d_min``
the landmark is not perceived ("approximate the error, when the landmark is too close, by
applying a minimum sight distance"). A huge ``a_max`` (10000°) makes the angle term vanish: an
omnidirectional landmark.

Recognition, eq. 9: "depends on the perception angle and the distance. So we get the same
distribution": ``P_wrong(a, d) = min(1, 4 a^2/a_max^2 + p_recog * g(d))`` for a perceived
landmark; a wrong id is drawn uniformly from the *other* ``n - 1`` landmark ids (eq. 9's ``1/n``
would include the true id; we draw from the others so that ``p_recog`` is the rate of ids that
are actually wrong, the quantity one measures). With a single landmark no wrong id exists.

Distance, eq. 10–12::

    d_est = d + eps_near * N(0, 1) + eps_far * |N(0, 1)|       (10)
    eps_far  = dist * d_mid * 2^((d - d_mid) / far_doubling_m)  (11), far_doubling_m = 2 (text)
    eps_near = dist * d                                         (12)

so at ``d = d_mid`` each term is ``+-dist`` (relative) as the seed says; the far term is one-sided
(half-normal), which is what makes "the estimated mean distance ... highly erroneous" at far range
while it stays close to the truth for near landmarks (a zero-mean term could not bias the mean).
Stereo ranging over-estimates far distances (the disparity shrinks towards the noise), hence
positive.

Bearing, eq. 13–14: the two cameras are approximated by one virtual camera between them (eq. 13
is that geometry, which the ray geometry here gives directly); eq. 14 "(alpha_C +- random()) *
alpha_ang" is read as ``bearing_est = bearing + bearing_sigma * N(0, 1)`` ("This again is a
Gaussian error").

The simulator's stateful model is :class:`CameraErrorModel` (end of this module; the truth it
perturbs comes from ``sim/sensors/camera.py``, its factory :func:`error_model` is registered in
``sim.models.ERROR_MODELS``). Compiled kernel (``sim/models/_kernels.py``): ``camera_kernel`` (with
``_distance_factor``); the truth's visibility test is ``sim/sensors/camera.py``
``visible_landmarks``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any, ClassVar

import numpy as np
from koala_bridge.core.geometry import wrap_angle
from koala_bridge.core.schema import (
    Bool,
    ConfigError,
    NonNegative,
    Positive,
    Probability,
    section,
)
from koala_bridge.sim.models import _kernels
from koala_bridge.sim.models._params import (
    params_from_dict,
)
from koala_bridge.sim.noise import Variates
from koala_bridge.sim.sensors.camera import CameraTruth
from koala_bridge.sim.types import CameraReading, LandmarkObservation


@section
class CameraErrorParams:
    """``[sensors.camera]`` error-model keys. Distances in m, angles in degrees.

    Keyword defaults are the values of ``config/default.toml`` (sim/models/_params.py).
    """

    # Keys of the table that the sensor's section (sim/sensors/) owns and hands over.
    FROM_SENSOR: ClassVar[tuple[str, ...]] = ("ideal", "min_range_m", "max_range_m")
    # The values of this model's error terms that mean "no such error" (not config defaults):
    # what `koala-bridge calibrate --write-config` writes for the terms it did not measure when
    # it switches the model on (bridge/calibration/config_update.py).
    ABSENT: ClassVar[Mapping[str, Any]] = MappingProxyType({})

    ideal: Bool = False
    p_perc: Probability = 0.01        # eq. 5/8: miss probability at 0° and d_max (Figure 2)
    p_recog: Probability = 0.01       # eq. 9: wrong-id probability at 0° and d_max
    # eq. 6 d_min / d_max (shared with the camera's field of view in [sensors.camera]):
    min_range_m: NonNegative = 0.1    # minimum sight distance; nearer is not perceived
    max_range_m: Positive = 4.0       # maximum sight distance; g(d_max) = 1, beyond: not seen
    distance_base: Positive = 2.0     # eq. 6: "exponential at base 2"
    dist: NonNegative = 0.05          # eq. 10–12: relative distance error (+-dist at d_mid)
    d_mid_m: Positive = 1.0           # eq. 11: medium sight distance
    far_doubling_m: Positive = 2.0    # eq. 11: the far error doubles every 2 m (the text's "/2")
    bearing_sigma_deg: NonNegative = 2.0  # eq. 14: alpha_ang

    def __post_init__(self) -> None:
        if not self.max_range_m > self.min_range_m:
            raise ConfigError("'max_range_m' must be > 'min_range_m'")

    @classmethod
    def from_dict(cls, d: dict[str, Any], section: str = "sensors.camera") -> CameraErrorParams:
        return params_from_dict(cls, d, section)


def angle_term(a_rad: np.ndarray | float, a_max_rad: np.ndarray | float) -> np.ndarray:
    """``4 a^2 / a_max^2`` (seeds/000 eq. 5 without p_perc)."""
    a = np.asarray(a_rad, dtype=float)
    return 4.0 * a * a / np.asarray(a_max_rad, dtype=float) ** 2


def distance_factor(d_m: np.ndarray | float, params: CameraErrorParams) -> np.ndarray:
    """``g(d) = b^((d - d_max)/d_max)`` of seeds/000 eq. 6 (its approximation: eq. 7): the factor
    on the base rates ``p_perc``/``p_recog``; 1 at ``d_max``, ``1/b`` at the camera."""
    d = np.asarray(d_m, dtype=float)
    return np.power(params.distance_base, (d - params.max_range_m) / params.max_range_m)


def _in_sight(d_m: np.ndarray | float, params: CameraErrorParams) -> np.ndarray:
    d = np.asarray(d_m, dtype=float)
    return (d >= params.min_range_m) & (d <= params.max_range_m)


def miss_probability(a_rad: np.ndarray | float, d_m: np.ndarray | float,
                     a_max_rad: np.ndarray | float, params: CameraErrorParams) -> np.ndarray:
    """Perception error probability ``P_miss(a, d)`` (seeds/000 eq. 5–8, multiplicative reading);
    1 outside ``[d_min, d_max]``."""
    p = angle_term(a_rad, a_max_rad) + params.p_perc * distance_factor(d_m, params)
    return np.where(_in_sight(d_m, params), np.minimum(1.0, p), 1.0)


def wrong_id_probability(a_rad: np.ndarray | float, d_m: np.ndarray | float,
                         a_max_rad: np.ndarray | float, params: CameraErrorParams) -> np.ndarray:
    """Recognition error probability for a perceived landmark (seeds/000 eq. 9 text: "the same
    distribution" as perception, with base rate ``p_recog``)."""
    p = angle_term(a_rad, a_max_rad) + params.p_recog * distance_factor(d_m, params)
    return np.minimum(1.0, p)


def far_sigma(d_m: np.ndarray | float, params: CameraErrorParams) -> np.ndarray:
    """``eps_far`` of seeds/000 eq. 11 (m)."""
    d = np.asarray(d_m, dtype=float)
    doublings = (d - params.d_mid_m) / params.far_doubling_m
    return params.dist * params.d_mid_m * np.power(2.0, doublings)


def near_sigma(d_m: np.ndarray | float, params: CameraErrorParams) -> np.ndarray:
    """``eps_near`` of seeds/000 eq. 12 (m)."""
    return params.dist * np.asarray(d_m, dtype=float)


def distance_error_mean(d_m: np.ndarray | float, params: CameraErrorParams) -> np.ndarray:
    """E[d_est - d] = eps_far * sqrt(2/pi) (mean of the half-normal far term)."""
    return far_sigma(d_m, params) * math.sqrt(2.0 / math.pi)


def distance_error_std(d_m: np.ndarray | float, params: CameraErrorParams) -> np.ndarray:
    """Std of d_est - d: sqrt(eps_near^2 + eps_far^2 (1 - 2/pi))."""
    return np.sqrt(near_sigma(d_m, params) ** 2 + far_sigma(d_m, params) ** 2 * (1 - 2 / math.pi))


@dataclass(frozen=True)
class CameraMeasurement:
    """What the camera reports for the landmarks in its field of view (arrays of equal length)."""

    ids: np.ndarray        # (k,) int, reported ids (possibly wrong)
    ranges: np.ndarray     # (k,) m
    bearings: np.ndarray   # (k,) rad, CCW from the robot's heading
    source: np.ndarray     # (k,) int, index into the input arrays of the landmark seen


def measure(
    ids: np.ndarray,
    ranges_m: np.ndarray,
    bearings_rad: np.ndarray,
    view_angles_rad: np.ndarray,
    a_max_rad: np.ndarray,
    all_ids: np.ndarray,
    params: CameraErrorParams,
    rng: Variates,
) -> CameraMeasurement:
    """Apply perception, recognition, distance and bearing errors to the landmarks in view.

    Inputs are the noise-free values of the ``m`` landmarks in the field of view (shape ``(m,)``):
    true ids, ranges, bearings, viewing angles ``a`` (see module doc) and each landmark's
    ``a_max``; ``all_ids`` are the ids of every landmark in the world (eq. 9's ``n``).
    Draws a fixed number of variates per landmark in view (6 per landmark), so the stream's use
    does not depend on the outcomes. ``ideal`` reports every landmark in view unchanged.
    Compiled: ``sim/models/_kernels.py`` (same equations as the helpers above).
    """
    ids = np.asarray(ids, dtype=int)
    m = ids.shape[0]
    if params.ideal or m == 0:
        return CameraMeasurement(ids.copy(), np.asarray(ranges_m, float).copy(),
                                 np.asarray(bearings_rad, float).copy(), np.arange(m))
    rows = np.column_stack([ids.astype(float), np.asarray(ranges_m, dtype=float),
                            np.asarray(bearings_rad, dtype=float),
                            np.asarray(view_angles_rad, dtype=float),
                            np.broadcast_to(np.asarray(a_max_rad, dtype=float), (m,))])
    u = np.asarray(rng.random(3 * m))           # per landmark: miss, wrong id, which wrong id
    z = np.asarray(rng.standard_normal(3 * m))  # per landmark: near, far, bearing
    out = np.empty((m, 4))
    c = _kernels.camera_kernel(rows, np.asarray(all_ids, dtype=np.int64),
                               kernel_constants(params), u, z, out)
    return CameraMeasurement(out[:c, 0].astype(np.int64), out[:c, 1], out[:c, 2],
                             out[:c, 3].astype(np.int64))


def kernel_constants(params: CameraErrorParams) -> np.ndarray:
    """``fp`` of ``_kernels.camera_kernel`` (fixed for a run)."""
    p = params
    return np.array([p.p_perc, p.p_recog, p.min_range_m, p.max_range_m, p.distance_base, p.dist,
                     p.d_mid_m, p.far_doubling_m, math.radians(p.bearing_sigma_deg)])


def viewing_angle(landmark_xy: np.ndarray, facing_rad: np.ndarray, robot_xy: np.ndarray
                  ) -> np.ndarray:
    """Angle (rad, in [0, pi]) between each landmark's facing direction and the direction from
    the landmark to the robot: the ``a`` of seeds/000 eq. 5. ``landmark_xy`` (m, 2)."""
    v = np.asarray(robot_xy, dtype=float)[None, :] - np.asarray(landmark_xy, dtype=float)
    ang = np.arctan2(v[:, 1], v[:, 0]) - np.asarray(facing_rad, dtype=float)
    return np.abs(wrap_angle(ang))


# ------------------------------------------------------------------ the simulator's model


class CameraErrorModel:
    """The stateful camera error model the simulator calls (``sim/sensors/camera.py`` seam):
    the params, the per-run state, and ``measure(truth, variates)`` built on the functions
    above, drawing the same variates in the same order as :func:`measure`."""

    def __init__(self, params: CameraErrorParams) -> None:
        self.params = params
        self.fp = kernel_constants(params)

    def measure(self, truth: CameraTruth, rng: Variates) -> CameraReading:
        # measure on the truth's rows, with its draws (3 uniforms and 3 normals per
        # landmark in view).
        m = truth.rows.shape[0]
        if self.params.ideal or m == 0:
            return CameraReading(observations=truth.observations, truth=truth.observations)
        u = np.asarray(rng.random(3 * m))
        z = np.asarray(rng.standard_normal(3 * m))
        out = np.empty((m, 4))
        c = _kernels.camera_kernel(truth.rows, truth.all_ids, self.fp, u, z, out)
        measured = tuple(LandmarkObservation(int(i), r, b) for i, r, b, _s in
                         out[:c].tolist())
        return CameraReading(observations=measured, truth=truth.observations)


def error_model(cfg: Any, rng: np.random.Generator) -> CameraErrorModel:
    """The simulator's factory (``sim.models.ERROR_MODELS``), called at every reset with the
    ``[sensors.camera]`` config and the sensor's own generator."""
    return CameraErrorModel(cfg.errors)
