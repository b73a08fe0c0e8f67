"""Trapezoidal point-to-point motion profile, as a position controller with a speed limit and an
acceleration limit runs it (the classic Koala's ``C`` move under its ``J`` profile).

Pure functions of (distance, max speed, acceleration, time); units are the caller's, consistent
(e.g. pulses, pulses/s, pulses/s^2). The profile starts and ends at rest: accelerate at ``a`` to
``v_max``, cruise, decelerate at ``a``. When the distance is too short to reach ``v_max``
(``|d| < v_max^2 / a``) it is a triangle with peak speed ``sqrt(|d| a)``. Closed form (any motion
control text, e.g. Biagiotti & Melchiorri, *Trajectory Planning for Automatic Machines and
Robots*, 2008, §3.2 "trapezoidal velocity profile").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["Trapezoid", "ramp_speed", "trapezoid"]


@dataclass(frozen=True, slots=True)
class Trapezoid:
    """A rest-to-rest move of signed ``distance``.

    Attributes:
        distance: signed displacement.
        v_peak: highest speed reached (>= 0), ``min(v_max, sqrt(|distance| a))``.
        accel: acceleration magnitude (> 0).
        t_accel: duration of the acceleration ramp (= of the deceleration ramp).
        t_cruise: duration at ``v_peak`` (0 for a triangle).
    """

    distance: float
    v_peak: float
    accel: float
    t_accel: float
    t_cruise: float

    @property
    def duration(self) -> float:
        """Total time of the move."""
        return 2.0 * self.t_accel + self.t_cruise

    def velocity(self, t: float) -> float:
        """Signed speed at time ``t`` after the start (0 before and after the move)."""
        sign = math.copysign(1.0, self.distance)
        if t <= 0.0 or t >= self.duration:
            return 0.0
        if t < self.t_accel:
            return sign * self.accel * t
        if t < self.t_accel + self.t_cruise:
            return sign * self.v_peak
        return sign * self.accel * (self.duration - t)

    def position(self, t: float) -> float:
        """Signed displacement from the start at time ``t`` (``distance`` once finished)."""
        sign = math.copysign(1.0, self.distance)
        if t <= 0.0:
            return 0.0
        if t >= self.duration:
            return self.distance
        ta, tc, a, v = self.t_accel, self.t_cruise, self.accel, self.v_peak
        if t < ta:
            return sign * 0.5 * a * t * t
        if t < ta + tc:
            return sign * (0.5 * v * ta + v * (t - ta))
        remaining = self.duration - t
        return self.distance - sign * 0.5 * a * remaining * remaining


def trapezoid(distance: float, v_max: float, accel: float) -> Trapezoid:
    """The rest-to-rest trapezoid covering ``distance`` with ``|v| <= v_max`` and ``|a| <= accel``.

    Raises:
        ValueError: ``v_max`` or ``accel`` not finite and > 0, or ``distance`` not finite.
    """
    if not (math.isfinite(v_max) and v_max > 0 and math.isfinite(accel) and accel > 0):
        raise ValueError("v_max and accel must be finite and > 0")
    if not math.isfinite(distance):
        raise ValueError("distance must be finite")
    d = abs(distance)
    v_peak = min(v_max, math.sqrt(d * accel))
    t_accel = v_peak / accel
    # distance covered by the two ramps together is v_peak * t_accel; the rest is cruise
    t_cruise = (d - v_peak * t_accel) / v_peak if v_peak > 0 else 0.0
    return Trapezoid(float(distance), v_peak, accel, t_accel, max(0.0, t_cruise))


def ramp_speed(v_from: float, v_to: float, accel: float, t: float) -> float:
    """Speed ``t`` after a ramp from ``v_from`` towards ``v_to`` at ``|a| = accel`` started (the
    Koala 2.5's ``K``: a speed set-point reached under the ``J`` acceleration); ``v_to`` once
    reached. ``accel`` must be > 0."""
    if t <= 0.0:
        return v_from
    step = accel * t
    if abs(v_to - v_from) <= step:
        return v_to
    return v_from + math.copysign(step, v_to - v_from)
