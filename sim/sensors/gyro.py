"""Yaw-rate gyroscope (z axis, counter-clockwise positive, rad/s).

Truth (pure, :func:`mean_yaw_rate`): the mean yaw rate over the interval since the previous sample,
``(heading_now - heading_prev) / interval``, with the unwrapped heading -- what an ideal
rate-integrating gyro with an anti-aliasing filter reports. Summing ``yaw_rate * interval`` over
the samples therefore gives the heading change exactly.

Seam: ``GyroSensor.measure(state, t, variates)``; an error model (issue 3, seeds/000 eq. 15:
scale error, turn-on bias, angle random walk, bias random walk) gets :class:`GyroTruth` (rate and
interval).
The sensor object keeps the heading of its previous sample; the simulator builds a new one on
every reset.

Error model: ``sim/models/gyro.py`` (its params, pure functions and
:class:`~koala_bridge.sim.models.gyro.GyroErrorModel`); config section ``[sensors.gyro]``,
typed here by :class:`GyroConfig` (its keys; the error model's keys beside them go to its params).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from koala_bridge.core.schema import Bool, Positive, section
from koala_bridge.sim.noise import Variates
from koala_bridge.sim.robot import RobotState
from koala_bridge.sim.sections import empty_errors, sensor_section
from koala_bridge.sim.sensors.base import ErrorModel
from koala_bridge.sim.types import GyroReading


@section
class GyroConfig:
    """``[sensors.gyro]``: a rate and the ideal switch; the rest of the table is the error
    model's (``sim/models/gyro.py``)."""

    rate_hz: Positive
    ideal: Bool
    errors: Any = field(default_factory=empty_errors)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> GyroConfig:
        return sensor_section(cls, d, "sensors.gyro", "gyro")


@dataclass(frozen=True, slots=True)
class GyroTruth:
    yaw_rate: float         # rad/s, mean over the interval
    interval_s: float       # time since the previous sample (0 at the first sample)
    heading: float          # unwrapped heading at this sample, rad


def mean_yaw_rate(heading_now: float, heading_prev: float, interval_s: float) -> float:
    return (heading_now - heading_prev) / interval_s if interval_s > 0 else 0.0


class GyroSensor:
    name = "gyro"

    def __init__(
        self,
        params: GyroConfig,
        error_model: ErrorModel[GyroTruth, GyroReading] | None = None,
    ) -> None:
        self.params = params
        self.error_model = None if params.ideal else error_model
        self._prev_heading: float | None = None
        self._prev_t = 0.0

    def measure(self, state: RobotState, t: float, variates: Variates) -> GyroReading:
        if self._prev_heading is None:
            truth = GyroTruth(0.0, 0.0, state.heading)
        else:
            dt = t - self._prev_t
            truth = GyroTruth(mean_yaw_rate(state.heading, self._prev_heading, dt), dt,
                              state.heading)
        self._prev_heading = state.heading
        self._prev_t = t
        if self.error_model is None:
            return GyroReading(truth.yaw_rate, truth.yaw_rate)
        return self.error_model.measure(truth, variates)
