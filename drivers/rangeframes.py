"""Binary range frames (IR proximity and sonar) streamed on a serial line.

Layout, little-endian (docs/protocols.md, "Binary range frames")::

    offset  size  field
    0       2     sync 0xA5 0x5A
    2       1     version = 1
    3       1     kind: 1 = IR proximity, 2 = sonar
    4       2     sequence number, u16, per kind, wraps
    6       4     sample time, u32, microseconds of simulation time, wraps
    10      1     n = number of readings
    11      2n    readings, u16 (IR: counts; sonar: mm, 0xFFFF = no echo)
    11+2n   2     CRC-16/CCITT-FALSE over bytes 2 .. 10+2n

:class:`RangeFrameDecoder` reads a byte stream from any source (the simulated pty or a real
sensor board), resynchronises after garbage, truncated or corrupted frames, and counts rejects.
"""

from __future__ import annotations

import binascii
import struct
from collections import Counter

from koala_bridge.drivers.messages import FrameError, RangeFrame, RangeKind, Reject, RejectReason

__all__ = [
    "HEADER_SIZE",
    "MAX_READINGS",
    "NO_ECHO",
    "SYNC",
    "VERSION",
    "RangeFrameDecoder",
    "crc16_ccitt_false",
    "decode_range_frame",
    "encode_range_frame",
    "frame_size",
]

SYNC = b"\xa5\x5a"
VERSION = 1
NO_ECHO = 0xFFFF
"""Sonar reading meaning "no echo within range"."""
MAX_READINGS = 255
HEADER_SIZE = 11
"""Bytes before the readings: sync(2) version(1) kind(1) seq(2) t_us(4) n(1)."""
_CRC_SIZE = 2
_HEADER = struct.Struct("<2sBBHIB")
_KINDS = frozenset(int(k) for k in RangeKind)


def crc16_ccitt_false(data: bytes) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, xorout 0); check 0x29B1.

    ``binascii.crc_hqx`` is that CRC (the XMODEM/CCITT polynomial, MSB first, no final xor)
    started from ``0xFFFF``, in C: the Python loop of crccheck cost ~15 us a frame.
    (Catalogue: https://reveng.sourceforge.io/crc-catalogue/16.htm, CRC-16/IBM-3740.)
    """
    return binascii.crc_hqx(data, 0xFFFF)


def frame_size(n: int) -> int:
    """Total size in bytes of a frame carrying ``n`` readings: 13 + 2n."""
    return HEADER_SIZE + 2 * n + _CRC_SIZE


def encode_range_frame(frame: RangeFrame) -> bytes:
    """Encode ``frame``; raises :class:`FrameError` if a field does not fit its wire type."""
    n = len(frame.readings)
    if n > MAX_READINGS:
        raise FrameError(f"at most {MAX_READINGS} readings per frame, got {n}")
    if int(frame.kind) not in _KINDS:
        raise FrameError(f"unknown range kind {frame.kind!r}")
    if not 0 <= frame.seq <= 0xFFFF:
        raise FrameError(f"seq must be a u16, got {frame.seq}")
    if not 0 <= frame.t_us <= 0xFFFFFFFF:
        raise FrameError(f"t_us must be a u32, got {frame.t_us}")
    if any(not 0 <= r <= 0xFFFF for r in frame.readings):
        raise FrameError("readings must be u16")
    body = _HEADER.pack(SYNC, VERSION, int(frame.kind), frame.seq, frame.t_us, n)
    body += struct.pack(f"<{n}H", *frame.readings)
    return body + struct.pack("<H", crc16_ccitt_false(body[2:]))


def decode_range_frame(data: bytes) -> RangeFrame | Reject:
    """Decode exactly one complete frame; anything else is a :class:`Reject`."""
    if len(data) < HEADER_SIZE + _CRC_SIZE:
        return Reject(
            RejectReason.BAD_LENGTH, f"{len(data)} bytes is shorter than any frame", data[:32]
        )
    sync, version, kind, seq, t_us, n = _HEADER.unpack_from(data)
    if sync != SYNC:
        return Reject(RejectReason.BAD_SYNC, "frame does not start with A5 5A", data[:32])
    if version != VERSION:
        return Reject(RejectReason.BAD_VERSION, f"version {version}", data[:32])
    if kind not in _KINDS:
        return Reject(RejectReason.BAD_KIND, f"kind {kind}", data[:32])
    if len(data) != frame_size(n):
        return Reject(
            RejectReason.BAD_LENGTH,
            f"n={n} needs {frame_size(n)} bytes, got {len(data)}",
            data[:32],
        )
    end = HEADER_SIZE + 2 * n
    (crc,) = struct.unpack_from("<H", data, end)
    if crc != crc16_ccitt_false(data[2:end]):
        return Reject(RejectReason.BAD_CRC, f"crc {crc:#06x}", data[:32])
    readings = struct.unpack_from(f"<{n}H", data, HEADER_SIZE)
    return RangeFrame(RangeKind(kind), seq, t_us, tuple(readings))


class RangeFrameDecoder:
    """Streaming decoder: feed arbitrary chunks, get complete valid frames.

    On a bad version, kind or CRC the decoder skips one byte past the sync it had locked on and
    searches again, so a good frame hidden behind a truncated one is still found. Memory is bounded
    by one maximum-size frame.

    Attributes:
        frames: number of valid frames decoded.
        rejects: counts per :class:`RejectReason` (``garbage`` counts runs of bytes skipped
            while searching for a sync word).
        bytes_discarded: total bytes thrown away while resynchronising.
        seq_gaps: frames whose ``seq`` did not follow the previous frame of the same kind.
    """

    def __init__(self, max_readings: int = MAX_READINGS) -> None:
        if not 0 <= max_readings <= MAX_READINGS:
            raise ValueError(f"max_readings must be in 0..{MAX_READINGS}")
        self.max_readings = max_readings
        self.frames = 0
        self.rejects: Counter[RejectReason] = Counter()
        self.bytes_discarded = 0
        self.seq_gaps = 0
        self._buf = bytearray()
        self._last_seq: dict[int, int] = {}
        # True while skipping one bad stretch, so that it is counted as one reject, not many.
        self._in_bad_run = False

    @property
    def rejected(self) -> int:
        """Total rejects of every reason."""
        return sum(self.rejects.values())

    def feed(self, data: bytes) -> list[RangeFrame]:
        """Consume ``data``; return the frames it completed, in order."""
        self._buf += data
        out: list[RangeFrame] = []
        while True:
            start = self._buf.find(SYNC)
            if start < 0:
                # Keep a trailing 0xA5: it may be the first half of a sync split across chunks.
                keep = 1 if self._buf.endswith(SYNC[:1]) else 0
                self._discard(len(self._buf) - keep, RejectReason.GARBAGE)
                return out
            if start:
                self._discard(start, RejectReason.GARBAGE)
            if len(self._buf) < HEADER_SIZE:
                return out
            _, version, kind, _, _, n = _HEADER.unpack_from(self._buf)
            if version != VERSION:
                self._skip_sync(RejectReason.BAD_VERSION)
                continue
            if kind not in _KINDS:
                self._skip_sync(RejectReason.BAD_KIND)
                continue
            if n > self.max_readings:
                self._skip_sync(RejectReason.BAD_LENGTH)
                continue
            size = frame_size(n)
            if len(self._buf) < size:
                return out
            result = decode_range_frame(bytes(self._buf[:size]))
            if isinstance(result, Reject):
                self._skip_sync(result.reason)
                continue
            del self._buf[:size]
            self._in_bad_run = False
            self._track_seq(result)
            self.frames += 1
            out.append(result)

    def _discard(self, count: int, reason: RejectReason) -> None:
        if count <= 0:
            return
        del self._buf[:count]
        self.bytes_discarded += count
        if not self._in_bad_run:
            self.rejects[reason] += 1
        self._in_bad_run = True

    def _skip_sync(self, reason: RejectReason) -> None:
        del self._buf[:1]
        self.bytes_discarded += 1
        self.rejects[reason] += 1
        self._in_bad_run = True

    def _track_seq(self, frame: RangeFrame) -> None:
        last = self._last_seq.get(frame.kind)
        if last is not None and frame.seq != (last + 1) & 0xFFFF:
            self.seq_gaps += 1
        self._last_seq[frame.kind] = frame.seq
