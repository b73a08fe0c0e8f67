"""Differential-drive kinematics of the Koala with wall collisions. Pure functions of
``(state, command, params, walls, rng)``.

Kinematics (world frame x east, y north; theta CCW from +x). Wheel surface speeds ``v_l, v_r``
(m/s) and wheel base ``b`` give ``v = (v_l + v_r) / 2`` and ``w = (v_r - v_l) / b``. Over one fixed
step ``dt`` the speeds are constant, so the robot moves exactly along a circular arc; in the body
frame of the pose at the start of the step the displacement is::

    dx_b = v dt sinc(w dt),  dy_b = v dt (1 - cos(w dt)) / (w dt),  dtheta = w dt

(the straight line ``dx_b = v dt, dy_b = 0`` in the limit ``w -> 0``). There is no integration
error, whatever ``dt``.

Collisions: the body is a circle of ``body_radius_m`` around the robot's centre. A move is split
into sub-steps no longer than half the radius (so no wall is tunnelled through, whatever the
speed and ``dt``); a sub-step that would bring the body closer to a wall it already penetrates
or touches (distance < radius) is cut back by bisection to the last non-penetrating fraction, the
robot stops there for the rest of the step and :attr:`RobotState.collided` is set. Moves that
increase the distance to every touched wall (backing away, turning in place) are always allowed.
With ideal drive the wheels stall against the wall: wheel travel (what the encoders count) is cut
by the same fraction as the body motion.

Wheel diameters (``[robot] wheel_diameter_ratio`` rho = D_left / D_right, the mean diameter
kept): a command is a wheel *rotation* rate (the Koala's PID servoes encoder pulses), expressed
as the surface speed of a nominal wheel; each wheel's surface moves by its own diameter,
``v_l (2 rho / (1 + rho))`` and ``v_r (2 / (1 + rho))`` (UMBmark's E_d, Borenstein & Feng 1996).
:attr:`RobotState.left_travel_m` is that surface travel; the encoders count rotation
(:mod:`sim.sensors.encoders` divides by the same factors), so they report the commanded rotation
while the pose follows the unequal wheels.

Seam for the drive-error model (issue 3, seeds/000 eq. 1-4, wheel slip): :func:`step` takes an
optional ``drive_error`` object (see :class:`DriveErrorSeam`). It receives the ideal body-frame
displacement of the step and returns the displacement that really happens (and may change the
wheel travel the encoders see); collision handling applies to the displacement it returns.

Parameters: ``[robot]`` (:class:`RobotConfig`) and its ``[robot.drive_error]`` table
(:class:`DriveConfig`; the model's own keys go to ``sim/models/drive.py``) are typed here; its
``[robot.battery]`` table in ``sim/battery.py``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Annotated, Any, Protocol

import numpy as np
from koala_bridge.core.geometry import wrap_angle
from koala_bridge.core.raycast import SegmentSet, point_segment_distances, sweep_circle
from koala_bridge.core.schema import (
    Bool,
    ConfigError,
    Positive,
    Str,
    reject_unknown,
    require,
    section,
    validate,
)
from koala_bridge.sim.battery import BatteryConfig
from koala_bridge.sim.noise import Variates
from koala_bridge.sim.sections import empty_errors, own_keys, sensor_section
from pydantic import AfterValidator


def _key_safe(name: str) -> str:
    if not name or any(c in name for c in "/*?$# "):
        raise ValueError(f"must be a non-empty key-safe word, got {name!r}")
    return name


@section
class DriveConfig:
    """``[robot.drive_error]``: the drive-error model's switch and parameters (seeds/000 1-4)."""

    ideal: Bool
    errors: Any = field(default_factory=empty_errors)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> DriveConfig:
        return sensor_section(cls, d, "robot.drive_error", "drive")


@section
class RobotConfig:
    """``[robot]``: geometry and drive limits of the Koala (sources in config/README.md)."""

    name: Annotated[Str, AfterValidator(_key_safe)]
    ticks_per_metre: Positive       # encoder pulses per metre of wheel travel
    wheel_diameter_m: Positive
    wheel_base_m: Positive          # distance between the left and right wheel contact lines
    wheel_diameter_ratio: Positive  # left / right wheel diameter (1: equal); see above
    body_radius_m: Positive         # collision body: a circle around the robot's centre
    max_wheel_speed_mps: Positive   # wheel surface speed limit, each wheel
    speed_unit_s: Positive          # K-Team speed unit = pulses per this many seconds (10 ms)
    drive: DriveConfig              # the file's [robot.drive_error] table
    battery: BatteryConfig          # the file's [robot.battery] table (sim/battery.py)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> RobotConfig:
        sec = "robot"
        if not isinstance(d, Mapping):
            raise ConfigError(f"[{sec}] must be a table, got {d!r}")
        keys = [k for k in own_keys(cls) if k != "drive"] + ["drive_error"]
        reject_unknown(d, keys, sec)
        own = {k: v for k, v in d.items() if k not in ("drive_error", "battery")}
        drive = DriveConfig.from_dict(require(d, "drive_error", sec))
        battery = BatteryConfig.from_dict(require(d, "battery", sec))
        return validate(cls, {**own, "drive": drive, "battery": battery}, sec)


@dataclass(frozen=True, slots=True)
class RobotState:
    """Truth state of the robot after a step."""

    x: float
    y: float
    theta: float                # wrapped to (-pi, pi]
    heading: float              # unwrapped heading (theta + 2 pi k): integrates yaw rate exactly
    left_travel_m: float        # cumulative wheel surface travel, m (encoders count this)
    right_travel_m: float
    left_speed: float           # mean wheel surface speed over the last step, m/s
    right_speed: float
    yaw_rate: float             # mean yaw rate over the last step, rad/s
    collided: bool = False
    # Lower bound of (distance from the centre to the nearest wall - body radius), m; -inf when
    # unknown. Distance to a set is 1-Lipschitz, so after a displacement of length L the bound
    # drops by at most L: while it exceeds the next step's length no wall test is needed.
    clearance: float = -math.inf

    @classmethod
    def at(cls, x: float, y: float, theta: float) -> RobotState:
        return cls(x, y, wrap_angle(theta), theta, 0.0, 0.0, 0.0, 0.0, 0.0, False)


@dataclass(frozen=True, slots=True)
class Motion:
    """What one step does: body-frame displacement (frame of the pose at the step's start) and the
    wheel surface travel the encoders count."""

    dx_b: float
    dy_b: float
    dtheta: float
    left_m: float
    right_m: float


class DriveErrorSeam(Protocol):
    """Seam for drive errors (seeds/000 eq. 1-4) and wheel slip; implemented in ``sim/models``."""

    def perturb(self, ideal: Motion, state: RobotState, rng: Variates) -> Motion:
        """Return the motion that really happens given the ideal one (pure but for ``rng``)."""
        ...


def limit_wheel_speeds(left: float, right: float, max_speed: float) -> tuple[float, float]:
    """Clip each wheel's surface speed to ``[-max_speed, max_speed]`` (non-finite -> 0)."""
    lf = left if math.isfinite(left) else 0.0
    rf = right if math.isfinite(right) else 0.0
    return (min(max(lf, -max_speed), max_speed), min(max(rf, -max_speed), max_speed))


def arc_motion(v_left: float, v_right: float, wheel_base: float, dt: float) -> Motion:
    """Exact body-frame displacement of one step at constant wheel speeds (module docstring)."""
    dx, dy, dth = arc_displacement(v_left, v_right, wheel_base, dt)
    return Motion(dx, dy, dth, v_left * dt, v_right * dt)


def arc_displacement(v_left: float, v_right: float, wheel_base: float, dt: float
                     ) -> tuple[float, float, float]:
    """``(dx_b, dy_b, dtheta)`` of :func:`arc_motion`."""
    s = 0.5 * (v_left + v_right) * dt
    dth = (v_right - v_left) / wheel_base * dt
    if abs(dth) < 1e-9:
        # Series of sin(x)/x and (1 - cos x)/x; exact to double precision here.
        return s * (1.0 - dth * dth / 6.0), s * 0.5 * dth, dth
    return s * math.sin(dth) / dth, s * (1.0 - math.cos(dth)) / dth, dth


def _pose_after(state: RobotState, m: Motion, frac: float) -> tuple[float, float, float]:
    c = math.cos(state.theta)
    s = math.sin(state.theta)
    dx = frac * m.dx_b
    dy = frac * m.dy_b
    return (state.x + c * dx - s * dy, state.y + s * dx + c * dy, state.heading + frac * m.dtheta)


def step(
    state: RobotState,
    left_speed: float,
    right_speed: float,
    dt: float,
    params: RobotConfig,
    walls: SegmentSet,
    rng: Variates | None = None,
    drive_error: DriveErrorSeam | None = None,
) -> RobotState:
    """Advance the robot by one fixed step ``dt`` at the given wheel surface speeds (m/s).

    Speeds are clipped to ``params.max_wheel_speed_mps``. Returns the new state; ``collided`` is
    True when a wall stopped the robot during this step.
    """
    vl, vr = limit_wheel_speeds(left_speed, right_speed, params.max_wheel_speed_mps)
    rho = params.wheel_diameter_ratio
    if rho != 1.0:
        # The wheels turn as commanded; their surfaces move by their own diameters.
        vl, vr = vl * (2.0 * rho / (1.0 + rho)), vr * (2.0 / (1.0 + rho))
    motion = arc_motion(vl, vr, params.wheel_base_m, dt)
    if drive_error is not None:
        if rng is None:
            raise ValueError("a drive-error model needs an rng")
        motion = drive_error.perturb(motion, state, rng)

    radius = params.body_radius_m
    length = math.hypot(motion.dx_b, motion.dy_b)
    collided = False
    clearance = state.clearance
    if length == 0.0 or len(walls) == 0:
        x, y, heading = _pose_after(state, motion, 1.0)
        done = 1.0
    else:
        if clearance <= length:
            d_start = point_segment_distances(walls, state.x, state.y)
            clearance = float(d_start.min()) - radius
        if clearance > length:
            # Free space: no wall within reach of this step (the common case).
            x, y, heading = _pose_after(state, motion, 1.0)
            done = 1.0
            clearance -= length
        else:
            x, y, heading, done, collided = _move_near_walls(state, motion, length, radius,
                                                             walls, d_start)
            clearance = -math.inf
    # Ideal drive: the wheels stall with the body. With a drive-error model (issue 3) they slip
    # against the wall: the encoders count the wheel travel the model returned.
    wheel_frac = done if drive_error is None else 1.0
    left_m = motion.left_m * wheel_frac
    right_m = motion.right_m * wheel_frac
    dheading = heading - state.heading
    return RobotState(          # positional: x, y, theta, heading, travel, speeds, yaw rate, ...
        x,
        y,
        wrap_angle(heading),
        heading,
        state.left_travel_m + left_m,
        state.right_travel_m + right_m,
        left_m / dt,
        right_m / dt,
        dheading / dt,
        collided,
        clearance,
    )


def _move_near_walls(
    state: RobotState,
    motion: Motion,
    length: float,
    radius: float,
    walls: SegmentSet,
    d_start: np.ndarray,
) -> tuple[float, float, float, float, bool]:
    """Sub-stepped move with wall tests (module docstring; compiled in
    :func:`core.raycast.sweep_circle`). Returns x, y, heading, the fraction of the motion done,
    and whether a wall stopped it."""
    # Only walls within reach of this step matter.
    near = d_start <= radius + length + 1e-9
    seg = np.ascontiguousarray(walls.packed[:, near])
    done, collided = sweep_circle(seg, state.x, state.y, math.cos(state.theta),
                                  math.sin(state.theta), motion.dx_b, motion.dy_b, radius)
    x, y, heading = _pose_after(state, motion, done)
    return x, y, heading, done, collided
