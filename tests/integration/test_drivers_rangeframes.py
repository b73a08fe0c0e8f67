"""Binary range frames: CRC, golden frames, streaming resynchronisation, and a pty + pyserial."""

from __future__ import annotations

import random
from pathlib import Path

import pytest
import serial
from koala_bridge.drivers.messages import FrameError, RangeFrame, RangeKind, Reject, RejectReason
from koala_bridge.drivers.rangeframes import (
    NO_ECHO,
    RangeFrameDecoder,
    crc16_ccitt_false,
    decode_range_frame,
    encode_range_frame,
    frame_size,
)
from koala_bridge.drivers.transports.pty import PtyTransport

GOLDEN = Path(__file__).parents[1] / "data" / "drivers" / "range_frames.txt"


def _golden() -> list[tuple[RangeFrame, bytes]]:
    cases = []
    for line in GOLDEN.read_text().splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        fields, hexbytes = line.split("|")
        kind, seq, t_us, *rest = fields.split()
        readings = tuple(int(r) for r in rest[0].split(",")) if rest else ()
        frame = RangeFrame(RangeKind(int(kind)), int(seq), int(t_us), readings)
        cases.append((frame, bytes.fromhex(hexbytes)))
    return cases


def _frames(rng: random.Random, count: int) -> list[RangeFrame]:
    out = []
    for i in range(count):
        kind = rng.choice(list(RangeKind))
        n = rng.choice([0, 1, 8, 16])
        readings = tuple(rng.choice([rng.randrange(1024), NO_ECHO]) for _ in range(n))
        out.append(RangeFrame(kind, i & 0xFFFF, rng.randrange(2**32), readings))
    return out


def test_crc_is_ccitt_false() -> None:
    assert crc16_ccitt_false(b"123456789") == 0x29B1
    fastcrc = pytest.importorskip("fastcrc")  # an independent implementation as a cross-check
    data = bytes(range(256))
    assert crc16_ccitt_false(data) == fastcrc.crc16.ibm_3740(data)


@pytest.mark.parametrize(("frame", "wire"), _golden())
def test_golden_frames(frame: RangeFrame, wire: bytes) -> None:
    assert encode_range_frame(frame) == wire
    assert decode_range_frame(wire) == frame
    assert len(wire) == frame_size(len(frame.readings))


def test_encoder_refuses_values_that_do_not_fit() -> None:
    for bad in (
        RangeFrame(RangeKind.IR, 65536, 0, ()),
        RangeFrame(RangeKind.IR, 0, 2**32, ()),
        RangeFrame(RangeKind.IR, 0, 0, (65536,)),
        RangeFrame(RangeKind.SONAR, 0, 0, (1,) * 256),
    ):
        with pytest.raises(FrameError):
            encode_range_frame(bad)


def test_decode_one_frame_reports_why() -> None:
    wire = bytearray(_golden()[0][1])
    assert decode_range_frame(bytes(wire[:-1])).reason is RejectReason.BAD_LENGTH  # type: ignore[union-attr]
    corrupted = bytearray(wire)
    corrupted[12] ^= 0x01
    assert decode_range_frame(bytes(corrupted)).reason is RejectReason.BAD_CRC  # type: ignore[union-attr]
    corrupted = bytearray(wire)
    corrupted[2] = 9
    assert decode_range_frame(bytes(corrupted)).reason is RejectReason.BAD_VERSION  # type: ignore[union-attr]
    corrupted[2], corrupted[3] = 1, 3
    assert decode_range_frame(bytes(corrupted)).reason is RejectReason.BAD_KIND  # type: ignore[union-attr]
    assert isinstance(decode_range_frame(b"\x00" + bytes(wire[1:])), Reject)


def test_stream_in_random_chunks() -> None:
    rng = random.Random(42)
    frames = _frames(rng, 300)
    stream = b"".join(encode_range_frame(f) for f in frames)
    decoder = RangeFrameDecoder()
    out: list[RangeFrame] = []
    pos = 0
    while pos < len(stream):
        step = rng.randrange(1, 40)
        out += decoder.feed(stream[pos : pos + step])
        pos += step
    assert out == frames
    assert decoder.rejected == 0 and decoder.bytes_discarded == 0


def test_resynchronises_after_garbage_truncation_and_corruption() -> None:
    rng = random.Random(2024)
    good = _frames(rng, 6)
    wires = [encode_range_frame(f) for f in good]
    corrupted = bytearray(wires[3])
    corrupted[-3] ^= 0x40  # a reading bit flips: CRC must catch it
    stream = (
        bytes(rng.randrange(256) for _ in range(500)).replace(b"\xa5", b"\x00")  # garbage
        + wires[0]
        + wires[1][:9]  # truncated mid-header
        + wires[2]
        + bytes(corrupted)
        + b"\xa5\x5a\x07"  # a sync word with a bad version
        + wires[4]
        + wires[5][: len(wires[5]) - 4]  # truncated mid-readings ...
        + wires[5]  # ... and the frame sent again whole
    )
    # A decoder told the largest n it expects rejects a bogus length at once ...
    bounded = RangeFrameDecoder(max_readings=16)
    assert bounded.feed(stream) == [good[0], good[2], good[4], good[5]]
    assert bounded.rejects[RejectReason.GARBAGE] >= 1
    assert bounded.rejects[RejectReason.BAD_LENGTH] >= 1  # truncated header -> bogus n
    assert bounded.rejects[RejectReason.BAD_CRC] >= 2  # corrupted + truncated mid-readings
    assert bounded.rejects[RejectReason.BAD_VERSION] >= 1
    assert bounded.seq_gaps >= 1
    assert bounded.feed(wires[1]) == [good[1]]  # still working afterwards
    # ... the default one waits for at most one maximum-size frame, then recovers every frame.
    default = RangeFrameDecoder()
    out = default.feed(stream) + default.feed(bytes(frame_size(255)))
    assert out == [good[0], good[2], good[4], good[5]]
    assert default.rejects[RejectReason.BAD_CRC] >= 3


def test_random_bytes_only_are_counted_not_raised() -> None:
    rng = random.Random(99)
    decoder = RangeFrameDecoder()
    for _ in range(100):
        assert decoder.feed(bytes(rng.randrange(256) for _ in range(rng.randrange(1, 200)))) == []
    assert decoder.rejected > 0
    assert len(decoder._buf) <= frame_size(255)  # bounded memory


def test_frames_over_a_pty_to_pyserial() -> None:
    rng = random.Random(5)
    frames = _frames(rng, 50)
    with PtyTransport() as port:
        with serial.Serial(port.endpoint.path, 115200, timeout=5) as client:
            garbage = bytes(rng.randrange(256) for _ in range(64))
            for i, frame in enumerate(frames):
                if i == 25:
                    assert port.write(garbage) == len(garbage)
                assert port.write(encode_range_frame(frame)) > 0
            expected = sum(frame_size(len(f.readings)) for f in frames) + len(garbage)
            decoder = RangeFrameDecoder()
            out: list[RangeFrame] = []
            received = 0
            while received < expected:
                port.flush()
                chunk = client.read(max(1, min(client.in_waiting, expected - received)))
                assert chunk, "pty delivered nothing"
                received += len(chunk)
                out += decoder.feed(chunk)
    assert out == frames
    assert decoder.rejected >= 1


def test_pty_without_a_client_drops_and_counts() -> None:
    with PtyTransport() as port:
        assert not port.has_client()
        assert port.write(b"\xa5\x5a" * 10) == 0
        assert port.stats.dropped == 1
        with serial.Serial(port.endpoint.path, timeout=0.2) as client:
            assert port.has_client()
            port.write(b"fresh")
            assert client.read(5) == b"fresh"  # nothing stale from before the client opened
