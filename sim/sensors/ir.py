"""Infrared proximity sensors (16 on the Koala): K-Team counts 0..1023, larger = closer.

Truth (pure, :func:`ir_truth`): each sensor casts ``rays`` rays over its aperture
(``[sensors.ir]``); each ray's range maps to counts through the response table
``response_range_m -> response_counts`` (linear interpolation, 0 beyond the last range, as Webots'
distance-sensor lookup table does); the sensor's counts are the mean over its rays. The axis
ray's range is the sensor's ``truth_ranges`` value (inf: nothing within the table's last range).
Ambient light is the constant ``ambient_counts`` (no light sources are simulated yet).

Seam: ``IrSensor.measure(hits, rng)``; with ``ideal = false`` an error model (issue 3: reflectivity,
distance error table of seeds/004 +-3 %, ambient light) gets the :class:`IrTruth` -- per-ray
ranges, incidence angles and hit wall indices -- and returns an :class:`~sim.types.IrReading`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from sim.config import IrConfig
from sim.raycast import RayHits
from sim.sensors.base import ErrorModel
from sim.sensors.fan import RayFan
from sim.types import IrReading


@dataclass(frozen=True)
class IrTruth:
    counts: np.ndarray          # (n,) int, noise-free counts
    counts_float: np.ndarray    # (n,) float, before rounding
    axis_ranges: np.ndarray     # (n,) m, along each sensor's axis (inf: nothing)
    ray_ranges: np.ndarray      # (n, k) m
    ray_incidence: np.ndarray   # (n, k) rad (nan: no hit)
    ray_wall: np.ndarray        # (n, k) index into the simulator's SegmentSet (-1: none)
    ambient: np.ndarray         # (n,) int
    world_rays: np.ndarray | None = None    # (4, n, k) ox, oy, dx, dy (None: not provided)


def response_counts(ranges_m: np.ndarray, params: IrConfig) -> np.ndarray:
    """Counts of the response table at ``ranges_m`` (float; 0 beyond the table, inf -> 0)."""
    return np.interp(ranges_m, params.response_range_m, params.response_counts, right=0.0)


@numba.njit(cache=True, nogil=True)
def _mean_counts(
    ray_ranges: np.ndarray, table_r: np.ndarray, table_c: np.ndarray, n: int, k: int
) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - compiled; tested through ir_truth
    # Equal to response_counts(...).reshape(n, k).mean(axis=1) and its rounding, in one pass.
    per_ray = np.interp(ray_ranges, table_r, table_c)
    last = table_r[-1]
    counts_f = np.empty(n)
    counts = np.empty(n, dtype=np.int64)
    for i in range(n):
        acc = 0.0
        for j in range(k):
            r = ray_ranges[i * k + j]
            acc += per_ray[i * k + j] if r <= last else 0.0
        counts_f[i] = acc / k
        counts[i] = np.int64(np.rint(acc / k))
    return counts_f, counts


def ir_truth(
    hits: RayHits,
    fan: RayFan,
    params: IrConfig,
    world_rays: np.ndarray | None = None,
    ambient: np.ndarray | None = None,
) -> IrTruth:
    """Noise-free IR truth from the hits of ``fan``'s rays; ``ambient`` may pass a prebuilt
    read-only array of ``params.ambient_counts`` (it is the same at every step)."""
    n, k = fan.n, fan.k
    counts_f, counts = _mean_counts(hits.range, params.response_range_m,
                                    params.response_counts, n, k)
    ray_ranges = hits.range.reshape(n, k)
    return IrTruth(
        counts=counts,                          # table values lie in 0..1023 (config)
        counts_float=counts_f,
        axis_ranges=ray_ranges[:, k // 2],
        ray_ranges=ray_ranges,
        ray_incidence=hits.incidence.reshape(n, k),
        ray_wall=hits.index.reshape(n, k),
        ambient=(np.full(n, params.ambient_counts, dtype=np.int64) if ambient is None
                 else ambient),
        world_rays=None if world_rays is None else world_rays.reshape(4, n, k),
    )


def ideal_reading(truth: IrTruth) -> IrReading:
    return IrReading(
        counts=truth.counts,
        ambient=truth.ambient,
        truth_counts=truth.counts,
        truth_ranges=truth.axis_ranges,
    )


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
        self, hits: RayHits, rng: np.random.Generator, world_rays: np.ndarray | None = None
    ) -> IrReading:
        """Reading from this step's hits of :attr:`fan` (cast by the caller, see simulator)."""
        truth = ir_truth(hits, self.fan, self.params, world_rays, self._ambient)
        if self.error_model is None:
            return ideal_reading(truth)
        return self.error_model.measure(truth, rng)
