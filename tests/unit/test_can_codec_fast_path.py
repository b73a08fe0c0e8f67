"""The struct fast path of :class:`KoalaCanCodec` gives cantools' bytes, values and errors.

Every message of ``koala.dbc`` takes the fast path; cantools (the reference) encodes and decodes
the same values here, over the DBC ranges, their edges and beyond.
"""

from __future__ import annotations

from collections.abc import Mapping

import can
import cantools
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from koala_bridge.drivers.can_codec import KoalaCanCodec, _ByteAlignedLayout
from koala_bridge.drivers.messages import (
    FrameError,
    GyroFrame,
    MotorCommandFrame,
    WheelOdometryFrame,
)

CODEC = KoalaCanCodec()


def _cantools_only() -> KoalaCanCodec:
    """A codec without the struct fast path: every message decoded by cantools (the reference)."""
    codec = KoalaCanCodec()
    codec._layouts = dict.fromkeys(codec._layouts)
    return codec


REFERENCE = _cantools_only()
SPEED = st.floats(min_value=-2.2, max_value=2.2) | st.sampled_from([-2.0, 2.0, 2.0000005, -0.0])
RATE = st.floats(min_value=-21.0, max_value=21.0) | st.sampled_from([-20.0, 20.0, 20.0000001])
TICKS = st.integers(min_value=-(2**40), max_value=2**40)


def _reference(frame: WheelOdometryFrame | GyroFrame | MotorCommandFrame) -> bytes | None:
    name = {WheelOdometryFrame: "WheelOdometry", GyroFrame: "Gyro",
            MotorCommandFrame: "MotorCommand"}[type(frame)]
    message = CODEC.db.get_message_by_name(name)
    if isinstance(frame, WheelOdometryFrame):
        values: dict[str, float] = {"left_ticks": (frame.left_ticks + 2**31) % 2**32 - 2**31,
                                    "right_ticks": (frame.right_ticks + 2**31) % 2**32 - 2**31}
    elif isinstance(frame, GyroFrame):
        values = {"yaw_rate": frame.yaw_rate}
    else:
        values = {"left_speed": frame.left_speed, "right_speed": frame.right_speed}
    try:
        return bytes(message.encode(values, strict=True))
    except (cantools.database.EncodeError, ValueError, OverflowError):
        return None


def test_every_koala_message_takes_the_fast_path() -> None:
    assert all(isinstance(v, _ByteAlignedLayout) for v in CODEC._layouts.values())


@settings(max_examples=300, deadline=None)
@given(st.one_of(
    st.builds(WheelOdometryFrame, TICKS, TICKS),
    st.builds(GyroFrame, RATE),
    st.builds(MotorCommandFrame, SPEED, SPEED),
))
def test_encode_matches_cantools(frame: WheelOdometryFrame | GyroFrame | MotorCommandFrame) -> None:
    expected = _reference(frame)
    if expected is None:
        with pytest.raises(FrameError):
            CODEC.encode(frame)
    else:
        assert bytes(CODEC.encode(frame).data) == expected


@settings(max_examples=300, deadline=None)
@given(st.sampled_from(["WheelOdometry", "Gyro", "MotorCommand"]), st.data())
def test_decode_matches_cantools(name: str, data: st.DataObject) -> None:
    message = CODEC.db.get_message_by_name(name)
    raw = data.draw(st.binary(min_size=message.length, max_size=message.length))
    expected = message.decode(raw, decode_choices=False, scaling=True)
    assert isinstance(expected, Mapping)
    got = CODEC._layouts[name].decode(raw)  # type: ignore[union-attr]
    assert got == {k: float(v) for k, v in expected.items()}
    assert all(type(v) is float for v in got.values())


@settings(max_examples=200, deadline=None)
@given(st.sampled_from([0x100, 0x110, 0x120, 0x121]), st.binary(max_size=9), st.booleans())
def test_decode_data_is_decode_of_the_data_frame(can_id: int, raw: bytes, extended: bool) -> None:
    """decode() goes through decode_data(), so the two agree by construction; what is tested is
    that both give what cantools' decoding gives (frames, range and DLC rejects alike)."""
    msg = can.Message(arbitration_id=can_id, data=raw, is_extended_id=extended)
    assert CODEC.decode_data(can_id, raw, extended) == CODEC.decode(msg) == REFERENCE.decode(msg)
