"""The emulated Koala 2.5: its command set (``[buses.kteam] dialect = "koala25"``) and auto mode.

:class:`Koala25Responder` answers the Koala 2.5 commands (:mod:`koala_bridge.drivers.koala25`,
docs/protocols.md §1 "Koala 2.5 (koala25) commands") from the latest simulator readings held by
:class:`runtime.robot_io.RobotPort`, and commands the wheels through the same
:class:`runtime.robot_io.MotorArbiter` as the classic dialect and CAN (the last command wins).
:meth:`Koala25Responder.auto_lines` gives the lines auto mode (``A,bits``) pushes at a simulation
time; the simulation loop writes them.

Motion (the manual's controller modes, reported by ``Y``):

- ``D`` speed (mode 1): the set-point applies from the next step, as the classic ``D``.
- ``K`` speed with ramp (mode 2): the speeds move to the set-point at the ``J`` acceleration.
- ``F`` position (mode 3): a rest-to-rest trapezoid to the targets with the ``J`` profile's
  cruise speed (at most ``[robot] max_wheel_speed_mps``) and acceleration, followed open loop as
  the classic ``C``; on target (``Y`` 3rd/4th field) once the
  profile has ended and the counter is within ``pos_margin`` of the target.
- ``L`` open loop (mode 4): duty / 2940 of full wheel speed (no motor model).
- mode 5 (current limitation) is reported while a motor's current (the battery model's,
  ``sim/battery.py``) exceeds ``J``'s ``max_current``; the simulation does not limit the torque.

``J,acc_inc,acc_div,min_speed,cst_speed,pos_margin,max_current`` -- our reading of the manual's
field names (its text gives ranges, not the arithmetic): the acceleration is
``acc_inc / (acc_div + 1)`` speed units per 10 ms control period (the defaults 5, 1 give 2.5
units per 10 ms, 0.28 m/s^2 with the Koala 2.5's 1.1 mm/s unit); ``cst_speed`` is the cruise
speed of an ``F`` move; ``min_speed`` is kept but not used (the trapezoid ends at rest).
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

from koala_bridge.drivers.koala25 import (
    ACCEL_G_PER_UNIT,
    AUTO_BITS,
    AUTO_COMMANDS,
    GYRO_DEG_S_PER_UNIT,
    KOALA25,
    SAMPLES,
    SONARS,
    US_DISABLED,
    US_NEAR,
    US_NONE,
    US_RANGE_CM,
    VERSION_REPLY,
)
from koala_bridge.drivers.messages import KteamCommand, KteamReply, Reject
from koala_bridge.runtime.robot_io import (
    STANDARD_GRAVITY,
    MotorArbiter,
    RobotPort,
    RobotUnits,
    wheel_moves,
)

#: Controller modes reported by ``Y`` (Koala 2.5 manual).
IDLE, SPEED, SPEED_ACCEL, POSITION, OPEN_LOOP, CURRENT_LIMIT = 0, 1, 2, 3, 4, 5
PWM_FULL = 2940
"""``L`` duty of full speed (the manual's range; libkoala's comment says 2000)."""
GPS_NO_FIX = ("V", "0", "0.0", "N", "0.0", "E", "00:00:00", "00.00.00", "0.0", "0")
"""``Q`` without a GPS fix: valid flag ``V`` (void), 0 satellites; the 14 fields libkoala's
``koala_read_gps_data`` parses. The simulated robot has no GPS."""
BATTERY_TYPE = {"Li-ion": 0, "NiMH": 1}
"""``V`` battery type codes (manual: 0 Li-ION, 1 NiMH, 2 not initialised)."""

#: Power-on values (libkoala's ``koala_robot.h`` defaults).
DEFAULT_PID = (10, 3, 1)
DEFAULT_PROFILE = (5, 1, 10, 200, 10, 10)
DEFAULT_US_MASK = 0x1FF


@dataclass(frozen=True)
class AutoRates:
    """Auto-mode periods, s (the manual's: sonar 20 ms per enabled sensor, accelerometer and
    gyro 10 samples per ~100 ms, magnetometer 10 Hz; speed, position and current: no rate given,
    10 Hz is our choice)."""

    sonar_per_sensor: float = 0.020
    accel: float = 0.100
    gyro: float = 0.100
    magnetometer: float = 0.100
    motors: float = 0.100


_AUTO_RATE = {"sonar": "sonar_per_sensor", "speed": "motors", "position": "motors",
              "current": "motors", "accel": "accel", "gyro": "gyro",
              "magnetometer": "magnetometer"}
"""The :class:`AutoRates` field of each auto-mode stream (``AUTO_COMMANDS``)."""


class Koala25Responder:
    """Acts on one parsed Koala 2.5 command and returns the reply; produces auto-mode lines."""

    dialect = KOALA25

    def __init__(
        self,
        port: RobotPort,
        arbiter: MotorArbiter,
        units: RobotUnits,
        max_wheel_speed_mps: float,
        battery_type: str = "NiMH",
        source: str = "kteam",
        rates: AutoRates | None = None,
    ) -> None:
        self.port = port
        self.arbiter = arbiter
        self.units = units
        self.max_wheel_speed_mps = max_wheel_speed_mps
        self.battery_type = BATTERY_TYPE.get(battery_type, 2)
        self.source = source
        self.rates = rates or AutoRates()
        self.specs = KOALA25.specs
        self._lock = threading.Lock()
        self._power_on()

    def _power_on(self) -> None:
        self.auto_bits = 0
        self.us_mask = DEFAULT_US_MASK
        self.io_dir = 0
        self.pid = DEFAULT_PID
        self.profile = DEFAULT_PROFILE
        self.outputs = (0, 0, 0, 0, 0)
        self.mode = [IDLE, IDLE]
        self._targets = (0, 0)
        self._next_due: dict[str, float] = {}
        self._auto_t0 = 0.0

    # -- commands ----------------------------------------------------------------------------

    def reject(self, reject: Reject) -> KteamReply:
        return KOALA25.error_reply(reject)

    def respond(self, cmd: KteamCommand) -> KteamReply:  # noqa: C901, PLR0911, PLR0912 (a table)
        letter, a = cmd.letter, cmd.args
        reply = KOALA25.reply
        if letter == "B":
            return KteamReply("b", (VERSION_REPLY.split(",")[1],))
        if letter == "A":
            with self._lock:
                self.auto_bits = a[0]
                self._next_due = {}
                self._auto_t0 = self.port.t     # the streams' periods count from here
            return reply("A")
        if letter == "C":
            with self._lock:
                self.us_mask, self.io_dir = a[0], a[1]
            return reply("C")
        if letter == "D":
            self._speed(a[0], a[1], SPEED)
            return reply("D")
        if letter == "K":
            self._speed(a[0], a[1], SPEED_ACCEL)
            return reply("K")
        if letter == "L":
            full = self.max_wheel_speed_mps / PWM_FULL
            self.arbiter.set(a[0] * full, a[1] * full, self.source)
            self._set_mode(OPEN_LOOP)
            return reply("L")
        if letter == "F":
            self._position_move(a[0], a[1])
            return reply("F")
        if letter == "I":
            if self.arbiter.move()[0] is not None:   # the manual: I stops a position move
                self.arbiter.set(0.0, 0.0, self.source)
            self.port.set_counters(a[0], a[1])
            return reply("I")
        if letter == "H":
            with self._lock:
                self.pid = (a[0], a[1], a[2])
            return reply("H")
        if letter == "J":
            with self._lock:
                self.profile = (a[0], a[1], a[2], a[3], a[4], a[5])
            return reply("J")
        if letter == "S":
            with self._lock:
                self.outputs = (a[0], a[1], a[2], a[3], a[4])
            return reply("S")
        if letter in ("W", "X"):
            return reply(letter)        # no I2C device, no GPS: accepted, nothing happens
        if letter == "Z":
            self.reset()
            return reply("Z")
        return reply(letter, self._read(letter, a))

    def _read(self, letter: str, a: tuple[int, ...]) -> tuple[object, ...]:  # noqa: PLR0911
        """The fields of a read command's reply."""
        if letter == "E":
            return tuple(self._speed_units(v) for v in self._wheel_speeds())
        if letter == "P":
            return self.port.counters()
        if letter == "G":
            return self.sonar_cm()
        if letter == "M":
            return self.accel_raw()
        if letter == "N":
            return self.gyro_raw()
        if letter == "O":
            return self.motor_currents()
        if letter == "V":
            return self.battery_fields()
        if letter == "Y":
            return self.status()
        if letter == "&":
            return self.magnetometer_mgauss()
        if letter == "T":
            with self._lock:
                # IO pins configured as outputs (C's 2-bit direction 00) show S's values
                io = sum(1 << i for i in range(4)
                         if (self.io_dir >> (2 * i)) & 3 == 0 and self.outputs[1 + i])
            return (io, 0)
        if letter == "U":
            return (0, 0)               # nothing is wired to the analog inputs
        if letter == "Q":
            return GPS_NO_FIX
        if letter == "R":
            return (0,) * a[2]          # no I2C device is simulated: registers read 0
        if letter == "?":
            return (0,)                 # the I2C scan finds no device
        # parse_command only lets through the letters of KOALA25.specs.
        raise AssertionError(f"no handler for Koala 2.5 command {letter!r}")

    def reset(self) -> None:
        """``Z``: the microcontroller restarts: wheels stop, counters 0, power-on settings."""
        self.arbiter.set(0.0, 0.0, self.source)
        self.port.set_counters(0, 0)
        with self._lock:
            self._power_on()

    # -- readings in the robot's units ---------------------------------------------------------

    def sonar_cm(self) -> tuple[int, ...]:
        """``G``: per sensor 0 (closer than 25 cm), 25..250 cm, 1000 (nothing), 2000 (disabled)."""
        ranges = self.port.sonar()
        with self._lock:
            mask = self.us_mask
        out = []
        for i in range(SONARS):
            r = ranges[i] if i < len(ranges) else math.nan
            if not (mask >> i) & 1:
                out.append(US_DISABLED)
            elif not math.isfinite(r):
                out.append(US_NONE)
            elif r * 100.0 < US_RANGE_CM[0]:
                out.append(US_NEAR)
            else:
                out.append(min(US_RANGE_CM[1], round(r * 100.0)))
        return tuple(out)

    def accel_raw(self) -> tuple[int, ...]:
        """``M``: the last 10 accelerometer samples x, y, z (1/16384 g), newest first."""
        hist = self.port.accel_history()
        hist += [(0.0, 0.0, STANDARD_GRAVITY)] * (SAMPLES - len(hist))
        scale = 1.0 / (STANDARD_GRAVITY * ACCEL_G_PER_UNIT)
        return tuple(_i16(c * scale) for sample in hist[:SAMPLES] for c in sample)

    def gyro_raw(self) -> tuple[int, ...]:
        """``N``: the last 10 gyro samples x, y, z (0.066 deg/s), newest first. The simulated
        gyro measures yaw (z) with its error model (``[sensors.gyro]``, as on CAN); x and y of a
        robot on a level floor are 0."""
        hist = self.port.gyro_history()
        hist += [0.0] * (SAMPLES - len(hist))
        scale = 180.0 / math.pi / GYRO_DEG_S_PER_UNIT
        return tuple(v for z in hist[:SAMPLES] for v in (0, 0, _i16(z * scale)))

    def magnetometer_mgauss(self) -> tuple[int, int, int]:
        """``&``: the magnetometer (``[sensors.compass]`` model, as on MAVLink), body FLU,
        mGauss (1 uT = 10 mGauss)."""
        field = self.port.compass() or (0.0, 0.0, 0.0)
        return (_i16(field[0] * 10.0), _i16(field[1] * 10.0), _i16(field[2] * 10.0))

    def motor_currents(self) -> tuple[int, int]:
        """``O``: motor currents, 0.1 A, signed with the wheel's direction."""
        bat = self.port.battery()
        if bat is None:
            return (0, 0)
        speeds = self._wheel_speeds()
        return tuple(  # type: ignore[return-value]
            round(math.copysign(i, v if math.isfinite(v) else 0.0) * 10.0)
            for i, v in zip(bat.motor_currents_A, speeds, strict=True)
        )

    def battery_fields(self) -> tuple[int, int, int, int]:
        """``V``: type, voltage (0.1 V), current (0.1 A), charge current (10 mA; no charger: 0)."""
        bat = self.port.battery()
        if bat is None:
            return (2, 0, 0, 0)
        return (self.battery_type, round(bat.voltage_V * 10.0), round(bat.current_A * 10.0), 0)

    def status(self) -> tuple[int, int, int, int]:
        """``Y``: control mode left, right; on target left, right (position mode)."""
        move, ended = self.arbiter.move()
        with self._lock:
            modes = list(self.mode)
            targets, margin, max_current = self._targets, self.profile[4], self.profile[5]
        on_target = [0, 0]
        if move is not None:
            counts = self.port.counters()
            on_target = [int(ended and abs(t - c) <= margin)
                         for t, c in zip(targets, counts, strict=True)]
        elif modes == [POSITION, POSITION]:
            on_target = [1, 1]          # a move ended, or was replaced by a stop
        bat = self.port.battery()
        if bat is not None and max_current > 0:
            for i, current in enumerate(bat.motor_currents_A):
                if current > max_current / 10.0:
                    modes[i] = CURRENT_LIMIT
        return (modes[0], modes[1], on_target[0], on_target[1])

    # -- auto mode ---------------------------------------------------------------------------

    def auto_lines(self, t: float) -> list[KteamReply]:
        """The lines auto mode pushes at simulation time ``t`` (call once per step)."""
        with self._lock:
            if not self.auto_bits:
                return []
            letters = [letter for name, letter in AUTO_COMMANDS.items()
                       if self.auto_bits & AUTO_BITS[name] and self._due(name, t)]
        return [KOALA25.reply(letter, self._read(letter, ())) for letter in letters]

    def _due(self, name: str, t: float) -> bool:
        """Whether auto-mode stream ``name`` pushes at ``t`` (and schedules its next push);
        the caller holds the lock."""
        period = getattr(self.rates, _AUTO_RATE[name])
        if name == "sonar":
            period *= bin(self.us_mask & 0x1FF).count("1")
        if period <= 0:
            return False
        due = self._next_due.get(name)
        if due is None:
            due = self._next_due[name] = self._auto_t0 + period
        if t + 1e-9 < due:
            return False
        # on the grid from A; a late call (a stalled loop) skips the missed pushes
        self._next_due[name] = due + period if t < due + period else t + period
        return True

    # -- helpers -----------------------------------------------------------------------------

    def _wheel_speeds(self) -> tuple[float, float]:
        ws = self.port.wheel_speeds()
        return (ws.left, ws.right)

    def _speed_units(self, v: float) -> int:
        return _i16(self.units.mps_to_kteam_speed(v)) if math.isfinite(v) else 0

    def _accel_mps2(self) -> float:
        with self._lock:
            acc_inc, acc_div = self.profile[0], self.profile[1]
        per_period = acc_inc / (acc_div + 1.0)            # speed units per 10 ms
        return self.units.kteam_speed_to_mps(per_period) / self.units.speed_unit_s

    def _speed(self, left: int, right: int, mode: int) -> None:
        to_mps = self.units.kteam_speed_to_mps
        if mode == SPEED_ACCEL:
            self.arbiter.set_ramp(to_mps(left), to_mps(right), self._accel_mps2(), self.source)
        else:
            self.arbiter.set(to_mps(left), to_mps(right), self.source)
        self._set_mode(mode)

    def _position_move(self, left_target: int, right_target: int) -> None:
        now = self.port.counters()
        with self._lock:
            self._targets = (left_target, right_target)
            cruise = self.profile[3]
        accel = self._accel_mps2()
        # the motors cannot cruise faster than the robot's top wheel speed ([robot])
        v_max = min(self.units.kteam_speed_to_mps(cruise), self.max_wheel_speed_mps)
        moves = wheel_moves(self.units, now, (left_target, right_target), [(v_max, accel)] * 2)
        self.arbiter.set_move(*moves, self.source)
        self._set_mode(POSITION)

    def _set_mode(self, mode: int) -> None:
        with self._lock:
            self.mode = [mode, mode]


def _i16(value: float) -> int:
    """Round to the nearest integer and clip to a signed 16-bit register."""
    if not math.isfinite(value):
        return 0
    return max(-32768, min(32767, round(value)))
