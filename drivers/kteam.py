"""K-Team ASCII serial protocol codec (Koala), usable from both ends of the line, in two dialects.

Robot side (the bridge emulating a Koala): :class:`LineSplitter` -> :func:`parse_command` ->
(bridge acts) -> :func:`format_reply`; a rejected line is answered with :func:`error_reply`.
Controller side (firmware, or a tool reading a real Koala): :func:`format_command` ->
:class:`LineSplitter` -> :func:`parse_reply`.

Wire format (docs/protocols.md, "K-Team ASCII"): a command is an upper-case letter, optional
comma-separated decimal integer arguments, ended by CR (LF and CRLF accepted too); the reply is the
same letter in lower case, ``,`` and the values, ended by the dialect's terminator.

A :class:`Dialect` is one robot's command set and line discipline: :data:`KOALA1` (the classic
Koala / Koala II as KoreBot ``koala.c`` and the ROS koala driver drive it: 38400 8N2, replies end
CR LF, errors ``z,<text>``) here, ``KOALA25`` (the Koala 2.5 as K-Team ``libkoala`` drives it)
in :mod:`koala_bridge.drivers.koala25`; :func:`koala_bridge.drivers.dialects.dialect` returns
either by name.

Units are the robot's: speeds in pulse/10 ms, positions in encoder pulses, sensors in raw counts.
Conversion to SI lives in :mod:`bridge`, with the constants in ``config/``.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

from koala_bridge.drivers.messages import FrameError, KteamCommand, KteamReply, Reject, RejectReason

__all__ = [
    "KOALA1",
    "Dialect",
    "SerialLine",
    "ERROR_OUT_OF_RANGE",
    "ERROR_PROTOCOL",
    "ERROR_UNKNOWN_COMMAND",
    "INT32_MAX",
    "INT32_MIN",
    "MANAGEMENT_CHANNELS",
    "MANAGEMENT_UNITS",
    "CommandSpec",
    "KteamLimits",
    "LineSplitter",
    "command_specs",
    "error_reply",
    "format_command",
    "format_reply",
    "parse_command",
    "parse_reply",
]

INT32_MIN = -(2**31)
INT32_MAX = 2**31 - 1

ERROR_PROTOCOL = "Protocol error"
"""Text of the error reply to a syntax or arity error (K-Team firmware's own wording)."""
ERROR_UNKNOWN_COMMAND = "Unknown command"
"""Text of the error reply to a command letter the robot does not implement."""
ERROR_OUT_OF_RANGE = "Out of range"
"""Text of the error reply to a well-formed command with an argument outside its range."""

_ERROR_TEXT: Mapping[RejectReason, str] = MappingProxyType(
    {
        RejectReason.UNKNOWN_COMMAND: ERROR_UNKNOWN_COMMAND,
        RejectReason.OUT_OF_RANGE: ERROR_OUT_OF_RANGE,
    }
)

MANAGEMENT_CHANNELS = 6
"""Classic Koala ``M,n`` channels (the ROS koala driver reads 0..5)."""
MANAGEMENT_UNITS = (0.020, 0.008, 0.1, 0.004, 0.004, 0.1)
"""Classic Koala ``M,n`` units: V, A, degC, A, A, degC per count (the ROS koala driver's
conversions: 20 mV, 8 mA, 0.1 degC, 4 mA, 4 mA, 0.1 degC)."""

_INT_FIELD = re.compile(r"[+-]?[0-9]{1,11}")
#: Printable ASCII but the separator: the one text argument (Koala 2.5 ``X``) and text fields.
_TEXT_ARG = re.compile(r"[ -~]{1,200}")
#: Upper bound on the arguments of a variadic command (Koala 2.5 ``W``: I2C bytes).
MAX_ARGS = 64
_TERMINATORS = re.compile(rb"[\r\n]")
#: First characters of a reply: the lower-case letters, and the Koala 2.5's ``@`` (``&``),
#: ``!`` (``?``) and ``#`` (error).
_REPLY_LETTERS = frozenset("abcdefghijklmnopqrstuvwxyz@!#")


@dataclass(frozen=True, slots=True)
class KteamLimits:
    """Argument ranges of the emulated Koala; the defaults are the real robot's.

    Attributes:
        max_speed: largest ``|speed|`` accepted by ``D``, pulse/10 ms. K-Team's KoreBot library
            (``koala.c``, ``koa_setSpeed``) documents the range -127..127. Also the largest
            profile speed ``J`` accepts.
        max_acceleration: largest ``J`` acceleration, in 1/256 pulse/10 ms per 10 ms
            (about 1.758 mm/s^2 on the classic Koala); 8-bit, our reading (docs/protocols.md).
        pid_max: largest ``A`` / ``F`` PID gain (16-bit signed positive range; our reading).
        pwm_max: largest ``|duty|`` accepted by ``P`` (8-bit duty; our reading).
        analog_inputs: number of channels ``I`` reads (``0..analog_inputs-1``).
        outputs: number of digital outputs ``Q`` sets (``0..outputs-1``).
        leds: number of LEDs; ``L`` accepts LED numbers ``0..leds-1`` (0 lateral, 1 frontal).
        sensors: number of IR proximity / ambient light sensors returned by ``N`` / ``O``.
        sensor_max: largest IR/ambient count (10-bit ADC).
    """

    max_speed: int = 127
    leds: int = 2
    sensors: int = 16
    sensor_max: int = 1023
    max_acceleration: int = 255
    pid_max: int = 32767
    pwm_max: int = 255
    analog_inputs: int = 6
    outputs: int = 4


@dataclass(frozen=True, slots=True)
class CommandSpec:
    """What one command letter takes and what its reply carries.

    Attributes:
        letter: upper-case command letter.
        name: short description for docs and logs.
        arg_ranges: inclusive ``(low, high)`` per argument; its length is the command's arity.
        reply_fields: number of reply fields, or ``None`` when variable or textual (``b``).
        more: range of further arguments after ``arg_ranges`` (a variadic command, at most
            :data:`MAX_ARGS` in all); None: exactly ``len(arg_ranges)``.
        text: the command takes one free-text argument instead (Koala 2.5 ``X,<NMEA>``).
    """

    letter: str
    name: str
    arg_ranges: tuple[tuple[int, int], ...]
    reply_fields: int | None
    more: tuple[int, int] | None = None
    text: bool = False


def command_specs(limits: KteamLimits | None = None) -> Mapping[str, CommandSpec]:
    """The implemented commands, keyed by letter, with ranges taken from ``limits``."""
    lim = limits or KteamLimits()
    speed = (-lim.max_speed, lim.max_speed)
    counter = (INT32_MIN, INT32_MAX)
    gain = (0, lim.pid_max)
    profile_speed = (1, lim.max_speed)
    profile_acc = (1, lim.max_acceleration)
    pwm = (-lim.pwm_max, lim.pwm_max)
    specs = (
        CommandSpec("A", "set speed PID gains (Kp, Ki, Kd)", (gain, gain, gain), 0),
        CommandSpec("B", "read firmware version", (), None),
        CommandSpec("C", "move to position targets (left, right) in pulses", (counter, counter), 0),
        CommandSpec("F", "set position PID gains (Kp, Ki, Kd)", (gain, gain, gain), 0),
        CommandSpec(
            "J",
            "set position profile (max speed left, acc left, max speed right, acc right)",
            (profile_speed, profile_acc, profile_speed, profile_acc),
            0,
        ),
        CommandSpec(
            "K", "read motion status (on target, mode, error) left then right", (), 6
        ),
        CommandSpec("I", "read analog input channel", ((0, lim.analog_inputs - 1),), 1),
        CommandSpec("P", "set open-loop PWM duty (left, right)", (pwm, pwm), 0),
        CommandSpec(
            "Q", "set digital output (number, 0 off / 1 on)", ((0, lim.outputs - 1), (0, 1)), 0
        ),
        CommandSpec("Y", "read digital inputs (bit field)", (), 1),
        CommandSpec(
            "M",
            "read management sensor n (0 battery voltage, 1 current, 2 ambient temperature, "
            "3 / 4 left / right motor current, 5 battery temperature)",
            ((0, MANAGEMENT_CHANNELS - 1),),
            1,
        ),
        CommandSpec("S", "read the battery's remaining charge, mAh", (), 1),
        CommandSpec("D", "set wheel speeds (left, right) in pulse/10 ms", (speed, speed), 0),
        CommandSpec("E", "read wheel speeds in pulse/10 ms", (), 2),
        CommandSpec("G", "set encoder counters (left, right) in pulses", (counter, counter), 0),
        CommandSpec("H", "read encoder counters in pulses", (), 2),
        CommandSpec("N", "read IR proximity counts", (), lim.sensors),
        CommandSpec("O", "read ambient light counts", (), lim.sensors),
        CommandSpec(
            "L", "LED (number, action 0 off / 1 on / 2 toggle)", ((0, lim.leds - 1), (0, 2)), 0
        ),
    )
    return MappingProxyType({s.letter: s for s in specs})


_DEFAULT_SPECS = command_specs()


@dataclass(frozen=True, slots=True)
class SerialLine:
    """A serial port's line settings, as pyserial names them (a pty ignores them)."""

    baudrate: int
    bytesize: int = 8
    parity: str = "N"
    stopbits: float = 1

    def pyserial(self) -> dict[str, object]:
        """Keyword arguments of ``serial.Serial`` / ``serial_for_url``."""
        return {"baudrate": self.baudrate, "bytesize": self.bytesize, "parity": self.parity,
                "stopbits": self.stopbits}

    def __str__(self) -> str:
        return f"{self.baudrate} {self.bytesize}{self.parity}{self.stopbits:g}"


@dataclass(frozen=True, slots=True)
class Dialect:
    """One Koala's command set and line discipline (docs/protocols.md §1 "Dialects").

    Attributes:
        name: ``koala1`` or ``koala25`` (``[buses.kteam] dialect``, ``[real] kteam_dialect``).
        specs: the commands, keyed by letter.
        line: the serial line settings of the real robot's port.
        reply_terminator: what ends every reply line.
        command_terminator: what a controller ends a command with.
        error_letter: first character of the reply to a rejected command.
        reply_letters: reply first characters that are not the command's lower-case letter
            (Koala 2.5: ``&`` -> ``@``, ``?`` -> ``!``).
    """

    name: str
    specs: Mapping[str, CommandSpec]
    line: SerialLine
    reply_terminator: bytes
    command_terminator: bytes
    error_letter: str
    reply_letters: Mapping[str, str] = field(default_factory=lambda: MappingProxyType({}))

    def reply_letter(self, command_letter: str) -> str:
        """The first character of the reply to ``command_letter``."""
        return self.reply_letters.get(command_letter, command_letter.lower())

    @property
    def reply_commands(self) -> Mapping[str, str]:
        """Reply first character -> command letter, for the exceptions of ``reply_letters``."""
        return {v: k for k, v in self.reply_letters.items()}

    def reply(self, command_letter: str, fields: tuple[object, ...] = ()) -> KteamReply:
        """The reply to ``command_letter`` carrying ``fields`` (numbers or text)."""
        return KteamReply(self.reply_letter(command_letter), tuple(str(f) for f in fields))

    def error_reply(self, reject: Reject) -> KteamReply:
        return error_reply(reject, self.error_letter)

    def format_reply(self, reply: KteamReply) -> bytes:
        return format_reply(reply, self.reply_terminator)

    def format_command(self, command: KteamCommand) -> bytes:
        return format_command(command, self.command_terminator)

    def parse_command(self, line: bytes | str) -> KteamCommand | Reject:
        return parse_command(line, self.specs)

    def parse_reply(self, line: bytes | str) -> KteamReply | Reject:
        return parse_reply(line, self)


KOALA1 = Dialect(
    name="koala1",
    specs=_DEFAULT_SPECS,
    # The ROS koala driver (jdawkins/koala-ros, jjdawkins/koala_ros2) opens the classic Koala's
    # port at 38400 baud, 8 data bits, no parity, 2 stop bits.
    line=SerialLine(38400, 8, "N", 2),
    reply_terminator=b"\r\n",
    command_terminator=b"\r",
    error_letter="z",
)
"""The classic Koala / Koala II (docs/protocols.md §1 "Classic Koala (koala1) commands")."""


# --------------------------------------------------------------------------- line framing


class LineSplitter:
    """Incremental splitter: bytes in, complete lines out, memory bounded.

    Lines end at CR, LF or CRLF; empty lines are skipped (so CRLF is one terminator). A line longer
    than ``max_line`` bytes is reported once as a :class:`Reject` (``LINE_TOO_LONG``) and the rest
    of it is discarded up to the next terminator, so garbage without terminators cannot grow memory.
    """

    def __init__(self, max_line: int = 256) -> None:
        if max_line < 1:
            raise ValueError("max_line must be >= 1")
        self.max_line = max_line
        self._buf = bytearray()
        self._discarding = False

    def feed(self, data: bytes) -> list[bytes | Reject]:
        """Consume ``data``; return the lines it completed (terminators stripped) and rejects."""
        out: list[bytes | Reject] = []
        pos = 0
        for m in _TERMINATORS.finditer(data):
            self._append(data[pos : m.start()], out)
            if self._discarding:
                self._discarding = False
            elif self._buf:
                out.append(bytes(self._buf))
            self._buf.clear()
            pos = m.end()
        self._append(data[pos:], out)
        return out

    def reset(self) -> None:
        """Drop any partial line (e.g. when a new client opens the port)."""
        self._buf.clear()
        self._discarding = False

    def _append(self, chunk: bytes, out: list[bytes | Reject]) -> None:
        if self._discarding or not chunk:
            return
        self._buf += chunk
        if len(self._buf) > self.max_line:
            out.append(
                Reject(
                    RejectReason.LINE_TOO_LONG,
                    f"line over {self.max_line} bytes",
                    bytes(self._buf[:32]),
                )
            )
            self._buf.clear()
            self._discarding = True


# --------------------------------------------------------------------------- robot side


def parse_command(
    line: bytes | str, specs: Mapping[str, CommandSpec] = _DEFAULT_SPECS
) -> KteamCommand | Reject:
    """Parse one command line (terminator already stripped) into a :class:`KteamCommand`.

    Returns a :class:`Reject` -- never raises -- for non-ASCII input, an unknown letter, bad syntax,
    wrong arity or an argument out of range.
    """
    raw = line.encode("latin-1", "replace") if isinstance(line, str) else bytes(line)
    try:
        text = raw.decode("ascii").strip()
    except UnicodeDecodeError:
        return Reject(RejectReason.SYNTAX, "non-ASCII byte in command", raw[:32])
    if not text:
        return Reject(RejectReason.SYNTAX, "empty command", raw[:32])
    letter, rest = text[0], text[1:]
    spec = specs.get(letter)
    if spec is None:
        return Reject(RejectReason.UNKNOWN_COMMAND, f"command {letter!r} not implemented", raw[:32])
    if spec.text:
        if not rest.startswith(",") or not _TEXT_ARG.fullmatch(rest[1:]) or "," in rest[1:]:
            return Reject(RejectReason.SYNTAX, f"{letter} takes one text argument", raw[:32])
        return KteamCommand(letter, (), rest[1:])
    args = _parse_int_fields(rest)
    if args is None:
        return Reject(RejectReason.SYNTAX, f"{letter}: arguments must be ,<decimal>...", raw[:32])
    n_fixed = len(spec.arg_ranges)
    if len(args) != n_fixed and not (
        spec.more is not None and n_fixed < len(args) <= MAX_ARGS
    ):
        return Reject(
            RejectReason.ARITY,
            f"{letter} takes {n_fixed}{'+' if spec.more else ''} argument(s), got {len(args)}",
            raw[:32],
        )
    ranges = spec.arg_ranges + ((spec.more,) * (len(args) - n_fixed) if spec.more else ())
    for i, (value, (low, high)) in enumerate(zip(args, ranges, strict=True)):
        if not low <= value <= high:
            return Reject(
                RejectReason.OUT_OF_RANGE,
                f"{letter} argument {i + 1}={value} not in [{low}, {high}]",
                raw[:32],
            )
    return KteamCommand(letter, args)


def format_reply(reply: KteamReply, terminator: bytes = b"\r\n") -> bytes:
    """Encode a reply as sent by the robot: ``letter[,field...]`` + ``terminator`` (the
    dialect's: CR LF for :data:`KOALA1`)."""
    if len(reply.letter) != 1 or reply.letter not in _REPLY_LETTERS:
        raise FrameError(f"reply letter must be one lower-case letter, got {reply.letter!r}")
    for f in reply.fields:
        if any(c in f for c in ",\r\n") or not f.isascii():
            raise FrameError(f"reply field {f!r} contains a separator or non-ASCII character")
    return ",".join((reply.letter, *reply.fields)).encode("ascii") + terminator


def error_reply(reject: Reject, letter: str = "z") -> KteamReply:
    """The ``z,<text>`` reply the robot sends for a rejected command line (``letter``: the
    dialect's error letter)."""
    return KteamReply(letter, (_ERROR_TEXT.get(reject.reason, ERROR_PROTOCOL),))


# --------------------------------------------------------------------------- controller side


def format_command(command: KteamCommand, terminator: bytes = b"\r") -> bytes:
    """Encode a command as a controller sends it: ``LETTER[,arg...]`` + ``terminator``."""
    if len(command.letter) != 1 or not ("A" <= command.letter <= "Z" or command.letter in "&?"):
        raise FrameError(f"command letter must be one upper-case letter, got {command.letter!r}")
    if terminator not in (b"\r", b"\n", b"\r\n"):
        raise FrameError("terminator must be CR, LF or CRLF")
    if command.text and (not _TEXT_ARG.fullmatch(command.text) or "," in command.text):
        raise FrameError(f"text argument {command.text!r} must be printable ASCII without ','")
    fields = (command.text,) if command.text else tuple(str(int(a)) for a in command.args)
    return ",".join((command.letter, *fields)).encode("ascii") + terminator


def parse_reply(
    line: bytes | str, specs: Mapping[str, CommandSpec] | Dialect = _DEFAULT_SPECS
) -> KteamReply | Reject:
    """Parse one reply line (terminator stripped) into a :class:`KteamReply`.

    ``specs``: the command set (a :class:`Dialect` or its ``specs``; default :data:`KOALA1`'s).
    An error reply (``z,...``; Koala 2.5 ``#...``) is returned as a reply (``is_error``), not a
    reject: it is a valid message. Replies to known commands are checked for their field count
    and integer fields.
    """
    commands = specs.reply_commands if isinstance(specs, Dialect) else {}
    if isinstance(specs, Dialect):
        specs = specs.specs
    raw = line.encode("latin-1", "replace") if isinstance(line, str) else bytes(line)
    try:
        text = raw.decode("ascii").strip()
    except UnicodeDecodeError:
        return Reject(RejectReason.SYNTAX, "non-ASCII byte in reply", raw[:32])
    if not text or text[0] not in _REPLY_LETTERS:
        return Reject(RejectReason.SYNTAX, "reply must start with a lower-case letter", raw[:32])
    letter, rest = text[0], text[1:]
    if rest and rest[0] != ",":
        return Reject(RejectReason.SYNTAX, "reply letter must be followed by ',' or end", raw[:32])
    fields = tuple(f.strip() for f in rest[1:].split(",")) if rest else ()
    spec = specs.get(commands.get(letter, letter.upper()))
    error = letter == "#" or (letter == "z" and bool(fields))
    if not error and spec is not None and spec.reply_fields is not None:
        if len(fields) != spec.reply_fields:
            return Reject(
                RejectReason.ARITY,
                f"{letter} carries {spec.reply_fields} field(s), got {len(fields)}",
                raw[:32],
            )
        if not all(_INT_FIELD.fullmatch(f) for f in fields):
            return Reject(
                RejectReason.SYNTAX, f"{letter}: fields must be decimal integers", raw[:32]
            )
    return KteamReply(letter, fields)


def _parse_int_fields(rest: str) -> tuple[int, ...] | None:
    """``",1,-2"`` -> ``(1, -2)``; ``""`` -> ``()``; anything else -> None."""
    if not rest:
        return ()
    if rest[0] != ",":
        return None
    parts = [p.strip() for p in rest[1:].split(",")]
    if not all(_INT_FIELD.fullmatch(p) for p in parts):
        return None
    return tuple(int(p) for p in parts)
