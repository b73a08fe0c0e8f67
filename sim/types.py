"""Value types passed between the simulator and its callers.

Units and frames as in docs/architecture.md: SI, world x east / y north, body x forward / y left /
z up, magnetic field in microtesla. Every reading carries its noise-free companion ``truth`` built
from the same state, so measurement can be held against model.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True, slots=True)
class Pose:
    x: float
    y: float
    theta: float


@dataclass(frozen=True, slots=True)
class WheelCommand:
    """Commanded wheel surface speeds, m/s (positive = forward)."""

    left: float = 0.0
    right: float = 0.0


@dataclass(frozen=True, slots=True)
class IrReading:
    counts: np.ndarray          # (n,) int, K-Team proximity counts 0..1023, larger = closer
    ambient: np.ndarray         # (n,) int, ambient light counts 0..1023 (K-Team 'O')
    truth_counts: np.ndarray    # (n,) int, noise-free counts
    truth_ranges: np.ndarray    # (n,) float m, distance along the sensor axis (inf: nothing)
    # (n,) float rad, incidence of the axis ray on the surface at truth_ranges (nan: nothing);
    # None only in a reading built by hand (tests), the simulator always sets it.
    truth_incidence: np.ndarray | None = None


@dataclass(frozen=True, slots=True)
class SonarReading:
    ranges: np.ndarray          # (n,) float m; nan = no echo
    truth_ranges: np.ndarray    # (n,) float m; nan = nothing within max range
    incidence: np.ndarray       # (n,) float rad, angle between beam and surface normal (nan: none)


@dataclass(frozen=True, slots=True)
class OdometryReading:
    left_ticks: int             # cumulative encoder counts
    right_ticks: int


@dataclass(frozen=True, slots=True)
class GyroReading:
    yaw_rate: float             # rad/s, CCW positive
    truth_yaw_rate: float


@dataclass(frozen=True, slots=True)
class CompassReading:
    field_uT: np.ndarray        # (3,) body frame FLU, microtesla
    truth_field_uT: np.ndarray  # (3,) noise-free (Earth + local sources, no robot disturbance)


@dataclass(frozen=True, slots=True)
class LandmarkObservation:
    id: int
    range: float                # m
    bearing: float              # rad, CCW from the robot's heading


@dataclass(frozen=True, slots=True)
class CameraReading:
    observations: tuple[LandmarkObservation, ...]
    truth: tuple[LandmarkObservation, ...]  # every landmark in the field of view, true values


@dataclass(frozen=True, slots=True)
class BatteryReading:
    """The battery and motors after a step (SI units but charge, in mAh)."""

    voltage_V: float                    # at the terminals, under load
    current_A: float                    # drawn from the battery, > 0 discharging
    charge_mAh: float                   # remaining
    capacity_mAh: float
    temperature_C: float                # battery
    ambient_temperature_C: float
    motor_currents_A: tuple[float, float]   # left, right

    @property
    def state_of_charge(self) -> float:
        return self.charge_mAh / self.capacity_mAh


@dataclass(frozen=True, slots=True)
class Readings:
    """What one simulation step produced: the truth pose and every reading due at this step."""

    t: float
    pose: Pose
    wheel_speeds: WheelCommand          # actual wheel surface speeds after limits, m/s
    ir: IrReading | None = None
    sonar: SonarReading | None = None
    odometry: OdometryReading | None = None
    gyro: GyroReading | None = None
    compass: CompassReading | None = None
    camera: CameraReading | None = None
    collided: bool = False
    extra: dict[str, object] = field(default_factory=dict)
    battery: BatteryReading | None = None   # every step (sim/battery.py)
