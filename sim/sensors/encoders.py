"""Wheel encoders: cumulative ticks of each wheel's rotation.

Truth (pure, :func:`encoder_truth`): ``ticks = round(wheel surface travel * ticks_per_metre)``
for each wheel, where the travel is what the drive model says the wheel turned
(:attr:`sim.robot.RobotState.left_travel_m`). With ideal drive that is the body's motion; a
drive-error or slip model (issue 3) makes the body move differently from the wheels, so dead
reckoning drifts from truth as on the real robot. The counters start at 0 on ``reset``; setting
them (K-Team ``G``) is an offset kept by the bridge.

Seam: ``EncoderSensor.measure(state, rng)``; an error model gets :class:`EncoderTruth`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sim.config import BasicSensorConfig
from sim.robot import RobotState
from sim.sensors.base import ErrorModel
from sim.types import OdometryReading


@dataclass(frozen=True)
class EncoderTruth:
    left_ticks: int
    right_ticks: int
    left_travel_m: float
    right_travel_m: float
    ticks_per_metre: float


def encoder_truth(state: RobotState, ticks_per_metre: float) -> EncoderTruth:
    return EncoderTruth(
        left_ticks=math.floor(state.left_travel_m * ticks_per_metre + 0.5),
        right_ticks=math.floor(state.right_travel_m * ticks_per_metre + 0.5),
        left_travel_m=state.left_travel_m,
        right_travel_m=state.right_travel_m,
        ticks_per_metre=ticks_per_metre,
    )


class EncoderSensor:
    name = "encoders"

    def __init__(
        self,
        params: BasicSensorConfig,
        ticks_per_metre: float,
        error_model: ErrorModel[EncoderTruth, OdometryReading] | None = None,
    ) -> None:
        self.params = params
        self.ticks_per_metre = ticks_per_metre
        self.error_model = None if params.ideal else error_model

    def measure(self, state: RobotState, rng: np.random.Generator) -> OdometryReading:
        truth = encoder_truth(state, self.ticks_per_metre)
        if self.error_model is None:
            return OdometryReading(truth.left_ticks, truth.right_ticks)
        return self.error_model.measure(truth, rng)
