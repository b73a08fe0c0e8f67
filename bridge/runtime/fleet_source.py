"""Several simulated robots in one world, one process: the source of a configuration with
``[[robots]]`` (runtime/fleet_config.py; docs/multirobot.md).

Each robot is a :class:`runtime.sim_source.SimulatedRobotSource` of its own configuration: its
own buses (ptys, CAN, MAVLink), readers, motor arbiter, faults and Zenoh prefix. The fleet owns
what is one for all: the world stepping (:class:`sim.fleet.Fleet`: each robot sees and collides
with the others), the clock, the Zenoh session (every robot publishes through it under its own
prefix) and the loop. Each step: every robot's wheel command in force, one fleet step, then
every robot's readings to its buses and Zenoh, robot by robot in their order.

Clocks: ``realtime`` and ``fast`` pace the fleet with one clock. In ``lockstep`` each robot keeps
its own :class:`runtime.clock.LockstepClock`, granted by its own firmware's cycle messages, and a
step runs only once every robot's clock has granted it: simulated time waits for the slowest
firmware (and stands at 0 until each has sent its first cycle message). A firmware that leaves
ends the run, as with one robot.

Recording: robot ``NAME``'s Zenoh keys are recorded as ``NAME/<key>`` (MCAP topic
``/NAME/sensors/ir``) and its bus frames as bus ``NAME/<bus>`` (``/bus/NAME/can``).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterable, Mapping
from typing import Any

from koala_bridge.runtime.clock import Clock
from koala_bridge.runtime.endpoints import Endpoints, FleetEndpoints
from koala_bridge.runtime.fleet_config import RobotEntry, check_clashes, entry_errors
from koala_bridge.runtime.settings import BridgeSettings
from koala_bridge.runtime.sim_source import SimulatedRobotSource
from koala_bridge.runtime.source import Tap, until_text
from koala_bridge.runtime.zenoh_io import open_session
from koala_bridge.sim.fleet import Fleet
from koala_bridge.sim.types import Readings

__all__ = ["FleetSource", "RobotTap"]


class RobotTap:
    """One robot's view of the run's recorder: its keys and buses under its name."""

    def __init__(self, tap: Tap, name: str) -> None:
        self.tap = tap
        self.name = name

    def declare(self, keys: Iterable[str] = (), buses: Iterable[str] = ()) -> None:
        self.tap.declare([f"{self.name}/{k}" for k in keys],
                         [f"{self.name}/{b}" for b in buses])

    def record(self, channel: str, t: float, payload: Mapping[str, Any]) -> None:
        self.tap.record(f"{self.name}/{channel}", t, payload)

    def record_frame(self, bus: str, direction: str, t: float, data: bytes,
                     **fields: object) -> None:
        self.tap.record_frame(f"{self.name}/{bus}", direction, t, data, **fields)


class FleetSource:
    """The robots of ``[[robots]]`` in one world: a :class:`runtime.source.Source`.

    Args:
        config: the whole configuration (with ``[[robots]]``), for the run's own sections.
        settings: its typed bridge sections (the clock, duration, Zenoh session).
        entries: the robots (:func:`runtime.fleet_config.robot_entries`).
        seed: the run's seed; None uses ``[sim] seed``.
    """

    def __init__(self, config: Mapping[str, Any], settings: BridgeSettings,
                 entries: list[RobotEntry], seed: int | None = None) -> None:
        self.settings = settings
        self.entries = entries
        robot_settings = []
        self.robots = []
        for e in entries:
            # the endpoints file is the fleet's (one file naming every robot)
            e.config.setdefault("run", {})["endpoints_file"] = ""
            with entry_errors(e):       # an error in the entry's keys names its path
                s = BridgeSettings.from_config(e.config)
                self.robots.append(SimulatedRobotSource(e.config, s, seed=seed))
            robot_settings.append(s)
        if settings.run.clock != "lockstep":
            clock: Clock = self.robots[0].clock      # one clock paces them all
            for robot in self.robots:
                robot.clock = clock
        check_clashes(entries, robot_settings,
                      [r.sim.config.robot.body_radius_m for r in self.robots])
        self.fleet = Fleet([r.sim for r in self.robots], [e.stream_key for e in entries])
        self.sim = self.fleet           # .t: the progress line's simulated time
        self.seed = seed
        self.dt = self.fleet.dt
        self._session: Any = None
        self._tap: Tap | None = None
        self._last: list[Readings] | None = None
        self._t0 = 0.0
        self.endpoints: FleetEndpoints | None = None

    @property
    def names(self) -> list[str]:
        return [e.name for e in self.entries]

    @property
    def tap(self) -> Tap | None:
        return self._tap

    @tap.setter
    def tap(self, tap: Tap | None) -> None:
        """Every robot records into ``tap`` under its name."""
        self._tap = tap
        for e, robot in zip(self.entries, self.robots, strict=True):
            robot.tap = None if tap is None else RobotTap(tap, e.name)

    def robots_metadata(self) -> list[dict[str, Any]]:
        """Each robot's name, Zenoh prefix, start pose, random-stream key, K-Team dialect and
        parameters (its ``world`` answer's ``robot``): a recording's metadata, which ``export``
        and ``replay --robot`` read (recording/mcap_file.py, :func:`robot_view`)."""
        return [{"name": e.name, "prefix": r.settings.zenoh.prefix,
                 "start": e.config["world"]["start"], "seed_offset": e.stream_key,
                 "kteam_dialect": r.settings.buses.kteam_dialect,
                 "robot": r.world_answer().get("robot")}
                for e, r in zip(self.entries, self.robots, strict=True)]

    def world_answer(self) -> dict[str, Any]:
        """The world with the first robot (each robot's own answers its ``<prefix>/world``)."""
        return self.robots[0].world_answer()

    # -- lifecycle ---------------------------------------------------------------------------

    def open(self) -> Endpoints:
        """Open the Zenoh session and every robot's buses; return where clients connect."""
        try:
            self._session = open_session(self.settings.zenoh)
            for robot in self.robots:
                robot.zenoh_session = self._session
                robot.open()
            for robot, r in zip(self.robots, self.fleet.reset(self.seed), strict=True):
                robot.use_initial(r)
        except BaseException:
            self.close()
            raise
        eps = []
        for e, robot in zip(self.entries, self.robots, strict=True):
            assert robot.endpoints is not None
            eps.append((e.name, robot.endpoints))
        self.endpoints = FleetEndpoints(robots=tuple(eps))
        return self.endpoints

    def close(self) -> None:
        """Close every robot, then the Zenoh session. Idempotent."""
        for robot in self.robots:
            robot.close()
        if self._session is not None:
            self._session.close()
            self._session = None

    def __enter__(self) -> FleetSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def describe(self) -> str:
        run = self.settings.run
        how = (f"lockstep: each step waits for every robot's firmware "
               f"({self.settings.lockstep.period_s:g} s per cycle message)"
               if run.clock == "lockstep" else f"{run.clock} clock")
        return (f"Simulating {len(self.robots)} robots ({', '.join(self.names)}) in one world "
                f"({how}) {until_text(run.duration_s)}.")

    def summary(self) -> str:
        t = 0.0 if self._last is None else self._last[0].t
        wall = time.monotonic() - self._t0
        rtf = t / wall if wall > 0 else 0.0
        return (f"Stopped at t = {t:.3f} s with {len(self.robots)} robots "
                f"(real-time factor {rtf:.2f}).")

    # -- the loop ------------------------------------------------------------------------------

    def run(self, stop: threading.Event, duration_s: float | None = None) -> list[Readings]:
        """Step every robot together until ``stop`` is set or ``duration_s`` simulation seconds
        have run (None: ``[run] duration_s``; 0: no limit). Returns each robot's last
        readings."""
        duration = self.settings.run.duration_s if duration_s is None else duration_s
        last_step = round(duration / self.dt) if duration > 0 else None
        self._t0 = time.monotonic()
        rs = [robot.begin_run() for robot in self.robots]
        wait = self.robots[0].hold_wait_s()
        n = 0
        while not stop.is_set() and (last_step is None or n < last_step):
            if not self._wait_for_step(n + 1, wait):
                late = [robot.on_step_late() for robot in self.robots]   # each re-sends step 0
                if any(late):
                    break
                continue
            commands = [robot.next_command(n) for robot in self.robots]
            stepped = self.fleet.step(commands)
            n += 1
            rs = [robot.finish_step(r, n) for robot, r in zip(self.robots, stepped, strict=True)]
        out = [robot.end_run(r, n) for robot, r in zip(self.robots, rs, strict=True)]
        self._last = out
        return out

    def _wait_for_step(self, n: int, timeout: float) -> bool:
        """Whether step ``n`` may run: in lockstep, once every robot's firmware has granted
        it (a robot whose firmware a fault has cut does not hold it up); else the one clock."""
        first = self.robots[0]
        if first.lockstep is None:
            return first.clock.wait_for_step(n, timeout=timeout)
        deadline = time.monotonic() + timeout
        cut = [robot.firmware_cut() for robot in self.robots]
        for robot, unpaced in zip(self.robots, cut, strict=True):
            if unpaced:
                continue
            if not robot.clock.wait_for_step(n, timeout=max(0.0, deadline - time.monotonic())):
                return False
        for robot, unpaced in zip(self.robots, cut, strict=True):
            if unpaced:
                robot.unpaced_step()        # counted once the step runs
        return True
