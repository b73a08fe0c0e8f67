"""Infrared proximity sensors (16 on the Koala): K-Team counts 0..1023, larger = closer.

Truth (pure, :func:`ir_counts`): each sensor casts ``rays`` rays over its aperture
(``[sensors.ir]``); each ray's range maps to counts through the response table
``response_range_m -> response_counts`` (linear interpolation, 0 beyond the last range, as Webots'
distance-sensor lookup table does); the sensor's counts are the mean over its rays. The axis
ray's range is the sensor's ``truth_ranges`` value (inf: nothing within the table's last range).
Ambient light is the constant ``ambient_counts`` (no light sources are simulated yet).

Seam: ``IrSensor.measure(rays, index, start, variates)`` takes the simulator's cast of this
step (:func:`core.raycast.cast_fan_arrays`); with ``ideal = false`` the error model (seeds/004:
reflectivity, distance error table +-3 %, ambient light; ``sim/models/ir.py``) gets the
:class:`IrTruth` -- per-ray ranges -- and returns an :class:`koala_bridge.sim.types.IrReading`.

Error model: ``sim/models/ir.py`` (its params, pure functions and
:class:`~koala_bridge.sim.models.ir.IrErrorModel`); config section ``[sensors.ir]``,
typed here by :class:`IrConfig` (its keys; the error model's keys beside them go to its params).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numba
import numpy as np
from koala_bridge.core.schema import (
    Bool,
    ConfigError,
    NonNegative,
    NonNegativeInt,
    Positive,
    PositiveInt,
    section,
)
from koala_bridge.sim.noise import Variates
from koala_bridge.sim.sections import Curve, Poses, Rays, empty_errors, sensor_section
from koala_bridge.sim.sensors.base import ErrorModel
from koala_bridge.sim.sensors.fan import RayFan
from koala_bridge.sim.types import IrReading


@section(eq=False)
class IrConfig:
    """``[sensors.ir]``: proximity sensors, K-Team counts from a response table range -> counts."""

    rate_hz: Positive
    ideal: Bool
    poses: Poses                        # (n, 3) body frame [x, y, theta_rad]
    rays: Rays                          # rays per sensor, spread over the aperture
    aperture_deg: NonNegative
    response_range_m: Curve             # (k,) increasing
    response_counts: Curve              # (k,) counts at those ranges (linear interpolation)
    ambient_counts: NonNegativeInt      # ambient light reading (K-Team 'O')
    max_counts: PositiveInt             # full scale of the counts (K-Team: 10 bits, 1023)
    errors: Any = field(default_factory=empty_errors)

    def __post_init__(self) -> None:
        sec = "sensors.ir"
        rng_m, counts, full = self.response_range_m, self.response_counts, self.max_counts
        if rng_m.shape != counts.shape or rng_m.size < 2:
            raise ConfigError(
                f"[{sec}] 'response_range_m' and 'response_counts' must be lists of equal "
                "length >= 2"
            )
        if np.any(np.diff(rng_m) <= 0) or rng_m[0] < 0:
            raise ConfigError(f"[{sec}] 'response_range_m' must be >= 0 and strictly increasing")
        if np.any(counts < 0) or np.any(counts > full):
            raise ConfigError(f"[{sec}] 'response_counts' must lie in 0..max_counts ({full})")
        if self.ambient_counts > full:
            raise ConfigError(
                f"[{sec}] 'ambient_counts' must lie in 0..max_counts ({full}), "
                f"got {self.ambient_counts}")
        offsets = getattr(self.errors, "per_sensor_offset_counts", ())
        if len(offsets) not in (0, self.poses.shape[0]):
            raise ConfigError(
                f"[{sec}] 'per_sensor_offset_counts' must be [] or one value per sensor "
                f"({self.poses.shape[0]}), got {len(offsets)}"
            )

    @property
    def max_range_m(self) -> float:
        return float(self.response_range_m[-1])

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> IrConfig:
        return sensor_section(cls, d, "sensors.ir", "ir")


@dataclass(frozen=True, slots=True, eq=False)
class IrTruth:
    """What an IR error model starts from: views of the step's cast, nothing computed yet."""

    ray_ranges: np.ndarray      # (n, k) m, inf: nothing within the response table's range
    axis_ranges: np.ndarray     # (n,) m, along each sensor's axis (inf: nothing)
    ambient: np.ndarray         # (n,) int, the constant ambient reading
    params: IrConfig

    @property
    def counts(self) -> np.ndarray:
        """(n,) int, the ideal sensor's counts (mean of the rays' responses)."""
        n, k = self.ray_ranges.shape
        return ir_counts(np.ascontiguousarray(self.ray_ranges).reshape(-1),
                         self.params.response_range_m, self.params.response_counts, n, k)


def response_counts(ranges_m: np.ndarray, params: IrConfig) -> np.ndarray:
    """Counts of the response table at ``ranges_m`` (float; 0 beyond the table, inf -> 0)."""
    return np.interp(ranges_m, params.response_range_m, params.response_counts, right=0.0)


@numba.njit(cache=True, nogil=True)
def ir_counts(
    ray_ranges: np.ndarray, table_r: np.ndarray, table_c: np.ndarray, n: int, k: int
) -> np.ndarray:  # pragma: no cover - compiled; tested through the simulator
    """Per sensor, ``rint(mean over its k rays of response_counts(range))`` (int64, (n,));
    ``ray_ranges`` (n k,) sensor-major."""
    last = table_r[-1]
    counts = np.empty(n, dtype=np.int64)
    for i in range(n):
        acc = 0.0
        for j in range(k):
            r = ray_ranges[i * k + j]
            if r <= last:
                acc += np.interp(r, table_r, table_c)
        counts[i] = np.int64(np.rint(acc / k))
    return counts


class IrSensor:
    """The ring of IR proximity sensors; see the module docstring."""

    name = "ir"

    def __init__(
        self, params: IrConfig, error_model: ErrorModel[IrTruth, IrReading] | None = None
    ) -> None:
        self.params = params
        self.error_model = None if params.ideal else error_model
        self.fan = RayFan.build(params.poses, params.rays, math.radians(params.aperture_deg))
        self._ambient = np.full(self.fan.n, params.ambient_counts, dtype=np.int64)
        self._ambient.flags.writeable = False

    @property
    def max_range_m(self) -> float:
        return self.params.max_range_m

    def measure(
        self, rays: np.ndarray, index: np.ndarray, start: int, variates: Variates
    ) -> IrReading:
        """Reading from this step's cast (:func:`core.raycast.cast_fan_arrays` of a fan whose rays
        ``start..`` are :attr:`fan`'s): ``rays`` (6, R) rows ox, oy, dx, dy, range, incidence."""
        n, k = self.fan.n, self.fan.k
        rr = rays[4, start:start + n * k]
        axis = rr[k // 2::k]
        # The axis ray's incidence, from the same cast (so the same surface as ``axis``).
        incidence = np.where(np.isfinite(axis), rays[5, start + k // 2:start + n * k:k], np.nan)
        if self.error_model is None:
            p = self.params
            counts = ir_counts(rr, p.response_range_m, p.response_counts, n, k)
            return IrReading(counts, self._ambient, counts, axis, incidence)
        reading = self.error_model.measure(
            IrTruth(rr.reshape(n, k), axis, self._ambient, self.params), variates)
        return dataclasses.replace(reading, truth_incidence=incidence)
