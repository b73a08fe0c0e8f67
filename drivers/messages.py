"""Typed bus messages and the drivers' error tree.

Every codec in :mod:`drivers` turns bytes into the frozen dataclasses below and back. None of them
imports :mod:`sim`; :mod:`bridge` converts between these wire-level values and simulator units.

A frame that fails to decode is a *value*, :class:`Reject`, returned by the decoder and counted by
its caller -- never an exception that ends a read loop. Exceptions (:class:`DriverError` and its
subclasses) are for programming errors (encoding a value the wire format cannot carry) and for
transports that cannot be opened or have been closed.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum, StrEnum

__all__ = [
    "CompassSample",
    "DriverError",
    "FrameError",
    "GyroFrame",
    "KteamCommand",
    "KteamReply",
    "MavlinkHeartbeat",
    "MotorCommandFrame",
    "RangeFrame",
    "RangeKind",
    "Reject",
    "RejectReason",
    "TransportClosedError",
    "TransportError",
    "WheelOdometryFrame",
]


# --------------------------------------------------------------------------- errors


# Defined once in the project's error tree (core/errors.py); re-exported here, their old home.
from koala_bridge.core.errors import (  # noqa: E402
    DriverError,
    FrameError,
    TransportClosedError,
    TransportError,
)


class RejectReason(StrEnum):
    """Why a received frame was rejected; the value is the counter key used in status reports."""

    UNKNOWN_COMMAND = "unknown_command"
    SYNTAX = "syntax"
    ARITY = "arity"
    OUT_OF_RANGE = "out_of_range"
    LINE_TOO_LONG = "line_too_long"
    BAD_SYNC = "bad_sync"
    BAD_VERSION = "bad_version"
    BAD_KIND = "bad_kind"
    BAD_LENGTH = "bad_length"
    BAD_CRC = "bad_crc"
    UNKNOWN_ID = "unknown_id"
    WRONG_DLC = "wrong_dlc"
    UNSUPPORTED = "unsupported"
    GARBAGE = "garbage"


@dataclass(frozen=True, slots=True)
class Reject:
    """A frame that was received but could not be decoded.

    Attributes:
        reason: machine-readable category, also the key of reject counters.
        detail: a short human-readable explanation for logs.
        raw: the offending bytes (possibly truncated by the decoder to keep logs small).
    """

    reason: RejectReason
    detail: str = ""
    raw: bytes = b""


# --------------------------------------------------------------------------- K-Team serial


@dataclass(frozen=True, slots=True)
class KteamCommand:
    """A K-Team ASCII command, e.g. ``D,10,-10`` -> ``KteamCommand("D", (10, -10))``.

    Attributes:
        letter: the upper-case command letter ``A``..``Z``.
        args: the decimal integer arguments, in K-Team units (speeds in pulse/10 ms, positions in
            pulses; see docs/protocols.md).
    """

    letter: str
    args: tuple[int, ...] = ()
    text: str = ""              # the one text argument of a text command (Koala 2.5 ``X``)


@dataclass(frozen=True, slots=True)
class KteamReply:
    """A K-Team ASCII reply, e.g. ``h,120,-7`` -> ``KteamReply("h", ("120", "-7"))``.

    Fields are kept as text because a few replies (``b``: version, ``z``: error message) are not
    integers; :attr:`ints` converts the usual numeric case.

    Attributes:
        letter: lower-case letter of the command answered (Koala 2.5: ``@`` for ``&``, ``!`` for
            ``?``), or the dialect's error letter (``z,<text>``; Koala 2.5 ``#``).
        fields: comma-separated fields after the letter, without the separators.
    """

    letter: str
    fields: tuple[str, ...] = ()

    @property
    def is_error(self) -> bool:
        """True for an error reply: ``z,<message>`` (classic Koala; a bare ``z`` is the Koala
        2.5's answer to its reset command ``Z``) or ``#...`` (Koala 2.5)."""
        return self.letter == "#" or (self.letter == "z" and bool(self.fields))

    @property
    def ints(self) -> tuple[int, ...]:
        """The fields as integers; raises :class:`FrameError` if one is not a decimal integer."""
        try:
            return tuple(int(f) for f in self.fields)
        except ValueError as e:
            raise FrameError(f"reply {self.letter!r} has a non-integer field: {self.fields}") from e


# --------------------------------------------------------------------------- binary range frames


class RangeKind(IntEnum):
    """Kind byte of a binary range frame."""

    IR = 1
    """Infrared proximity; readings are K-Team counts 0..1023, larger = closer."""
    SONAR = 2
    """Ultrasonic range finder; readings are ranges in millimetres, 0xFFFF = no echo."""


@dataclass(frozen=True, slots=True)
class RangeFrame:
    """One binary range frame (see docs/protocols.md, "Binary range frames").

    Attributes:
        kind: IR proximity or sonar.
        seq: sequence number per kind, u16, wraps at 65536.
        t_us: sample time in microseconds of simulation time, u32, wraps at 2**32.
        readings: u16 values, one per sensor in the configured sensor order.
    """

    kind: RangeKind
    seq: int
    t_us: int
    readings: tuple[int, ...]


# --------------------------------------------------------------------------- CAN (config/koala.dbc)


@dataclass(frozen=True, slots=True)
class WheelOdometryFrame:
    """CAN ``WheelOdometry``: cumulative wheel encoder counts (signed 32-bit, wrapping).

    Attributes:
        left_ticks: left wheel counter, encoder pulses, positive when the wheel drives forward.
        right_ticks: right wheel counter, encoder pulses, positive when the wheel drives forward.
    """

    left_ticks: int
    right_ticks: int


@dataclass(frozen=True, slots=True)
class GyroFrame:
    """CAN ``Gyro``: yaw rate about body z (up), rad/s, counter-clockwise positive."""

    yaw_rate: float


@dataclass(frozen=True, slots=True)
class MotorCommandFrame:
    """CAN ``MotorCommand`` from the firmware: wheel speed set-points, m/s, forward positive."""

    left_speed: float
    right_speed: float


# --------------------------------------------------------------------------- MAVLink compass


@dataclass(frozen=True, slots=True)
class CompassSample:
    """A 3-axis magnetometer sample in the FLU body frame (x forward, y left, z up).

    Attributes:
        time_boot_ms: milliseconds since the component started (MAVLink ``time_boot_ms``).
        x_ut: field along body x (forward), microtesla.
        y_ut: field along body y (left), microtesla.
        z_ut: field along body z (up), microtesla.
    """

    time_boot_ms: int
    x_ut: float
    y_ut: float
    z_ut: float


@dataclass(frozen=True, slots=True)
class MavlinkHeartbeat:
    """A decoded MAVLink HEARTBEAT: who sent it and what it claims to be."""

    system_id: int
    component_id: int
    mav_type: int
    autopilot: int
