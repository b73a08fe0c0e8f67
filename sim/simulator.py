"""The simulated Koala: ``reset(seed) -> Readings``, ``step(command) -> Readings``, nothing else.

Fixed step ``dt = [sim] dt_s``. Step ``k`` ends at simulation time ``t = k * dt`` (computed from the
integer counter, so there is no floating-point drift). A sensor with rate ``f`` is due at every step
``k`` with ``k % round(1 / (f dt)) == 0`` (rates must divide ``1/dt``; the config loader checks),
so ``reset`` (step 0) returns a reading of every sensor. :class:`sim.types.Readings` holds the
truth pose and the readings due at that step; the others are None.

Randomness (Gymnasium pattern): ``reset(seed)`` builds ``numpy.random.SeedSequence(seed)`` and
spawns one child per name of :data:`RNG_STREAMS`, in that fixed order, each feeding its own
``numpy.random.Generator``; enabling an error model for one sensor never changes another sensor's
draws. New streams must be appended to the end of :data:`RNG_STREAMS`. The same config and seed
give bit-identical readings. Factories draw turn-on state (biases) from the sensor's
``Generator``; per-step draws come from a :class:`sim.noise.BlockStream` on it (normals and
uniforms drawn in blocks from two child streams), which is what ``measure`` receives.

Error models plug in through ``error_models`` (see :mod:`koala_bridge.sim.sensors.base`).

Fault hooks (bridge/runtime/faults.py, docs/faults.md), outside the step and drawing nothing from
the simulator's streams: :meth:`Simulator.teleport` moves the truth pose (a kidnapped robot: the
encoders do not count the jump) and :meth:`Simulator.set_wheel_traction` makes wheels slip (the
body moves as if each wheel's surface speed were scaled by its traction, while the encoders count
the whole wheel turn).

The rays of all range sensors due at a step go through one compiled cast
(:func:`core.raycast.cast_fan_arrays`); each range sensor then reads its slice of it in one
compiled call (truth and error model fused). The camera tests its lines of sight in its own
compiled call.

Other bodies (several robots in one world, :mod:`sim.fleet`): :meth:`Simulator.share_bodies`
gives the circles of the other robots' bodies. Each is added, for the step's collision test and
ray casts (IR, sonar with its second legs, the camera's lines of sight), as a regular polygon of
:data:`OBSTACLE_SIDES` sides circumscribed about the circle (its edges touch the circle at their
midpoints: a body stops at or outside the circle, and a ray's range is at most
``r (1 / cos(pi / OBSTACLE_SIDES) - 1)`` (1.9 % of r) long near a vertex). Only bodies within
reach of the step (collisions) or of the longest range sensor (ray casts) are added. A step is
:meth:`Simulator.move` then :meth:`Simulator.sense` (:meth:`Simulator.step` does both), so that a
fleet moves every robot before any of them senses.
"""

from __future__ import annotations

import dataclasses
import importlib
import math
from collections.abc import Mapping
from typing import Any

import numpy as np
from koala_bridge.core.geometry import wrap_angle
from koala_bridge.core.raycast import SegmentSet, cast_fan_arrays
from koala_bridge.core.schema import ConfigError
from koala_bridge.sim import robot as kin
from koala_bridge.sim.battery import Battery
from koala_bridge.sim.config import SENSOR_NAMES, SimConfig, load_sim_config
from koala_bridge.sim.noise import BlockStream, Variates
from koala_bridge.sim.robot import DriveErrorSeam, Motion, RobotState
from koala_bridge.sim.sections import poses_to_list
from koala_bridge.sim.sensors.base import ErrorModelFactory
from koala_bridge.sim.sensors.camera import CameraSensor
from koala_bridge.sim.sensors.compass import CompassSensor
from koala_bridge.sim.sensors.encoders import EncoderSensor
from koala_bridge.sim.sensors.fan import RayFan
from koala_bridge.sim.sensors.gyro import GyroSensor
from koala_bridge.sim.sensors.ir import IrSensor
from koala_bridge.sim.sensors.sonar import SonarSensor
from koala_bridge.sim.types import Pose, Readings, WheelCommand

# Fixed order of the per-sensor RNG streams (SeedSequence.spawn). Append only.
RNG_STREAMS: tuple[str, ...] = ("drive", *SENSOR_NAMES)

#: Sides of the polygon that stands for another robot's body circle (module docstring).
OBSTACLE_SIDES = 16


class Simulator:
    """One simulated Koala in one world. See the module docstring."""

    def __init__(
        self,
        config: SimConfig | Mapping[str, Any],
        error_models: Mapping[str, ErrorModelFactory] | None = None,
    ) -> None:
        self.config: SimConfig = (
            config if isinstance(config, SimConfig) else load_sim_config(config)
        )
        cfg = self.config
        self.dt: float = cfg.sim.dt_s
        self.world = cfg.world
        self.walls = SegmentSet.from_segments(cfg.world.segments, merge=True)
        self.periods: dict[str, int] = {
            name: cfg.period_steps(rate) for name, rate in cfg.sensors.rates_hz().items()
        }
        self._factories = self._resolve_error_models(error_models)
        self._k = 0
        self._state: RobotState | None = None
        self._rngs: dict[str, np.random.Generator] = {}
        self._streams: dict[str, BlockStream] = {}
        self._traction = (1.0, 1.0)
        self._obstacles = np.empty((0, 3))
        self._self_row = -1         # share_bodies: this robot's own row of the obstacles
        self._near_cache: tuple[np.ndarray, SegmentSet] = (np.empty((0, 3)), self.walls)
        r = cfg.robot
        # How far another body may be and still matter to one step's move: three times the
        # longest commanded step (drive errors perturb a step by a few per cent) and 1 cm.
        self._move_reach = r.body_radius_m + 0.01 + 3.0 * r.max_wheel_speed_mps * self.dt
        s = cfg.sensors
        self._sense_reach = r.body_radius_m + max(s.ir.max_range_m, s.sonar.max_range_m,
                                                  s.camera.max_range_m)

    # ------------------------------------------------------------------ public API
    @property
    def t(self) -> float:
        """Simulation time of the last step, s (``step_count * dt``)."""
        return self._k * self.dt

    @property
    def step_count(self) -> int:
        return self._k

    def reset(self, seed: int | None = None, spawn_key: tuple[int, ...] = ()) -> Readings:
        """Put the robot at the world's start pose, reseed every stream, return step-0 readings.

        ``spawn_key``: the robot's streams come from ``SeedSequence(seed, spawn_key=spawn_key)``
        (``(i,)`` is the ``i``-th child of ``SeedSequence(seed)``: one robot of a fleet); ``()``
        is ``SeedSequence(seed)`` itself."""
        seed = self.config.sim.seed if seed is None else seed
        children = np.random.SeedSequence(seed, spawn_key=spawn_key).spawn(len(RNG_STREAMS))
        self._rngs = {name: np.random.Generator(np.random.PCG64(ss))
                      for name, ss in zip(RNG_STREAMS, children, strict=True)}
        self._streams = {name: BlockStream(rng) for name, rng in self._rngs.items()}
        self._build_sensors()
        start = self.world.start
        if start is None:
            x, y = self.world.cell_centre(*self.world.free_cells()[0])
            self._state = RobotState.at(x, y, 0.0)
        else:
            self._state = RobotState.at(start.x, start.y, start.theta)
        self._k = 0
        self._traction = (1.0, 1.0)
        self.battery = Battery(self.config.robot.battery, self.config.robot.max_wheel_speed_mps)
        return self._readings(self._state)

    def step(self, command: WheelCommand) -> Readings:
        """Advance one step ``dt`` with the commanded wheel surface speeds (m/s)."""
        self.move(command)
        return self.sense()

    def move(self, command: WheelCommand) -> None:
        """The first half of :meth:`step`: move the robot (and its battery) by one step."""
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        before = self._state
        drive: DriveErrorSeam | None = self._drive_error
        if self._traction != (1.0, 1.0):
            drive = _WheelSlip(self._traction, self.config.robot.wheel_base_m, self.dt, drive)
        start = before
        walls = self._walls_near(before.x, before.y, self._move_reach)
        if walls is not self.walls:
            # the clearance bound holds for the walls only: another body may have come closer
            start = dataclasses.replace(before, clearance=-math.inf)
        self._state = kin.step(
            start, command.left, command.right, self.dt, self.config.robot, walls,
            self._streams["drive"], drive,
        )
        self._k += 1
        st = self._state
        self.battery.step((st.left_speed, st.right_speed), (command.left, command.right), self.dt,
                          _ground_speeds(before, st, self.dt, self.config.robot.wheel_base_m)
                          if st.collided else None)

    def sense(self) -> Readings:
        """The second half of :meth:`step`: the readings due after the last move (at ``t``)."""
        return self._readings(self._require_state())

    def share_bodies(self, bodies: np.ndarray, row: int) -> None:
        """The bodies of a fleet, ``(N, 3)`` rows ``x, y, radius`` (m), of which row ``row`` is
        this robot's own: the others are obstacles for every :meth:`move` and :meth:`sense`
        (module docstring, "Other bodies"). The array is shared, not copied: its owner
        (:class:`sim.fleet.Fleet`) moves the rows in place."""
        self._obstacles = bodies
        self._self_row = row

    def _walls_near(self, x: float, y: float, reach: float) -> SegmentSet:
        """The walls plus the obstacles whose circle comes within ``reach`` of ``(x, y)``."""
        obs = self._obstacles
        if obs.shape[0] == 0:
            return self.walls
        gap = np.hypot(obs[:, 0] - x, obs[:, 1] - y) - obs[:, 2]
        if self._self_row >= 0:
            gap[self._self_row] = np.inf
        near = obs[gap <= reach]
        if near.shape[0] == 0:
            return self.walls
        # bodies pressed together stay where they are for many steps: reuse their polygons
        cached_near, cached = self._near_cache
        if cached_near.shape == near.shape and np.array_equal(cached_near, near):
            return cached
        walls = self.walls.with_circles(near, OBSTACLE_SIDES)
        self._near_cache = (near, walls)
        return walls

    @property
    def pose(self) -> Pose:
        """The truth pose after the last step (or reset, or teleport)."""
        st = self._require_state()
        return Pose(st.x, st.y, st.theta)

    @property
    def wheel_traction(self) -> tuple[float, float]:
        """The traction of the left and right wheel set by :meth:`set_wheel_traction`."""
        return self._traction

    def teleport(self, x: float, y: float, theta: float) -> None:
        """Move the robot to ``(x, y)`` m heading ``theta`` rad between two steps, as a robot
        picked up and put down (a "kidnapped robot"): the truth pose jumps, the encoders count
        nothing (wheel travel is kept), no collision is tested for the jump itself and no
        random number is drawn. The next step starts from the new pose; the next readings see
        it. A pose overlapping a wall is allowed: the robot can then only move away from it
        (sim/robot.py, "Collisions")."""
        st = self._require_state()
        if not all(math.isfinite(v) for v in (x, y, theta)):
            raise ValueError(f"teleport needs finite x, y, theta, got {(x, y, theta)}")
        turn = wrap_angle(theta - st.theta)
        self._state = dataclasses.replace(
            st, x=float(x), y=float(y), theta=wrap_angle(theta), heading=st.heading + turn,
            collided=False, clearance=-math.inf,   # the wall distance bound is void after a jump
        )

    def set_wheel_traction(self, left: float, right: float) -> None:
        """Wheel slip: from the next step the body moves as if each wheel's surface speed were
        multiplied by its traction (0 = spinning in place, 1 = no slip), while the encoders
        count the whole wheel turn -- the odometry over-reads, as on a wheel slipping on a
        smooth floor. ``(1, 1)`` is off (the default; :meth:`reset` restores it). Applied
        before the drive-error model (issue 3), which then perturbs the slipped wheel steps;
        it draws nothing itself. With slip on, wheels against a wall keep turning (the encoders
        count) as they do with a drive-error model."""
        for name, v in (("left", left), ("right", right)):
            if not (math.isfinite(v) and 0.0 <= v <= 1.0):
                raise ValueError(f"wheel traction '{name}' must be in [0, 1], got {v!r}")
        self._traction = (float(left), float(right))

    def robot_description(self) -> dict[str, Any]:
        """The robot's parameters, JSON-ready (the ``robot`` part of the Zenoh ``world`` answer)."""
        r = self.config.robot
        s = self.config.sensors
        return {
            "name": r.name,
            "wheel_base_m": r.wheel_base_m,
            "wheel_diameter_m": r.wheel_diameter_m,
            "wheel_diameter_ratio": r.wheel_diameter_ratio,
            "ticks_per_metre": r.ticks_per_metre,
            "body_radius_m": r.body_radius_m,
            "max_wheel_speed_mps": r.max_wheel_speed_mps,
            "speed_unit_s": r.speed_unit_s,
            "dt_s": self.dt,
            "frames": {"world": "x east, y north, theta CCW from x",
                       "body": "x forward, y left, z up (FLU)"},
            "sensors": {
                "ir": {"rate_hz": s.ir.rate_hz, "poses": poses_to_list(s.ir.poses),
                       "rays": s.ir.rays, "aperture_rad": float(np.radians(s.ir.aperture_deg)),
                       "max_range_m": s.ir.max_range_m,
                       "response_range_m": s.ir.response_range_m.tolist(),
                       "response_counts": s.ir.response_counts.tolist(),
                       "ideal": s.ir.ideal},
                "sonar": {"rate_hz": s.sonar.rate_hz, "poses": poses_to_list(s.sonar.poses),
                          "rays": s.sonar.rays,
                          "aperture_rad": float(np.radians(s.sonar.aperture_deg)),
                          "min_range_m": s.sonar.min_range_m,
                          "max_range_m": s.sonar.max_range_m, "ideal": s.sonar.ideal},
                "encoders": {"rate_hz": s.encoders.rate_hz, "ideal": s.encoders.ideal},
                "gyro": {"rate_hz": s.gyro.rate_hz, "ideal": s.gyro.ideal},
                "compass": {"rate_hz": s.compass.rate_hz, "ideal": s.compass.ideal,
                            "min_source_distance_m": s.compass.min_source_distance_m},
                "camera": {"rate_hz": s.camera.rate_hz,
                           "pose": poses_to_list([s.camera.pose])[0],
                           "fov_rad": float(np.radians(s.camera.fov_deg)),
                           "min_range_m": s.camera.min_range_m,
                           "max_range_m": s.camera.max_range_m, "ideal": s.camera.ideal},
            },
        }

    # ------------------------------------------------------------------ internals
    def _require_state(self) -> RobotState:
        if self._state is None:
            raise RuntimeError("call reset() first")
        return self._state

    def _resolve_error_models(
        self, given: Mapping[str, ErrorModelFactory] | None
    ) -> Mapping[str, ErrorModelFactory]:
        cfg = self.config
        wanted = [n for n in SENSOR_NAMES if n != "encoders" and not getattr(cfg.sensors, n).ideal]
        if not cfg.robot.drive.ideal:
            wanted.insert(0, "drive")
        if not wanted:
            return {}
        if given is None:
            try:
                given = importlib.import_module("koala_bridge.sim.models").ERROR_MODELS
            except (ImportError, AttributeError) as e:
                raise ConfigError(
                    f"ideal = false for {wanted}, but no error models are available "
                    f"(sim.models.ERROR_MODELS): {e}"
                ) from e
        missing = [n for n in wanted if n not in given]
        if missing:
            raise ConfigError(f"ideal = false for {missing}, but no error model is registered "
                              f"for them (known: {sorted(given)})")
        return given

    def _make(self, name: str, params: Any) -> Any:
        """The error model of ``name`` for this run, or None when ideal. Factories draw any
        turn-on state (biases) from the sensor's own stream."""
        if params.ideal:
            return None
        return self._factories[name](params, self._rngs[name])

    def _build_sensors(self) -> None:
        cfg = self.config
        s = cfg.sensors
        # The drive model needs the wheel base and dt: its factory gets the whole SimConfig.
        self._drive_error = (None if cfg.robot.drive.ideal
                             else self._factories["drive"](cfg, self._rngs["drive"]))
        self.ir = IrSensor(s.ir, self._make("ir", s.ir))
        # walls: late echoes via a second surface and crosstalk need the sonar's world geometry.
        self.sonar = SonarSensor(s.sonar, self._make("sonar", s.sonar), walls=self.walls)
        self.encoders = EncoderSensor(s.encoders, cfg.robot.ticks_per_metre,
                                      cfg.robot.wheel_diameter_ratio)   # no error model
        self.gyro = GyroSensor(s.gyro, self._make("gyro", s.gyro))
        self.compass = CompassSensor(s.compass, self.world, self._make("compass", s.compass))
        self.camera = CameraSensor(s.camera, self.world, self.walls,
                                   self._make("camera", s.camera))
        self._fans: dict[tuple[bool, bool], tuple[np.ndarray, np.ndarray, int]] = {}

    def _fan_for(self, ir_due: bool, sonar_due: bool) -> tuple[np.ndarray, np.ndarray, int]:
        """The rays of the range sensors due at a step as one fan (cached per combination):
        body rays (3, R), max ranges (R,), and where the sonar's rays start."""
        key = (ir_due, sonar_due)
        got = self._fans.get(key)
        if got is None:
            fans = ([self.ir.fan] if ir_due else []) + ([self.sonar.fan] if sonar_due else [])
            maxr = ([np.full(self.ir.fan.size, self.ir.max_range_m)] if ir_due else []) + (
                [np.full(self.sonar.fan.size, self.sonar.max_range_m)] if sonar_due else [])
            got = (RayFan.concat(fans).body, np.concatenate(maxr),
                   self.ir.fan.size if ir_due else 0)
            self._fans[key] = got
        return got

    def _readings(self, st: RobotState) -> Readings:
        streams = self._streams
        k = self._k
        p = self.periods
        ir_due = k % p["ir"] == 0
        sonar_due = k % p["sonar"] == 0
        camera_due = k % p["camera"] == 0
        ir = sonar = None
        walls = self.walls
        if self._obstacles.shape[0] and (ir_due or sonar_due or camera_due):
            walls = self._walls_near(st.x, st.y, self._sense_reach)
        self.sonar.walls = self.camera.walls = walls
        if ir_due or sonar_due:
            # One compiled cast for the rays of every range sensor due at this step.
            body, maxr, sonar_start = self._fan_for(ir_due, sonar_due)
            rays, index = cast_fan_arrays(walls, body, maxr, st.x, st.y, st.theta)
            if ir_due:
                ir = self.ir.measure(rays, index, 0, streams["ir"])
            if sonar_due:
                sonar = self.sonar.measure(rays, index, sonar_start, streams["sonar"])
        t = k * self.dt
        return Readings(
            t,
            Pose(st.x, st.y, st.theta),
            WheelCommand(st.left_speed, st.right_speed),
            ir,
            sonar,
            self.encoders.measure(st) if k % p["encoders"] == 0 else None,
            self.gyro.measure(st, t, streams["gyro"]) if k % p["gyro"] == 0 else None,
            self.compass.measure(st, streams["compass"]) if k % p["compass"] == 0 else None,
            self.camera.measure(st, streams["camera"]) if camera_due else None,
            st.collided,
            battery=self.battery.reading,
        )


class _WheelSlip:
    """The drive seam with wheel traction (:meth:`Simulator.set_wheel_traction`): the body moves
    by the arc of the scaled wheel steps (sim/robot.py's exact arc), the drive-error model (if
    any) perturbs those, and the wheel travel the encoders count stays the commanded one."""

    __slots__ = ("traction", "wheel_base", "dt", "inner")

    def __init__(self, traction: tuple[float, float], wheel_base: float, dt: float,
                 inner: DriveErrorSeam | None) -> None:
        self.traction = traction
        self.wheel_base = wheel_base
        self.dt = dt
        self.inner = inner

    def perturb(self, ideal: Motion, state: RobotState, rng: Variates) -> Motion:
        left = ideal.left_m * self.traction[0]
        right = ideal.right_m * self.traction[1]
        dx, dy, dth = kin.arc_displacement(left / self.dt, right / self.dt, self.wheel_base,
                                           self.dt)
        slipped = Motion(dx, dy, dth, left, right)
        if self.inner is not None:
            slipped = self.inner.perturb(slipped, state, rng)
        return Motion(slipped.dx_b, slipped.dy_b, slipped.dtheta, ideal.left_m, ideal.right_m)


def _ground_speeds(before: RobotState, after: RobotState, dt: float,
                   wheel_base: float) -> tuple[float, float]:
    """The body's mean speed over a step at the left and right wheel contact, m/s (forward speed
    along the starting heading, minus / plus half the wheel base times the yaw rate)."""
    c, s = np.cos(before.theta), np.sin(before.theta)
    v = float((after.x - before.x) * c + (after.y - before.y) * s) / dt
    w = (after.heading - before.heading) / dt
    return (v - 0.5 * wheel_base * w, v + 0.5 * wheel_base * w)
