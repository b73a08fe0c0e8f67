"""IR proximity sensors: response curve, beam of several rays, distance error, ambient light.

Sources
- seeds/004_38ad9834df6871a1.txt "Sensor Models": the Webots Khepera3_DistanceSensor uses
  ``aperture 0.03`` rad (1.72°) and ``numberOfRays 3``; "IR Sensors have a distance error of
  +-3.0 %" with the range table 0–5 cm +-0.0, 5 cm +-0.01 cm, 10 cm +-0.04 cm, 30 cm +-0.3 cm,
  60 cm +-1.25 cm, 100 cm +-3 cm. We read each "+-" as one standard deviation of a Gaussian
  (the third column of a Webots ``lookupTable`` is a standard deviation), linearly interpolated
  between rows and held beyond the last (``koala_bridge.sim.noise.LookupTable``).
- Webots reference, DistanceSensor "infra-red": several rays within the aperture, each ray's
  weight ``exp(-(t_i / (aperture * gaussian_width))^2)`` normalised over the rays (``t_i`` the
  ray's angle from the axis); the response scaled by the reflectivity of the surface hit.

Model, per sensor with rays ``i``::

    d_i' = d_i + sigma(d_i) * z        (one z per sensor and reading: the table is per reading)
    c    = sum_i w_i * rho_i * R(d_i')  (R: [sensors.ir] response table; rho: reflectivity)
    c_m  = round(clip(c * (1 - ambient_saturation * A / max_counts) + o_s + count_noise_sigma * n,
                      0, max_counts))
    A_m  = round(clip(ambient_counts + ambient_noise_counts * n', 0, max_counts))

We average the rays' *responses* (reflected light adds), where Webots averages distances; for a
flat wall across the beam both agree. ``A`` is the ambient light level; strong ambient light
narrows the emitter-on/emitter-off difference the Koala measures (``ambient_saturation``).
``o_s`` is sensor ``s``'s own offset (``per_sensor_offset_counts``, 0 when empty).
The noise-free companion is ``c`` with ``z = n = 0`` and no ambient effect.

The simulator's stateful model is :class:`IrErrorModel` (end of this module; the truth it perturbs
comes from ``sim/sensors/ir.py``, its factory :func:`error_model` is registered in
``sim.models.ERROR_MODELS``). Compiled kernel (``sim/models/_kernels.py``): ``ir_kernel`` (with
``interp``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import field
from types import MappingProxyType
from typing import Any, ClassVar

import numpy as np
from koala_bridge.core.schema import Bool, FloatTuple, NonNegative, Positive, PositiveInt, section
from koala_bridge.sim.models import _kernels
from koala_bridge.sim.models._params import Table, params_from_dict
from koala_bridge.sim.noise import LookupTable, Variates
from koala_bridge.sim.sensors.base import fan_offsets
from koala_bridge.sim.sensors.ir import IrTruth
from koala_bridge.sim.types import IrReading


def _seed004_ir_table() -> LookupTable:
    # seeds/004 "IR Sensors have a distance error of +-3.0%": [range m, sigma m].
    return LookupTable.from_rows(
        [[0.0, 0.0], [0.05, 0.0001], [0.10, 0.0004], [0.30, 0.003], [0.60, 0.0125], [1.00, 0.03]]
    )


@section
class IrErrorParams:
    """``[sensors.ir]`` error-model keys. Distances in m, counts 0..max_counts.

    Keyword defaults are the values of ``config/default.toml`` (sim/models/_params.py).
    """

    # Keys of the table that the sensor's section (sim/sensors/) owns and hands over.
    FROM_SENSOR: ClassVar[tuple[str, ...]] = ("ideal", "ambient_counts", "max_counts")
    # The values of this model's error terms that mean "no such error" (not config defaults):
    # what `koala-bridge calibrate --write-config` writes for the terms it did not measure when
    # it switches the model on (bridge/calibration/config_update.py).
    ABSENT: ClassVar[Mapping[str, Any]] = MappingProxyType({
        "count_noise_sigma": 0.0, "ambient_noise_counts": 0.0, "ambient_saturation": 0.0,
        "per_sensor_offset_counts": ()})

    ideal: Bool = False
    distance_error: Table = field(default_factory=_seed004_ir_table)
    gaussian_width: Positive = 1.0         # Webots DistanceSensor.gaussianWidth
    reflectivity: NonNegative = 1.0        # walls' IR reflectivity relative to the response's white
    count_noise_sigma: NonNegative = 2.0   # electrical noise, counts
    ambient_counts: NonNegative = 450.0    # ambient light level A, counts
    ambient_noise_counts: NonNegative = 3.0
    ambient_saturation: NonNegative = 0.05  # proximity loss at full-scale ambient light, fraction
    max_counts: PositiveInt = 1023
    # Per-sensor offset of the counts (a sensor's own emitter/receiver gain and ambient leak, as
    # `koala-bridge calibrate` measures it: effect offset_per:sensor); () = none, else one value
    # per sensor (IrConfig in sim/sensors/ir.py checks the length).
    per_sensor_offset_counts: FloatTuple = ()

    @classmethod
    def from_dict(cls, d: dict[str, Any], section: str = "sensors.ir") -> IrErrorParams:
        return params_from_dict(cls, d, section)


def ray_weights(ray_offsets_rad: np.ndarray, gaussian_width: float) -> np.ndarray:
    """Webots Gaussian ray weights, normalised to sum 1. The aperture is the rays' span."""
    t = np.asarray(ray_offsets_rad, dtype=float)
    aperture = float(t.max() - t.min()) if t.shape[0] > 1 else 0.0
    if aperture <= 0.0:
        return np.full(t.shape[0], 1.0 / t.shape[0])
    w = np.exp(-((t / (aperture * gaussian_width)) ** 2))
    return w / w.sum()


def counts_from_distances(ray_dists_m: np.ndarray, weights: np.ndarray,
                          reflectivity: np.ndarray | float, response: LookupTable) -> np.ndarray:
    """Noise-free response ``sum_i w_i rho_i R(d_i)`` (float counts), ``ray_dists_m`` (n, r);
    ``inf`` (no hit) gives the table's last value."""
    d = np.where(np.isfinite(ray_dists_m), ray_dists_m, response.x[-1])
    return (np.asarray(reflectivity) * response.value(d)) @ weights


def measure(ray_dists_m: np.ndarray, ray_offsets_rad: np.ndarray, response: LookupTable,
            params: IrErrorParams, rng: Variates,
            reflectivity: np.ndarray | float | None = None, weights: np.ndarray | None = None
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(counts, ambient, truth_counts)``, int64, for ``n`` sensors with ``r`` rays each.

    ``ray_dists_m`` (n, r): distance along each ray to the first surface (``inf``: none within
    range). ``ray_offsets_rad`` (r,): each ray's angle from the sensor axis. ``response``: the
    distance -> counts table of a white surface (``[sensors.ir] response_range_m`` /
    ``response_counts``). ``reflectivity`` overrides ``params.reflectivity`` per sensor/ray;
    ``weights`` (r,) the ray weights of :func:`ray_weights` (computed when not given).
    Draws ``3 n`` normals per call (none when ideal). Compiled: ``sim/models/_kernels.py``.
    """
    rho = params.reflectivity if reflectivity is None else reflectivity
    w = ray_weights(ray_offsets_rad, params.gaussian_width) if weights is None else weights
    d = np.ascontiguousarray(ray_dists_m, dtype=float)
    n = d.shape[0]
    rho2 = np.ascontiguousarray(np.broadcast_to(np.asarray(rho, dtype=float), d.shape))
    z = _NO_Z if params.ideal else np.asarray(rng.standard_normal(3 * n))
    return measure_with(d, np.ascontiguousarray(w, dtype=float), rho2, response, params, z)


def measure_with(d: np.ndarray, w: np.ndarray, rho: np.ndarray, response: LookupTable,
                 params: IrErrorParams, z: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`measure` with the variates given: ``z`` (3 n,) standard normals (distance, count,
    ambient noise of each sensor; ignored when ideal), ``d``/``rho`` (n, r) and ``w`` (r,)
    C-contiguous."""
    out = np.empty((3, d.shape[0]), dtype=np.int64)
    w_, rho_, rx, ry, ex, ey, fp, off = kernel_constants(w, rho, response, params)
    _kernels.ir_kernel(d, z, w_, rho_, rx, ry, ex, ey, fp, off, out)
    return out[0], out[1], out[2]


KernelConstants = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                        np.ndarray, np.ndarray]


def kernel_constants(w: np.ndarray, rho: np.ndarray, response: LookupTable,
                     params: IrErrorParams) -> KernelConstants:
    """The arguments of ``_kernels.ir_kernel`` between the variates and the outputs (fixed for a
    run: the simulator computes them once)."""
    amb = min(params.ambient_counts, params.max_counts)
    gain = 1.0 - params.ambient_saturation * amb / params.max_counts
    fp = np.array([float(params.ideal), gain, params.count_noise_sigma, params.ambient_counts,
                   params.ambient_noise_counts, float(params.max_counts)])
    off = np.asarray(params.per_sensor_offset_counts, dtype=float)
    return (w, rho, response.x, response.y, params.distance_error.x, params.distance_error.y, fp,
            off)


_NO_Z = np.zeros(0)


# ------------------------------------------------------------------ the simulator's model


class IrErrorModel:
    """The stateful ir error model the simulator calls (``sim/sensors/ir.py`` seam):
    the params, the per-run state, and ``measure(truth, variates)`` built on the functions
    above, drawing the same variates in the same order as :func:`measure`."""

    def __init__(self, params: IrErrorParams, response: LookupTable,
                 ray_offsets: np.ndarray, n_sensors: int) -> None:
        self.params = params
        self.response = response
        self.ray_offsets = ray_offsets
        self.weights = np.ascontiguousarray(ray_weights(ray_offsets, params.gaussian_width))
        self.rho = np.full((n_sensors, ray_offsets.shape[0]), params.reflectivity)
        self.n = n_sensors
        self.n_draws = 0 if params.ideal else 3 * n_sensors
        self.constants = kernel_constants(self.weights, self.rho, response, params)

    def measure(self, truth: IrTruth, rng: Variates) -> IrReading:
        # measure_with, with the kernel's constant arguments computed once.
        z = np.asarray(rng.standard_normal(self.n_draws)) if self.n_draws else _NO_Z
        out = np.empty((3, self.n), dtype=np.int64)
        w, rho, rx, ry, ex, ey, fp, off = self.constants
        _kernels.ir_kernel(truth.ray_ranges, z, w, rho, rx, ry, ex, ey, fp, off, out)
        return IrReading(counts=out[0], ambient=out[1], truth_counts=out[2],
                         truth_ranges=truth.axis_ranges)


def error_model(cfg: Any, rng: np.random.Generator) -> IrErrorModel:
    """The simulator's factory (``sim.models.ERROR_MODELS``), called at every reset with the
    ``[sensors.ir]`` config and the sensor's own generator."""
    # The response table is the IR core's ([sensors.ir] response_range_m -> response_counts).
    table = LookupTable(cfg.response_range_m, cfg.response_counts,
                        np.zeros(cfg.response_range_m.shape[0]))
    return IrErrorModel(cfg.errors, table, fan_offsets(cfg.rays, math.radians(cfg.aperture_deg)),
                        int(cfg.poses.shape[0]))
