"""Ultrasonic range sensors: beam of rays, distance error table, specular reflection, crosstalk,
glitches (seeds/004 "Sensor Models").

Sources
- seeds/004_38ad9834df6871a1.txt: Webots ``Khepera3_USSensor`` ``aperture 0.4`` rad (22.9°),
  ``numberOfRays 5``: "The three red beams are all horizontal at the height of the sensor. The two
  orange beams are centered horizontally but go up and down vertically." In a 2-D world of walls
  the vertical pair never gives the reading (each lies above/below the centre ray's azimuth: on a
  wall it is longer, ``d / cos(e)``, at a larger incidence, ``acos(cos(inc) cos(e))``, ``e`` its
  elevation, so it is a direct echo only when the centre ray is a shorter one; the floor meets it
  at a grazing incidence beyond the critical angle), so the simulator casts the 3 horizontal rays
  only (``[sensors.sonar] rays = 3``; docs/models.md "Seed readings decided on purpose").
  "Ultrasonic Sensors have a distance error of +-6.6 %" with the range table
  0–5 cm +-0.0, 5 cm +-0.03 cm, 10 cm +-0.1 cm, 30 cm +-0.7 cm, 60 cm +-2.5 cm, 100 cm +-6.6 cm
  (each "+-" read as one Gaussian standard deviation, interpolated linearly). Beyond the table's
  last row its *relative* error is held (:func:`distance_sigma`: 6.6 % of the range, 13.2 cm at
  2 m): the headline "+-6.6 %", and the unit of Webots' lookup tables (the noise column is a
  fraction of the response), of which the table's ``~d^2`` growth inside 1 m is the linear rise;
  holding the last row holds that fraction;
  "3. Reflection Errors": beyond a critical angle specular reflection makes the echo "never
  return to the sensor" ("maximum distance reading") or "return to the sensor too late"
  ("distance returned represents total round-trip delay"); "crosstalk: echoes emitted from one
  sensor are detected by others".
- Webots reference, DistanceSensor "sonar": the reading is the nearest collision of any ray,
  and a ray whose angle of incidence exceeds pi/8 (22.5°) is lost: our ``critical_angle_deg``.

Model, per sensor (rays ``k``; incidence = angle between ray and surface normal)::

    truth      = min_k d_k                       (nearest surface in the beam; nan if none)
    echo       = min { d_k : incidence_k <= critical }           (direct echoes)
    if no direct echo and some ray hit: with probability late_echo_probability, a late echo of
               length (d_k + second_leg_k) / 2 from the nearest hit ray whose specular reflection
               reaches a second surface (second_leg_k = |p1 p2| + |p2 sensor|), else no echo (nan)
    crosstalk: for each other sensor j fired in the same cycle, each of j's direct-echo hit
               points p inside this sensor's cone gives an echo (d_jk + |p - s_i|) / 2; it is
               heard (per pair and cycle) with probability crosstalk_probability; the first echo
               to arrive (the smallest) is the reading
    range      = echo + sigma(echo) * z          (seed-004 table, relative beyond; clipped at 0)
    glitch:    with probability glitch_probability the reading is U(min_range_m, max_range_m)
    beyond max range: nan (no echo)

The simulator's stateful model is :class:`SonarErrorModel` (end of this module; the truth it
perturbs comes from ``sim/sensors/sonar.py``, its factory :func:`error_model` is registered in
``sim.models.ERROR_MODELS``). Compiled kernels (``sim/models/_kernels.py``): ``sonar_kernel``
(:func:`measure`) and ``sonar_ring_kernel`` with ``_second_leg`` (:class:`SonarErrorModel`, on the
simulator's cast).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Annotated, Any, ClassVar

import numpy as np
from koala_bridge.core.schema import (
    Bool,
    ConfigError,
    NestedFloats,
    NonNegative,
    Probability,
    section,
)
from koala_bridge.sim.models import _kernels
from koala_bridge.sim.models._params import Table, params_from_dict
from koala_bridge.sim.noise import LookupTable, Variates
from koala_bridge.sim.sensors.sonar import SonarTruth
from koala_bridge.sim.types import SonarReading
from pydantic import Field


def _seed004_us_table() -> LookupTable:
    # seeds/004 "Ultrasonic Sensors have a distance error of +-6.6%": [range m, sigma m].
    return LookupTable.from_rows(
        [[0.0, 0.0], [0.05, 0.0003], [0.10, 0.001], [0.30, 0.007], [0.60, 0.025], [1.00, 0.066]]
    )


def distance_sigma(range_m: np.ndarray | float, table_x: np.ndarray, table_y: np.ndarray
                   ) -> np.ndarray:
    """sigma (m) of the distance error at ``range_m`` (seeds/004 ultrasonic table): the table
    ``(table_x, table_y)`` interpolated linearly within it; beyond its last row that row's
    relative error ``y_last / x_last`` is held, ``sigma = range * y_last / x_last`` (6.6 % with
    the seed's table). Compiled twin: ``_kernels.table_sigma``."""
    r = np.asarray(range_m, dtype=float)
    xl, yl = float(table_x[-1]), float(table_y[-1])
    rel = yl / xl if xl > 0 else 0.0
    return np.where(r > xl, r * rel, np.interp(r, table_x, table_y))


@section
class SonarErrorParams:
    """``[sensors.sonar]`` error-model keys.

    Keyword defaults are the values of ``config/default.toml`` (sim/models/_params.py).
    """

    # Keys of the table that the sensor's section (sim/sensors/) owns and hands over.
    FROM_SENSOR: ClassVar[tuple[str, ...]] = ("ideal", "min_range_m")
    # The values of this model's error terms that mean "no such error" (not config defaults):
    # what `koala-bridge calibrate --write-config` writes for the terms it did not measure when
    # it switches the model on (bridge/calibration/config_update.py).
    ABSENT: ClassVar[Mapping[str, Any]] = MappingProxyType({
        "late_echo_probability": 0.0, "crosstalk_probability": 0.0, "glitch_probability": 0.0,
        "firing_groups": ()})

    ideal: Bool = False
    distance_error: Table = field(default_factory=_seed004_us_table)
    critical_angle_deg: Annotated[NonNegative, Field(le=90)] = 22.5  # beyond pi/8: lost (Webots)
    late_echo_probability: Probability = 0.3   # lost echo returns via a second surface
    crosstalk_probability: Probability = 0.05  # per pair of sensors fired together, per cycle
    glitch_probability: Probability = 0.002    # per reading
    min_range_m: NonNegative = 0.25            # lower end of a glitch's uniform value
    # () = all sonars fired together; the default: one after the other (Koala 2.5 manual 4.1)
    firing_groups: NestedFloats = tuple((float(i),) for i in range(9))

    def __post_init__(self) -> None:
        for g in self.firing_groups:
            if any(int(i) != i or i < 0 for i in g):
                raise ConfigError("'firing_groups' must be lists of sensor indices")

    @classmethod
    def from_dict(cls, d: dict[str, Any], section: str = "sensors.sonar") -> SonarErrorParams:
        return params_from_dict(cls, d, section)


@functools.lru_cache(maxsize=16)
def same_cycle(n: int, firing_groups: tuple[tuple[float, ...], ...]) -> np.ndarray:
    """(n, n) bool, read-only: sensors i and j (i != j) are fired in the same cycle."""
    if not firing_groups:
        m = np.ones((n, n), dtype=bool)
    else:
        group = np.full(n, -1)
        for gi, g in enumerate(firing_groups):
            for i in g:
                if int(i) < n:
                    group[int(i)] = gi
        m = (group[:, None] == group[None, :]) & (group[:, None] >= 0)
    np.fill_diagonal(m, False)
    m.flags.writeable = False
    return m


@dataclass(frozen=True)
class SonarMeasurement:
    ranges: np.ndarray        # (n,) m, nan = no echo
    truth_ranges: np.ndarray  # (n,) m, nearest surface in the beam, nan = none within range
    incidence: np.ndarray     # (n,) rad, incidence of the ray giving truth_ranges, nan = none
    kind: np.ndarray          # (n,) int8: 0 none, 1 direct, 2 late, 3 crosstalk, 4 glitch


def measure(
    ray_dists_m: np.ndarray,
    incidence_rad: np.ndarray,
    max_range_m: float,
    params: SonarErrorParams,
    rng: Variates,
    *,
    second_leg_m: np.ndarray | None = None,
    sensor_xy: np.ndarray | None = None,
    sensor_heading: np.ndarray | None = None,
    hit_xy: np.ndarray | None = None,
    half_aperture_rad: float = math.radians(22.9) / 2,
) -> SonarMeasurement:
    """Sonar ring reading from per-ray geometry.

    ``ray_dists_m`` (n, r): distance to the first surface along each ray, ``inf`` if none within
    ``max_range_m``; ``incidence_rad`` (n, r) angle between the ray and that surface's normal.
    Optional geometry: ``second_leg_m`` (n, r) length of the specular continuation back to the
    sensor (``inf``: none) for late echoes; ``sensor_xy`` (n, 2), ``sensor_heading`` (n,) and
    ``hit_xy`` (n, r, 2), world frame, for crosstalk. Draws ``4 n`` variates per call, plus
    ``n^2`` when crosstalk is modelled.
    """
    d = np.ascontiguousarray(ray_dists_m, dtype=float)
    inc = np.ascontiguousarray(incidence_rad, dtype=float)
    n, _k = d.shape
    out_range = np.empty(n)
    out_truth = np.empty(n)
    out_inc = np.empty(n)
    kind = np.zeros(n, dtype=np.int8)
    use_leg = second_leg_m is not None and params.late_echo_probability > 0
    cycle = _NO_CYCLE
    use_cross = False
    if (hit_xy is not None and sensor_xy is not None and sensor_heading is not None
            and params.crosstalk_probability > 0 and n > 1):
        cycle = same_cycle(n, params.firing_groups)
        use_cross = bool(cycle.any())
    z: np.ndarray
    if params.ideal:
        u, z, u_cross = _NO_Z, _NO_Z, _NO_Z
    else:
        # Fixed draws (4 n); the crosstalk draws (n^2) come last and only when two sonars share
        # a cycle, so switching crosstalk on does not shift the other draws of the stream.
        u = np.asarray(rng.random(3 * n))       # late echo, glitch, glitch value
        z = np.asarray(rng.standard_normal(n))
        u_cross = np.asarray(rng.random(n * n)) if use_cross else _NO_Z
    table = params.distance_error
    _kernels.sonar_kernel(
        d, inc, float(max_range_m), table.x, table.y, math.radians(params.critical_angle_deg),
        params.late_echo_probability, params.crosstalk_probability, params.glitch_probability,
        params.min_range_m, params.ideal, use_leg,
        np.ascontiguousarray(second_leg_m, dtype=float) if use_leg else _NO_LEG,
        use_cross,
        np.ascontiguousarray(hit_xy, dtype=float) if use_cross else _NO_HIT,
        np.ascontiguousarray(sensor_xy, dtype=float) if use_cross else _NO_XY,
        np.ascontiguousarray(sensor_heading, dtype=float) if use_cross else _NO_Z,
        float(half_aperture_rad), cycle, u, z, u_cross, out_range, out_truth, out_inc, kind,
    )
    return SonarMeasurement(out_range, out_truth, out_inc, kind)


# Placeholders for the kernel's unused inputs (typed, empty, read-only).
_NO_LEG = np.empty((0, 0))
_NO_HIT = np.empty((0, 0, 2))
_NO_XY = np.empty((0, 2))
_NO_Z = np.empty(0)
_NO_CYCLE = np.empty((0, 0), dtype=bool)


def reflect(directions: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Specular reflection of unit ``directions`` (..., 2) off surfaces with unit ``normals``."""
    dot = (directions * normals).sum(axis=-1, keepdims=True)
    return directions - 2.0 * dot * normals


# ------------------------------------------------------------------ the simulator's model


class SonarErrorModel:
    """The sonar model on the simulator's cast: one compiled call (second legs, crosstalk
    geometry, echoes, noise) with the variates of :func:`sim.models.sonar.measure` pre-drawn."""

    def __init__(self, params: SonarErrorParams, half_aperture_rad: float,
                 n_sensors: int, min_range_m: float, max_range_m: float) -> None:
        self.params = p = params
        self.half_aperture_rad = half_aperture_rad
        self.n = n_sensors
        self.cycle = same_cycle(n_sensors, p.firing_groups)
        self.use_cross = bool(p.crosstalk_probability > 0 and n_sensors > 1 and self.cycle.any())
        self.table_x = p.distance_error.x
        self.table_y = p.distance_error.y
        self.fp = np.array([max_range_m, min_range_m, math.radians(p.critical_angle_deg),
                            p.late_echo_probability, p.crosstalk_probability,
                            p.glitch_probability, p.min_range_m, half_aperture_rad])
        # The draws of sim.models.sonar.measure: 3 n uniforms and n normals, and n^2 uniforms
        # more when two sonars share a firing cycle (uniforms and normals are separate streams,
        # so the 3 n + n^2 uniforms are one contiguous draw).
        self.n_uniforms = 0 if p.ideal else 3 * n_sensors + (n_sensors ** 2 if self.use_cross
                                                              else 0)
        self.n_normals = 0 if p.ideal else n_sensors
        # ideal, use_leg (late echoes need the walls), use_cross
        self.flags = np.array([p.ideal, p.late_echo_probability > 0, self.use_cross],
                              dtype=np.int64)
        self.flags_no_walls = np.array([p.ideal, False, self.use_cross], dtype=np.int64)

    def measure(self, truth: SonarTruth, rng: Variates) -> SonarReading:
        n = truth.n
        flags = self.flags if truth.walls is not None else self.flags_no_walls
        u = np.asarray(rng.random(self.n_uniforms)) if self.n_uniforms else _NONE
        z = np.asarray(rng.standard_normal(self.n_normals)) if self.n_normals else _NONE
        seg = truth.walls.packed if truth.walls is not None else _NO_SEG
        out = np.empty((3, n))
        _kernels.sonar_ring_kernel(seg, truth.rays, truth.index, truth.start, n, truth.k, self.fp,
                                   flags, self.table_x, self.table_y, self.cycle, u, z, out)
        return SonarReading(ranges=out[0], truth_ranges=out[1], incidence=out[2])


_NONE = np.zeros(0)
_NO_SEG = np.zeros((5, 0))


def error_model(cfg: Any, rng: np.random.Generator) -> SonarErrorModel:
    """The simulator's factory (``sim.models.ERROR_MODELS``), called at every reset with the
    ``[sensors.sonar]`` config and the sensor's own generator."""
    return SonarErrorModel(cfg.errors, 0.5 * math.radians(cfg.aperture_deg),
                           int(cfg.poses.shape[0]), cfg.min_range_m, cfg.max_range_m)
