"""Ultrasonic range sensors (a ring of 9 on the Koala 2.5): first echo within a cone of rays.

Truth (pure, :func:`first_echo`): each sensor casts ``rays`` rays over ``aperture_deg`` (defaults
from seeds/004's Webots Khepera III ultrasonic sensor: 22.9 deg, and its 3 horizontal rays of 5;
the 2 vertical ones never give the reading in 2-D, see ``sim/models/sonar.py``); its range is the
nearest hit of any ray (the first echo), with that ray's incidence angle. ``truth_ranges`` is nan
when nothing lies within ``max_range_m``.

Ideal reading, as the Koala 2.5 reports (User Manual rev 1.1 section 4.1): nearer than
``min_range_m`` -> 0.0 (the Koala returns 0); farther than ``max_range_m`` -> nan (no echo; the
Koala returns 1000); otherwise the true range.

Seam: ``SonarSensor.measure(rays, index, start, variates)`` takes the simulator's cast of this
step (:func:`core.raycast.cast_fan_arrays`); with ``ideal = false`` the error model (distance
error table +-6.6 %, specular reflection beyond a critical incidence angle, late echoes via a
second wall, crosstalk, glitches; ``sim/models/sonar.py``) gets the :class:`SonarTruth`: every
ray's world geometry, range, incidence and wall index, and the walls.

Error model: ``sim/models/sonar.py`` (its params, pure functions and
:class:`~koala_bridge.sim.models.sonar.SonarErrorModel`); config section ``[sensors.sonar]``,
typed here by :class:`SonarConfig` (its keys; the error model's keys beside them go to its params).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numba
import numpy as np
from koala_bridge.core.raycast import SegmentSet
from koala_bridge.core.schema import Bool, NonNegative, Positive, section
from koala_bridge.sim.noise import Variates
from koala_bridge.sim.sections import Poses, Rays, empty_errors, range_limits, sensor_section
from koala_bridge.sim.sensors.base import ErrorModel
from koala_bridge.sim.sensors.fan import RayFan
from koala_bridge.sim.types import SonarReading


@section(eq=False)
class SonarConfig:
    """``[sensors.sonar]``: ultrasonic ring, each sensor a cone of rays; first echo wins."""

    rate_hz: Positive
    ideal: Bool
    poses: Poses                        # (n, 3) body frame [x, y, theta_rad]
    rays: Rays
    aperture_deg: NonNegative
    min_range_m: NonNegative            # closer: the Koala reports 0
    max_range_m: Positive               # farther: no echo
    errors: Any = field(default_factory=empty_errors)

    def __post_init__(self) -> None:
        range_limits(self.min_range_m, self.max_range_m, "sensors.sonar")

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> SonarConfig:
        return sensor_section(cls, d, "sensors.sonar", "sonar")


@dataclass(frozen=True, eq=False)
class SonarTruth:
    """What a sonar error model starts from: the step's cast (views), nothing computed yet.

    ``rays`` (6, R) rows origin x, y, unit direction x, y (world frame), range (inf: nothing
    within max range), incidence (rad, nan: none); ``index`` (R,) wall hit (-1: none), an index
    into ``walls``. The ring's ``n * k`` rays start at ``start``, sensor-major.
    """

    rays: np.ndarray
    index: np.ndarray
    start: int
    n: int
    k: int
    min_range_m: float
    max_range_m: float
    walls: SegmentSet | None = None

    def _rows(self, row: int) -> np.ndarray:
        return self.rays[row, self.start:self.start + self.n * self.k].reshape(self.n, self.k)

    @property
    def ray_ranges(self) -> np.ndarray:
        """(n, k) m (inf: nothing within max range)."""
        return self._rows(4)

    @property
    def world_rays(self) -> tuple[np.ndarray, ...]:
        """(ox, oy, dx, dy), each (n, k), world frame."""
        return tuple(self._rows(i) for i in range(4))

    @cached_property
    def _first(self) -> np.ndarray:
        out = np.empty((3, self.n))
        first_echo(self.rays, self.start, self.n, self.k, self.min_range_m, out)
        return out

    @property
    def ranges(self) -> np.ndarray:
        """(n,) m, the first echo; nan: nothing within max range."""
        return self._first[1]

    @property
    def incidence(self) -> np.ndarray:
        """(n,) rad, of the ray giving the first echo (nan: none)."""
        return self._first[2]


@numba.njit(cache=True, nogil=True)
def first_echo(
    rays: np.ndarray, start: int, n: int, k: int, min_range: float, out: np.ndarray
) -> None:  # pragma: no cover - compiled
    """Per sensor: the nearest of its k rays (first index on ties); ``rays`` as in
    :class:`SonarTruth`. Writes ``out`` (3, n): the ideal reading (0 nearer than ``min_range``,
    nan: no echo), the truth ranges (nan: none) and their incidence (nan: none)."""
    reading = out[0]
    ranges = out[1]
    incidence = out[2]
    for i in range(n):
        best = np.inf
        inc = np.nan
        for j in range(k):
            r = rays[4, start + i * k + j]
            if r < best:
                best = r
                inc = rays[5, start + i * k + j]
        ranges[i] = best if best < np.inf else np.nan
        incidence[i] = inc
        reading[i] = 0.0 if best < min_range else ranges[i]


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
        self, rays: np.ndarray, index: np.ndarray, start: int, variates: Variates
    ) -> SonarReading:
        """Reading from this step's cast (:func:`core.raycast.cast_fan_arrays` of a fan whose rays
        ``start..`` are :attr:`fan`'s)."""
        p = self.params
        if self.error_model is None:
            out = np.empty((3, self.fan.n))
            first_echo(rays, start, self.fan.n, self.fan.k, p.min_range_m, out)
            return SonarReading(ranges=out[0], truth_ranges=out[1], incidence=out[2])
        truth = SonarTruth(rays, index, start, self.fan.n, self.fan.k, p.min_range_m,
                           p.max_range_m, self.walls)
        return self.error_model.measure(truth, variates)
