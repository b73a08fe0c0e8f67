"""The Koala 2.5 dialect of the K-Team ASCII protocol: its command set, units and auto mode.

Sources (docs/protocols.md §1 "Koala 2.5 (koala25) commands" has the table):

- **LK** = K-Team ``libkoala`` 1.0 (J. Tharin, K-Team S.A. 2013; ``src/koala_robot.c`` and
  ``koala_robot.h``): the exact request strings (``sprintf(buffer,"D,%d,%d\\r",...)``), how each
  reply is checked (its first character) and parsed (``sscanf`` / ``process_param``), the port
  settings (``/dev/ttyS1``, ``B115200``, ``CS8 | CLOCAL | CREAD``: 115200 8N1) and the unit
  constants (``KOALA_ACCEL_G``, ``KOALA_GYRO_DEG_S``, ``KOALA_US_*``).
- **UM** = *Koala 2.5 User Manual* rev 1.3 (2017) §6 "Serial communication protocol" (the same
  text as rev 1.1): meanings, ranges and auto-mode rates.

Line discipline: commands end with CR (LK always sends ``\\r``); a reply is one line ended by
**one** byte. libkoala reads a line up to CR or LF, so a CR LF reply would leave an empty line
that fails the next command's check; the manual's notation table swaps CR and LF, so which byte
the firmware sends cannot be settled from the sources -- we send **LF** (issue 13's reading;
libkoala accepts either). ``B`` is read by LK as one raw ``read(fd, buf, 7)``: the reply
``b,A-02\\n`` is exactly 7 bytes and must be written at once.

Errors: libkoala treats any reply whose first character is not the expected one as an error;
``koala_robot.h`` defines ``KOALA_RS232_MESSAGE_ERROR_CHAR '#'`` (used nowhere in the library,
documented nowhere in the manual). We answer a rejected command ``#,<text>``: every libkoala
check fails on it, unlike a ``z,...`` reply, which ``koala_reset_microcontroller`` would read as
the success of ``Z``.

Units (LK header, UM): speed in pulses per 10 ms; position in pulses; sonar in cm; accelerometer
raw, 1/16384 g per unit (``KOALA_ACCEL_G``); gyro raw, 0.066 deg/s per unit (``KOALA_GYRO_DEG_S``;
the manual's "360 dps = 5898" is 0.061: we follow the library, which converts with 0.066);
magnetometer in mGauss (LK comments; 1 uT = 10 mGauss); motor current 0.1 A; battery voltage
0.1 V, current 0.1 A, charge current 10 mA.
"""

from __future__ import annotations

from types import MappingProxyType

from koala_bridge.drivers.kteam import INT32_MAX, INT32_MIN, CommandSpec, Dialect, SerialLine

__all__ = [
    "ACCEL_G_PER_UNIT",
    "AUTO_BITS",
    "AUTO_COMMANDS",
    "GYRO_DEG_S_PER_UNIT",
    "KOALA25",
    "SAMPLES",
    "SONARS",
    "US_DISABLED",
    "US_NEAR",
    "US_NONE",
    "VERSION_REPLY",
]

SONARS = 9
"""Ultrasonic sensors; ``G`` order = bit order of the ``C`` mask: left rear, left front, front
left, front, front right, right front, right rear, back right, back left (UM)."""
US_NEAR = 0
"""``G`` value of an obstacle closer than 25 cm (LK ``KOALA_US_OBJECT_NEAR``)."""
US_NONE = 1000
"""``G`` value of nothing in range (LK ``KOALA_US_NO_OBJECT_IN_RANGE``)."""
US_DISABLED = 2000
"""``G`` value of a sensor disabled by the ``C`` mask (LK ``KOALA_US_DISABLED_SENSOR``)."""
US_RANGE_CM = (25, 250)
"""``G`` distances are whole cm in this range (UM)."""

SAMPLES = 10
"""``M`` and ``N`` carry the last 10 samples, x y z each, newest first (LK, UM)."""
ACCEL_G_PER_UNIT = 1.0 / 16384.0
"""Accelerometer raw unit, g (LK ``KOALA_ACCEL_G``; UM: "1g will return a value of 16'384")."""
GYRO_DEG_S_PER_UNIT = 66.0 / 1000.0
"""Gyroscope raw unit, deg/s (LK ``KOALA_GYRO_DEG_S``)."""

VERSION_REPLY = "b,A-02"
"""``B``: firmware version ``A``, revision 02 (the manual's example). With the one terminator byte
it is the 7 bytes libkoala's ``koala_get_firmware_version`` reads."""

AUTO_BITS = MappingProxyType({
    "sonar": 1 << 0,
    "speed": 1 << 1,
    "position": 1 << 2,
    "current": 1 << 3,
    "accel": 1 << 4,
    "gyro": 1 << 5,
    "gps": 1 << 6,
    "nmea": 1 << 7,
    "magnetometer": 1 << 8,
})
"""``A,bits``: what auto mode pushes (LK ``KOALA_AUTOM_*``; 0 = off, 511 = all)."""

AUTO_COMMANDS = MappingProxyType({
    "sonar": "G",
    "speed": "E",
    "position": "P",
    "current": "O",
    "accel": "M",
    "gyro": "N",
    "magnetometer": "&",
})
"""The read command whose reply line each auto-mode stream pushes (UM: "the same format as the
protocol"); GPS and NMEA are not simulated."""

_I16 = (-32768, 32767)
_U16 = (0, 65535)
_COUNTER = (INT32_MIN, INT32_MAX)


def _specs() -> dict[str, CommandSpec]:
    specs = (
        CommandSpec("A", "auto mode: bit mask of the data the robot pushes (0 = off)",
                    ((0, 0x1FF),), 0),
        CommandSpec("B", "read firmware version and revision", (), None),
        CommandSpec("C", "configure: ultrasonic enable mask (9 bits), I/O directions (2 bits each)",
                    ((0, 0x1FF), (0, 0xFF)), 0),
        CommandSpec("D", "set wheel speeds (left, right), pulse/10 ms", (_I16, _I16), 0),
        CommandSpec("E", "read wheel speeds, pulse/10 ms", (), 2),
        CommandSpec("F", "move to position targets (left, right), pulses", (_COUNTER, _COUNTER), 0),
        CommandSpec("G", "read the 9 ultrasonic ranges, cm", (), SONARS),
        CommandSpec("H", "set the motor PID gains (P, I, D)", (_U16, _U16, _U16), 0),
        CommandSpec("I", "set the encoder counters (left, right), pulses", (_COUNTER, _COUNTER), 0),
        CommandSpec("J", "set the speed profile (acc_inc, acc_div, min_speed, cst_speed, "
                         "pos_margin, max_current)",
                    ((1, 255), (0, 255), (0, 32767), (1, 32767), (0, 32767), (0, 30)), 0),
        CommandSpec("K", "set wheel speeds with the J acceleration ramp, pulse/10 ms",
                    (_I16, _I16), 0),
        CommandSpec("L", "open-loop PWM (left, right), -2940..2940", ((-2940, 2940),) * 2, 0),
        CommandSpec("M", "read the accelerometer: 10 samples x, y, z, newest first",
                    (), 3 * SAMPLES),
        CommandSpec("N", "read the gyroscope: 10 samples x, y, z, newest first", (), 3 * SAMPLES),
        CommandSpec("O", "read the motor currents (left, right), 0.1 A", (), 2),
        CommandSpec("P", "read the encoder counters (left, right), pulses", (), 2),
        CommandSpec("Q", "read the GPS", (), None),
        CommandSpec("R", "read I2C registers (address, register, count)",
                    ((0, 127), (0, 255), (1, 32)), None),
        CommandSpec("S", "set outputs: power mask (4 bits), IO0..IO3",
                    ((0, 15), (0, 255), (0, 255), (0, 255), (0, 255)), 0),
        CommandSpec("T", "read the I/O states (IO, inputs)", (), 2),
        CommandSpec("U", "read the analog inputs AD0, AD1 (0..1023 = 0..3.3 V)", (), 2),
        CommandSpec("V", "read the battery: type, voltage 0.1 V, current 0.1 A, charge 10 mA",
                    (), 4),
        CommandSpec("W", "write I2C registers (address, register, bytes...)",
                    ((0, 127), (0, 255)), 0, more=(0, 255)),
        CommandSpec("X", "send a sentence to the GPS", (), 0, text=True),
        CommandSpec("Y", "read motor control status (mode left, right, on target left, right)",
                    (), 4),
        CommandSpec("Z", "reset the microcontroller", (), 0),
        CommandSpec("?", "scan the I2C bus", (), None),
        CommandSpec("&", "read the magnetometer x, y, z, mGauss", (), 3),
    )
    return {s.letter: s for s in specs}


KOALA25 = Dialect(
    name="koala25",
    specs=MappingProxyType(_specs()),
    line=SerialLine(115200, 8, "N", 1),
    reply_terminator=b"\n",
    command_terminator=b"\r",
    error_letter="#",
    reply_letters=MappingProxyType({"&": "@", "?": "!"}),
)
"""The Koala 2.5 (docs/protocols.md §1 "Koala 2.5 (koala25) commands")."""
