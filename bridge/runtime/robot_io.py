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

Everything here is thread-safe and does no I/O: ``runtime.sim_source`` feeds it lines and readings.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

import numpy as np
from koala_bridge.drivers.kteam import INT32_MIN, KteamLimits, command_specs, error_reply
from koala_bridge.drivers.messages import KteamCommand, KteamReply, Reject
from koala_bridge.sim.types import Readings, WheelCommand

VERSION_TEXT = "koala-bridge 0.1.0"


def _wrap_int32(value: int) -> int:
    return (int(value) - INT32_MIN) % 2**32 + INT32_MIN


class MotorArbiter:
    """Last command received wins; optional watchdog in simulation seconds (0 = off)."""

    def __init__(self, watchdog_s: float = 0.0) -> None:
        self._lock = threading.Lock()
        self._command = WheelCommand(0.0, 0.0)
        self._source = ""
        self._t_command: float | None = None
        self._t_now = 0.0
        self.watchdog_s = watchdog_s

    def set(self, left_mps: float, right_mps: float, source: str) -> None:
        """A command just received from ``source`` (``kteam``, ``can.slcan``, ...)."""
        with self._lock:
            self._command = WheelCommand(float(left_mps), float(right_mps))
            self._source = source
            self._t_command = self._t_now

    def command(self, t: float) -> WheelCommand:
        """The command to apply at simulation time ``t`` (also advances the watchdog's clock)."""
        with self._lock:
            self._t_now = t
            if (
                self.watchdog_s > 0
                and self._t_command is not None
                and t - self._t_command > self.watchdog_s
            ):
                self._command = WheelCommand(0.0, 0.0)
                self._source = "watchdog"
                self._t_command = None
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

    def kteam_speed_to_mps(self, pulses: int) -> float:
        return pulses / self.speed_unit_s / self.ticks_per_metre

    def mps_to_kteam_speed(self, v: float) -> int:
        return int(round(v * self.ticks_per_metre * self.speed_unit_s))


class RobotPort:
    """The latest readings as the robot's controller sees them, plus its counters and LEDs.

    Written by the simulation loop (:meth:`update`), read by bus handlers on other threads.
    """

    def __init__(self, n_ir: int = 16) -> None:
        self._lock = threading.Lock()
        self.n_ir = n_ir
        self._ticks = (0, 0)                # simulator's cumulative counts
        self._offset = (0, 0)               # set by K-Team G
        self._wheel_speeds = WheelCommand(0.0, 0.0)
        self._ir = np.zeros(n_ir, dtype=np.int64)
        self._ambient = np.zeros(n_ir, dtype=np.int64)
        self.leds = [0, 0]
        self.t = 0.0

    def update(self, r: Readings) -> None:
        with self._lock:
            self.t = r.t
            self._wheel_speeds = r.wheel_speeds
            if r.odometry is not None:
                self._ticks = (int(r.odometry.left_ticks), int(r.odometry.right_ticks))
            if r.ir is not None:
                self._ir = np.asarray(r.ir.counts)
                self._ambient = np.asarray(r.ir.ambient)

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
    """Acts on one parsed K-Team command and returns the reply (docs/protocols.md)."""

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

    def reject(self, reject: Reject) -> KteamReply:
        return error_reply(reject)

    def respond(self, cmd: KteamCommand) -> KteamReply:
        letter, args = cmd.letter, cmd.args
        lo = letter.lower()
        if letter == "B":
            return KteamReply(lo, (VERSION_TEXT,))
        if letter == "D":
            self.arbiter.set(
                self.units.kteam_speed_to_mps(args[0]),
                self.units.kteam_speed_to_mps(args[1]),
                self.source,
            )
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
