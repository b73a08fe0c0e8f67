"""Wheel encoders: cumulative ticks of each wheel's rotation.

``ticks = round(wheel surface travel * ticks_per_metre)`` for each wheel (per wheel: divided by
its diameter relative to nominal, ``[robot] wheel_diameter_ratio``, see sim/robot.py), where the
travel is what the drive model says the wheel turned
(:attr:`sim.robot.RobotState.left_travel_m`). With ideal drive that is the body's motion; the
drive-error model (``[robot.drive_error]``: per-wheel error,
wall slip) makes the body move differently from the wheels, so dead reckoning drifts from truth as
on the real robot. The counters start at 0 on ``reset``; setting them (K-Team ``G``) is an offset
kept by the bridge.

The encoders have no error model of their own: whole ticks of the commanded rotation is what they
report (``[sensors.encoders] ideal = false`` is a config error, see config/README.md); config
section ``[sensors.encoders]``, typed here by :class:`EncoderConfig`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import field
from typing import Any

from koala_bridge.core.schema import Bool, ConfigError, Positive, section
from koala_bridge.sim.robot import RobotState
from koala_bridge.sim.sections import empty_errors, error_params_class, sensor_section
from koala_bridge.sim.types import OdometryReading


@section
class EncoderConfig:
    """``[sensors.encoders]``: a rate and the ideal switch, which must be true: the encoders have
    no error model of their own."""

    rate_hz: Positive
    ideal: Bool
    errors: Any = field(default_factory=empty_errors)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> EncoderConfig:
        sec, model = "sensors.encoders", "encoders"
        out = sensor_section(cls, d, sec, model)
        if not out.ideal and error_params_class(model) is None:
            raise ConfigError(
                f"[{sec}] 'ideal' must be true: the {model} have no error model of their own "
                "(their errors come from [robot.drive_error]: the counts are whole ticks of the "
                "commanded wheel rotation, from which the truth pose drifts); see "
                "config/README.md"
            )
        return out


def encoder_ticks(travel_m: float, ticks_per_metre: float) -> int:
    """Whole ticks of a wheel's cumulative surface travel (round half up)."""
    return math.floor(travel_m * ticks_per_metre + 0.5)


class EncoderSensor:
    name = "encoders"

    def __init__(self, params: EncoderConfig, ticks_per_metre: float,
                 wheel_diameter_ratio: float = 1.0) -> None:
        self.params = params
        self.ticks_per_metre = ticks_per_metre
        # Ticks per metre of each wheel's *surface* travel: a wheel smaller than nominal turns
        # more per metre (sim/robot.py, wheel diameters).
        rho = wheel_diameter_ratio
        self._tpm_left = ticks_per_metre if rho == 1.0 else ticks_per_metre * (1 + rho) / (2 * rho)
        self._tpm_right = ticks_per_metre if rho == 1.0 else ticks_per_metre * (1 + rho) / 2

    def measure(self, state: RobotState) -> OdometryReading:
        return OdometryReading(encoder_ticks(state.left_travel_m, self._tpm_left),
                               encoder_ticks(state.right_travel_m, self._tpm_right))
