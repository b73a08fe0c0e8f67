"""The Koala's battery and motor currents: charge that drains with what the wheels do.

What the robot's management sensors report (classic Koala ``M`` / ``S``, Koala 2.5 ``V`` / ``O``;
docs/protocols.md) comes from here. No seed document models a battery: the model below is the
textbook one, every parameter is ``[robot.battery]`` (config/default.toml, where each value is
marked ASSUMED or sourced), and it is deterministic (no noise: the management sensors are read
seldom and their quantisation, one ADC count, dominates).

Per wheel, each step (``v`` the wheel's mean surface speed over the step, ``v_cmd`` its set-point,
``a = (v - v_prev) / dt``; SI units)::

    I_wheel = min(I_stall, k_v |v| + k_a |a| + I_stall (|v_cmd - v| + |v - v_ground|) / v_max)

``k_v |v|`` is the running current (friction and viscous losses grow with speed), ``k_a |a|`` the
torque that accelerates the robot, and the last term the motor pushing against what stops the
robot: a wheel that does not follow its set-point (stalled against a wall with ideal drive:
``v = 0`` while ``v_cmd`` is not) or, in wall contact, a wheel that turns while the ground under
it does not move as fast (``v_ground``: the body's motion at the wheel; with the drive-error
model a pushing wheel slips at its set-point and works against the friction). Either way the
motor draws up to its stall current; a DC motor at full duty cannot draw more.

The battery (a charge counter, an open-circuit voltage linear in the state of charge, and a series
resistance)::

    I     = I_idle + I_left + I_right
    Q    -= I dt / 3.6                           (Q in mAh, floored at 0)
    soc   = Q / capacity
    V     = V_empty + (V_full - V_empty) soc - R I
    T_bat -> T_amb + R I^2 R_th                  (first order, time constant tau)

An empty battery does not stop the simulated robot (a real Koala browns out); the voltage then
reads ``V_empty - R I`` and the charge 0 -- a firmware's low-battery logic can be tested before
that point.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Annotated, Any

from koala_bridge.core.schema import (
    ConfigError,
    Finite,
    NonNegative,
    Positive,
    Probability,
    Str,
    one_of,
    section,
    validate,
)
from koala_bridge.sim.types import BatteryReading

CHEMISTRIES = ("NiMH", "Li-ion")


@section
class BatteryConfig:
    """``[robot.battery]``: the battery and motor-current model above (units in the key names)."""

    chemistry: Annotated[Str, one_of(CHEMISTRIES)]  # reported by Koala 2.5 V (type code)
    capacity_mAh: Positive
    initial_charge: Probability   # state of charge at reset, 0..1
    voltage_full_V: Positive            # open-circuit voltage at full charge
    voltage_empty_V: Positive           # open-circuit voltage at zero charge
    internal_resistance_ohm: NonNegative
    idle_current_A: NonNegative          # electronics, wheels at rest
    motor_current_per_mps_A: NonNegative  # k_v, per wheel
    motor_current_per_mps2_A: NonNegative  # k_a, per wheel
    motor_stall_current_A: NonNegative    # I_stall, per wheel
    ambient_temperature_C: Finite
    thermal_resistance_K_per_W: NonNegative
    thermal_time_constant_s: Positive

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> BatteryConfig:
        sec = "robot.battery"
        out = validate(cls, d, sec)
        if out.voltage_empty_V >= out.voltage_full_V:
            raise ConfigError(
                f"[{sec}] 'voltage_empty_V' ({out.voltage_empty_V}) must be below "
                f"'voltage_full_V' ({out.voltage_full_V})"
            )
        return out


def motor_current(v: float, v_prev: float, v_cmd: float, dt: float, v_max: float,
                  cfg: BatteryConfig, v_ground: float | None = None) -> float:
    """``I_wheel`` of the module docstring, A (non-finite inputs count as 0; ``v_ground`` None:
    no wall contact, no slip term)."""
    v = v if math.isfinite(v) else 0.0
    v_prev = v_prev if math.isfinite(v_prev) else 0.0
    v_cmd = min(max(v_cmd, -v_max), v_max) if math.isfinite(v_cmd) else 0.0
    accel = abs(v - v_prev) / dt if dt > 0 else 0.0
    slip = abs(v - v_ground) if v_ground is not None and math.isfinite(v_ground) else 0.0
    push = cfg.motor_stall_current_A * (abs(v_cmd - v) + slip) / v_max
    running = cfg.motor_current_per_mps_A * abs(v) + cfg.motor_current_per_mps2_A * accel
    return min(cfg.motor_stall_current_A, running + push)


class Battery:
    """The state of the model (charge, temperature, last wheel speeds); one per simulator reset."""

    def __init__(self, cfg: BatteryConfig, max_wheel_speed_mps: float) -> None:
        self.cfg = cfg
        self.v_max = max_wheel_speed_mps
        self.charge_mAh = cfg.capacity_mAh * cfg.initial_charge
        self.temperature_C = cfg.ambient_temperature_C
        self._speeds = (0.0, 0.0)
        self._reading = self._read((0.0, 0.0), cfg.idle_current_A)

    def step(self, speeds: tuple[float, float], commands: tuple[float, float],
             dt: float, ground: tuple[float, float] | None = None) -> BatteryReading:
        """Advance by ``dt`` s with the wheels' mean surface speeds and set-points (m/s) over
        it; ``ground``: in wall contact, the body's speed at each wheel (else None)."""
        cfg = self.cfg
        g = ground or (None, None)
        motors = (
            motor_current(speeds[0], self._speeds[0], commands[0], dt, self.v_max, cfg, g[0]),
            motor_current(speeds[1], self._speeds[1], commands[1], dt, self.v_max, cfg, g[1]),
        )
        self._speeds = speeds
        current = cfg.idle_current_A + motors[0] + motors[1]
        self.charge_mAh = max(0.0, self.charge_mAh - current * dt / 3.6)
        target = (cfg.ambient_temperature_C
                  + cfg.internal_resistance_ohm * current**2 * cfg.thermal_resistance_K_per_W)
        self.temperature_C += (target - self.temperature_C) * (
            1.0 - math.exp(-dt / cfg.thermal_time_constant_s))
        self._reading = self._read(motors, current)
        return self._reading

    @property
    def reading(self) -> BatteryReading:
        return self._reading

    def _read(self, motors: tuple[float, float], current: float) -> BatteryReading:
        cfg = self.cfg
        soc = self.charge_mAh / cfg.capacity_mAh
        ocv = cfg.voltage_empty_V + (cfg.voltage_full_V - cfg.voltage_empty_V) * soc
        return BatteryReading(
            voltage_V=ocv - cfg.internal_resistance_ohm * current,
            current_A=current,
            charge_mAh=self.charge_mAh,
            capacity_mAh=cfg.capacity_mAh,
            temperature_C=self.temperature_C,
            ambient_temperature_C=cfg.ambient_temperature_C,
            motor_currents_A=motors,
        )
