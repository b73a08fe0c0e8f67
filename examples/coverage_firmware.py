#!/usr/bin/env python3
"""A Koala firmware that localises itself and covers every cell -- talking only to the buses.

The reference example of "firmware connects unchanged": it opens the robot's links exactly as it
would on a real Koala, with the project's codecs (the same ones that read a real robot):

* K-Team ASCII serial (pyserial): ``N`` for the 16 IR proximity counts, ``D`` for wheel speeds;
* CAN through python-can's ``socketcand`` interface, decoded with the DBC: ``WheelOdometry``
  ticks and ``Gyro`` yaw rate;
* MAVLink 2 (UDP): ``SCALED_IMU`` magnetometer (the compass).

Where to connect comes from the bridge's ``--endpoints-file``; what the robot is (wheel base,
ticks per metre, IR poses, sensor rates, the control period) from the config file the robot was
built with; what the world is (the grid, its walls, magnetic north) from a world file -- the
lab's "Key values" (seeds/003 A-D) are the program's parameters. Nothing is read from Zenoh or
from the simulator.

What it does (seeds/003, Lab 4):

1. *Find landmarks / calibrate*: one turn on the spot. The gyro tracks the turn; the horizontal
   magnetic field draws a circle whose centre is the magnetometer's hard-iron offset; the compass
   then gives the absolute heading.
2. *Statistical wall localisation*: from a uniform prior, read the walls around the cell with the
   IR ring (twice per stop), update the histogram filter, move to a side seen open (not straight
   back), predict; until one cell holds ``--p-name`` of the belief.
3. *Full-grid navigation*: from that cell, the lab's order -- left, up, down, right, else back the
   way it came -- until every reachable cell is visited. Moves are closed-loop on an EKF
   (odometry + gyro + compass) to the next cell centre; the grid filter keeps running.

*The control cycle.* The firmware runs a fixed control period ``P`` -- the config file's
``[lockstep] period_s`` (a firmware chooses its period; the bridge's config must say the same, so
both read one file) -- and does exactly this every cycle ``k``:

1. send one K-Team ``D`` (the wheel speeds for the period ``(T_k-1, T_k]``; sent even when they
   did not change, which also feeds a motor watchdog) and read its ``d``;
2. wait until the robot's data has reached the cycle's end ``T_k = T_0 + k P``: every CAN and
   MAVLink stream has delivered its last sample at or before ``T_k`` (each sample carries its
   sampling time: the socketcand frame's time stamp, MAVLink's ``time_boot_ms``; a stream of rate
   ``r`` samples at multiples of ``1/r``). ``T_0`` is the newest ``WheelOdometry`` time seen before
   the first ``D``. A stream still short of ``T_k`` ``--stream-grace-s`` wall seconds after the
   others is taken as silent (a fault, a dead link) and not waited for until it speaks again;
3. drain every link and process *all* the samples up to ``T_k`` in one fixed order -- by sample
   time, then gyro, odometry, compass (the gyro integral closes at the odometry sample of the
   same time) -- not in arrival order across links; a repeated or older sample of a stream is
   dropped (while the bridge holds at t = 0 it re-sends step 0's frames);
4. decide the next command; an IR reading is a K-Team ``N`` sent and answered within the cycle.

Every decision depends on robot data and the seed only; the wall clock is a liveness watchdog
(``--timeout-s`` aborts the run), the bound on waiting for a silent stream (in lockstep all data
up to the boundary is readable once ``d`` has come: waiting longer would bring nothing) and a
sleep that avoids busy-waiting, so the same bridge config, seed and arguments give the same
commands.

With ``koala-bridge run --clock lockstep`` (docs/protocols.md "Lockstep"; ``[lockstep] cycle_bus =
"kteam"``, ``cycle_message = "D"``) the bridge simulates the period when the ``D`` arrives and
answers ``d`` afterwards, so step 2 never waits and a run is reproducible bit for bit, however
slow the machine. With ``--clock fast`` or ``realtime`` the robot does not wait for the firmware:
step 2 waits for the data to arrive, and if the robot ran ahead (a slow or stopped firmware) the
cycle ends at the period boundary at or after the newest ``WheelOdometry`` sample, counted in
the report as ``skipped_periods`` (always 0 in lockstep).

It prints a JSON report (``--report`` also writes it to a file) and exits 0 when every reachable
cell was visited, 1 otherwise -- also when ``--max-sim-s`` of robot time ran out (the report then
says ``"ended": "robot-time budget"``). The report carries the final pose estimate with its robot
time, and the run's cost: control cycles, wall seconds and cycles per wall second.

example::

    koala-bridge run --clock lockstep --endpoints-file /tmp/koala.json --config my.toml &
    python examples/coverage_firmware.py --endpoints-file /tmp/koala.json --config my.toml \\
        --world config/worlds/lab_walls_1.toml
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import select
import socket
import sys
import time
import tomllib
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import numpy as np
import serial
from koala_bridge.core.geometry import circle_centre
from koala_bridge.core.geometry import wrap_angle as wrap
from koala_bridge.core.grid import SIDE_STEP, SIDES, Grid
from koala_bridge.drivers.can_codec import KoalaCanCodec, load_koala_dbc
from koala_bridge.drivers.kteam import LineSplitter, format_command, parse_reply
from koala_bridge.drivers.mavlink_codec import CompassDecoder, CompassEncoder, MavlinkIdentity
from koala_bridge.drivers.messages import (
    CompassSample,
    GyroFrame,
    KteamCommand,
    KteamReply,
    WheelOdometryFrame,
)
from koala_bridge.estimation import (
    BeamModel,
    GridLocaliser,
    GridParams,
    OccupancyGrid,
    OccupancyParams,
    PoseTracker,
    PoseTrackerParams,
    heading_from_field,
    occupancy_message,
    sensor_sides,
    walls_from_ir,
)

log = logging.getLogger("coverage_firmware")

OPPOSITE = {"N": "S", "S": "N", "E": "W", "W": "E"}
LAB_ORDER = ("W", "N", "S", "E")  # seeds/003 "Full grid navigation": left, up, down, right
#: the bridge's [lockstep] period_s default (config/default.toml), for a config without [lockstep]
DEFAULT_PERIOD_S = 0.01
#: sample times are exact multiples of the simulation step, carried to the microsecond
#: (socketcand SECS.USECS) or millisecond (MAVLink time_boot_ms): compare them this loosely
TIME_EPS_S = 2e-3

# The streams, in the order samples of the same time are processed.
GYRO, ODOMETRY, COMPASS = 0, 1, 2
STREAM_NAMES = ("gyro", "odometry", "compass")


class WatchdogTimeout(TimeoutError):
    """The wall-clock liveness watchdog (``--timeout-s``) ran out: the robot stopped answering."""


class RobotTimeBudget(Exception):
    """``--max-sim-s`` of robot time have passed: the run ends with what it has (the report
    says ``"ended": "robot-time budget"``)."""


# --------------------------------------------------------------------------- parameters


@dataclass(frozen=True)
class RobotParams:
    """What the firmware knows about its robot, from the robot's config file."""

    ticks_per_metre: float
    wheel_base_m: float
    max_speed_units: int  # K-Team D range, pulse / 10 ms
    ir_poses: np.ndarray  # (16, 3) body frame [x, y, yaw rad]
    ir_response_m: np.ndarray  # response curve: range (m) ...
    ir_response_counts: np.ndarray  # ... -> counts (decreasing)
    ir_aperture_rad: float
    encoders_rate_hz: float
    gyro_rate_hz: float
    compass_rate_hz: float
    period_s: float  # the control period: [lockstep] period_s

    @classmethod
    def from_config(cls, d: Mapping[str, Any]) -> RobotParams:
        ir = np.array(d["sensors"]["ir"]["poses"], dtype=float)
        ir[:, 2] = np.radians(ir[:, 2])
        period = float(d.get("lockstep", {}).get("period_s", DEFAULT_PERIOD_S))
        if not (math.isfinite(period) and period > 0):
            raise SystemExit(f"[lockstep] period_s must be > 0, got {period!r}")
        return cls(
            ticks_per_metre=float(d["robot"]["ticks_per_metre"]),
            wheel_base_m=float(d["robot"]["wheel_base_m"]),
            max_speed_units=int(d["buses"]["kteam"]["max_speed"]),
            ir_poses=ir,
            ir_response_m=np.array(d["sensors"]["ir"]["response_range_m"], dtype=float),
            ir_response_counts=np.array(d["sensors"]["ir"]["response_counts"], dtype=float),
            ir_aperture_rad=math.radians(float(d["sensors"]["ir"]["aperture_deg"])),
            encoders_rate_hz=float(d["sensors"]["encoders"]["rate_hz"]),
            gyro_rate_hz=float(d["sensors"]["gyro"]["rate_hz"]),
            compass_rate_hz=float(d["sensors"]["compass"]["rate_hz"]),
            period_s=period,
        )

    def stream_rates_hz(self) -> tuple[float, float, float]:
        """Sample rates of the streams GYRO, ODOMETRY, COMPASS."""
        return (self.gyro_rate_hz, self.encoders_rate_hz, self.compass_rate_hz)


# --------------------------------------------------------------------------- the buses


@dataclass(frozen=True, slots=True)
class Sample:
    """One sample of a stream, stamped with its sampling time (robot seconds)."""

    t: float
    stream: int  # GYRO, ODOMETRY or COMPASS
    value: GyroFrame | WheelOdometryFrame | CompassSample


class Links:
    """The robot's three links, opened from the endpoints file as on a real Koala."""

    def __init__(self, endpoints: Mapping[str, Any], watchdog_s: float) -> None:
        kteam = endpoints["serial"]["kteam"]
        sc = endpoints["can"]["socketcand"]
        mav_url = endpoints["mavlink"]["url"]
        if not (kteam and sc and mav_url):
            raise SystemExit("the firmware needs the K-Team serial, socketcand and MAVLink buses")
        self.watchdog_s = watchdog_s
        self.wall_deadline = time.monotonic() + watchdog_s
        self.serial = serial.Serial(kteam, 115200, timeout=0)
        self.lines = LineSplitter()
        self.can = can.Bus(
            interface="socketcand", host=sc["host"], port=sc["port"], channel=sc["channel"]
        )
        self.codec = KoalaCanCodec(load_koala_dbc(endpoints["can"]["dbc"]))
        self.compass = CompassDecoder()
        kind, host, port = mav_url.split(":")
        self.mav_heard = kind != "udpout"  # udpout: the robot answers once it has heard us
        if kind == "udpin":
            self.mav = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self.mav.bind((host, int(port)))
        elif kind == "udpout":  # the bridge listens (port 0): say hello as a ground station
            self.mav = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self.mav.connect((host, int(port)))
        elif kind == "tcp":
            self.mav = socket.create_connection((host, int(port)))
        else:
            raise SystemExit(f"unsupported MAVLink connection {mav_url!r} (udpin:, udpout:, tcp:)")
        self.mav_datagrams = kind != "tcp"
        self.mav.setblocking(False)
        self.say_hello()

    def say_hello(self) -> None:
        """On ``udpout:`` only: send a ground station's HEARTBEAT, so the robot knows where to
        send its stream (repeated by :meth:`samples` until it answers)."""
        if not self.mav_heard:
            self.mav.send(gcs_heartbeat())

    def check_watchdog(self) -> None:
        """Liveness only: abort when the run has taken ``--timeout-s`` wall seconds."""
        if time.monotonic() > self.wall_deadline:
            raise WatchdogTimeout(f"wall-clock watchdog: no result within {self.watchdog_s:g} s")

    def samples(self, wait_s: float = 0.0) -> list[Sample]:
        """Every CAN and MAVLink sample received so far, each with its sampling time; with
        ``wait_s`` > 0, first wait that long at most for the CAN link to have data."""
        out: list[Sample] = []
        timeout = wait_s
        while (msg := self.can.recv(timeout)) is not None:
            timeout = 0.0
            frame = self.codec.decode(msg)
            if isinstance(frame, GyroFrame):
                out.append(Sample(float(msg.timestamp), GYRO, frame))
            elif isinstance(frame, WheelOdometryFrame):
                out.append(Sample(float(msg.timestamp), ODOMETRY, frame))
        while True:
            try:
                data = self.mav.recv(65536)
            except BlockingIOError:
                break
            if not data:
                break
            self.mav_heard = True
            parsed = (self.compass.feed_datagram(data) if self.mav_datagrams
                      else self.compass.feed(data))
            out += [Sample(s.time_boot_ms / 1000.0, COMPASS, s) for s in parsed
                    if isinstance(s, CompassSample)]
        return out

    def wait_compass(self, timeout_s: float) -> None:
        """Sleep until the MAVLink socket is readable or ``timeout_s`` passed (no busy-wait)."""
        select.select([self.mav], [], [], timeout_s)

    def request(self, command: KteamCommand, answer: str) -> KteamReply:
        """Send a K-Team command and return its reply (the first with letter ``answer``; lines
        the robot pushes unasked are skipped). An error reply is fatal: the firmware only sends
        what it knows the robot takes."""
        self.serial.write(format_command(command))
        while True:
            self.check_watchdog()
            if not self.serial.in_waiting:
                select.select([self.serial.fileno()], [], [], 0.05)
            data = self.serial.read(self.serial.in_waiting or 1)
            for line in self.lines.feed(data):
                reply = parse_reply(line) if isinstance(line, bytes) else line
                if isinstance(reply, KteamReply):
                    if reply.letter == answer:
                        return reply
                    if reply.letter == "z":
                        raise RuntimeError(f"the robot refused {command}: {reply}")

    def close(self) -> None:
        try:
            self.serial.write(format_command(KteamCommand("D", (0, 0))))
            self.serial.flush()
        finally:
            self.serial.close()
            self.can.shutdown()
            self.mav.close()


class RobotClock:
    """The firmware's time: the robot's sample times, cut into control periods.

    ``T_0`` is the newest odometry time before the first cycle; cycle ``k`` ends at
    ``T_0 + k P``. Samples are kept per cycle; a stream's sample at or before its newest one is a
    repeat and dropped. Pure bookkeeping, no I/O: :class:`CoverageFirmware` feeds it.
    """

    def __init__(self, period_s: float, rates_hz: Iterable[float]) -> None:
        self.period_s = period_s
        self.rates_hz = tuple(rates_hz)
        self.newest = [-math.inf] * len(self.rates_hz)  # per stream, newest sample time
        self.pending: list[Sample] = []
        self.origin: float | None = None                  # T_0
        self.index = 0                                     # k: T_k = T_0 + k P
        self.skipped = 0                                   # periods the robot ran ahead

    def add(self, samples: Iterable[Sample]) -> None:
        for s in samples:
            if s.t > self.newest[s.stream]:
                self.newest[s.stream] = s.t
                self.pending.append(s)

    @property
    def end(self) -> float:
        """``T_k``, the end of the current cycle (robot seconds)."""
        assert self.origin is not None
        return self.origin + self.index * self.period_s

    def start(self) -> None:
        """Fix ``T_0`` at the newest odometry sample (the robot has been heard from)."""
        self.origin = self.newest[ODOMETRY]

    def next_cycle(self) -> None:
        self.index += 1

    def catch_up(self) -> None:
        """If odometry is already past ``T_k`` (the robot did not wait: fast or realtime clock),
        end the cycle at the first period boundary at or after the newest odometry sample."""
        assert self.origin is not None
        ahead = (self.newest[ODOMETRY] - self.origin) / self.period_s
        if ahead > self.index + TIME_EPS_S / self.period_s:
            k = math.ceil(ahead - TIME_EPS_S / self.period_s)
            self.skipped += k - self.index
            self.index = k

    def behind(self) -> list[int]:
        """The streams that have not yet delivered their last sample at or before ``T_k`` (a
        stream of rate ``r`` samples at multiples of ``1/r``)."""
        end = self.end
        out = []
        for stream, (rate, newest) in enumerate(zip(self.rates_hz, self.newest, strict=True)):
            last_due = math.floor(end * rate + 1e-6) / rate
            if newest < last_due - TIME_EPS_S / 2:
                out.append(stream)
        return out

    def take(self) -> list[Sample]:
        """The pending samples up to ``T_k`` in processing order (time, then stream)."""
        end = self.end + TIME_EPS_S / 2
        due = [s for s in self.pending if s.t <= end]
        self.pending = [s for s in self.pending if s.t > end]
        due.sort(key=lambda s: (s.t, s.stream))
        return due


# --------------------------------------------------------------------------- the firmware


class CoverageFirmware:
    """Calibrate, localise, cover, one control cycle at a time (:meth:`cycle`). Time is *robot*
    time: the sampling times the robot's frames carry."""

    #: the streams' names, by stream number (a subclass with more streams extends it)
    stream_names: tuple[str, ...] = STREAM_NAMES

    def __init__(self, links: Links, robot: RobotParams, world: Grid, args: argparse.Namespace):
        self.links = links
        self.robot = robot
        self.world = world
        self.args = args
        self.rng = np.random.default_rng(args.seed)
        self.tracker = PoseTracker(PoseTrackerParams(
            wheel_base_m=robot.wheel_base_m, ticks_per_metre=robot.ticks_per_metre,
            compass_sigma_rad=math.radians(args.compass_sigma_deg),
        ))
        # Start-relative frame until localised: origin at the (unknown) start cell's centre.
        self.tracker.reset(0.0, 0.0, 0.0, np.diag([1e-6, 1e-6, math.pi**2]))
        self.grid = GridLocaliser(world, GridParams(p_move=args.p_move, p_hit=0.9, p_clear=0.7))
        self.north = math.radians(world.earth_field.north_deg)
        self.clock = RobotClock(robot.period_s, robot.stream_rates_hz())
        self.t = 0.0  # the end of the last cycle, robot seconds
        self.cycles = 0
        self.ir_requests = 0
        self.silent: set[int] = set()  # streams not waited for (see cycle())
        self.silent_streams = 0        # times a stream was found silent
        self.hard_iron: np.ndarray | None = None
        self.spin_fields: list[tuple[float, np.ndarray]] = []
        self.collect_fields = False
        self.ir: tuple[int, ...] | None = None
        self.units: tuple[int, int] = (0, 0)  # the wheel command of the next cycle
        self.resyncs = 0
        self.localised: tuple[int, int] | None = None
        #: [t, x, y] of the estimate once a second of robot time after localising (the
        #: report's "estimates": a campaign's localisation-error check judges them)
        self.estimates: list[list[float]] = []
        self.localised_at: float | None = None  # robot time since T_0, s
        self.localisation_moves: int | None = None
        self.order: list[tuple[int, int]] = []
        self.last_counts: tuple[int, ...] | None = None
        self.wall_fixes = 0
        self.compass_rejects = 0  # consecutive
        self.heading_resets = 0
        # The lecture's occupancy grid (seeds/004) from the IR ring at every stop once localised.
        # The free cone stops a cell short of each echo: a grazing IR ray must not clear the
        # cells a wall touches (docs/localisation.md, "Occupancy grid").
        self.occupancy = OccupancyGrid.for_world(world, args.map_resolution_m,
                                                 OccupancyParams(free_margin_cells=1.0))
        self.ir_beam = BeamModel(robot.ir_aperture_rad, 0.03,
                                 max_range_m=float(robot.ir_response_m[-1]))

    # -- the control cycle -----------------------------------------------------------------
    def start(self) -> None:
        """Before the first cycle: wait until the robot is heard from (an odometry sample),
        which fixes ``T_0``."""
        # (udpout: the robot's MAVLink stream only starts once our hello has arrived; wait for
        # it here, where the robot holds at t = 0, so the first cycle sees the same samples)
        while self.clock.newest[ODOMETRY] == -math.inf or not self.links.mav_heard:
            self.links.check_watchdog()
            self.links.say_hello()
            self.clock.add(self.links.samples(wait_s=0.05))
        self.clock.add(self.links.samples())
        self.clock.start()
        self.t = self.clock.end
        log.info("robot time starts at %.3f s; control period %g s", self.t,
                 self.robot.period_s)

    def cycle(self) -> None:
        """One control cycle: send ``D`` with :attr:`units` and read its ``d``; wait until every
        stream reached the cycle's end; process its samples in (time, stream) order.

        A stream that has not reached the cycle's end ``--stream-grace-s`` wall seconds after
        the others is taken as silent (a fault, a dead link) and not waited for until it
        speaks again. In lockstep this changes no decision: after ``d`` everything sampled up
        to the boundary is already readable, so waiting longer would bring nothing more."""
        self.links.request(KteamCommand("D", self.units), "d")
        self.cycles += 1
        clock = self.clock
        clock.next_cycle()
        waiting_since: float | None = None
        while True:
            clock.add(self.links.samples())
            clock.catch_up()
            behind = clock.behind()
            self.silent.intersection_update(behind)  # a stream that spoke is silent no more
            behind = [s for s in behind if s not in self.silent]
            if not behind:
                break
            self.links.check_watchdog()
            now = time.monotonic()
            if waiting_since is None:
                waiting_since = now
            elif now - waiting_since > self.args.stream_grace_s:
                log.warning("t = %.2f s: no %s data up to the cycle's end; not waiting for it",
                            clock.end, ", ".join(self.stream_names[s] for s in behind))
                self.silent.update(behind)
                self.silent_streams += len(behind)
                break
            if GYRO in behind or ODOMETRY in behind:
                clock.add(self.links.samples(wait_s=0.01))  # blocks on the CAN socket
            else:
                self.links.wait_compass(0.01)
        self.t = clock.end
        for s in clock.take():
            self.on_sample(s)
        if self.localised is not None and (
                not self.estimates or self.t - self.estimates[-1][0] >= 1.0 - 1e-9):
            x, y, _ = self.tracker.pose
            self.estimates.append([round(self.t, 6), x, y])
        if self.t - clock.origin > self.args.max_sim_s:  # type: ignore[operator]
            raise RobotTimeBudget(f"{self.args.max_sim_s:g} s of robot time have passed")

    def on_sample(self, s: Sample) -> None:
        """Feed one sample to the pose tracker (and the calibration)."""
        if s.stream == GYRO:
            assert isinstance(s.value, GyroFrame)
            self.tracker.on_gyro(s.t, s.value.yaw_rate)
        elif s.stream == ODOMETRY:
            assert isinstance(s.value, WheelOdometryFrame)
            self.tracker.on_odometry(s.t, s.value.left_ticks, s.value.right_ticks)
        else:
            assert isinstance(s.value, CompassSample)
            field = np.array([s.value.x_ut, s.value.y_ut, s.value.z_ut])
            if self.collect_fields:
                self.spin_fields.append((self.tracker.pose[2], field))
            if self.hard_iron is not None:
                heading = heading_from_field(field, self.north, self.hard_iron)
                ok = self.tracker.on_compass(s.t, heading)
                # Count disagreement only outside turns (where the field is bent least by the
                # motor currents, docs/models.md "Compass").
                turning = self.units[0] != self.units[1]
                if ok:
                    self.compass_rejects = 0
                elif not turning:
                    self.compass_rejects += 1

    def drive(self, v: float, w: float) -> None:
        """Wheel speeds for forward speed ``v`` (m/s) and turn rate ``w`` (rad/s), sent as
        K-Team ``D`` by the next :meth:`cycle`."""
        b = self.robot.wheel_base_m
        scale = self.robot.ticks_per_metre / 100.0  # m/s -> pulse / 10 ms
        lim = self.robot.max_speed_units
        left, right = (
            max(-lim, min(lim, round(s * scale))) for s in (v - w * b / 2, v + w * b / 2)
        )
        self.units = (left, right)

    def wait(self, seconds: float) -> None:
        """Run cycles for ``seconds`` of robot time, keeping the current wheel command."""
        end = self.t + seconds
        while self.t < end - TIME_EPS_S / 2:
            self.cycle()

    def stop(self) -> None:
        """Stop the wheels and let them settle. Standing still is also when a heading that the
        compass has contradicted for a long time (every update gated out) is re-initialised."""
        self.drive(0.0, 0.0)
        self.wait(0.2)
        if self.hard_iron is not None and self.compass_rejects > 50:
            heading = self.compass_heading_at_rest()
            log.warning("compass disagreed %d times in a row: heading %.1f -> %.1f deg",
                        self.compass_rejects, math.degrees(self.tracker.pose[2]),
                        math.degrees(heading))
            x, y, _ = self.tracker.pose
            cov = self.tracker.pose_cov
            cov[2, :] = cov[:, 2] = 0.0
            cov[2, 2] = math.radians(3) ** 2
            self.tracker.reset(x, y, heading, cov, t=self.t, gyro_bias=self.tracker.gyro_bias)
            self.compass_rejects = 0
            self.heading_resets += 1

    def read_ir(self) -> tuple[int, ...]:
        """One ``N`` reading, asked for and answered within the cycle (at its boundary)."""
        self.ir = self.links.request(KteamCommand("N"), "n").ints
        self.ir_requests += 1
        return self.ir

    # -- motion primitives ---------------------------------------------------------------
    def turn_to(self, heading: float, tolerance: float = 0.03) -> None:
        """Turn on the spot to ``heading``: proportionally while far, then in timed pulses with
        a stop between them. A command acts one cycle after the data it was decided on (and,
        with ``--clock fast`` on a busy machine, the robot may run ahead of the firmware by many
        periods); proportional control through such a lag overshoots, whereas a pulse timed on
        the robot clock has the right length, and deciding only when the robot stands still
        removes the lag from the decision."""
        end = self.t + 30.0
        while self.t < end:
            err = wrap(heading - self.tracker.pose[2])
            if abs(err) < 0.25:
                break
            self.drive(0.0, math.copysign(min(0.8, 2.0 * abs(err)), err))
            self.cycle()
        self.stop()
        for _ in range(8):
            err = wrap(heading - self.tracker.pose[2])
            if abs(err) < tolerance:
                return
            rate = 0.3
            self.drive(0.0, math.copysign(rate, err))
            self.wait(abs(err) / rate)
            self.stop()

    def blocked_ahead(self) -> bool:
        """Bumper by IR: a sensor within 50 deg of forward reads more than 600 counts (~4 cm)."""
        if self.ir is None:
            return False
        yaw = self.robot.ir_poses[:, 2]
        return any(c > 600 for c, a in zip(self.ir, yaw, strict=True) if abs(a) <= 0.88)

    def drive_to(self, x: float, y: float) -> bool:
        """Closed-loop drive to ``(x, y)`` on the EKF pose; False when the IR bumper trips or
        on timeout (blocked)."""
        px, py, th = self.tracker.pose
        d0 = math.hypot(x - px, y - py)
        if d0 > 0.05:
            self.turn_to(math.atan2(y - py, x - px))
        end = self.t + d0 / 0.02 + 10.0
        vmax = self.args.speed_mps
        next_ir = self.t
        while self.t < end:
            if self.t >= next_ir - TIME_EPS_S / 2:  # IR every 0.1 s of robot time
                self.read_ir()
                next_ir = self.t + 0.1
            if self.blocked_ahead():
                log.warning("IR bumper: obstacle ahead at t=%.1f", self.t)
                break
            px, py, th = self.tracker.pose
            dx, dy = x - px, y - py
            along = dx * math.cos(th) + dy * math.sin(th)
            dist = math.hypot(dx, dy)
            if along < 0.005 or dist < 0.008:
                self.stop()
                return True
            err = wrap(math.atan2(dy, dx) - th) if dist > 0.05 else 0.0
            if abs(err) > 0.4:
                self.turn_to(math.atan2(dy, dx))
                continue
            self.drive(min(vmax, max(0.02, 0.8 * along)), max(-0.4, min(0.4, 2.0 * err)))
            self.cycle()
        self.stop()
        return False

    # -- Lab 4 ---------------------------------------------------------------------------
    def calibrate(self) -> None:
        """One turn on the spot: hard iron = centre of the circle the horizontal field draws;
        then, standing still, the absolute heading = the mean compass heading. (Pairing each
        field sample with the gyro heading would be wrong whenever the CAN and MAVLink streams
        are drained at different lags.)"""
        self.wait(0.3)
        turned, last = 0.0, self.tracker.pose[2]
        self.collect_fields = True
        end = self.t + 40.0
        while turned < 2 * math.pi + 0.3 and self.t < end:
            self.drive(0.0, 0.6)
            self.cycle()
            th = self.tracker.pose[2]
            turned += abs(wrap(th - last))
            last = th
        self.collect_fields = False
        self.stop()
        xy = np.array([f[:2] for _, f in self.spin_fields])
        self.hard_iron = np.array([*circle_centre(xy), 0.0])
        heading = self.compass_heading_at_rest()
        x, y, _ = self.tracker.pose
        self.tracker.reset(x, y, heading, np.diag([1e-6, 1e-6, math.radians(3) ** 2]),
                           t=self.t, gyro_bias=self.tracker.gyro_bias)
        log.info("hard iron %.2f %.2f uT from %d samples, heading %.1f deg", self.hard_iron[0],
                 self.hard_iron[1], len(xy), math.degrees(heading))

    def compass_heading_at_rest(self, seconds: float = 0.5) -> float:
        """Circular mean of the compass headings over ``seconds`` of standing still."""
        self.spin_fields.clear()
        self.collect_fields = True
        self.wait(seconds)
        self.collect_fields = False
        assert self.hard_iron is not None
        h = np.array([heading_from_field(f, self.north, self.hard_iron)
                      for _, f in self.spin_fields])
        return math.atan2(float(np.mean(np.sin(h))), float(np.mean(np.cos(h))))

    def read_walls(self, n: int) -> list[tuple[bool | None, ...]]:
        out: list[tuple[bool | None, ...]] = []
        for _ in range(n):
            self.wait(0.06)  # IR samples at 20 Hz: a fresh one per reading
            counts = self.read_ir()
            self.last_counts = counts
            out.append(walls_from_ir(counts, self.tracker.pose[2], self.robot.ir_poses,
                                     self.args.ir_threshold, cell_m=self.world.cell_m))
        return out

    def ir_ranges(self, counts: tuple[int, ...]) -> np.ndarray:
        """IR counts to ranges by the robot's response curve; below the noise floor
        ``--ir-echo-counts`` nothing is in range."""
        c = np.asarray(counts, dtype=float)
        r = np.interp(c, self.robot.ir_response_counts[::-1], self.robot.ir_response_m[::-1])
        return np.where(c >= self.args.ir_echo_counts, r, np.inf)

    def map_stop(self) -> None:
        """Add the last IR reading, taken at rest, to the occupancy grid."""
        if self.last_counts is not None:
            self.occupancy.integrate_scan(self.tracker.pose, self.robot.ir_poses,
                                          self.ir_ranges(self.last_counts), self.ir_beam)

    def correct_from_walls(
        self, centre: tuple[float, float], walls: tuple[bool | None, ...]
    ) -> None:
        """Position fix at a stop: a sensor facing a wall of the current cell (centre
        ``centre``, walls ``N, E, S, W``) within 20 deg of its normal measures the robot's
        coordinate across that wall (IR counts to range by the robot's response curve). Before
        localisation the cell is the start-relative one and its walls are the ones just seen."""
        if self.last_counts is None:
            return
        x, y, th = self.tracker.pose
        poses = self.robot.ir_poses
        sides = sensor_sides(th, poses, self.world.cell_m, math.radians(20.0))
        half = self.world.cell_m / 2
        c, s = math.cos(th), math.sin(th)
        for i, k in enumerate(sides):
            counts = self.last_counts[i]
            if k is None or not walls[k] or not 40 <= counts < 1000:
                continue
            r = float(np.interp(counts, self.robot.ir_response_counts[::-1],
                                self.robot.ir_response_m[::-1]))
            bx, by, yaw = poses[i]
            ox, oy = c * bx - s * by, s * bx + c * by
            phi = th + yaw
            side = SIDES[k]
            sigma = 0.004 + 0.05 * r
            if side in ("N", "S"):
                wall_y = centre[1] + (half if side == "N" else -half)
                ok = self.tracker.on_coordinate(self.t, 1, wall_y - r * math.sin(phi) - oy, sigma)
            else:
                wall_x = centre[0] + (half if side == "E" else -half)
                ok = self.tracker.on_coordinate(self.t, 0, wall_x - r * math.cos(phi) - ox, sigma)
            self.wall_fixes += int(ok)

    def map_walls(self, cell: tuple[int, int]) -> tuple[bool, ...]:
        return tuple(self.world.has_wall(*cell, side) for side in SIDES)

    def move(self, target_xy: tuple[float, float], side: str) -> bool:
        """Drive to the neighbour's centre; the grid filter predicts the move only if it was
        made (a blocked move brings the robot back to where it was: no motion to predict)."""
        ok = self.drive_to(*target_xy)
        if ok:
            self.grid.move(side)
        x, y, th = self.tracker.pose
        log.debug("t=%.1f move %s to (%.3f, %.3f): %s; pose (%.3f, %.3f, %.1f deg)", self.t,
                  side, target_xy[0], target_xy[1], "ok" if ok else "blocked", x, y,
                  math.degrees(th))
        return ok

    def localise(self) -> tuple[tuple[int, int], int]:
        """Wall localisation from a uniform prior; returns (cell, moves)."""
        cm = self.world.cell_m
        rel = (0, 0)
        last: str | None = None
        confident = 0
        for moves in range(self.args.max_localise_moves + 1):
            readings = self.read_walls(self.args.readings_per_stop)
            for walls in readings:
                self.grid.observe(walls)
            self.correct_from_walls((rel[0] * cm, rel[1] * cm), readings[-1])
            guess = self.grid.guess()
            p = self.grid.probability(guess)
            log.info("localising: move %d, guess %s p=%.3f walls %s", moves, guess, p,
                     readings[-1])
            confident = confident + 1 if p >= self.args.p_name else 0
            if confident >= 2:  # named at two stops in a row (a move apart)
                # Shift the start-relative EKF frame onto the world.
                gx, gy = self.world.cell_centre(*guess)
                self.tracker.x[0] += gx - rel[0] * cm
                self.tracker.x[1] += gy - rel[1] * cm
                return guess, moves
            seen = readings[-1]
            open_sides = [s for s, z in zip(SIDES, seen, strict=True) if z is False]
            open_sides = open_sides or list(SIDES)
            onward = [s for s in open_sides if last is None or s != OPPOSITE[last]] or open_sides
            side = onward[int(self.rng.integers(len(onward)))]
            dc, dr = SIDE_STEP[side]
            target = (rel[0] + dc, rel[1] + dr)
            if self.move((target[0] * cm, target[1] * cm), side):
                rel = target
            else:
                self.drive_to(rel[0] * cm, rel[1] * cm)  # blocked: back to the centre
            last = side
        raise RuntimeError("not localised within the move budget")

    def cover(self, start: tuple[int, int]) -> list[tuple[int, int]]:
        """The lab's full-grid navigation from ``start``: left, up, down, right into an unvisited
        cell, else back the way it came; returns the cells in visit order. If the plan had to be
        re-anchored (the grid filter disagreed), the way back is lost: the robot then takes the
        shortest path to the nearest unvisited cell."""
        w = self.world
        cell = start
        reachable = w.reachable(start)
        visited = {cell}
        order = self.order  # kept on the firmware: a run cut short reports what it visited
        order.append(cell)
        history: list[str] = []
        doubt = 0
        self.correct_from_walls(w.cell_centre(*cell), self.map_walls(cell))
        self.map_stop()
        while True:
            side = next((s for s in LAB_ORDER if w.can_move(*cell, s)
                         and _step(cell, s) not in visited), None)
            if side is not None:
                history.append(side)
            elif history:
                side = OPPOSITE[history.pop()]
            else:
                path = _path_to_nearest(w, cell, reachable - visited)
                if not path:
                    return order
                side = path[0]
            n = _step(cell, side)
            if not self.move(w.cell_centre(*n), side):
                log.warning("move %s from %s blocked; back to the centre", side, cell)
                self.drive_to(*w.cell_centre(*cell))
                if history and history[-1] == side:
                    history.pop()
                continue
            cell = n
            visited.add(cell)
            order.append(cell)
            for walls in self.read_walls(1):
                self.grid.observe(walls)
            self.correct_from_walls(w.cell_centre(*cell), self.map_walls(cell))
            self.map_stop()
            guess = self.grid.guess()
            doubt = doubt + 1 if guess != cell and self.grid.probability(guess) > 0.95 else 0
            if doubt >= 2:
                # Two stops in a row the filter is sure we are elsewhere: trust it, re-anchor.
                log.warning("grid filter says %s, plan says %s: re-anchoring", guess, cell)
                self.resyncs += 1
                gx, gy = w.cell_centre(*guess)
                cx, cy = w.cell_centre(*cell)
                self.tracker.x[0] += gx - cx
                self.tracker.x[1] += gy - cy
                cell = guess
                visited.add(cell)
                order.append(cell)
                history.clear()
                doubt = 0

    def run(self) -> dict[str, Any]:
        """Calibrate, localise, cover; the report (also when ``--max-sim-s`` ran out)."""
        self.start()
        assert self.clock.origin is not None
        wall0 = time.monotonic()  # for the report only: the run's cost, never a decision
        ended = "covered"
        try:
            self.calibrate()
            start, moves = self.localise()
            self.localised, self.localisation_moves = start, moves
            self.localised_at = self.t - self.clock.origin
            log.info("localised in %s after %d moves, t = %.1f s", start, moves,
                     self.localised_at)
            self.cover(start)
            self.stop()
        except RobotTimeBudget as e:
            log.warning("%s: the run ends here", e)
            ended = "robot-time budget"
        wall = time.monotonic() - wall0
        order = self.order
        reachable = (set() if self.localised is None
                     else self.world.reachable(self.localised))
        x, y, th = self.tracker.pose
        return {
            "ended": ended,
            "localised_cell": None if self.localised is None else list(self.localised),
            "localisation_moves": self.localisation_moves,
            "localised_at_s": (None if self.localised_at is None
                               else round(self.localised_at, 6)),
            "visited": [list(c) for c in order],
            "reachable": len(reachable),
            "complete": bool(reachable) and reachable <= set(order),
            "robot_time_s": round(self.t - self.clock.origin, 6),
            # the final estimate, in the world frame, at robot time t (the robot's own clock)
            "estimate": {"t": round(self.t, 6), "x": x, "y": y, "theta": th},
            "estimates": self.estimates,
            "period_s": self.robot.period_s,
            "cycles": self.cycles,
            "skipped_periods": self.clock.skipped,
            "ir_requests": self.ir_requests,
            "silent_streams": self.silent_streams,
            "wall_s": round(wall, 3),
            "cycles_per_wall_s": round(self.cycles / wall, 1) if wall > 0 else None,
            "resyncs": self.resyncs,
            "wall_fixes": self.wall_fixes,
            "heading_resets": self.heading_resets,
            "occupancy": occupancy_message(self.t, self.occupancy.log_odds,
                                           self.occupancy.resolution_m,
                                           self.occupancy.params.l_max),
            "gated_out": self.tracker.counters.rejected,
        }


def _step(cell: tuple[int, int], side: str) -> tuple[int, int]:
    return (cell[0] + SIDE_STEP[side][0], cell[1] + SIDE_STEP[side][1])


def _path_to_nearest(
    world: Grid, start: tuple[int, int], goals: set[tuple[int, int]]
) -> list[str]:
    """Sides of a shortest path from ``start`` to the nearest of ``goals`` (breadth first)."""
    prev: dict[tuple[int, int], tuple[tuple[int, int], str] | None] = {start: None}
    queue = [start]
    for c in queue:
        if c in goals:
            path: list[str] = []
            while (link := prev[c]) is not None:
                c, side = link[0], link[1]
                path.append(side)
            return path[::-1]
        for s in SIDES:
            n = _step(c, s)
            if world.can_move(*c, s) and n not in prev:
                prev[n] = (c, s)
                queue.append(n)
    return []


def gcs_heartbeat() -> bytes:
    """A ground station's HEARTBEAT (system 255, component 190: MAVLink's convention)."""
    identity = MavlinkIdentity(system_id=255, component_id=190, mav_type=6)  # MAV_TYPE_GCS
    return CompassEncoder(identity).heartbeat()


def argument_parser(description: str = __doc__.split("\n\n")[0],
                    epilog: str = "example:\n  python examples/coverage_firmware.py "
                                  "--endpoints-file /tmp/koala.json --config "
                                  "config/default.toml --world config/worlds/lab_walls_1.toml",
                    ) -> argparse.ArgumentParser:
    """The command line; a firmware built on this one (examples/trilateration_firmware.py)
    adds its own options to it."""
    ap = argparse.ArgumentParser(
        description=description,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=epilog,
    )
    ap.add_argument("--endpoints-file", type=Path, required=True,
                    help="the JSON the bridge wrote (koala-bridge run --endpoints-file)")
    ap.add_argument("--config", type=Path, required=True,
                    help="the robot's config (robot, sensors, buses.kteam tables)")
    ap.add_argument("--world", type=Path, required=True,
                    help="the map: a TOML file with a [world] table")
    ap.add_argument("--seed", type=int, default=0, help="exploration choices (default 0)")
    ap.add_argument("--p-name", type=float, default=0.98,
                    help="belief at which a cell is taken as the robot's (default 0.98)")
    ap.add_argument("--p-move", type=float, default=0.95,
                    help="grid filter's move success probability (default 0.95)")
    ap.add_argument("--readings-per-stop", type=int, default=2, help="(default 2)")
    ap.add_argument("--ir-threshold", type=float, default=40.0,
                    help="IR counts meaning 'wall at the cell side' (default 40)")
    ap.add_argument("--compass-sigma-deg", type=float, default=3.0, help="(default 3)")
    ap.add_argument("--speed-mps", type=float, default=0.1, help="top speed (default 0.1)")
    ap.add_argument("--max-localise-moves", type=int, default=40, help="(default 40)")
    ap.add_argument("--max-sim-s", type=float, default=1500.0,
                    help="robot-time budget, s (default 1500)")
    ap.add_argument("--stream-grace-s", type=float, default=0.5,
                    help="wall seconds to wait for a stream that lags the others before taking "
                         "it as silent (default 0.5; no effect on decisions in lockstep)")
    ap.add_argument("--timeout-s", type=float, default=300.0,
                    help="liveness watchdog: abort after this many wall seconds (default 300)")
    ap.add_argument("--ir-echo-counts", type=float, default=10.0,
                    help="IR counts below this are noise, not an echo (default 10)")
    ap.add_argument("--map-resolution-m", type=float, default=0.05,
                    help="occupancy grid cell side (default 0.05)")
    ap.add_argument("--report", type=Path, help="also write the JSON report here")
    ap.add_argument("--log-level", default="INFO")
    return ap


def run_firmware(
    args: argparse.Namespace,
    make_links: Callable[[Mapping[str, Any], float], Links] = Links,
    make_firmware: Callable[[Any, RobotParams, Grid, Mapping[str, Any], argparse.Namespace],
                            CoverageFirmware] = (
        lambda links, robot, world, _config, args: CoverageFirmware(links, robot, world, args)),
) -> int:
    """Open the links, run the firmware, print (and ``--report``) its JSON report; the exit
    status: 0 when every reachable cell was visited. ``make_links(endpoints, watchdog_s)`` and
    ``make_firmware(links, robot, world, config, args)`` let a firmware built on this one bring
    its own links and firmware class."""
    logging.basicConfig(level=args.log_level, stream=sys.stderr,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s")
    logging.getLogger("can").setLevel(logging.ERROR)  # python-can socketcand is chatty

    endpoints = json.loads(args.endpoints_file.read_text())
    config = tomllib.loads(args.config.read_text())
    robot = RobotParams.from_config(config)
    world = Grid.from_dict(tomllib.loads(args.world.read_text())["world"])
    links = make_links(endpoints, args.timeout_s)
    try:
        report = make_firmware(links, robot, world, config, args).run()
    finally:
        links.close()
    text = json.dumps(report)
    print(text, flush=True)
    if args.report:
        args.report.write_text(text + "\n")
    return 0 if report["complete"] else 1


def main(argv: list[str] | None = None) -> int:
    return run_firmware(argument_parser().parse_args(argv))


if __name__ == "__main__":
    raise SystemExit(main())
