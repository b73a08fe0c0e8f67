"""The simulator's configuration composed: ``[sim]``, ``[robot]``, ``[sensors.*]``, ``[world]``.

Built from plain dicts (the parsed TOML; file I/O lives in ``bridge/``) by :func:`load_sim_config`.
Each section is typed where what it configures lives: a sensor's in ``sim/sensors/<name>.py``
(``IrConfig`` ... ``CameraConfig``, beside the sensor's truth; its error model's params in
``sim/models/<name>.py``), ``[robot]`` and ``[robot.drive_error]`` in ``sim/robot.py``,
``[world]`` in ``sim/world.py``; this module holds ``[sim]`` (:class:`StepConfig`) and the
composition (:class:`SensorsConfig`, :class:`SimConfig`). Every section is a
:func:`koala_bridge.core.schema.section`, so the schema's one policy applies (config/README.md
"Policy"): every key these sections own is *required* and written in ``config/default.toml``;
types are strict; numbers finite and in range; unknown keys are
:class:`koala_bridge.core.schema.ConfigError` that suggest the nearest valid key. Top-level
sections other than ``sim``, ``robot``, ``sensors`` and ``world`` belong to ``bridge/`` and are
ignored here.

Seam for error models (issue 3): every sensor section and ``[robot.drive_error]`` has ``ideal``
(bool) and, side by side with the simulator's keys, the parameters of that sensor's error model
(``[sensors.gyro] gyroscope_noise_density = ...``). The error model's params class
(``sim/sections.py`` ``ERROR_PARAMS``, in ``sim/models/``, imported lazily) validates and types
them; the result is the sensor config's ``errors`` attribute. A value both need (``ideal``,
``min_range_m``, ...) has one key, owned and validated by the sensor's section and handed to the
params class (its ``FROM_SENSOR`` fields). With ``ideal = true`` the sensor reports its
noise-free value whatever those parameters say. The encoders have no error model:
``[sensors.encoders] ideal = false`` is a config error.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Annotated, Any

import numpy as np
from koala_bridge.core.geometry import wall_clearance
from koala_bridge.core.raycast import SegmentSet, point_segment_distances
from koala_bridge.core.schema import ConfigError, Finite, reject_unknown, require, section, validate
from koala_bridge.sim.robot import RobotConfig
from koala_bridge.sim.sensors.camera import CameraConfig
from koala_bridge.sim.sensors.compass import CompassConfig
from koala_bridge.sim.sensors.encoders import EncoderConfig
from koala_bridge.sim.sensors.gyro import GyroConfig
from koala_bridge.sim.sensors.ir import IrConfig
from koala_bridge.sim.sensors.sonar import SonarConfig
from koala_bridge.sim.world import World
from pydantic import Field, Strict

# The sensors of the simulated Koala, in the FIXED order used to spawn their RNG streams
# (sim.simulator.RNG_STREAMS appends "drive" first). Append new sensors at the end only.
SENSOR_NAMES = ("ir", "sonar", "encoders", "gyro", "compass", "camera")

#: ``[sim] dt_s`` bounds: 0.1 ms .. 1 s. A smaller step would take hours for a second of
#: simulated time (1e-9 would hang a run); a larger one is no longer a controller period.
STEP_LIMITS_S = (1e-4, 1.0)


# ------------------------------------------------------------------------------ sections


@section
class StepConfig:
    """``[sim]``: the fixed integration step and the default seed."""

    dt_s: Annotated[Finite, Field(ge=STEP_LIMITS_S[0], le=STEP_LIMITS_S[1])]
    seed: Annotated[int, Strict(), Field(ge=0)]

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> StepConfig:
        return validate(cls, d, "sim")


@dataclass(frozen=True)
class SensorsConfig:
    """``[sensors]``: one table per sensor of :data:`SENSOR_NAMES`."""

    ir: IrConfig
    sonar: SonarConfig
    encoders: EncoderConfig
    gyro: GyroConfig
    compass: CompassConfig
    camera: CameraConfig

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> SensorsConfig:
        reject_unknown(d, SENSOR_NAMES, "sensors")
        for name in SENSOR_NAMES:
            require(d, name, "sensors")
        return cls(
            ir=IrConfig.from_dict(d["ir"]),
            sonar=SonarConfig.from_dict(d["sonar"]),
            encoders=EncoderConfig.from_dict(d["encoders"]),
            gyro=GyroConfig.from_dict(d["gyro"]),
            compass=CompassConfig.from_dict(d["compass"]),
            camera=CameraConfig.from_dict(d["camera"]),
        )

    def rates_hz(self) -> dict[str, float]:
        return {name: getattr(self, name).rate_hz for name in SENSOR_NAMES}


@dataclass(frozen=True)
class SimConfig:
    """Everything :class:`sim.simulator.Simulator` needs: step, robot, sensors and world."""

    sim: StepConfig
    robot: RobotConfig
    sensors: SensorsConfig
    world: World

    def period_steps(self, rate_hz: float) -> int:
        """Steps between two samples of a sensor at ``rate_hz`` (exact multiple of ``dt``)."""
        return _period_steps(rate_hz, self.sim.dt_s)


def _period_steps(rate_hz: float, dt_s: float) -> int:
    n = 1.0 / (rate_hz * dt_s)
    k = round(n)
    if k < 1 or abs(n - k) > 1e-6 * max(1.0, n):
        raise ConfigError(
            f"a sensor rate of {rate_hz} Hz is not a whole number of {dt_s} s steps "
            f"(1 / (rate * dt) = {n:.6g}); choose a rate that divides 1/dt = {1 / dt_s:.6g} Hz"
        )
    return int(k)


def load_sim_config(d: Mapping[str, Any]) -> SimConfig:
    """Build a :class:`SimConfig` from a parsed config file (``tomllib.load`` output).

    Reads ``[sim]``, ``[robot]``, ``[sensors.*]`` and ``[world]``; other top-level tables are the
    bridge's and are ignored. Raises :class:`core.schema.ConfigError` naming section and key.
    """
    for key in ("sim", "robot", "sensors", "world"):
        require(d, key, "<top level>")
    step = StepConfig.from_dict(d["sim"])
    sensors = SensorsConfig.from_dict(d["sensors"])
    for name, rate in sensors.rates_hz().items():
        try:
            _period_steps(rate, step.dt_s)
        except ConfigError as e:
            raise ConfigError(f"[sensors.{name}] 'rate_hz': {e}") from None
    robot = RobotConfig.from_dict(d["robot"])
    world = World.from_dict(d["world"])
    check_start(world, robot.body_radius_m)
    return SimConfig(sim=step, robot=robot, sensors=sensors, world=world)


def check_start(world: World, body_radius_m: float) -> None:
    """Raise :class:`ConfigError` when the world's start pose puts the robot outside the world
    (its centre beyond ``0..width``, ``0..height``) or its body (a circle of ``body_radius_m``)
    across a wall segment: a robot that starts in a wall cannot move out of it."""
    start = world.start
    if start is None:
        return
    where = f"[world.start] x = {start.x:g}, y = {start.y:g}"
    if not (0.0 <= start.x <= world.width_m and 0.0 <= start.y <= world.height_m):
        raise ConfigError(f"{where} is outside the world (x 0..{world.width_m:g} m, "
                          f"y 0..{world.height_m:g} m)")
    if len(world.segments):
        # numpy for the one point (a compiled kernel's first call costs a quarter second of
        # every config load); the compiled one names the wall when there is one to name
        gap = float(wall_clearance(np.array([[start.x, start.y]]), world.segments)[0])
        if gap < body_radius_m - 1e-9:
            walls = SegmentSet.from_segments(world.segments, merge=False)
            nearest = int(np.argmin(point_segment_distances(walls, start.x, start.y)))
            x0, y0, x1, y1 = (float(v) for v in world.segments[nearest])
            raise ConfigError(
                f"{where}: the robot's body (radius {body_radius_m:g} m) overlaps the wall "
                f"({x0:g}, {y0:g})-({x1:g}, {y1:g}), {gap:.3f} m from its centre: start at "
                f"least {body_radius_m:g} m from every wall")
