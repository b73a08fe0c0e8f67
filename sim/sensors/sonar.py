"""Ultrasonic range sensors (a ring of 9 on the Koala 2.5): first echo within a cone of rays.

Truth (pure, :func:`sonar_truth`): each sensor casts ``rays`` rays over ``aperture_deg`` (defaults
of seeds/004: 5 rays, 22.9 deg, the Webots Khepera III ultrasonic sensor); its range is the
nearest hit of any ray (the first echo), with that ray's incidence angle. ``truth_ranges`` is nan
when nothing lies within ``max_range_m``.

Ideal reading, as the Koala 2.5 reports (User Manual rev 1.1 section 4.1): nearer than
``min_range_m`` -> 0.0 (the Koala returns 0); farther than ``max_range_m`` -> nan (no echo; the
Koala returns 1000); otherwise the true range.

Seam: ``SonarSensor.measure(hits, rng)``; with ``ideal = false`` an error model (issue 3: distance
error table +-6.6 %, specular reflection beyond a critical incidence angle, crosstalk, glitches)
gets the :class:`SonarTruth` with every ray's range, incidence and wall index.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numba
import numpy as np

from sim.config import SonarConfig
from sim.raycast import RayHits, SegmentSet
from sim.sensors.base import ErrorModel
from sim.sensors.fan import RayFan
from sim.types import SonarReading


@dataclass(frozen=True)
class SonarTruth:
    ranges: np.ndarray          # (n,) m, first echo; nan beyond max range
    incidence: np.ndarray       # (n,) rad, of the ray giving the first echo (nan: none)
    ray_ranges: np.ndarray      # (n, k) m (inf: nothing within max range)
    ray_incidence: np.ndarray   # (n, k) rad
    ray_wall: np.ndarray        # (n, k) int, index into ``walls`` (-1: none)
    min_range_m: float
    max_range_m: float
    # Set only for an error model (issue 3: late echoes via a second surface, crosstalk):
    world_rays: tuple[np.ndarray, ...] | None = None    # (ox, oy, dx, dy), each (n, k), world
    walls: SegmentSet | None = None


@numba.njit(cache=True, nogil=True)
def _first_echo(
    ray_ranges: np.ndarray, ray_incidence: np.ndarray, n: int, k: int
) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - compiled; tested through sonar_truth
    # Per sensor: the nearest of its k rays (first index on ties); nan when none hit.
    ranges = np.empty(n)
    incidence = np.empty(n)
    for i in range(n):
        best = np.inf
        inc = np.nan
        for j in range(k):
            r = ray_ranges[i * k + j]
            if r < best:
                best = r
                inc = ray_incidence[i * k + j]
        ranges[i] = best if best < np.inf else np.nan
        incidence[i] = inc
    return ranges, incidence


def sonar_truth(hits: RayHits, fan: RayFan, params: SonarConfig) -> SonarTruth:
    n, k = fan.n, fan.k
    ranges, incidence = _first_echo(hits.range, hits.incidence, n, k)
    return SonarTruth(
        ranges=ranges,
        incidence=incidence,
        ray_ranges=hits.range.reshape(n, k),
        ray_incidence=hits.incidence.reshape(n, k),
        ray_wall=hits.index.reshape(n, k),
        min_range_m=params.min_range_m,
        max_range_m=params.max_range_m,
    )


def ideal_reading(truth: SonarTruth) -> SonarReading:
    r = truth.ranges
    ranges = np.where(r < truth.min_range_m, 0.0, r)    # nan < x is False: no echo stays nan
    return SonarReading(ranges=ranges, truth_ranges=truth.ranges, incidence=truth.incidence)


class SonarSensor:
    """The sonar ring; see the module docstring."""

    name = "sonar"

    def __init__(
        self,
        params: SonarConfig,
        error_model: ErrorModel[SonarTruth, SonarReading] | None = None,
        walls: SegmentSet | None = None,
    ) -> None:
        self.params = params
        self.error_model = None if params.ideal else error_model
        self.fan = RayFan.build(params.poses, params.rays, math.radians(params.aperture_deg))
        self.walls = walls

    @property
    def max_range_m(self) -> float:
        return self.params.max_range_m

    def measure(
        self,
        hits: RayHits,
        rng: np.random.Generator,
        world_rays: np.ndarray | None = None,
        pose: tuple[float, float, float] | None = None,
    ) -> SonarReading:
        """Reading from this step's hits of :attr:`fan` (cast by the caller: see simulator).

        An error model also gets the rays' world geometry: ``world_rays`` ``(4, n*k)`` (origin x,
        y, direction x, y, as :func:`sim.raycast.cast_fan` returns them) or, when not given,
        rays recomputed from the robot ``pose`` (x, y, theta); and the walls.
        """
        truth = sonar_truth(hits, self.fan, self.params)
        if self.error_model is None:
            return ideal_reading(truth)
        shape = (self.fan.n, self.fan.k)
        rays: tuple[np.ndarray, ...] | None = None
        if world_rays is not None:
            rays = tuple(a.reshape(shape) for a in world_rays)
        elif pose is not None:
            rays = tuple(a.reshape(shape) for a in self.fan.world_rays(*pose))
        if rays is not None:
            truth = dataclasses.replace(truth, world_rays=rays, walls=self.walls)
        return self.error_model.measure(truth, rng)
