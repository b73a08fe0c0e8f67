"""Wheel encoders: cumulative ticks of each wheel's rotation.

``ticks = round(wheel surface travel * ticks_per_metre)`` for each wheel, where the travel is what
the drive model says the wheel turned (:attr:`sim.robot.RobotState.left_travel_m`). With ideal
drive that is the body's motion; the drive-error model (``[robot.drive_error]``: per-wheel error,
wall slip) makes the body move differently from the wheels, so dead reckoning drifts from truth as
on the real robot. The counters start at 0 on ``reset``; setting them (K-Team ``G``) is an offset
kept by the bridge.

The encoders have no error model of their own: whole ticks of the commanded rotation is what they
report (``[sensors.encoders] ideal = false`` is a config error, see config/README.md).
"""

from __future__ import annotations

import math

from sim.config import BasicSensorConfig
from sim.robot import RobotState
from sim.types import OdometryReading


def encoder_ticks(travel_m: float, ticks_per_metre: float) -> int:
    """Whole ticks of a wheel's cumulative surface travel (round half up)."""
    return math.floor(travel_m * ticks_per_metre + 0.5)


class EncoderSensor:
    name = "encoders"

    def __init__(self, params: BasicSensorConfig, ticks_per_metre: float) -> None:
        self.params = params
        self.ticks_per_metre = ticks_per_metre

    def measure(self, state: RobotState) -> OdometryReading:
        tpm = self.ticks_per_metre
        return OdometryReading(math.floor(state.left_travel_m * tpm + 0.5),
                               math.floor(state.right_travel_m * tpm + 0.5))
