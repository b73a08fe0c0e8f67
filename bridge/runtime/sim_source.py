"""The simulated robot as the source: steps the simulator on a clock and serves every bus and
Zenoh (one of the two :class:`runtime.source.Source` implementations; the other is
:mod:`runtime.real_source`).

Threads (all owned here, all joined by :meth:`SimulatedRobotSource.close`):

- the **simulation loop** (the caller's thread, :meth:`SimulatedRobotSource.run`): waits for step
  ``n`` on the clock, applies the wheel command in force (:class:`runtime.robot_io.MotorArbiter`),
  steps the simulator, and sends each reading that became due: binary range frames on the
  rangefinders pty, CAN ``WheelOdometry`` / ``Gyro`` on every CAN interface, MAVLink
  ``SCALED_IMU`` (and ``HEARTBEAT`` at ``heartbeat_hz``), and the Zenoh messages. Sample times are
  simulation times; a reading is on the wire within the step that produced it.
- one **reader thread per input**: K-Team commands (answered at once from the latest readings)
  and CAN frames from each interface (``MotorCommand``). What clients send on the rangefinders
  pty and the MAVLink link is read by the simulation loop itself, every ``DRAIN_PERIOD_S`` of
  wall time, as it is the only thread using those transports. Input that does not decode is
  rejected and counted and changes nothing else. When the client of a pty changes
  (``client_session``), its reader starts afresh: no half line or half packet carries over.

``status`` counters per bus: ``sent`` (writes/frames handed to clients, from the transport),
``received`` (well-formed frames the bridge acted on or accepted), ``rejected`` (input discarded:
by the codec here plus what the transport itself refused), ``dropped`` (output thrown away because
no client was connected or a client could not keep up).
"""

from __future__ import annotations

import heapq
import json
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from functools import partial
from typing import Any

import can
import numpy as np
from koala_bridge.core.topics import FaultEventMessage, StatusMessage, TruthPose, WorldMessage
from koala_bridge.drivers.kteam import KteamLimits, LineSplitter, parse_command
from koala_bridge.drivers.mavlink_codec import CompassDecoder, CompassEncoder, MavlinkIdentity
from koala_bridge.drivers.messages import (
    CompassSample,
    GyroFrame,
    MotorCommandFrame,
    RangeFrame,
    RangeKind,
    Reject,
    TransportError,
    WheelOdometryFrame,
)
from koala_bridge.drivers.rangeframes import NO_ECHO, encode_range_frame
from koala_bridge.drivers.transports.socketcand import SocketcandServer
from koala_bridge.estimation.messages import KEY_CELL, KEY_GRID, KEY_OCCUPANCY, KEY_POSE
from koala_bridge.runtime.buses import LockedByteLink, OpenBuses, open_buses
from koala_bridge.runtime.clock import Clock, LockstepClock, make_clock
from koala_bridge.runtime.counters import BusCounters
from koala_bridge.runtime.endpoints import Endpoints, endpoints_of, write_endpoints_file
from koala_bridge.runtime.faults import FaultInjector, fault_spec, faults_from_config
from koala_bridge.runtime.koala25_io import Koala25Responder
from koala_bridge.runtime.localisation import LocalisationNode
from koala_bridge.runtime.robot_io import KteamResponder, MotorArbiter, RobotPort, RobotUnits
from koala_bridge.runtime.settings import BridgeSettings, ConfigError
from koala_bridge.runtime.source import READ_TIMEOUT_S, Tap, start_reader, until_text
from koala_bridge.runtime.wire import CanWire, SerialWire, serial_time_s
from koala_bridge.runtime.zenoh_io import ZENOH_BUS, ZenohLink, sensor_topics, truth_pose
from koala_bridge.sim.simulator import Simulator
from koala_bridge.sim.types import Readings, WheelCommand

#: Held at t = 0, step 0 goes again to a bus whose clients cannot be seen (UDP) this often (s
#: of wall time): a firmware that starts listening gets it within this, and one that listens
#: without reading (a debugger's stop) is not flooded (a socket buffer holds ~300 datagrams).
UNSEEN_RESEND_S = 0.25

log = logging.getLogger(__name__)

DRAIN_PERIOD_S = 0.02       # wall time between reads of the output links' input
GYRO_LIMIT = 20.0           # rad/s: the DBC range of Gyro.yaw_rate
SYNC_TIMEOUT_S = 1.0        # lockstep: longest wait for socketcand to hand a cycle's frames over


class SimulatedRobotSource:
    """Simulator + buses + Zenoh for one run: a :class:`runtime.source.Source` (``open()``, then
    ``run(stop)``, then ``close()``).

    Args:
        config: the whole configuration (parsed TOML after command-line overrides).
        settings: its bridge sections, typed (:meth:`BridgeSettings.from_config`).
        seed: the run's seed; None uses ``[sim] seed``.
        clock: paces the loop; by default the clock named in ``[run] clock``.
        tap: optional recorder of Zenoh messages and bus frames.
        zenoh_session: an open Zenoh session to publish through (a fleet's robots share one);
            None opens one from ``[zenoh]``.
    """

    def __init__(
        self,
        config: Mapping[str, Any],
        settings: BridgeSettings,
        seed: int | None = None,
        clock: Clock | None = None,
        tap: Tap | None = None,
        zenoh_session: Any = None,
    ) -> None:
        self.settings = settings
        self.sim = Simulator(config)
        self.zenoh_session = zenoh_session      # shared by a fleet's robots; None: our own
        self.seed = seed
        self.dt = self.sim.dt
        ls = settings.lockstep
        if clock is None:
            steps = ls.steps_per_cycle(self.dt) if settings.run.clock == "lockstep" else 1
            clock = make_clock(settings.run.clock, self.dt, steps, ls.on_quiet,
                               ls.quiet_timeout_s)
        self.clock = clock
        #: the lockstep clock when the run is paced by the firmware (docs/protocols.md)
        self.lockstep: LockstepClock | None = clock if isinstance(clock, LockstepClock) else None
        self.tap = tap
        robot = self.sim.config.robot
        self.units = RobotUnits(robot.ticks_per_metre, robot.speed_unit_s)
        self.counters = BusCounters()
        self.arbiter = MotorArbiter(settings.buses.motor_watchdog_s)
        self.port = RobotPort(n_ir=len(self.sim.config.sensors.ir.poses))
        # [buses.kteam] dialect: the command set the K-Team pty speaks
        self.kteam: KteamResponder | Koala25Responder
        if settings.buses.kteam_dialect == "koala25":
            self.kteam = Koala25Responder(self.port, self.arbiter, self.units,
                                          robot.max_wheel_speed_mps, robot.battery.chemistry)
        else:
            self.kteam = KteamResponder(
                self.port,
                self.arbiter,
                self.units,
                KteamLimits(max_speed=settings.buses.kteam_max_speed, sensors=self.port.n_ir),
            )
        self.can_codec = settings.buses.can.codec()   # [buses.can] dbc
        # [lockstep] cycle_bus/cycle_message: what closes a control cycle
        self._cycle_letter = ls.cycle_message if ls.cycle_bus == "kteam" else None
        self._cycle_can_id: int | None = None
        if self.lockstep is not None and ls.cycle_bus == "kteam":
            if ls.cycle_message not in self.kteam.specs:
                raise ConfigError(
                    f"[lockstep] 'cycle_message' {ls.cycle_message!r} is not a command of the "
                    f"{settings.buses.kteam_dialect} dialect ([buses.kteam] dialect); its "
                    f"commands: {' '.join(sorted(self.kteam.specs))} (the wheel command is D)"
                )
        if self.lockstep is not None and ls.cycle_bus == "can":
            ids = self.can_codec.frame_ids
            # the robot acts on one CAN message: the wheel command the firmware sends
            command = ids.get("MotorCommand")
            if ids.get(ls.cycle_message) != command:
                what = ("a message the robot sends, not one the firmware sends"
                        if ls.cycle_message in ids else "not a message of the DBC")
                raise ConfigError(
                    f"[lockstep] 'cycle_message' {ls.cycle_message!r} is {what}; the firmware's "
                    f"message in the DBC is 'MotorCommand'"
                )
            self._cycle_can_id = command
        # [[faults]] and --fault (docs/faults.md): drawn from the run's seed
        self.faults = FaultInjector(faults_from_config(config),
                                    self.sim.config.sim.seed if seed is None else seed)
        self.faults.check(self._sensor_counts())
        self._offline: set[str] = set()      # buses a 'disconnect' fault has taken away
        self._bus_off = False                # a 'bus_off' fault: the robot's CAN controller is off
        # Wire timing (docs/wire-timing.md): frames leave when their bits have crossed the line
        b = settings.buses
        self._serial_wires: dict[str, SerialWire] = {}
        if b.kteam_wire_timing:
            line = self.kteam.dialect.line
            self._serial_wires["kteam"] = SerialWire.from_line(line)
        if b.rangefinders_wire_timing:
            self._serial_wires["rangefinders"] = SerialWire(b.rangefinders_baud,
                                                            b.rangefinders_framing)
        if b.mavlink.wire_timing:
            self._serial_wires["mavlink"] = SerialWire(b.mavlink.baud, b.mavlink.framing)
        self._can_wire = CanWire(b.can.bitrate) if b.can.wire_timing else None
        # frames waiting for their time: (t_write, seq, bus, write)
        self._pending: list[tuple[float, int, str, Callable[[float], None]]] = []
        self._pending_seq = 0
        self._shaped = self.faults.active or bool(self._serial_wires) or self._can_wire is not None
        # Step 0's bus frames, re-sent while lockstep holds at t = 0 (before the first command),
        # kept by the loop's thread (_capture_thread) while it emits step 0
        self._initial_frames: list[tuple[str, Callable[[], None]]] | None = None
        self._client_marks: dict[str, object] = {}
        self._unseen_resent: dict[str, float] = {}  # bus -> monotonic time of its last re-send
        self._unpaced_steps = 0             # lockstep steps taken while a fault cut the firmware
        self._awaiting_reconnect = False    # the cycle bus came back: the firmware may reconnect
        self._firmware_seen = False         # a client has been on the cycle bus
        self._capture_thread: int | None = None
        mav = settings.buses.mavlink
        # [buses.mavlink] signing_key_file: None = unsigned (a bad key file: ConfigError here)
        self.mav_signing = mav.signing(time.time())
        self.mav_encoder = CompassEncoder(
            MavlinkIdentity(mav.system_id, mav.component_id), self.mav_signing
        )
        self.buses = OpenBuses()
        self.zenoh: ZenohLink | None = None
        self.endpoints: Endpoints | None = None
        self._stop_readers = threading.Event()
        self._kteam_lock = threading.Lock()     # a K-Team command and its reply vs pushed lines
        self._readers: list[threading.Thread] = []
        self._range_seq = {RangeKind.IR: 0, RangeKind.SONAR: 0}
        self._last_readings: Readings | None = None
        self._initial: Readings | None = None
        self._last: Readings | None = None
        self._write_errors: set[str] = set()
        self._drains: list[Callable[[], None]] = []
        self._last_drain = 0.0
        # Frames put on the buses, for the localisation node: it reads them after the step's
        # every bus and Zenoh message is out (its work would delay the buses written after it).
        self._to_localise: deque[tuple[str, float, bytes, dict[str, Any]]] = deque()
        zs = settings.zenoh
        self._pose_period = max(1, round(1.0 / (zs.pose_rate_hz * self.dt)))
        self._status_period = max(1, round(1.0 / (zs.status_rate_hz * self.dt)))
        self._heartbeat_period = max(1, round(1.0 / (mav.heartbeat_hz * self.dt)))
        # The estimator node ([localisation]): fed with the frames this service puts on the
        # buses (_send_bytes, _send_can) and the camera's observations (no bus); None when off.
        self.localisation = LocalisationNode.from_config(
            config, self.sim.config, self._publish_estimate, can_codec=self.can_codec,
            kteam_dialect=settings.buses.kteam_dialect,
        )

    # -- lifecycle ---------------------------------------------------------------------------

    def world_answer(self) -> dict[str, Any]:
        """The answer of the ``<prefix>/world`` queryable: the world plus ``robot``."""
        return WorldMessage.of(self.sim.world, self.sim.robot_description()).to_json()

    def open(self) -> Endpoints:
        """Open every bus and the Zenoh session, start the readers; return where clients connect.

        When this returns, every endpoint accepts clients.
        """
        try:
            # Reset first: the first step loads compiled ray casting, so data flows as soon as
            # the endpoints are announced.
            self._initial = self.sim.reset(self.seed)
            self.buses = open_buses(self.settings.buses)
            self.zenoh = ZenohLink(self.settings.zenoh, self.world_answer, self.counters,
                                   session=self.zenoh_session)
            self._register_step_queryable()
            self._register_fault_queryable()
            self._start_readers()
        except BaseException:
            self.close()
            raise
        self.endpoints = endpoints_of(
            self.buses, self.settings, zenoh_listening=self._zenoh_listening())
        return self.endpoints

    def _zenoh_listening(self) -> tuple[str, ...] | None:
        return self.zenoh.listening if self.zenoh is not None else None

    def close(self) -> None:
        """Stop the readers, close every transport and the Zenoh session. Idempotent."""
        self._stop_readers.set()
        for t in self._readers:
            t.join(timeout=5.0)
            if t.is_alive():
                log.warning("reader thread %s did not stop", t.name)
        self._readers.clear()
        self.buses.close()
        if self.zenoh is not None:
            self.zenoh.close()
            self.zenoh = None

    def __enter__(self) -> SimulatedRobotSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- simulation loop ---------------------------------------------------------------------

    def run(self, stop: threading.Event, duration_s: float | None = None) -> Readings:
        """Step until ``stop`` is set or ``duration_s`` simulation seconds have run (None: the
        configured ``[run] duration_s``; 0: no limit). Returns the last readings."""
        duration = self.settings.run.duration_s if duration_s is None else duration_s
        last_step = round(duration / self.dt) if duration > 0 else None
        r = self.begin_run()
        n = 0
        wait = self.hold_wait_s()
        lockstep = self.lockstep
        while not stop.is_set() and (last_step is None or n < last_step):
            if lockstep is not None and self.unpaced_step():
                # A fault has cut the firmware's command line: it cannot pace the run, so time
                # goes on without it until the line is back (docs/protocols.md §6).
                pass
            elif not self.clock.wait_for_step(n + 1, timeout=wait):
                if self.on_step_late():
                    break
                continue
            r = self.finish_step(self.sim.step(self.next_command(n)), n + 1)
            n += 1
        return self.end_run(r, n)

    # The loop's phases, also driven by a fleet (runtime/fleet_source.py): begin_run, then per
    # step next_command -> (the simulator steps) -> finish_step, then end_run.

    def use_initial(self, r: Readings) -> None:
        """Serve ``r`` as step 0 (a fleet's reset, where the robot sees the others)."""
        self._initial = r

    def begin_run(self) -> Readings:
        """Step 0: reset (unless open() did), declare the recording's channels, start the
        clock, put step 0 on every bus; in lockstep, hold its frames for the firmware."""
        if self.zenoh is None:
            raise RuntimeError("open() the service before run()")
        r = self._initial if self._initial is not None else self.sim.reset(self.seed)
        self._initial = None
        r = self._faulted(r)
        if self.tap is not None:
            self.tap.declare(self._published_keys(r), self._tap_buses())
        self.clock.start()
        lockstep = self.lockstep
        if lockstep is not None:
            self._initial_frames = []     # _send_bytes/_send_can keep step 0's frames
            self._capture_thread = threading.get_ident()
        self._emit(r, 0)
        self._after_step(r.t)
        if lockstep is not None:
            # Held at t = 0 while the firmware starts: step 0's frames have time to cross their
            # wires (wire timing), those that need less than a step are there before its first
            # command (docs/protocols.md §6 rule 1).
            self._release_until(r.t, self.dt * 0.999)
        self._capture_thread = None
        if lockstep is not None:
            for bus, _ in self._initial_frames or ():
                self._client_marks[bus] = self._client_mark(bus)   # who has step 0 already
        self._last_readings = r
        return r

    def hold_wait_s(self) -> float:
        """How long the loop waits for a step before it looks after the held frames."""
        if self.lockstep is not None:
            # holding at t = 0: re-send step 0's frames every period of wall time
            return min(READ_TIMEOUT_S, max(self.settings.lockstep.period_s, 0.005))
        return READ_TIMEOUT_S

    def on_step_late(self) -> bool:
        """The next step was not granted in time: re-send step 0 while held; True when the
        firmware has gone and the run ends."""
        lockstep = self.lockstep
        if lockstep is None:
            return False
        if not lockstep.engaged:
            self._resend_initial(held=True)
        if self._firmware_left():
            t = self._last_readings.t if self._last_readings is not None else 0.0
            log.info("lockstep: the firmware has disconnected at t = %.3f s; the run ends", t)
            return True
        return False

    def firmware_cut(self) -> bool:
        """Lockstep: whether a fault has cut the engaged firmware's command line."""
        return self.lockstep is not None and self.lockstep.engaged and self._cycle_bus_cut()

    def unpaced_step(self) -> bool:
        """Lockstep: whether a fault has cut the firmware's command line, so that the next step
        runs without its grant (counted; docs/protocols.md §6)."""
        if self.firmware_cut():
            self._unpaced_steps += 1
            return True
        return False

    def next_command(self, n: int) -> WheelCommand:
        """Before step ``n + 1``: the faults act on the simulator and the wheel command in
        force."""
        if self.lockstep is not None and n == 0:
            # engaged: a client that came since the last re-send gets step 0 before step 1
            self._resend_initial()
        if self.faults.active:
            self.faults.apply_to_sim(self.sim, self.sim.t)   # kidnap, wheel slip
        return self.arbiter.command(self.sim.t)

    def finish_step(self, r: Readings, n: int) -> Readings:
        """Step ``n``'s readings ``r`` to every bus and Zenoh; returns them as sent."""
        r = self._faulted(r)
        self._emit(r, n)
        self._after_step(r.t)
        if self.lockstep is not None:
            self.lockstep.step_done(n)
        return r

    def end_run(self, r: Readings, n: int) -> Readings:
        """After the last step ``n``: wake the waiters, the last K-Team replies to the
        estimator, the final status."""
        if self.lockstep is not None:
            self.lockstep.wake()
        self._localise()  # K-Team replies since the last step
        # The final counters, unless the last step just published them (one status per t).
        if n == 0 or n % self._status_period != 0:
            self._publish_status(r.t)
        self._last = r
        return r

    def describe(self) -> str:
        run = self.settings.run
        if self.lockstep is not None:
            ls = self.settings.lockstep
            bus = "K-Team" if ls.cycle_bus == "kteam" else "CAN"
            quiet = ("waits for it" if ls.on_quiet == "wait"
                     else f"steps after {ls.quiet_timeout_s:g} s of silence")
            return (f"Simulating in lockstep: {ls.period_s:g} s per {bus} {ls.cycle_message} "
                    f"from the firmware (held at t = 0 until its first one; a silent firmware "
                    f"{quiet}) {until_text(run.duration_s)}.")
        return f"Simulating ({run.clock} clock) {until_text(run.duration_s)}."

    # -- lockstep ----------------------------------------------------------------------------

    def _resend_initial(self, held: bool = False) -> None:
        """Put step 0's frames again on each bus where a client has come since they were last
        sent (for a firmware that waits for data before its first command; a client there
        before sees them again), and where clients cannot be seen (UDP): at the firmware's
        first command, and while ``held`` at t = 0 every :data:`UNSEEN_RESEND_S` of wall time.
        Not every poll: a firmware that has bound its port but is not reading yet (starting
        on a loaded machine, or stopped in a debugger) would find its socket's buffer full of
        step 0 and the kernel dropping the samples of the steps it then asks for. Not
        recorded: the recording holds each sample once."""
        # A UDP client of a bridge listening on port 0 (udpout:) says hello first: read it, so
        # that step 0 goes to it before the firmware's first command.
        self._drain_output_links()
        now = time.monotonic()
        due: dict[str, bool] = {}
        for bus, resend in self._initial_frames or ():
            if bus not in due:
                mark = self._client_mark(bus)
                if mark is None:
                    due[bus] = not held or (
                        now - self._unseen_resent.get(bus, -math.inf) >= UNSEEN_RESEND_S)
                    if due[bus]:
                        self._unseen_resent[bus] = now
                else:
                    due[bus] = mark != self._client_marks.get(bus) and bool(mark)
                self._client_marks[bus] = mark
            if due[bus]:
                resend()

    def _client_mark(self, bus: str) -> object:
        """What changes when a new client comes on ``bus`` (falsy: none there), or None where
        the transport cannot tell (UDP: re-sent every poll)."""
        link = self.buses.byte_links().get(bus)
        if link is not None:
            if link.is_datagram:
                return None
            return (link.client_session, True) if link.has_client() else 0
        transport = self.buses.can.get(bus)
        if isinstance(transport, SocketcandServer):
            return transport.stats.clients
        return 0    # python-can interfaces (virtual, slcan): clients that were there all along

    def _firmware_left(self) -> bool:
        """Whether the firmware has gone: a client was on the cycle bus and is no more (before
        or after its first command). Never for a run nobody's client has joined (a harness
        stepping over Zenoh) or where clients cannot be seen (python-can interfaces); after a
        fault cut the line, only once the firmware has come back and left again."""
        wrote = False
        if self.settings.lockstep.cycle_bus == "kteam":
            link = self.buses.kteam
            present = link is not None and link.has_client()
            # a client wrote: it was there even if no poll caught it connected (one that asks
            # once and leaves, on a loaded machine)
            wrote = link is not None and link.stats.received > 0
        else:
            servers = [t for t in self.buses.can.values() if isinstance(t, SocketcandServer)]
            present = any(t.stats.clients > 0 for t in servers)
        if present:
            self._firmware_seen = True
            self._awaiting_reconnect = False
            return False
        # a firmware that sent cycle messages was there, even if no poll caught it connected
        seen = self._firmware_seen or wrote or (
            self.lockstep is not None and self.lockstep.cycles > 0)
        return seen and not self._awaiting_reconnect

    def _cycle_bus_cut(self) -> bool:
        """A ``disconnect`` fault has taken the firmware's command bus away."""
        return bool(self._offline) and self.settings.lockstep.cycle_bus in self._offline

    def _wait_lockstep(self, wait: Callable[[float], bool]) -> bool:
        """Run a lockstep wait in slices so that close() is not held up; False if stopping."""
        while not self._stop_readers.is_set():
            if wait(READ_TIMEOUT_S):
                return True
        return False

    def _run_cycles(self, cycles: int = 1, explicit: bool = False) -> bool:
        """Grant ``cycles`` periods (the firmware's cycle message, or an explicit step) and wait
        until they have been simulated and their frames handed to every transport; False if
        the bridge is stopping meanwhile."""
        lockstep = self.lockstep
        assert lockstep is not None
        target = lockstep.grant(cycles, explicit=explicit)
        if not self._wait_lockstep(lambda timeout: lockstep.wait_done(target, timeout)):
            return False
        # socketcand keeps what a client's socket did not take at once for its service thread:
        # wait for it (the other transports have written everything already)
        for transport in self.buses.can.values():
            if isinstance(transport, SocketcandServer):
                transport.sync(SYNC_TIMEOUT_S)
        return True

    def _at_cycle_boundary(self) -> bool:
        """Lockstep: wait until every granted step ran, so that a command takes effect (and a
        request is answered) at a cycle boundary. True at once in the other clocks."""
        if self.lockstep is None:
            return True
        return self._wait_lockstep(self.lockstep.wait_idle)

    def _register_step_queryable(self) -> None:
        """``<prefix>/lockstep/step`` (``[zenoh] remote_commands``): grant cycles from outside."""
        if self.zenoh is None or not self.settings.zenoh.remote_commands:
            return
        lockstep = self.lockstep

        def step(payload: bytes) -> dict[str, Any]:
            if lockstep is None:
                raise ValueError(f"lockstep/step: the bridge runs the {self.settings.run.clock} "
                                 "clock; only --clock lockstep is stepped")
            cycles = 1
            if payload.strip():
                try:
                    body = json.loads(payload)
                except ValueError as e:
                    raise ValueError(f"lockstep/step: payload is not JSON: {e}") from None
                if not isinstance(body, dict) or set(body) - {"cycles"}:
                    raise ValueError('lockstep/step: payload must be {"cycles": N} or empty')
                cycles = body.get("cycles", 1)
                if isinstance(cycles, bool) or not isinstance(cycles, int) or not (
                        1 <= cycles <= 1_000_000):
                    raise ValueError(f"lockstep/step: 'cycles' must be an integer 1..1000000, "
                                     f"got {cycles!r}")
            if not (self._at_cycle_boundary() and self._run_cycles(cycles, explicit=True)):
                raise ValueError("lockstep/step: the bridge is stopping")
            return {"t": self.port.t, "step": lockstep.done, "cycles": cycles}

        self.zenoh.command_queryable("lockstep/step", step)

    def summary(self) -> str:
        t = 0.0 if self._last is None else self._last.t
        rtf = self.clock.real_time_factor(t)
        return f"Stopped at t = {t:.3f} s (real-time factor {rtf:.2f})."

    def _published_keys(self, r: Readings) -> list[str]:
        """Every Zenoh key this run publishes (``r``: the step-0 readings, where every sensor
        reads), in the order a recording lists them."""
        keys = [TruthPose.TOPIC, *sensor_topics(r), StatusMessage.TOPIC]
        if self.localisation is not None:
            keys += [KEY_POSE, KEY_CELL, KEY_GRID, KEY_OCCUPANCY]
        if self.faults.active or self.settings.zenoh.remote_commands:
            keys.append(FaultEventMessage.TOPIC)
        return keys

    def _tap_buses(self) -> list[str]:
        """The recorder's names of the buses this run serves."""
        names = list(self.buses.byte_links()) + (["can"] if self.buses.can else [])
        return [_tap_bus(name) for name in names]

    def _emit(self, r: Readings, n: int) -> None:
        """Hand the readings of step ``n`` to every bus and to Zenoh."""
        self.port.update(r)
        self._last_readings = r
        if self.buses.rangefinders is not None:
            if r.ir is not None:
                self._send_range(RangeKind.IR, r.t, _ir_counts(r.ir.counts))
            if r.sonar is not None:
                self._send_range(RangeKind.SONAR, r.t, _sonar_mm(r.sonar.ranges))
        if self.buses.can:
            if r.odometry is not None:
                left, right = self.port.robot_counters(
                    (int(r.odometry.left_ticks), int(r.odometry.right_ticks))
                )
                self._send_can(WheelOdometryFrame(left, right), r.t)
            if r.gyro is not None and math.isfinite(r.gyro.yaw_rate):
                rate = max(-GYRO_LIMIT, min(GYRO_LIMIT, float(r.gyro.yaw_rate)))
                self._send_can(GyroFrame(rate), r.t)
        if self.buses.mavlink is not None:
            if n % self._heartbeat_period == 0:
                self._send_bytes("mavlink", self.buses.mavlink, self.mav_encoder.heartbeat(), r.t)
            if r.compass is not None:
                m = r.compass.field_uT
                t_ms = int(round(r.t * 1000))
                sample = CompassSample(t_ms, float(m[0]), float(m[1]), float(m[2]))
                self._send_bytes(
                    "mavlink", self.buses.mavlink, self.mav_encoder.scaled_imu(sample), r.t
                )
        if self.buses.kteam is not None:
            # What the robot pushes unasked, never between a command and its reply (after the
            # reply to A,0 nothing more is pushed): one lock with the K-Team reader.
            with self._kteam_lock:
                for line in self.kteam.auto_lines(r.t):
                    self._send_bytes("kteam", self.buses.kteam,
                                     self.kteam.dialect.format_reply(line), r.t)
        self._publish(r, n)
        self._localise(r.camera.observations if r.camera is not None else None, r.t)
        self._drain_output_links()

    def _localise(self, camera: Any = None, t: float = 0.0) -> None:
        """Feed the localisation node what went on the buses since the last call, in order, then
        the camera's observations of ``t`` (the camera has no bus)."""
        node = self.localisation
        queue = self._to_localise
        if node is None:
            queue.clear()
            return
        while queue:  # popleft: a K-Team reply may be appended by its reader meanwhile
            bus, frame_t, data, fields = queue.popleft()
            node.on_frame(bus, "from_robot", frame_t, data, **fields)
        if camera is not None:
            node.on_camera(t, camera)

    def _publish(self, r: Readings, n: int) -> None:
        assert self.zenoh is not None
        topics = sensor_topics(r, None if r.ir is None else r.ir.truth_incidence)
        if n % self._pose_period == 0:
            topics = {TruthPose.TOPIC: truth_pose(r), **topics}
        for suffix, typed in topics.items():
            self._put(suffix, r.t, typed.to_json())
        if n % self._status_period == 0 and n > 0:
            self._publish_status(r.t)

    def status(self, t: float) -> dict[str, Any]:
        """The ``status`` message: real-time factor and per-bus counters."""
        counts = self.counters.snapshot()
        buses: dict[str, dict[str, int]] = {}
        for name, st in self.buses.stats().items():
            mine = counts.get(name, {"sent": 0, "received": 0, "rejected": 0})
            buses[name] = {
                "sent": st.sent,
                "received": mine["received"],
                "rejected": mine["rejected"] + st.rejected,
                "dropped": st.dropped,
            }
        if ZENOH_BUS in counts:
            buses[ZENOH_BUS] = {**counts[ZENOH_BUS], "dropped": 0}
        return StatusMessage(
            t,
            self.clock.real_time_factor(t),
            buses,
            motor_command_source=self.arbiter.source,
            leds=tuple(self.port.led_states()),  # K-Team L: [lateral, frontal], 0 off / 1 on
            localisation=None if self.localisation is None else self.localisation.snapshot(),
            faults=self.faults.counts() if self.faults.active else None,
            bus_load=self._bus_load(t),
            lockstep=None if self.lockstep is None else {
                "engaged": self.lockstep.engaged, "cycles": self.lockstep.cycles,
                "explicit": self.lockstep.explicit, "misses": self.lockstep.misses,
                "unpaced_steps": self._unpaced_steps,
            },
        ).to_json()

    def _bus_load(self, t: float) -> dict[str, float] | None:
        """Wire timing: each paced bus's busy fraction over the last status period."""
        window = 1.0 / self.settings.zenoh.status_rate_hz
        load: dict[str, float] = {}
        if self._can_wire is not None and t > 0:
            load["can"] = round(self._can_wire.load(min(window, t, self._can_wire.history_s),
                                                    t), 6)
        for bus, wire in self._serial_wires.items():
            load[bus] = round(wire.load(min(window, t), t), 6) if t > 0 else 0.0
        return load or None

    def _publish_status(self, t: float) -> None:
        if self.zenoh is None:
            return
        self._put(StatusMessage.TOPIC, t, self.status(t))

    def _publish_estimate(self, suffix: str, msg: dict[str, Any]) -> None:
        """The localisation node's output: Zenoh and the recorder, like every other key."""
        self._put(suffix, msg["t"], msg)

    def _put(self, suffix: str, t: float, msg: dict[str, Any]) -> None:
        """Publish ``msg`` on Zenoh (a failure is counted; the loop and the other buses go on)
        and record it."""
        if self.zenoh is not None:
            try:
                self.zenoh.publish(suffix, msg)
            except TransportError as e:
                self._write_failed(ZENOH_BUS, e)
        if self.tap is not None:
            self.tap.record(suffix, t, msg)

    # -- faults and wire timing --------------------------------------------------------------

    def _after_step(self, t: float) -> None:
        """After step ``t``'s readings went out: buses a fault takes away or gives back, CAN
        error frames, the frames whose time has come, and the fault events."""
        if not self._shaped:
            return
        faults = self.faults
        if faults.active:
            for msg in faults.can_error_frames(t):
                self._write_can(msg, msg.timestamp, error=True)
        self._release_until(t, t)
        if faults.active:
            for event in faults.events():
                self._put(FaultEventMessage.TOPIC, event.t, event.to_json())

    def _release_until(self, t: float, until: float) -> None:
        """Write (at simulated time ``t``) the queued frames whose time is at or before
        ``until``: delayed by a fault or still on their wire."""
        while self._pending and self._pending[0][0] <= until + 1e-12:
            _, _, _, write = heapq.heappop(self._pending)
            write(t)
        if self._can_wire is not None:
            for _t_valid, msg, _tag in self._can_wire.release(until):
                self._write_can(msg, t)

    def _register_fault_queryable(self) -> None:
        """``<prefix>/faults/schedule`` (``[zenoh] remote_commands``): add a fault at run time.
        The payload is one ``[[faults]]`` table as JSON; the answer names the fault."""
        if self.zenoh is None or not self.settings.zenoh.remote_commands:
            return

        def schedule(payload: bytes) -> dict[str, Any]:
            try:
                table = json.loads(payload or b"null")
            except ValueError as e:
                raise ValueError(f"faults/schedule: payload is not JSON: {e}") from None
            try:
                spec = fault_spec(table, "faults/schedule", len(self.faults.specs) + 1)
                FaultInjector([spec], 0).check(self._sensor_counts())
                if not self._at_cycle_boundary():
                    raise ValueError("faults/schedule: the bridge is stopping")
                self.faults.add(spec)
            except ConfigError as e:
                raise ValueError(str(e)) from None
            self._shaped = True
            name = self.faults.specs[-1].name
            log.info("fault scheduled over Zenoh: %s", name)
            return {"name": name, "t": self.port.t}

        self.zenoh.command_queryable("faults/schedule", schedule)

    def _sensor_counts(self) -> dict[str, int]:
        sensors = self.sim.config.sensors
        return {"ir": len(sensors.ir.poses), "sonar": len(sensors.sonar.poses), "encoders": 2}

    def _faulted(self, r: Readings) -> Readings:
        """A step's readings with the sensor faults applied, and the buses a fault takes away
        or gives back (disconnect, bus-off) set for their frames to go out."""
        faults = self.faults
        if not faults.active:       # (faults may be added at run time: faults/schedule)
            return r
        r = faults.on_readings(r)
        for bus in self._fault_buses():
            gone = faults.disconnected(bus, r.t)
            if gone != (bus in self._offline):
                self._set_offline(bus, gone)
        if self.buses.can:
            self._bus_off = faults.bus_off("can", r.t)
        return r

    def _fault_buses(self) -> list[str]:
        present = [name for name in ("kteam", "rangefinders", "mavlink")
                   if name in self.buses.byte_links()]
        return present + (["can"] if self.buses.can else [])

    def _set_offline(self, bus: str, offline: bool) -> None:
        """Take ``bus`` away (fault ``disconnect``) or give it back."""
        if offline:
            self._offline.add(bus)
            if self.lockstep is not None and bus == self.settings.lockstep.cycle_bus:
                self._awaiting_reconnect = True
        else:
            self._offline.discard(bus)
        links = (list(self.buses.can.values()) if bus == "can"
                 else [self.buses.byte_links()[bus]])
        for link in links:
            try:
                link.set_offline(offline)
            except (NotImplementedError, TransportError) as e:
                self._write_failed(bus, e)
        log.info("fault: %s %s", bus, "offline" if offline else "back online")
        if not offline and self.endpoints is not None:
            # a pty comes back as a new device (like a USB serial adapter replugged): clients
            # find its path in the endpoints, rewritten
            self.endpoints = endpoints_of(
                self.buses, self.settings, zenoh_listening=self._zenoh_listening())
            if self.settings.run.endpoints_file:
                try:
                    write_endpoints_file(self.settings.run.endpoints_file, self.endpoints)
                except OSError as e:
                    log.warning("cannot rewrite the endpoints file: %s", e)

    def _later(self, t_write: float, bus: str, write: Callable[[float], None]) -> None:
        heapq.heappush(self._pending, (t_write, self._pending_seq, bus, write))
        self._pending_seq += 1

    def _shape_bytes(self, bus: str, link: LockedByteLink, data: bytes, t: float) -> None:
        """A frame the robot pushes (loop thread) through the faults and the wire."""
        deliveries = [(t, data)]
        if self.faults.active:
            if bus in self._offline:
                return
            deliveries = [(d.t, d.data) for d in self.faults.on_frame(bus, t, data)]
        wire = self._serial_wires.get(bus)
        for t_ready, payload in deliveries:
            t_write = t_ready if wire is None else wire.submit(t_ready, len(payload))
            if t_write <= t + 1e-12:
                self._write_bytes(bus, link, payload, t)
            else:
                self._later(t_write, bus, partial(self._write_bytes, bus, link, payload))

    def _send_reply(self, link: LockedByteLink, data: bytes, t: float) -> None:
        """A K-Team reply (reader thread): faults drop, corrupt or duplicate it, but never
        hold it back (a firmware waiting for it holds simulated time in lockstep); with wire
        timing it takes its time on the line in real time, and occupies the line in simulated
        time in the other clocks."""
        deliveries = [data]
        if self.faults.active:
            if "kteam" in self._offline:
                return
            deliveries = [d.data for d in self.faults.on_frame("kteam", t, data, reply=True)]
        wire = self._serial_wires.get("kteam")
        for payload in deliveries:
            if wire is not None:
                wire.submit(t, len(payload))
                if self.settings.run.clock == "realtime":
                    time.sleep(serial_time_s(len(payload), wire.baud, wire.framing))
            self._write_bytes("kteam", link, payload, t)

    # -- output helpers ----------------------------------------------------------------------

    def _send_range(self, kind: RangeKind, t: float, readings: tuple[int, ...]) -> None:
        seq = self._range_seq[kind]
        self._range_seq[kind] = (seq + 1) & 0xFFFF
        t_us = int(round(t * 1e6)) & 0xFFFFFFFF
        data = encode_range_frame(RangeFrame(kind, seq, t_us, readings))
        assert self.buses.rangefinders is not None
        self._send_bytes("rangefinders", self.buses.rangefinders, data, t)

    def _send_bytes(self, bus: str, link: LockedByteLink, data: bytes, t: float) -> None:
        """A frame the robot pushes at ``t`` (loop thread)."""
        if self._shaped:
            self._shape_bytes(bus, link, data, t)
        else:
            self._write_bytes(bus, link, data, t)

    def _write_bytes(self, bus: str, link: LockedByteLink, data: bytes, t: float) -> None:
        try:
            link.write(data)
        except TransportError as e:
            self._write_failed(bus, e)
            return
        if self._capture_thread is not None and self._capture_thread == threading.get_ident():
            self._keep_initial(bus, lambda: link.write(data))
        if self.tap is not None:
            self.tap.record_frame(_tap_bus(bus), "from_robot", t, data)
        if self.localisation is not None:
            self._to_localise.append((_tap_bus(bus), t, data, {}))

    def _send_can(self, frame: WheelOdometryFrame | GyroFrame, t: float) -> None:
        msg = self.can_codec.encode(frame)
        msg.timestamp = t
        if not self._shaped:
            self._write_can(msg, t)
            return
        deliveries = [(t, msg)]
        if self.faults.active:
            if "can" in self._offline or self._bus_off:
                return
            deliveries = [
                (d.t, msg if d.data == bytes(msg.data) else _with_data(msg, d.data))
                for d in self.faults.on_frame("can", t, bytes(msg.data), msg.arbitration_id)]
            for error in self.faults.can_error_frames(t):   # a corrupt frame's CRC error first
                self._write_can(error, t, error=True)
        for t_ready, m in deliveries:
            if self._can_wire is not None:
                self._can_wire.submit(t_ready, m)
            elif t_ready <= t + 1e-12:
                self._write_can(m, t)
            else:
                self._later(t_ready, "can", partial(self._write_can, m))

    def _write_can(self, msg: can.Message, t: float, error: bool = False) -> None:
        """Put ``msg`` on every CAN interface now (simulated time ``t``); record it and feed the
        estimator (not an error frame)."""
        for name, transport in self.buses.can.items():
            try:
                transport.send(msg)
            except TransportError as e:
                self._write_failed(name, e)
            if self._capture_thread is not None and self._capture_thread == threading.get_ident():
                self._keep_initial(name, partial(transport.send, msg))
        if error:   # an error frame is in the recording as its fault event
            return
        if self.tap is not None:
            self.tap.record_frame(
                "can", "from_robot", t, bytes(msg.data), can_id=msg.arbitration_id,
                extended=msg.is_extended_id,
            )
        if self.localisation is not None:
            self._to_localise.append(
                ("can", t, bytes(msg.data),
                 {"can_id": msg.arbitration_id, "extended": msg.is_extended_id})
            )

    def _keep_initial(self, bus: str, write: Callable[[], object]) -> None:
        def resend() -> None:
            try:
                write()
            except TransportError as e:
                self._write_failed(bus, e)

        assert self._initial_frames is not None
        self._initial_frames.append((bus, resend))

    def _write_failed(self, bus: str, e: Exception) -> None:
        if bus not in self._write_errors:  # log once per bus, the loop goes on
            self._write_errors.add(bus)
            log.warning("writing to %s failed (further failures not logged): %s", bus, e)

    # -- readers -----------------------------------------------------------------------------

    def _start_readers(self) -> None:
        b = self.buses
        if b.kteam is not None:
            self._spawn("kteam", self._kteam_reader(b.kteam))
        for name, transport in b.can.items():
            self._spawn(name, self._can_reader(name, transport))
        # The rangefinders and MAVLink links are written by the simulation loop; it also reads
        # what clients send there (_drain_output_links), so that no transport is used by two
        # threads at once.
        self._drains = []
        if b.rangefinders is not None:
            self._drains.append(self._reject_all_reader("rangefinders", b.rangefinders))
        if b.mavlink is not None:
            self._drains.append(self._mavlink_reader(b.mavlink))

    def _spawn(self, name: str, step: Callable[[], None]) -> None:
        self._readers.append(start_reader(name, step, self._stop_readers))

    def _kteam_reader(self, link: LockedByteLink) -> Callable[[], None]:
        splitter = LineSplitter()
        responder = self.kteam
        dialect = responder.dialect
        session = link.client_session

        def step() -> None:
            nonlocal session
            # Read even when nothing became readable: a client that has just gone may have left
            # input the transport took from the kernel when it saw the hang-up.
            link.wait(READ_TIMEOUT_S)
            data = link.read()
            if link.client_session != session:
                # Another client: the last one's half-sent command must not prefix its first.
                session = link.client_session
                splitter.reset()
            if not data:
                return
            if self.tap is not None:
                self.tap.record_frame("serial/kteam", "to_robot", self.port.t, data)
            for line in splitter.feed(data):
                # lockstep: every command acts at a cycle boundary, on the state simulated so far
                if not self._at_cycle_boundary():
                    return
                with self._kteam_lock:
                    cycle = False
                    cmd = (line if isinstance(line, Reject)
                           else parse_command(line, responder.specs))
                    if isinstance(cmd, Reject):
                        self.counters.rejected("kteam")
                        log.debug("kteam: rejected %s (%s)", cmd.raw, cmd.detail)
                        reply = responder.reject(cmd)
                    else:
                        self.counters.received("kteam")
                        reply = responder.respond(cmd)
                        cycle = self.lockstep is not None and cmd.letter == self._cycle_letter
                    if not cycle:
                        self._reply(link, dialect.format_reply(reply))
                if cycle:
                    # the cycle message: its reply leaves once the period is simulated (what
                    # the robot pushed meanwhile before it)
                    if not self._run_cycles():
                        return
                    with self._kteam_lock:
                        self._reply(link, dialect.format_reply(reply))

        return step

    def _reply(self, link: LockedByteLink, data: bytes) -> None:
        """One K-Team reply, in one write (libkoala reads the 7 bytes of Koala 2.5 'B' in one
        read())."""
        if self._shaped:
            self._send_reply(link, data, self.port.t)
        else:
            self._write_bytes("kteam", link, data, self.port.t)

    def _drain_output_links(self) -> None:
        """Read what clients sent on the links the loop writes (at most every DRAIN_PERIOD_S)."""
        now = time.monotonic()
        if now - self._last_drain < DRAIN_PERIOD_S:
            return
        self._last_drain = now
        for drain in self._drains:
            try:
                drain()
            except TransportError as e:
                self._write_failed("input", e)

    def _reject_all_reader(self, bus: str, link: LockedByteLink) -> Callable[[], None]:
        """An output-only link: anything a client sends is rejected (and counted)."""

        def step() -> None:
            for _ in range(64):  # bounded: the loop must not stall on a flood
                if not link.read():
                    return
                self.counters.rejected(bus)

        return step

    def _mavlink_reader(self, link: LockedByteLink) -> Callable[[], None]:
        decoder = CompassDecoder(signing=self.mav_signing)
        session = link.client_session

        def step() -> None:
            nonlocal decoder, session
            for _ in range(64):  # bounded: the loop must not stall on a flood
                data = link.read()
                if link.client_session != session:  # a new client on the pty: no half packet
                    session = link.client_session
                    decoder = CompassDecoder(signing=self.mav_signing)
                if not data:
                    return
                one(data)

        def one(data: bytes) -> None:
            before = (decoder.decoded + decoder.ignored, decoder.rejected)
            if link.is_datagram:
                decoder.feed_datagram(data)
            else:
                decoder.feed(data)
            # Valid MAVLink from a ground station (its HEARTBEAT, requests) is accepted and
            # ignored; the compass has no commands.
            self.counters.received("mavlink", decoder.decoded + decoder.ignored - before[0])
            self.counters.rejected("mavlink", decoder.rejected - before[1])
            if self.tap is not None:
                self.tap.record_frame("mavlink", "to_robot", self.port.t, data)

        return step

    def _can_reader(self, name: str, transport: Any) -> Callable[[], None]:
        codec = self.can_codec

        def step() -> None:
            msg = transport.recv(timeout=READ_TIMEOUT_S)
            if msg is None:
                return
            if self.tap is not None:
                self.tap.record_frame(
                    "can", "to_robot", self.port.t, bytes(msg.data), can_id=msg.arbitration_id,
                    extended=msg.is_extended_id, transport=name,
                )
            frame = codec.decode(msg)
            if isinstance(frame, MotorCommandFrame):
                if not self._at_cycle_boundary():   # lockstep: commands act at a boundary
                    return
                self.counters.received(name)
                if not self._bus_off:               # bus-off: the robot hears nothing
                    self.arbiter.set(frame.left_speed, frame.right_speed, name)
                if self.lockstep is not None and msg.arbitration_id == self._cycle_can_id:
                    # the cycle message: one more period (even when a fault ate its command)
                    self.lockstep.grant()
            else:
                # A Reject, or a frame only the robot sends (WheelOdometry, Gyro) coming from a
                # client: either way the robot does not act on it.
                self.counters.rejected(name)
                log.debug("%s: rejected %s", name, frame)

        return step


def _ir_counts(counts: Any) -> tuple[int, ...]:
    """IR counts clipped to the frame's 0..1023 (K-Team proximity range), as ints: the values of
    ``np.clip(counts, 0, 1023).astype(int)``, clipped in Python -- np.clip on 16 values cost
    ~35 us of CPU per frame in the cold caches of a real-time step (bench/bench_latency.py), a
    frame the step writes first."""
    return tuple(int(min(max(c, 0), 1023)) for c in np.asarray(counts).tolist())


def _sonar_mm(ranges: Any) -> tuple[int, ...]:
    """Sonar ranges (m, nan = no echo) as u16 millimetres with ``0xFFFF`` = no echo."""
    out = []
    for r in np.asarray(ranges, dtype=float):
        out.append(NO_ECHO if not math.isfinite(r) else int(min(max(round(r * 1000), 0), 0xFFFE)))
    return tuple(out)


def _with_data(msg: can.Message, data: bytes) -> can.Message:
    """``msg`` with another payload (a fault's copy)."""
    return can.Message(arbitration_id=msg.arbitration_id, is_extended_id=msg.is_extended_id,
                       data=data, timestamp=msg.timestamp)


def _tap_bus(bus: str) -> str:
    return {"kteam": "serial/kteam", "rangefinders": "serial/rangefinders"}.get(bus, bus)
