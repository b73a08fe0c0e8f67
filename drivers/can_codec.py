"""CAN codec for the Koala bus, described by ``config/koala.dbc`` and driven by cantools.

The DBC is the single source of ids, layouts and scaling; this module only maps its messages to
the typed frames of :mod:`koala_bridge.drivers.messages` and turns anything it cannot map into a
:class:`drivers.messages.Reject` (unknown id, wrong DLC, value outside the DBC range, remote /
error / FD frames). It performs no bus I/O: transports live in :mod:`drivers.transports`.
"""

from __future__ import annotations

import struct
from collections.abc import Mapping
from pathlib import Path
from types import MappingProxyType
from typing import TypeAlias

import can
import cantools
from cantools.database.can import Database
from cantools.database.can import Message as DbcMessage
from koala_bridge.core.resources import default_dbc_path
from koala_bridge.drivers.messages import (
    FrameError,
    GyroFrame,
    MotorCommandFrame,
    Reject,
    RejectReason,
    WheelOdometryFrame,
)

__all__ = [
    "DEFAULT_DBC_PATH",
    "CanFrame",
    "KoalaCanCodec",
    "load_koala_dbc",
    "wrap_int32",
]

CanFrame: TypeAlias = WheelOdometryFrame | GyroFrame | MotorCommandFrame
"""Any typed frame of the Koala bus."""

DEFAULT_DBC_PATH = default_dbc_path()
"""The DBC shipped with the package (``config/koala.dbc``, :mod:`koala_bridge.config`)."""

_NAMES: Mapping[type, str] = MappingProxyType(
    {WheelOdometryFrame: "WheelOdometry", GyroFrame: "Gyro", MotorCommandFrame: "MotorCommand"}
)


def load_koala_dbc(path: str | Path = DEFAULT_DBC_PATH) -> Database:
    """Load and check the Koala DBC; raises :class:`FrameError` if a required message is missing."""
    db = cantools.database.load_file(str(path), strict=True)
    if not isinstance(db, Database):
        raise FrameError(f"{path} is not a CAN database")
    missing = set(_NAMES.values()) - {m.name for m in db.messages}
    if missing:
        raise FrameError(f"{path} lacks message(s) {sorted(missing)}")
    return db


def wrap_int32(value: int) -> int:
    """Wrap an unbounded counter to signed 32 bits, as the encoder counters wrap on the wire."""
    return (int(value) + 2**31) % 2**32 - 2**31


_INT_CODES = {8: "b", 16: "h", 32: "i", 64: "q"}


class _ByteAlignedLayout:
    """A DBC message whose signals are all whole little-endian integers of 8/16/32/64 bits on
    byte boundaries, without value tables or multiplexing (every message of ``koala.dbc``):
    packed and unpacked with one :class:`struct.Struct` instead of cantools' bit-level codec.

    Same results as cantools (45): the raw value is ``conversion.numeric_scaled_to_raw`` and the
    scaled one ``raw * scale + offset`` (cantools' ``LinearConversion.raw_to_scaled``); the
    range check is ``Message._assert_signal_values_valid``'s, tolerance included. Anything this
    path does not accept is handed to cantools, which then raises its own error.
    """

    __slots__ = ("names", "_struct", "_signals", "_scaling")

    def __init__(self, names: tuple[str, ...], fmt: str, message: DbcMessage) -> None:
        self.names = names
        self._struct = struct.Struct(fmt)
        self._signals = tuple(message.get_signal_by_name(n) for n in names)
        self._scaling = tuple(
            None if (s.conversion.scale == 1 and s.conversion.offset == 0)
            else (s.conversion.scale, s.conversion.offset)
            for s in self._signals
        )

    @classmethod
    def of(cls, message: DbcMessage) -> _ByteAlignedLayout | None:
        """The layout of ``message``, or None when it is not that simple."""
        if message.is_container or message.is_multiplexed() or not message.signals:
            return None
        signals = sorted(message.signals, key=lambda s: s.start)
        fmt, pos = "<", 0
        for s in signals:
            code = _INT_CODES.get(s.length)
            if (code is None or s.byte_order != "little_endian" or s.start % 8
                    or s.start < 8 * pos or s.conversion.is_float or s.conversion.choices
                    or s.multiplexer_ids):
                return None
            fmt += "x" * (s.start // 8 - pos) + (code if s.is_signed else code.upper())
            pos = s.start // 8 + s.length // 8
        if pos > message.length:
            return None
        fmt += "x" * (message.length - pos)
        return cls(tuple(s.name for s in signals), fmt, message)

    def encode(self, values: Mapping[str, float]) -> bytes | None:
        """The payload of ``values`` (one per signal), or None to let cantools decide."""
        raws = []
        try:
            for s in self._signals:
                value = values[s.name]
                raw = s.conversion.numeric_scaled_to_raw(value)
                tol = abs(s.conversion.scale) * 1e-6
                if (s.minimum is not None and value < s.minimum - tol) or \
                        (s.maximum is not None and value > s.maximum + tol):
                    return None
                raws.append(raw)
            return self._struct.pack(*raws)
        except (KeyError, TypeError, ValueError, OverflowError, struct.error):
            return None

    def decode(self, data: bytes) -> dict[str, float]:
        """The scaled value of every signal of a payload of the message's length."""
        out = {}
        for name, raw, scaling in zip(self.names, self._struct.unpack(data), self._scaling,
                                      strict=True):
            out[name] = float(raw if scaling is None else raw * scaling[0] + scaling[1])
        return out


class KoalaCanCodec:
    """Typed frames <-> :class:`can.Message` using the Koala DBC.

    Args:
        db: a database from :func:`load_koala_dbc`; by default the shipped DBC is loaded.
    """

    def __init__(self, db: Database | None = None) -> None:
        self.db = db if db is not None else load_koala_dbc()
        self._by_type: dict[type, DbcMessage] = {
            t: self.db.get_message_by_name(name) for t, name in _NAMES.items()
        }
        self._by_id: dict[int, DbcMessage] = {m.frame_id: m for m in self._by_type.values()}
        # The hot path (a frame per sensor sample): struct instead of cantools' bit codec.
        self._layouts: dict[str, _ByteAlignedLayout | None] = {
            m.name: _ByteAlignedLayout.of(m) for m in self._by_type.values()
        }

    @property
    def frame_ids(self) -> Mapping[str, int]:
        """CAN id of each message, by DBC name (e.g. ``{"MotorCommand": 0x100, ...}``)."""
        return MappingProxyType({m.name: m.frame_id for m in self._by_type.values()})

    def encode(self, frame: CanFrame) -> can.Message:
        """Encode ``frame``; raises :class:`FrameError` if a value is outside its DBC range.

        Encoder counters are wrapped to 32 bits first (they are wrapping counters by definition).
        """
        message = self._by_type.get(type(frame))
        if message is None:
            raise FrameError(f"no CAN message for {type(frame).__name__}")
        if isinstance(frame, WheelOdometryFrame):
            values: dict[str, float] = {
                "left_ticks": wrap_int32(frame.left_ticks),
                "right_ticks": wrap_int32(frame.right_ticks),
            }
        elif isinstance(frame, GyroFrame):
            values = {"yaw_rate": frame.yaw_rate}
        else:
            values = {"left_speed": frame.left_speed, "right_speed": frame.right_speed}
        layout = self._layouts[message.name]
        fast = None if layout is None else layout.encode(values)
        try:
            data = fast if fast is not None else message.encode(values, strict=True)
        except (cantools.database.EncodeError, ValueError, OverflowError) as e:
            raise FrameError(f"cannot encode {frame}: {e}") from e
        return can.Message(
            arbitration_id=message.frame_id, is_extended_id=message.is_extended_frame, data=data
        )

    def decode(self, msg: can.Message) -> CanFrame | Reject:
        """Decode a received message into a typed frame, or a :class:`Reject` saying why not."""
        raw = bytes(msg.data)
        if msg.is_error_frame or msg.is_remote_frame or msg.is_fd:
            return Reject(RejectReason.UNSUPPORTED, "error, remote or FD frame", raw)
        return self.decode_data(msg.arbitration_id, raw, msg.is_extended_id, msg.dlc)

    def decode_data(self, can_id: int, raw: bytes, extended: bool = False,
                    dlc: int | None = None) -> CanFrame | Reject:
        """:meth:`decode` of a classic data frame given by its id and payload (``dlc``: as the
        frame says; None = the payload's length), without building a :class:`can.Message`."""
        if dlc is None:
            dlc = len(raw)
        message = self._by_id.get(can_id)
        if message is None or message.is_extended_frame != extended:
            kind = "extended" if extended else "standard"
            return Reject(RejectReason.UNKNOWN_ID, f"{kind} id {can_id:#x}", raw)
        if len(raw) != message.length or dlc != message.length:
            return Reject(
                RejectReason.WRONG_DLC,
                f"{message.name} needs DLC {message.length}, got {dlc}",
                raw,
            )
        layout = self._layouts[message.name]
        if layout is not None:
            values = layout.decode(raw)
        else:
            decoded = message.decode(raw, decode_choices=False, scaling=True)
            if not isinstance(decoded, Mapping):  # container messages are not used on this bus
                return Reject(RejectReason.UNSUPPORTED, f"{message.name} is a container", raw)
            values = {name: float(v) for name, v in decoded.items()
                      if isinstance(v, int | float)}
        for signal in message.signals:
            value = values[signal.name]
            low, high = signal.minimum, signal.maximum
            if (low is not None and value < low) or (high is not None and value > high):
                return Reject(
                    RejectReason.OUT_OF_RANGE,
                    f"{message.name}.{signal.name}={value} not in [{low}, {high}]",
                    raw,
                )
        if message.name == "WheelOdometry":
            return WheelOdometryFrame(int(values["left_ticks"]), int(values["right_ticks"]))
        if message.name == "Gyro":
            return GyroFrame(values["yaw_rate"])
        return MotorCommandFrame(values["left_speed"], values["right_speed"])
