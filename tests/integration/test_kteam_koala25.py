"""The Koala 2.5 dialect (``koala25``) as K-Team's ``libkoala`` drives it.

The client below, :class:`LibKoala`, is written from the library and the manual, not from the
bridge's code: K-Team ``libkoala`` 1.0 (``src/koala_serial.c``, ``src/koala_robot.c``,
``src/koala_robot.h``; J. Tharin, K-Team S.A. 2013) and the *Koala 2.5 User Manual* rev 1.3 §6
"Serial communication protocol". It mirrors what the library does, byte for byte:

- the port is opened as ``koala_rs232_open`` opens it: ``O_RDWR | O_NOCTTY | O_NONBLOCK``, then
  blocking, ``c_cflag = CS8 | CLOCAL | CREAD | B115200`` (115200 8N1, no flow control),
  ``c_iflag = IGNPAR``, ``c_oflag = c_lflag = 0`` (raw: no CR/LF translation either way),
  ``VMIN = 1``, ``VTIME = 1``;
- every command is the exact ``sprintf`` of the library, ended by ``'\\r'``;
- a reply line is read as ``koala_rs232_readLine`` reads it: one byte at a time up to the first
  ``'\\r'`` or ``'\\n'`` (not stored). A reply ended by CR LF therefore leaves an empty line that
  the *next* call reads, and fails -- as libkoala would;
- each reply is checked by its first character as the library checks it (the lower-case command
  letter; ``'@'`` for ``&``) and parsed with the library's ``sscanf`` formats or ``process_param``
  (``strtok`` on ``","`` from ``buffer + 2``, ``%d`` per token, up to n tokens);
- ``koala_get_firmware_version`` sends ``'B','\\r'`` and does ONE raw ``read(fd, buf, 7)``:
  ``b,A-02`` plus one terminator, ``version = buffer[2]``, ``revision = atoi(buffer + 4)``.

The one deliberate difference: libkoala waits 500 ms (``select``) for a reply and then blocks;
the client waits :data:`REPLY_TIMEOUT_S` for every byte, so a slow machine does not fail a test
and a missing terminator fails instead of hanging.

The tests run a ``koala-bridge run --config config/koala25.toml --set
buses.kteam.dialect=koala25`` subprocess and find its K-Team pty in the endpoints file
(tests/conftest.py ``bridge``). Simulated time comes from the
Zenoh ``truth/pose`` stream; every bound is derived in the test from the library's units, the
manual, config/koala25.toml or the Zenoh ``world`` answer -- never from what the bridge printed.
Waits are on conditions with a generous deadline.
"""

from __future__ import annotations

import fcntl
import math
import os
import re
import select
import termios
import time
import tomllib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import pytest
from conftest import REPO, BridgeProcess, ZenohWatch

# The Koala 2.5 robot (libkoala's geometry and units, its battery) with the koala25 dialect; the
# tests also pass --set buses.kteam.dialect=koala25, so they hold for any config that sets it.
KOALA25_CONFIG = REPO / "config" / "koala25.toml"
DEADLINE_S = 90.0          # wall-clock bound on a condition, generous for a busy machine
REPLY_TIMEOUT_S = 10.0     # per byte; libkoala's koala_rs232_readLine waits 500 ms
LINE_LENGTH = 256          # koala_serial.c LineLength: at most 255 bytes per line

# koala_robot.h
KOALA_ACCEL_G = 1.0 / 16384.0           # accelerometer raw unit, g
KOALA_GYRO_DEG_S = 66.0 / 1000.0        # gyroscope raw unit, deg/s (the manual: 360/5898)
KOALA_US_OBJECT_NEAR = 0
KOALA_US_NO_OBJECT_IN_RANGE = 1000
KOALA_US_DISABLED_SENSOR = 2000
KOALA_US_RANGE_CM = (25, 250)           # manual: "25–250 = distance"
KOALA_WHEEL_DIAM_MM = 82.5
KOALA_PULSE_TO_MM = math.pi * KOALA_WHEEL_DIAM_MM / 23400.0
KOALA_SPEED_TO_MM_S = KOALA_PULSE_TO_MM / 0.010   # one speed unit = one pulse per 10 ms

AUTO_US = 1 << 0          # KOALA_AUTOM_US_SENSOR_BIT
AUTO_SPEED = 1 << 1       # KOALA_AUTOM_MOTOR_SPEED
AUTO_POSITION = 1 << 2    # KOALA_AUTOM_MOTOR_POSITION
AUTO_CURRENT = 1 << 3     # KOALA_AUTOM_MOTOR_CURRENT
AUTO_ACCEL = 1 << 4       # KOALA_AUTOM_ACCEL_VALUE
AUTO_GYRO = 1 << 5        # KOALA_AUTOM_GYRO_VALUE
AUTO_MAGNE = 1 << 8       # KOALA_AUTOM_MAGNE_VALUE

# Y: MotL_CTRL / MotR_CTRL (manual)
MODE_IDLE, MODE_SPEED, MODE_SPEED_ACCEL, MODE_POSITION, MODE_OPEN_LOOP = 0, 1, 2, 3, 4

# Every first character some libkoala function accepts as success: a lower-case letter (the
# command's own), '@' (&) and '!' (?). libkoala pairs a reply with a request only by order, so an
# error reply starting with any of these could be read as a success.
LIBKOALA_SUCCESS_CHARS = frozenset("abcdefghijklmnopqrstuvwxyz@!")

ACCEL_TOL_G = 2 * KOALA_ACCEL_G   # at rest, ideal: 1 g to the raw quantum (and its rounding)

_INT = re.compile(rb"\s*([+-]?\d+)")


def _sscanf_ints(text: str, n: int) -> tuple[int, ...] | None:
    """``sscanf(buffer, "%*c,%d,%d,...")`` with ``n`` ``%d``: the values, or None when fewer
    than ``n`` convert (the library's field-count check)."""
    data = text.encode("ascii", "replace")
    if len(data) < 2 or data[1:2] != b",":
        return None
    pos, out = 2, []
    for i in range(n):
        if i:
            if data[pos:pos + 1] != b",":
                return None
            pos += 1
        m = _INT.match(data, pos)
        if m is None:
            return None
        out.append(int(m.group(1)))
        pos = m.end()
    return tuple(out)


def process_param(text: str, n: int) -> list[int | None]:
    """libkoala ``process_param(buffer + 2, dest, n)``: ``strtok`` on "," (empty tokens skipped),
    ``sscanf(token, "%d")`` on each of the first ``n``; a token that does not convert leaves its
    slot unset (None here). Like the library, it does not check that ``n`` tokens came."""
    tokens = [t for t in text[2:].split(",") if t][:n]
    out: list[int | None] = []
    for token in tokens:
        m = _INT.match(token.encode("ascii", "replace"))
        out.append(int(m.group(1)) if m else None)
    return out


def _atoi(data: bytes) -> int:
    m = re.match(rb"\s*([+-]?\d+)", data)
    return int(m.group(1)) if m else 0


class LibKoalaError(AssertionError):
    """A libkoala function returned a negative code (``code``) on ``line``."""

    def __init__(self, function: str, code: int, line: str | bytes | None) -> None:
        super().__init__(f"{function} returned {code} on {line!r}")
        self.code = code
        self.line = line


class LibKoala:
    """libkoala's functions over a pty (names as in ``koala_robot.c``)."""

    def __init__(self, path: str) -> None:
        # koala_serial.c koala_rs232_open
        self.fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        try:
            fcntl.fcntl(self.fd, fcntl.F_SETFL, 0)  # blocking input
            attrs = termios.tcgetattr(self.fd)
            attrs[0] = termios.IGNPAR
            attrs[1] = 0
            attrs[2] = termios.CS8 | termios.CLOCAL | termios.CREAD | termios.B115200
            attrs[3] = 0
            attrs[4] = attrs[5] = termios.B115200
            attrs[6][termios.VMIN] = 1
            attrs[6][termios.VTIME] = 1
            termios.tcsetattr(self.fd, termios.TCSANOW, attrs)
        except BaseException:
            os.close(self.fd)
            raise
        self.terminators: set[bytes] = set()   # every line terminator seen

    def close(self) -> None:
        os.close(self.fd)

    # -- koala_serial.c ---------------------------------------------------------------------

    def sendcommand(self, command: str) -> None:
        """``koala_sendcommand``: one ``write`` of the command and its ``'\\r'``."""
        data = command.encode("ascii") + b"\r"
        assert os.write(self.fd, data) == len(data)

    def _readable(self, timeout: float) -> bool:
        return bool(select.select([self.fd], [], [], timeout)[0])

    def read_line(self, timeout: float = REPLY_TIMEOUT_S) -> str | None:
        """``koala_rs232_readLine``: None on timeout (-2), else the bytes up to the first CR or
        LF, terminator dropped ("" for an empty line)."""
        if not self._readable(timeout):
            return None
        buf = bytearray()
        while len(buf) < LINE_LENGTH - 1:
            assert self._readable(REPLY_TIMEOUT_S), f"line without terminator: {bytes(buf)!r}"
            byte = os.read(self.fd, 1)
            assert byte, "port closed"
            if byte in (b"\r", b"\n"):
                self.terminators.add(byte)
                break
            buf += byte
        return buf.decode("ascii", "replace")

    def read_line_nowait(self) -> str | None:
        """``koala_rs232_readLine_nowait``: a line only if a byte is already waiting."""
        return self.read_line(timeout=0.0)

    def getcommand(self, n: int, timeout: float = REPLY_TIMEOUT_S) -> bytes:
        """``koala_getcommand(buf, n)``: ONE ``read(fd, buf, n)`` (VMIN 1, VTIME 1: it returns
        what has arrived once the line is quiet for 0.1 s). libkoala blocks; we wait for the
        first byte ``timeout`` s at most, so a silent bridge fails instead of hanging."""
        if not self._readable(timeout):
            return b""
        return os.read(self.fd, n)

    # -- koala_robot.c ----------------------------------------------------------------------

    def _command(self, function: str, request: str, expect: str) -> str:
        self.sendcommand(request)
        line = self.read_line()
        if line is None:
            raise LibKoalaError(function, -2, line)
        if line[:1] != expect:
            raise LibKoalaError(function, -1, line)
        return line

    def _ints(self, function: str, request: str, expect: str, n: int) -> tuple[int, ...]:
        line = self._command(function, request, expect)
        values = _sscanf_ints(line, n)
        if values is None:
            raise LibKoalaError(function, -2, line)
        return values

    def _params(self, function: str, request: str, expect: str, n: int) -> list[int]:
        line = self._command(function, request, expect)
        values = process_param(line, n)
        # libkoala does not check the count; the tests do (a short reply is a bridge bug)
        assert len(values) == n and None not in values, f"{function}: {line!r}"
        return [int(v) for v in values if v is not None]

    def get_firmware_version(self) -> tuple[str, int]:
        """``koala_get_firmware_version``: ``'B','\\r'``, then one raw 7-byte read."""
        self.sendcommand("B")
        buf = self.getcommand(7)
        if buf[:1] != b"b":
            raise LibKoalaError("koala_get_firmware_version", -3, buf)
        if len(buf) != 7:
            raise LibKoalaError("koala_get_firmware_version", -4, buf)
        version = chr(buf[2])
        revision = _atoi(buf[4:])
        return version, revision

    def reset_microcontroller(self) -> None:
        self._command("koala_reset_microcontroller", "Z", "z")

    def configure_auto_monitoring_mode(self, bit_config: int) -> None:
        self._command("koala_configure_auto_monitoring_mode", f"A,{bit_config}", "a")

    def configure_us_io(self, us_mask: int, io_dir: int) -> None:
        self._command("koala_configure_us_io", f"C,{us_mask},{io_dir}", "c")

    def set_motor_speed(self, left: int, right: int) -> None:
        self._command("koala_set_motor_speed", f"D,{left},{right}", "d")

    def read_motor_speed(self) -> tuple[int, int]:
        left, right = self._ints("koala_read_motor_speed", "E", "e", 2)
        return left, right

    def set_motor_target_position(self, left: int, right: int) -> None:
        self._command("koala_set_motor_target_position", f"F,{left},{right}", "f")

    def read_us_sensors(self) -> list[int]:
        return self._params("koala_read_us_sensors", "G", "g", 9)

    def configure_pid(self, kp: int, ki: int, kd: int) -> None:
        self._command("koala_configure_pid", f"H,{kp},{ki},{kd}", "h")

    def set_motor_encoders(self, left: int, right: int) -> None:
        self._command("koala_set_motor_encoders", f"I,{left},{right}", "i")

    def set_speed_profile(self, acc_inc: int, acc_div: int, min_speed: int, cst_speed: int,
                          pos_margin: int, max_current: int) -> None:
        self._command(
            "koala_set_speed_profile",
            f"J,{acc_inc},{acc_div},{min_speed},{cst_speed},{pos_margin},{max_current}", "j")

    def set_motor_speed_accel(self, left: int, right: int) -> None:
        self._command("koala_set_motor_speed_accel", f"K,{left},{right}", "k")

    def set_motor_speed_open_loop(self, left: int, right: int) -> None:
        self._command("koala_set_motor_speed_open_loop", f"L,{left},{right}", "l")

    def read_accelerometer(self) -> list[int]:
        return self._params("koala_read_accelerometer", "M", "m", 30)

    def read_gyroscope(self) -> list[int]:
        return self._params("koala_read_gyroscope", "N", "n", 30)

    def read_motor_current(self) -> tuple[int, int]:
        left, right = self._ints("koala_read_motor_current", "O", "o", 2)
        return left, right

    def read_motor_position(self) -> tuple[int, int]:
        left, right = self._ints("koala_read_motor_position", "P", "p", 2)
        return left, right

    def get_battery_data(self) -> tuple[int, int, int, int]:
        """``bat_type, bat_voltage (0.1 V), bat_current (0.1 A), chrg_current (10 mA)``."""
        t, v, i, c = self._ints("koala_get_battery_data", "V", "v", 4)
        return t, v, i, c

    def get_motor_status(self) -> tuple[int, int, int, int]:
        """``MotL_CTRL, MotR_CTRL, MotL_OnTrg, MotR_OnTrg``."""
        a, b, c, d = self._ints("koala_get_motor_status", "Y", "y", 4)
        return a, b, c, d

    def read_magnetometer(self) -> list[int]:
        return self._params("koala_read_magnetometer", "&", "@", 3)

    def read_gps(self) -> tuple[Any, ...]:
        """``koala_gps_data``: all 14 fields of ``sscanf(buffer,
        "%*c,%c,%d,%lf,%c,%lf,%c,%d:%d:%d,%d.%d.%d,%lf,%d")`` must convert."""
        line = self._command("koala_gps_data", "Q", "q")
        num, i = r"\s*([+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?)", r"\s*([+-]?\d+)"
        m = re.match(rf"q,(.),{i},{num},(.),{num},(.),{i}:{i}:{i},{i}\.{i}\.{i},{num},{i}",
                     line)
        if m is None:
            raise LibKoalaError("koala_gps_data", -2, line)
        return m.groups()

    def scan_i2c(self) -> list[int]:
        """``koala_scan_i2c``: ``'!'``, then the count, then that many addresses."""
        line = self._command("koala_scan_i2c", "?", "!")
        values = process_param(line, 128)
        if not values or None in values or len(values) != 1 + (values[0] or 0):
            raise LibKoalaError("koala_scan_i2c", -2, line)
        return [int(v) for v in values[1:] if v is not None]

    def read_i2c(self, addr: int, reg: int, n: int) -> list[int]:
        values = self._params("koala_read_i2c", f"R,{addr},{reg},{n}", "r", n)
        return values

    def write_i2c(self, addr: int, reg: int, data: list[int]) -> None:
        self._command("koala_write_i2c", f"W,{addr},{reg}" + "".join(f",{d}" for d in data), "w")

    def send_gps_cmd(self, text: str) -> None:
        self._command("koala_send_gps_cmd", f"X,{text}", "x")

    def set_pwr_io_output(self, pwr: int, io0: int, io1: int, io2: int, io3: int) -> None:
        self._command("koala_set_pwr_io_output", f"S,{pwr},{io0},{io1},{io2},{io3}", "s")

    def read_io(self) -> tuple[int, int]:
        io, inputs = self._ints("koala_read_io", "T", "t", 2)
        return io, inputs

    def read_ad(self) -> tuple[int, int]:
        ad0, ad1 = self._ints("koala_read_ad", "U", "u", 2)
        return ad0, ad1

    def get_from_auto_mode(self) -> tuple[str, Any] | None:
        """``koala_get_from_auto_mode``: None if no line waits (-1), else (mode, data); an
        unknown mode or a failed parse raises with the library's code."""
        line = self.read_line_nowait()
        if line is None:
            return None
        mode = line[:1]
        two = {"e": -2, "o": -6, "p": -7}
        many = {"g": (9, -3), "m": (30, -4), "n": (30, -5), "@": (3, -9)}
        if mode in two:
            values = _sscanf_ints(line, 2)
            if values is None:
                raise LibKoalaError("koala_get_from_auto_mode", two[mode], line)
            return mode, values
        if mode in many:
            n, code = many[mode]
            params = process_param(line, n)
            if len(params) != n or None in params:
                raise LibKoalaError("koala_get_from_auto_mode", code, line)
            return mode, params
        raise LibKoalaError("koala_get_from_auto_mode", -10, line)


# -- fixtures and helpers ------------------------------------------------------------------------

@dataclass
class Koala25:
    lib: LibKoala
    watch: ZenohWatch
    proc: BridgeProcess

    def sim_time(self) -> float:
        return float(self.watch.wait_for("truth/pose")["t"])

    def wait_sim(self, seconds: float) -> dict[str, Any]:
        """The first truth/pose at least ``seconds`` of simulated time after the latest one."""
        t0 = self.sim_time()
        return self.watch.after("truth/pose", t0 + seconds, timeout=DEADLINE_S)

    def wait_rest(self) -> dict[str, Any]:
        """The first truth/pose equal to the one 0.1 s of simulated time before it: the robot
        has stopped (a pose received over Zenoh may lag the simulation on a loaded machine, so
        "0.1 s after the latest pose received" may still be before the stop)."""
        p = self.wait_sim(0.0)
        while True:
            q = self.watch.after("truth/pose", p["t"] + 0.1, timeout=DEADLINE_S)
            if (q["x"], q["y"], q["theta"]) == (p["x"], p["y"], p["theta"]):
                return q
            p = q

    def world(self) -> dict[str, Any]:
        return self.watch.query("world")


def wait_until(read: Callable[[], Any], ok: Callable[[Any], bool], what: str) -> Any:
    """Call ``read`` until ``ok(value)``; fail with the last value after the deadline."""
    deadline = time.monotonic() + DEADLINE_S
    while True:
        value = read()
        if ok(value):
            return value
        assert time.monotonic() < deadline, f"{what}: last {value!r}"


def config() -> dict[str, Any]:
    with open(KOALA25_CONFIG, "rb") as f:
        return tomllib.load(f)


@pytest.fixture
def start_koala(bridge, zenoh_watch) -> Iterator[Callable[..., Koala25]]:
    """Factory: ``start_koala(clock="fast", sets=[...], ideal=True)`` -> a bridge in the
    ``koala25`` dialect, libkoala on its K-Team pty and a Zenoh watch."""
    opened: list[Koala25] = []

    def start(clock: str = "fast", sets: list[str] | None = None,
              ideal: bool = True) -> Koala25:
        b = bridge(clock=clock, ideal=ideal, config=KOALA25_CONFIG, sets=[
            "buses.kteam.dialect=koala25", "buses.rangefinders.enabled=false", *(sets or [])])
        k = Koala25(LibKoala(b.endpoints["serial"]["kteam"]), zenoh_watch(b), b)
        opened.append(k)
        return k

    yield start
    for k in opened:
        k.lib.close()
        assert k.proc.stop() == 0, k.proc.log()


@pytest.fixture
def koala(start_koala) -> Koala25:
    return start_koala()


def spin_rate_rad_s(world: dict[str, Any], left: int, right: int) -> float:
    """Yaw rate of wheel speeds ``left``/``right`` (pulses per speed unit): (v_r - v_l) / b."""
    robot = world["robot"]
    per_unit_mps = 1.0 / robot["ticks_per_metre"] / robot["speed_unit_s"]
    return (right - left) * per_unit_mps / robot["wheel_base_m"]


# -- line discipline and B -----------------------------------------------------------------------

def test_firmware_version_is_seven_bytes_read_at_once(koala: Koala25) -> None:
    version, revision = koala.lib.get_firmware_version()
    assert version.isalpha() and version.isupper(), version   # manual: b,A-02
    assert 0 <= revision <= 99                                 # two digits, stored in a char
    # a longer reply (two terminators) would leave a byte that fails the next command
    assert koala.lib.read_motor_speed() == (0, 0)


def test_each_reply_ends_in_one_terminator(koala: Koala25) -> None:
    """A CR LF reply leaves an empty line: the second of two commands would read it and fail."""
    lib = koala.lib
    for _ in range(3):
        lib.read_motor_speed()
        lib.read_motor_position()
        lib.get_motor_status()
        lib.read_us_sensors()
    assert len(lib.terminators) == 1, lib.terminators          # one byte, always the same
    assert lib.read_line_nowait() is None                     # nothing left behind


def test_unknown_command_does_not_look_like_success(koala: Koala25) -> None:
    """Every upper-case letter is a Koala 2.5 command; these are not. The reply must fail every
    libkoala check (in particular not ``z,...``, which ``koala_reset_microcontroller`` accepts)."""
    for command in ("%", "~", "1", "D,x,y", "D,1"):
        koala.lib.sendcommand(command)
        line = koala.lib.read_line()
        assert line is not None, f"no reply to {command!r}"
        assert line[:1] not in LIBKOALA_SUCCESS_CHARS, (command, line)
    assert koala.lib.read_motor_speed() == (0, 0)              # the port still works


def test_the_rest_of_the_command_set_answers_as_libkoala_checks(koala: Koala25) -> None:
    lib = koala.lib
    valid, sats, lat, ns, lon, ew, *_ = lib.read_gps()
    assert valid in "AV" and ns in "NS" and ew in "EW", (valid, ns, ew)
    lib.scan_i2c()
    assert len(lib.read_i2c(0x10, 0, 3)) == 3
    lib.write_i2c(0x10, 0, [1, 2])
    lib.send_gps_cmd("$PMTK000*32")
    lib.set_pwr_io_output(0, 0, 0, 0, 0)
    lib.read_io()
    assert all(0 <= v <= 1023 for v in lib.read_ad())        # 10 bits: 0..3.3 V


# -- motion --------------------------------------------------------------------------------------

def test_d_sets_speeds_that_e_reads_and_y_reports_speed_control(koala: Koala25) -> None:
    lib = koala.lib
    lib.set_motor_speed(-40, 40)                               # spin in place: no wall in reach
    wait_until(lib.read_motor_speed, lambda s: s == (-40, 40), "E after D,-40,40")
    # the step itself may hit the J current limit (Y mode 5) for a PID period: ask at steady speed
    koala.wait_sim(0.1)
    status = lib.get_motor_status()
    assert status[:2] == (MODE_SPEED, MODE_SPEED), status
    lib.set_motor_speed(0, 0)
    wait_until(lib.read_motor_speed, lambda s: s == (0, 0), "E after D,0,0")


def test_d_accepts_the_manuals_speed_range(koala: Koala25) -> None:
    """Manual: D from a minimum usable 10 to a maximum of about 490 (550 mm/s)."""
    lib = koala.lib
    for v in (10, 450):
        lib.set_motor_speed(-v, v)                             # spin in place
        koala.wait_sim(0.2)                                    # D is not ramped: 20 PID periods
        assert lib.read_motor_speed() == (-v, v), f"E after D,-{v},{v}"
    lib.set_motor_speed(0, 0)


def test_d_speed_and_p_pulses_are_the_koala25_units(koala: Koala25) -> None:
    """Manual: "an order of 100 will drive the motor to a speed of 110mm/s" and 88.185 pulses per
    mm; libkoala: ``KOALA_SPEED_TO_MM_S`` 1.1076 (mm/s)/unit, 23400 pulses per wheel turn of
    82.5 mm (90'290 pulses/m). The truth pose must agree with one of them (the classic Koala's
    4.5 mm/s per unit would not)."""
    lib, watch = koala.lib, koala.watch
    lib.set_motor_encoders(0, 0)
    rest0 = watch.wait_for("truth/pose", timeout=DEADLINE_S)
    lib.set_motor_speed(100, 100)                              # 1 m of free floor ahead
    wait_until(lib.read_motor_speed, lambda s: s == (100, 100), "E after D,100,100")
    p0 = koala.wait_sim(0.0)
    p1 = watch.after("truth/pose", p0["t"] + 2.0, timeout=DEADLINE_S)
    lib.set_motor_speed(0, 0)
    wait_until(lib.read_motor_speed, lambda s: s == (0, 0), "E after D,0,0")
    rest1 = koala.wait_rest()
    pulses = lib.read_motor_position()
    speed_mm_s = 1000.0 * math.hypot(p1["x"] - p0["x"], p1["y"] - p0["y"]) / (p1["t"] - p0["t"])
    lo = 100 * min(1.10, KOALA_SPEED_TO_MM_S) * 0.99           # 110 mm/s (manual), 110.8 (lib)
    hi = 100 / 88.185 / 0.010 * 1.01                           # 88.185 pulses/mm: 113.4 mm/s
    assert lo <= speed_mm_s <= hi, f"{speed_mm_s:.1f} mm/s at D,100 (manual: 110)"
    # pulses per mm over the whole move, the robot at rest at both ends
    distance_mm = 1000.0 * math.hypot(rest1["x"] - rest0["x"], rest1["y"] - rest0["y"])
    pulses_per_mm = pulses[0] / distance_mm
    assert 88.185 * 0.99 <= pulses_per_mm <= 1.01 / KOALA_PULSE_TO_MM, pulses_per_mm


def test_i_sets_the_encoders_and_p_reads_them(koala: Koala25) -> None:
    lib = koala.lib
    lib.set_motor_encoders(1000, -2000)
    assert lib.read_motor_position() == (1000, -2000)
    lib.set_motor_encoders(0, 0)
    assert lib.read_motor_position() == (0, 0)


def test_f_moves_to_the_target_under_the_j_profile_and_y_reports_it(koala: Koala25) -> None:
    lib = koala.lib
    acc_inc, acc_div, min_speed, cst_speed, pos_margin, max_current = 5, 1, 10, 100, 10, 10
    lib.set_speed_profile(acc_inc, acc_div, min_speed, cst_speed, pos_margin, max_current)
    lib.set_motor_encoders(0, 0)
    target = (-15000, 15000)                                   # a turn on the spot
    lib.set_motor_target_position(*target)
    status = lib.get_motor_status()
    assert status == (MODE_POSITION, MODE_POSITION, 0, 0), status
    speeds: list[tuple[int, int]] = []

    def moving() -> tuple[int, int, int, int]:
        speeds.append(lib.read_motor_speed())
        return lib.get_motor_status()

    status = wait_until(moving, lambda s: s[2] == 1 and s[3] == 1, "Y on target")
    assert status[:2] == (MODE_POSITION, MODE_POSITION), status
    assert all(abs(v) <= cst_speed for pair in speeds for v in pair), max(speeds)
    assert any(abs(v) > min_speed for pair in speeds for v in pair), speeds   # it did move
    position = lib.read_motor_position()
    # on target = within pos_margin; the controller may pass it by one 10 ms step at min speed
    errors = [p - t for p, t in zip(position, target, strict=True)]
    assert all(abs(e) <= pos_margin + min_speed for e in errors), position
    assert lib.get_motor_status()[:2] == (MODE_POSITION, MODE_POSITION)


def test_k_ramps_to_the_speed_under_the_j_profile(koala: Koala25) -> None:
    lib = koala.lib
    lib.set_speed_profile(1, 255, 10, 200, 10, 10)             # the slowest ramp J allows
    lib.set_motor_speed_accel(-60, 60)
    status = lib.get_motor_status()
    assert status[:2] == (MODE_SPEED_ACCEL, MODE_SPEED_ACCEL), status
    seen: list[tuple[int, int]] = []

    def speed() -> tuple[int, int]:
        seen.append(lib.read_motor_speed())
        return seen[-1]

    wait_until(speed, lambda s: s == (-60, 60), "E after K,-60,60")
    assert any(0 < abs(v) < 60 for pair in seen for v in pair), seen   # went through a ramp
    rights = [r for _, r in seen]
    assert all(b >= a for a, b in zip(rights, rights[1:], strict=False)), rights   # never backwards
    lib.set_motor_speed(0, 0)


def test_l_is_open_loop(koala: Koala25) -> None:
    """L under the default J current limit (1 A) may start in mode 5 (current limitation); with
    the limit off (J max_current 0 = disable, manual) it is mode 4 from the first period on."""
    lib = koala.lib
    lib.set_motor_speed_open_loop(-800, 800)
    wait_until(lib.read_motor_speed, lambda s: s[0] < 0 < s[1], "E under L,-800,800")
    koala.wait_sim(0.5)
    assert lib.get_motor_status()[:2] == (MODE_OPEN_LOOP, MODE_OPEN_LOOP)
    lib.set_motor_speed(0, 0)
    wait_until(lib.read_motor_speed, lambda s: s == (0, 0), "E after D,0,0")
    lib.set_speed_profile(5, 1, 10, 200, 10, 0)
    lib.set_motor_speed_open_loop(-800, 800)
    statuses = [lib.get_motor_status()[:2]]

    def speed() -> tuple[int, int]:
        statuses.append(lib.get_motor_status()[:2])
        return lib.read_motor_speed()

    wait_until(speed, lambda s: s[0] < 0 < s[1], "E under L,-800,800")
    assert set(statuses) == {(MODE_OPEN_LOOP, MODE_OPEN_LOOP)}, statuses
    lib.set_motor_speed_open_loop(0, 0)                        # free wheel
    lib.set_motor_speed(0, 0)
    wait_until(lib.read_motor_speed, lambda s: s == (0, 0), "E after D,0,0")


def test_h_sets_the_pid(koala: Koala25) -> None:
    koala.lib.configure_pid(10, 3, 1)                          # the defaults, KOALA_MOTOR_P/I/D
    assert koala.lib.read_motor_speed() == (0, 0)


def test_z_resets_counters_and_stops_the_motors(koala: Koala25) -> None:
    lib = koala.lib
    lib.set_motor_encoders(500, -500)                          # at rest: nothing to coast
    lib.reset_microcontroller()
    koala.wait_sim(3.0)
    while (line := lib.read_line_nowait()) is not None:
        assert line[:1] == "b", f"after Z: {line!r}"
    assert lib.read_motor_position() == (0, 0)
    v = 60
    lib.set_motor_speed(-v, v)
    wait_until(lib.read_motor_position, lambda p: p[1] > 20 * v, "P while spinning")
    lib.reset_microcontroller()
    # koala_test.c: sleep(3) for the restart, then read "any remaining line; usualy Koala version"
    koala.wait_sim(3.0)
    while (line := lib.read_line_nowait()) is not None:
        assert line[:1] == "b", f"after Z: {line!r}"
    assert lib.read_motor_speed() == (0, 0)
    position = lib.read_motor_position()
    # a reset motor stops well within one second of travel at the speed it had
    assert all(abs(p) <= 100 * v for p in position), position
    assert lib.read_motor_position() == position               # and stays stopped
    assert lib.get_motor_status()[:2] == (MODE_IDLE, MODE_IDLE)


# -- sensors -------------------------------------------------------------------------------------

def _valid_us(value: int) -> bool:
    lo, hi = KOALA_US_RANGE_CM
    return value in (KOALA_US_OBJECT_NEAR, KOALA_US_NO_OBJECT_IN_RANGE,
                     KOALA_US_DISABLED_SENSOR) or lo <= value <= hi


def test_g_values_are_the_manuals(koala: Koala25) -> None:
    for _ in range(10):
        values = koala.lib.read_us_sensors()
        assert all(_valid_us(v) for v in values), values
        assert KOALA_US_DISABLED_SENSOR not in values, values   # mask 511 (all) by default
        koala.wait_sim(0.2)


def test_c_mask_disables_sonars_that_g_reads_as_2000(koala: Koala25) -> None:
    lib = koala.lib
    mask = 0b101010101
    lib.configure_us_io(mask, 0)
    disabled = [i for i in range(9) if not mask >> i & 1]
    wait_until(lib.read_us_sensors,
               lambda g: all(g[i] == KOALA_US_DISABLED_SENSOR for i in disabled), "G after C")
    for _ in range(5):
        koala.wait_sim(0.2)
        values = lib.read_us_sensors()
        for i, v in enumerate(values):
            if i in disabled:
                assert v == KOALA_US_DISABLED_SENSOR, values
            else:
                assert _valid_us(v) and v != KOALA_US_DISABLED_SENSOR, values
    lib.configure_us_io(511, 0)
    wait_until(lib.read_us_sensors, lambda g: KOALA_US_DISABLED_SENSOR not in g, "G after C,511")


def test_g_order_is_the_manuals_sensor_names(koala: Koala25) -> None:
    """Manual: G (and the C mask) number the sonars left rear, left front, front left, front,
    front right, right front, right rear, back right, back left. At the default start (1.75,
    1.75) facing east, in row y 1.5..2 m: the west wall is at x = 1.0 (0.75 m behind the centre),
    the east wall at x = 3.0 (1.25 m ahead), no wall north below y = 3.0 or south above y = 0.
    A sensor sits within the body radius of the centre, and a perpendicular wall's nearest echo
    is its perpendicular distance."""
    world = koala.world()
    body = world["robot"]["body_radius_m"]
    start = world["start"]
    assert (start["x"], start["y"], start["theta"]) == (1.75, 1.75, 0.0)
    values = koala.lib.read_us_sensors()
    front, back_right, back_left = values[3], values[7], values[8]
    for name, v, wall in (("front", front, 1.25), ("back right", back_right, 0.75),
                          ("back left", back_left, 0.75)):
        assert 100 * (wall - body) - 2 <= v <= 100 * wall + 2, (name, values)


def test_m_accelerometer_reads_one_g_on_z_at_rest(koala: Koala25) -> None:
    values = koala.lib.read_accelerometer()
    x, y, z = values[0::3], values[1::3], values[2::3]
    one_g = 1.0 / KOALA_ACCEL_G                                # 16384
    # at rest on a level floor; the ideal sensor is exact to its quantum (1/16384 g)
    tol = ACCEL_TOL_G / KOALA_ACCEL_G
    assert all(abs(v - one_g) <= tol for v in z), z
    assert all(abs(v) <= tol for v in x + y), (x, y)


def _gyro_sigma_rad_s(rate_rad_s: float) -> float:
    """One sample's standard deviation about the true rate, from [sensors.gyro] (docs/models.md
    "Gyroscope"): turn-on bias, white noise density x sqrt(rate), the per-sample scale noise;
    the bias random walk over a few minutes is added as its own sigma."""
    g = config()["sensors"]["gyro"]
    white = g["gyroscope_noise_density"] * math.sqrt(g["rate_hz"])
    walk = g["gyroscope_random_walk"] * math.sqrt(300.0)
    scale = g["scale_noise"] * abs(rate_rad_s)
    return math.sqrt(g["turn_on_bias_sigma"] ** 2 + white**2 + walk**2 + scale**2)


def test_n_gyro_reads_zero_at_rest_and_the_spin_rate_when_spinning(start_koala) -> None:
    koala = start_koala(sets=["sensors.gyro.ideal=false"])
    lib = koala.lib
    g = config()["sensors"]["gyro"]
    assert g["bias_rad_s"] == 0.0 and g["scale_factor_error"] == 0.0
    quantum = math.radians(KOALA_GYRO_DEG_S)

    def check(values: list[int], rate: float) -> None:
        bound = 5.0 * _gyro_sigma_rad_s(rate) + quantum
        z = [v * quantum for v in values[2::3]]
        assert all(abs(w - rate) <= bound for w in z), (rate, bound, values[2::3])
        # the robot does not roll or pitch: x and y read the noise only
        xy = [v * quantum for v in values[0::3] + values[1::3]]
        assert all(abs(w) <= 5.0 * _gyro_sigma_rad_s(0.0) + quantum for w in xy), values

    koala.wait_sim(0.2)
    check(lib.read_gyroscope(), 0.0)
    left, right = -100, 100
    lib.set_motor_speed(left, right)
    wait_until(lib.read_motor_speed, lambda s: s == (left, right), "E when spinning")
    koala.wait_sim(0.3)                                        # 10 samples all at full rate
    rate = spin_rate_rad_s(koala.world(), left, right)
    assert rate > 0.0                                          # counter-clockwise, z up
    check(lib.read_gyroscope(), rate)
    lib.set_motor_speed(0, 0)


def test_magnetometer_reads_the_worlds_earth_field_in_mgauss(koala: Koala25) -> None:
    """|B| = |Earth field| (world answer, 1 uT = 10 mGauss) plus at most the world's magnetic
    sources at the start pose (strength at 1 m over d^2, the slower of the usual fall-offs;
    d less the body radius)."""
    world = koala.world()
    ef = world["earth_field"]
    earth_mg = 10.0 * math.hypot(ef["horizontal_uT"], ef["vertical_uT"])
    start = world["start"]
    body = world["robot"]["body_radius_m"]                     # the sensor is on the body
    local_mg = sum(10.0 * s["strength_uT"] / max(
        math.hypot(s["x"] - start["x"], s["y"] - start["y"]) - body, 0.05) ** 2
        for s in world["magnetic_sources"])
    for _ in range(3):
        x, y, z = koala.lib.read_magnetometer()
        magnitude = math.sqrt(x * x + y * y + z * z)
        assert abs(magnitude - earth_mg) <= local_mg + 2.0, (x, y, z, earth_mg, local_mg)
        koala.wait_sim(0.1)


def test_o_motor_currents_at_rest_and_spinning(koala: Koala25) -> None:
    """[robot.battery] (sim/battery.py): at rest a wheel draws nothing; at a steady speed v it
    draws k_v |v| (unit 0.1 A, so +-1 for the rounding)."""
    lib = koala.lib
    bat = config()["robot"]["battery"]
    assert lib.read_motor_current() == (0, 0)
    left, right = -120, 120
    lib.set_motor_speed(left, right)
    wait_until(lib.read_motor_speed, lambda s: s == (left, right), "E when spinning")
    koala.wait_sim(0.2)
    robot = koala.world()["robot"]
    v = right / robot["ticks_per_metre"] / robot["speed_unit_s"]
    expected = 10.0 * bat["motor_current_per_mps_A"] * v
    current = lib.read_motor_current()
    assert all(abs(abs(c) - expected) <= 1.0 for c in current), (current, expected)
    assert all(abs(c) <= 10.0 * bat["motor_stall_current_A"] for c in current)
    lib.set_motor_speed(0, 0)


def _battery_bounds() -> tuple[float, float]:
    """Terminal voltage range, V: V_empty - R I_max .. V_full (sim/battery.py)."""
    bat = config()["robot"]["battery"]
    i_max = bat["idle_current_A"] + 2 * bat["motor_stall_current_A"]
    return bat["voltage_empty_V"] - bat["internal_resistance_ohm"] * i_max, bat["voltage_full_V"]


def test_v_battery_at_rest(koala: Koala25) -> None:
    bat = config()["robot"]["battery"]
    bat_type, voltage, current, charging = koala.lib.get_battery_data()
    # Bat_Type 0 = Li-ION, 1 = NiMH, 2 = not initialised (manual)
    assert bat_type == {"Li-ion": 0, "NiMH": 1}[bat["chemistry"]], bat_type
    lo, hi = _battery_bounds()
    assert 10 * lo - 1 <= voltage <= 10 * hi + 1, voltage
    assert abs(current - 10 * bat["idle_current_A"]) <= 1, current
    assert charging == 0                                        # no charger in the simulation


def test_v_battery_voltage_drops_after_a_long_drive(start_koala) -> None:
    """A small battery (50 mAh) so that a drive of simulated seconds moves the open-circuit
    voltage by several 0.1 V steps: ΔV = (V_full - V_empty) ΔQ / capacity, ΔQ >= (I_idle +
    2 k_v v) T / 3.6 mAh while driving T s at v, <= (I_idle + 2 I_stall) T_all / 3.6."""
    capacity = 50.0
    koala = start_koala(sets=[f"robot.battery.capacity_mAh={capacity}"])
    lib = koala.lib
    bat = config()["robot"]["battery"]
    robot = koala.world()["robot"]
    span = bat["voltage_full_V"] - bat["voltage_empty_V"]
    t_start = koala.sim_time()
    _, rest0, _, _ = lib.get_battery_data()
    left, right = -120, 120
    v = right / robot["ticks_per_metre"] / robot["speed_unit_s"]
    i_low = bat["idle_current_A"] + 2 * bat["motor_current_per_mps_A"] * v
    drive_s = min(120.0, 0.6 / span * capacity * 3.6 / i_low)  # aim at a 0.6 V drop
    lib.set_motor_speed(left, right)
    wait_until(lib.read_motor_speed, lambda s: s == (left, right), "E when spinning")
    koala.wait_sim(drive_s)
    lib.set_motor_speed(0, 0)
    wait_until(lib.read_motor_speed, lambda s: s == (0, 0), "E after D,0,0")
    koala.wait_sim(0.1)
    _, rest1, _, _ = lib.get_battery_data()
    t_all = koala.sim_time() - t_start
    drop_low = span * i_low * drive_s / 3.6 / capacity
    i_high = bat["idle_current_A"] + 2 * bat["motor_stall_current_A"]
    drop_high = span * i_high * t_all / 3.6 / capacity
    drop = (rest0 - rest1) / 10.0
    assert drop_low - 0.2 <= drop <= drop_high + 0.2, (rest0, rest1, drop_low, drop_high)


# -- auto mode -----------------------------------------------------------------------------------

AUTO_FIRST_CHARS = {AUTO_US: "g", AUTO_SPEED: "e", AUTO_POSITION: "p", AUTO_CURRENT: "o",
                    AUTO_ACCEL: "m", AUTO_GYRO: "n", AUTO_MAGNE: "@"}


def _auto_lines(koala: Koala25, until: Callable[[list[tuple[float, str, Any]]], bool],
                ) -> list[tuple[float, str, Any]]:
    """Pushed lines as ``koala_get_from_auto_mode`` reads them, each stamped with the latest
    simulated time seen on Zenoh, until ``until(lines)``."""
    lines: list[tuple[float, str, Any]] = []
    deadline = time.monotonic() + DEADLINE_S
    while not until(lines):
        assert time.monotonic() < deadline, sorted({m for _, m, _ in lines})
        if not koala.lib._readable(0.05):
            continue
        got = koala.lib.get_from_auto_mode()
        if got is not None:
            lines.append((koala.sim_time(), *got))
    return lines


def test_auto_mode_pushes_lines_libkoala_parses_and_a0_stops_them(koala: Koala25) -> None:
    lib = koala.lib
    bits = sum(AUTO_FIRST_CHARS)
    lib.set_motor_speed(-50, 50)
    wait_until(lib.read_motor_speed, lambda s: s == (-50, 50), "E when spinning")
    lib.configure_auto_monitoring_mode(bits)
    wanted = set(AUTO_FIRST_CHARS.values())
    lines = _auto_lines(koala, lambda got: wanted <= {m for _, m, _ in got})
    for _, mode, data in lines:
        if mode == "g":
            assert all(_valid_us(v) for v in data), data
        if mode == "m":
            assert all(abs(z * KOALA_ACCEL_G - 1.0) <= ACCEL_TOL_G for z in data[2::3]), data
        if mode == "e":
            assert data == (-50, 50), data
    # A,0: its 'a' may come after lines already pushed ("after draining")
    lib.sendcommand("A,0")
    while True:
        line = lib.read_line()
        assert line is not None, "no reply to A,0"
        if line[:1] == "a":
            break
        assert line[:1] in wanted, line
    koala.wait_sim(1.0)                                        # >= 5 periods of every stream
    assert lib.read_line_nowait() is None
    assert lib.read_motor_speed() == (-50, 50)
    lib.set_motor_speed(0, 0)


def test_auto_mode_pushes_the_selected_streams_and_honours_the_sonar_mask(start_koala) -> None:
    """Every selected stream arrives, as koala_get_from_auto_mode parses it; with one sonar
    enabled (C mask) the others read disabled. (The rates, in simulated time, are asserted
    exactly in tests/unit/test_koala25_responder.py: a client's read times depend on the
    machine's load, so they are not counted here.)"""
    koala = start_koala(clock="realtime")
    koala.lib.configure_auto_monitoring_mode(AUTO_US | AUTO_ACCEL | AUTO_GYRO | AUTO_MAGNE)
    lines = _auto_lines(koala, lambda got: {"g", "m", "n", "@"} <= {m for _, m, _ in got})
    assert {mode for _, mode, _ in lines} == {"g", "m", "n", "@"}
    lib = koala.lib
    lib.sendcommand("A,0")
    while (line := lib.read_line()) is not None and line[:1] != "a":
        pass
    lib.configure_us_io(1 << 3, 0)
    lib.configure_auto_monitoring_mode(AUTO_US)
    lines = _auto_lines(koala, lambda got: len(got) >= 5)
    assert {mode for _, mode, _ in lines} == {"g"}
    assert all(data[i] == KOALA_US_DISABLED_SENSOR for _, _, data in lines
               for i in range(9) if i != 3)
    lib.sendcommand("A,0")
