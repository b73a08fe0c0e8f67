"""The emulated Koala's controller side: who commands the wheels, and the K-Team command set.

Motor commands arrive from the firmware by two paths, K-Team ``D`` (serial) and CAN
``MotorCommand``. :class:`MotorArbiter` applies one rule: **the last command received wins**,
whichever bus it came on; it holds until the next command (or, if ``motor_watchdog_s > 0``, until
that many simulation seconds pass without any command, when the wheels are set to 0).

:class:`KteamResponder` answers K-Team ASCII commands from the latest simulator readings
(docs/protocols.md, "K-Team ASCII"). Units of the Koala (Koala 2.5 User Manual):

- speed: encoder pulses per ``speed_unit_s`` (10 ms on the Koala), so with ``N`` pulses per metre
  (``[robot] ticks_per_metre``), ``D,10,10`` drives both wheels at 10 / 0.01 / N m/s (with the
  classic Koala's 22'222 pulses/m: 45 mm/s; with the Koala 2.5's 90'284: 11.1 mm/s);
- position: encoder pulses, cumulative, signed 32-bit. ``G,l,r`` sets the counters; the offset it
  introduces applies to every bus that reports them (K-Team ``H``, CAN ``WheelOdometry``), as the
  robot has one pair of counters. Zenoh ``sensors/odometry`` carries the simulator's counts since
  reset, unaffected by ``G``.

Position moves (classic Koala ``C`` under the ``J`` profile): the wheels follow, open loop, the
speed of a rest-to-rest trapezoid (:mod:`koala_bridge.core.motion_profile`) from the counters at
the time of ``C`` to its targets; the move is a wheel command like ``D`` (the last command wins).
``J`` units: speed in pulse/10 ms, acceleration in 1/256 pulse/10 ms per 10 ms (with the classic
Koala's 22'222 pulses/m: 4.5 mm/s and 1.758 mm/s^2, KoreBot ``koala.c``).

Everything here is thread-safe and does no I/O: ``runtime.sim_source`` feeds it lines and readings.
"""

from __future__ import annotations

import math
import threading
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from koala_bridge.core.motion_profile import Trapezoid, ramp_speed, trapezoid
from koala_bridge.drivers.kteam import (
    INT32_MIN,
    KOALA1,
    MANAGEMENT_UNITS,
    KteamLimits,
    command_specs,
    error_reply,
)
from koala_bridge.drivers.messages import KteamCommand, KteamReply, Reject
from koala_bridge.sim.types import BatteryReading, Pose, Readings, WheelCommand

HISTORY = 10
"""Gyro and accelerometer samples kept (the Koala 2.5's ``N`` / ``M`` report the last 10)."""
STANDARD_GRAVITY = 9.80665
"""m/s^2 (CGPM 1901), what a level accelerometer at rest reads on its up axis."""

VERSION_TEXT = "0.1,1.0"
"""``B`` reply fields, KoreBot ``koala.c`` format ``V.R,P.Q``: firmware (BIOS) version.revision,
protocol version.revision. 0.1 = koala-bridge 0.1; the protocol is the classic Koala's, 1.0 (our
numbering: K-Team's real numbers are not known to us)."""


def _wrap_int32(value: int) -> int:
    return (int(value) - INT32_MIN) % 2**32 + INT32_MIN


def _duration(move: tuple[Trapezoid, Trapezoid]) -> float:
    """How long a two-wheel move lasts: until the longer profile ends."""
    return max(move[0].duration, move[1].duration)


class MotorArbiter:
    """Last command received wins; optional watchdog in simulation seconds (0 = off)."""

    def __init__(self, watchdog_s: float = 0.0) -> None:
        self._lock = threading.Lock()
        self._command = WheelCommand(0.0, 0.0)
        self._source = ""
        self._t_command: float | None = None
        self._t_now = 0.0
        self._move: tuple[Trapezoid, Trapezoid] | None = None
        self._ramp: tuple[WheelCommand, float] | None = None   # start speeds, acceleration
        self._applied = WheelCommand(0.0, 0.0)                  # what command() last returned
        self.watchdog_s = watchdog_s

    def set(self, left_mps: float, right_mps: float, source: str) -> None:
        """A command just received from ``source`` (``kteam``, ``can.slcan``, ...)."""
        with self._lock:
            self._command = WheelCommand(float(left_mps), float(right_mps))
            self._source = source
            self._t_command = self._t_now
            self._move = None
            self._ramp = None
            # a set-point applies in full (no acceleration model): a ramp that follows at once
            # starts from it, not from the speeds of the step before
            self._applied = self._command

    def set_ramp(self, left_mps: float, right_mps: float, accel_mps2: float, source: str) -> None:
        """A speed set-point reached from the speeds in force at ``accel_mps2`` (Koala 2.5
        ``K``); then held like :meth:`set`."""
        with self._lock:
            start = self._applied
            self._command = WheelCommand(float(left_mps), float(right_mps))
            self._source = source
            self._t_command = self._t_now
            self._move = None
            self._ramp = (start, float(accel_mps2))

    def set_move(self, left: Trapezoid, right: Trapezoid, source: str) -> None:
        """A position move (profiles in metres, m/s, m/s^2), starting now: the wheels follow its
        speeds until it ends, then stop. The watchdog does not cut a move short."""
        with self._lock:
            self._move = (left, right)
            self._ramp = None
            self._command = WheelCommand(0.0, 0.0)
            self._source = source
            self._t_command = self._t_now

    def move(self) -> tuple[tuple[Trapezoid, Trapezoid] | None, bool]:
        """The position move in force (None in speed mode) and whether its profile has ended."""
        with self._lock:
            t0 = self._t_command if self._t_command is not None else self._t_now
            move = self._move
            return move, move is not None and self._t_now - t0 >= _duration(move)

    def command(self, t: float) -> WheelCommand:
        """The command to apply at simulation time ``t`` (also advances the watchdog's clock)."""
        with self._lock:
            self._applied = self._command_at(t)
            return self._applied

    def _command_at(self, t: float) -> WheelCommand:
        self._t_now = t
        if self._move is not None and self._t_command is not None:
            elapsed = t - self._t_command
            left, right = self._move
            if elapsed < _duration(self._move):
                return WheelCommand(left.velocity(elapsed), right.velocity(elapsed))
            self._command = WheelCommand(0.0, 0.0)
            return self._command
        if (
            self.watchdog_s > 0
            and self._t_command is not None
            and t - self._t_command > self.watchdog_s
        ):
            self._command = WheelCommand(0.0, 0.0)
            self._source = "watchdog"
            self._t_command = None
            self._ramp = None
        if self._ramp is not None and self._t_command is not None:
            start, accel = self._ramp
            elapsed = t - self._t_command
            cmd = WheelCommand(ramp_speed(start.left, self._command.left, accel, elapsed),
                               ramp_speed(start.right, self._command.right, accel, elapsed))
            if cmd == self._command:
                self._ramp = None
            return cmd
        return self._command

    def command_in_force(self) -> WheelCommand:
        """The last speed command, without advancing the watchdog's clock."""
        with self._lock:
            return self._command

    @property
    def source(self) -> str:
        """Where the command in force came from ("" before any)."""
        with self._lock:
            return self._source


@dataclass(frozen=True)
class RobotUnits:
    """Conversion between SI and the Koala's units."""

    ticks_per_metre: float
    speed_unit_s: float                 # K-Team speed unit: pulses per this many seconds

    def kteam_speed_to_mps(self, pulses: float) -> float:
        return pulses / self.speed_unit_s / self.ticks_per_metre

    def kteam_acceleration_to_mps2(self, units: int) -> float:
        """``J`` acceleration: 1 unit = 1/256 speed unit per speed period (KoreBot ``koala.c``:
        about 1.758 mm/s^2 with 4.5 mm/s speed units, 4.5 / 2.56)."""
        return units / (256.0 * self.speed_unit_s**2 * self.ticks_per_metre)

    def pulses_to_m(self, pulses: float) -> float:
        return pulses / self.ticks_per_metre

    def mps_to_kteam_speed(self, v: float) -> int:
        return int(round(v * self.ticks_per_metre * self.speed_unit_s))


def wheel_moves(units: RobotUnits, counters: tuple[int, int], targets: tuple[int, int],
                limits: Sequence[tuple[float, float]]) -> tuple[Trapezoid, Trapezoid]:
    """The rest-to-rest trapezoid of each wheel (left, right) from its counter to its target
    (pulses), with its ``(max speed m/s, acceleration m/s^2)`` of ``limits``: a position move
    (classic ``C``, Koala 2.5 ``F``)."""
    left, right = (trapezoid(units.pulses_to_m(target - pos), v_max, accel)
                   for target, pos, (v_max, accel) in zip(targets, counters, limits, strict=True))
    return left, right


class RobotPort:
    """The latest readings as the robot's controller sees them, plus its counters and LEDs.

    Written by the simulation loop (:meth:`update`), read by bus handlers on other threads.
    Besides the latest reading of each sensor it keeps the last :data:`HISTORY` gyro and
    accelerometer samples (the Koala 2.5 reports 10 at a time).

    The accelerometer is not a simulated sensor of its own: its samples are the specific force of
    the planar robot at the body centre, from the truth pose of each step (``v`` forward speed,
    ``w`` yaw rate): ``f = (dv/dt, v w, g)`` in FLU, m/s^2 -- exact for the simulated motion,
    no noise (no accelerometer error model exists yet).
    """

    def __init__(self, n_ir: int = 16) -> None:
        self._lock = threading.Lock()
        self.n_ir = n_ir
        self._ticks = (0, 0)                # simulator's cumulative counts
        self._offset = (0, 0)               # set by K-Team G
        self._wheel_speeds = WheelCommand(0.0, 0.0)
        self._ir = np.zeros(n_ir, dtype=np.int64)
        self._ambient = np.zeros(n_ir, dtype=np.int64)
        self._sonar: tuple[float, ...] = ()
        self._compass: tuple[float, float, float] | None = None
        self._battery: BatteryReading | None = None
        self._gyro: deque[float] = deque(maxlen=HISTORY)
        self._accel: deque[tuple[float, float, float]] = deque(maxlen=HISTORY)
        self.leds = [0, 0]
        self.t = 0.0
        self._t_prev: float | None = None
        self._pose = Pose(0.0, 0.0, 0.0)
        self._body_speed = 0.0

    def update(self, r: Readings) -> None:
        with self._lock:
            if self._t_prev is not None and r.t > self._t_prev:
                self._accel.append(self._specific_force(r.pose, r.t - self._t_prev))
            self._t_prev = r.t
            self._pose = r.pose
            self.t = r.t
            self._wheel_speeds = r.wheel_speeds
            if r.odometry is not None:
                self._ticks = (int(r.odometry.left_ticks), int(r.odometry.right_ticks))
            if r.ir is not None:
                self._ir = np.asarray(r.ir.counts)
                self._ambient = np.asarray(r.ir.ambient)
            if r.sonar is not None:
                self._sonar = tuple(float(v) for v in r.sonar.ranges)
            if r.gyro is not None:
                self._gyro.append(float(r.gyro.yaw_rate))
            if r.compass is not None:
                f = r.compass.field_uT
                self._compass = (float(f[0]), float(f[1]), float(f[2]))
            if r.battery is not None:
                self._battery = r.battery

    def _specific_force(self, pose: Pose, dt: float) -> tuple[float, float, float]:
        """The body's specific force from its motion (truth pose): forward speed ``v`` and yaw
        rate ``w`` of the step, ``f = (dv/dt, v w, g)`` -- a robot pinned against a wall whose
        wheels spin reads no acceleration, as a real accelerometer would not."""
        prev = self._pose
        c, s = math.cos(prev.theta), math.sin(prev.theta)
        v = ((pose.x - prev.x) * c + (pose.y - prev.y) * s) / dt
        w = math.remainder(pose.theta - prev.theta, math.tau) / dt
        fx, fy = (v - self._body_speed) / dt, v * w
        self._body_speed = v
        if not (math.isfinite(fx) and math.isfinite(fy)):
            fx = fy = 0.0
        return (fx, fy, STANDARD_GRAVITY)

    def sonar(self) -> tuple[float, ...]:
        """The latest sonar ranges, m (nan: no echo); () before the first reading."""
        with self._lock:
            return self._sonar

    def compass(self) -> tuple[float, float, float] | None:
        """The latest magnetometer field, body FLU, uT."""
        with self._lock:
            return self._compass

    def battery(self) -> BatteryReading | None:
        with self._lock:
            return self._battery

    def gyro_history(self) -> list[float]:
        """The last yaw rates (rad/s), newest first."""
        with self._lock:
            return list(reversed(self._gyro))

    def accel_history(self) -> list[tuple[float, float, float]]:
        """The last specific forces (m/s^2, FLU), newest first."""
        with self._lock:
            return list(reversed(self._accel))

    def counters(self) -> tuple[int, int]:
        """Encoder counters as the robot reports them (after ``G``), wrapped to int32."""
        with self._lock:
            return self.robot_counters(self._ticks)

    def robot_counters(self, ticks: tuple[int, int]) -> tuple[int, int]:
        """``ticks`` (simulator counts) as the robot's counters: minus the ``G`` offset."""
        return (_wrap_int32(ticks[0] - self._offset[0]), _wrap_int32(ticks[1] - self._offset[1]))

    def set_counters(self, left: int, right: int) -> None:
        with self._lock:
            self._offset = (self._ticks[0] - left, self._ticks[1] - right)

    def set_led(self, n: int, action: int) -> None:
        """K-Team ``L,n,action``: 0 off, 1 on, 2 toggle."""
        with self._lock:
            self.leds[n] = {0: 0, 1: 1, 2: 1 - self.leds[n]}[action]

    def led_states(self) -> list[int]:
        """``[lateral, frontal]``, 0 off / 1 on (reported in Zenoh ``status`` as ``leds``)."""
        with self._lock:
            return list(self.leds)

    def wheel_speeds(self) -> WheelCommand:
        with self._lock:
            return self._wheel_speeds

    def ir(self) -> tuple[list[int], list[int]]:
        with self._lock:
            return [int(c) for c in self._ir], [int(c) for c in self._ambient]


class KteamResponder:
    """Acts on one parsed classic-Koala (``koala1``) command and returns the reply
    (docs/protocols.md)."""

    dialect = KOALA1

    def __init__(
        self,
        port: RobotPort,
        arbiter: MotorArbiter,
        units: RobotUnits,
        limits: KteamLimits | None = None,
        source: str = "kteam",
    ) -> None:
        self.port = port
        self.arbiter = arbiter
        self.units = units
        self.limits = limits or KteamLimits()
        self.specs = command_specs(self.limits)
        self.source = source
        self._lock = threading.Lock()
        # J profile per wheel: (max speed, acceleration) in K-Team units. The Khepera manual's
        # power-on values (20, 64); the Koala's are not documented where we looked.
        self.profile = [(20, 64), (20, 64)]
        self.speed_pid = (0, 0, 0)          # A: stored, acknowledged; the simulator has no PID
        self.position_pid = (0, 0, 0)       # F: idem
        self.outputs = [0] * self.limits.outputs
        self._targets = (0, 0)              # last C targets, robot counters

    def reject(self, reject: Reject) -> KteamReply:
        return error_reply(reject)

    def auto_lines(self, t: float) -> list[KteamReply]:
        """Lines pushed unasked at simulation time ``t``: none (the classic Koala has no auto
        mode; the Koala 2.5's is :meth:`runtime.koala25_io.Koala25Responder.auto_lines`)."""
        return []

    def respond(self, cmd: KteamCommand) -> KteamReply:
        letter, args = cmd.letter, cmd.args
        lo = letter.lower()
        if letter == "B":
            return KteamReply(lo, tuple(VERSION_TEXT.split(",")))
        if letter in ("A", "F"):
            with self._lock:
                if letter == "A":
                    self.speed_pid = (args[0], args[1], args[2])
                else:
                    self.position_pid = (args[0], args[1], args[2])
            return KteamReply(lo)
        if letter == "J":
            with self._lock:
                self.profile = [(args[0], args[1]), (args[2], args[3])]
            return KteamReply(lo)
        if letter == "C":
            self._start_move(args[0], args[1])
            return KteamReply(lo)
        if letter == "K":
            return KteamReply(lo, tuple(str(v) for v in self._motion_status()))
        if letter == "P":
            # open-loop duty as a fraction of full speed (max_speed pulse/10 ms): the simulator
            # has no motor model, so duty maps linearly to speed
            full = self.limits.max_speed / self.limits.pwm_max
            self._set_speeds(args[0] * full, args[1] * full)
            return KteamReply(lo)
        if letter == "Q":
            with self._lock:
                self.outputs[args[0]] = args[1]
            return KteamReply(lo)
        if letter == "M":
            return KteamReply(lo, (str(self._management(args[0])),))
        if letter == "S":
            bat = self.port.battery()
            return KteamReply(lo, (str(round(bat.charge_mAh) if bat else 0),))
        if letter == "I":
            return KteamReply(lo, ("0",))    # nothing is wired to the analog inputs
        if letter == "Y":
            return KteamReply(lo, ("0",))    # nor to the digital inputs
        if letter == "D":
            self._set_speeds(args[0], args[1])
            return KteamReply(lo)
        if letter == "E":
            ws = self.port.wheel_speeds()
            lim = self.limits.max_speed * 8  # generous clamp: E reports, it does not command
            vals = [
                max(-lim, min(lim, self.units.mps_to_kteam_speed(v))) if math.isfinite(v) else 0
                for v in (ws.left, ws.right)
            ]
            return KteamReply(lo, tuple(str(v) for v in vals))
        if letter == "G":
            self.port.set_counters(args[0], args[1])
            return KteamReply(lo)
        if letter == "H":
            return KteamReply(lo, tuple(str(v) for v in self.port.counters()))
        if letter in ("N", "O"):
            ir, ambient = self.port.ir()
            values = ir if letter == "N" else ambient
            top = self.limits.sensor_max
            return KteamReply(lo, tuple(str(max(0, min(top, v))) for v in values))
        if letter == "L":
            self.port.set_led(*args)
            return KteamReply(lo)
        # parse_command only lets through the letters of command_specs.
        raise AssertionError(f"no handler for K-Team command {letter!r}")

    def _management(self, channel: int) -> int:
        """``M,n``: the battery model's value in the channel's unit (``MANAGEMENT_UNITS``)."""
        bat = self.port.battery()
        if bat is None:
            return 0
        value = (bat.voltage_V, bat.current_A, bat.ambient_temperature_C,
                 bat.motor_currents_A[0], bat.motor_currents_A[1], bat.temperature_C)[channel]
        return max(0, min(0xFFFF, round(value / MANAGEMENT_UNITS[channel])))

    def _set_speeds(self, left: float, right: float) -> None:
        """Command wheel speeds given in K-Team speed units (pulse/10 ms)."""
        self.arbiter.set(
            self.units.kteam_speed_to_mps(left), self.units.kteam_speed_to_mps(right), self.source
        )

    def _start_move(self, left_target: int, right_target: int) -> None:
        now = self.port.counters()
        with self._lock:
            self._targets = (left_target, right_target)
            profile = list(self.profile)
        limits = [(self.units.kteam_speed_to_mps(vmax), self.units.kteam_acceleration_to_mps2(acc))
                  for vmax, acc in profile]
        moves = wheel_moves(self.units, now, (left_target, right_target), limits)
        self.arbiter.set_move(*moves, self.source)

    def _motion_status(self) -> tuple[int, ...]:
        """``K``: per wheel, left then right, (on target 0/1, mode 0 position / 1 speed, error).

        Position mode: error = target - counter, pulses; on target once the profile has ended.
        Speed mode: error = set-point - measured speed, pulse/10 ms; on target when |error| <= 1.
        """
        move, ended = self.arbiter.move()
        if move is not None:
            with self._lock:
                targets = self._targets
            done = int(ended)
            counts = self.port.counters()
            left_err, right_err = (t - c for t, c in zip(targets, counts, strict=True))
            return (done, 0, left_err, done, 0, right_err)
        cmd = self.arbiter.command_in_force()
        ws = self.port.wheel_speeds()
        errs = [
            self.units.mps_to_kteam_speed(c - m) if math.isfinite(c - m) else 0
            for c, m in ((cmd.left, ws.left), (cmd.right, ws.right))
        ]
        return (int(abs(errs[0]) <= 1), 1, errs[0], int(abs(errs[1]) <= 1), 1, errs[1])
