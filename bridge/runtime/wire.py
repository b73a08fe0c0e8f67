"""Wire timing: when a frame written now has reached the other end of its bus, in simulated time.

A UART moves one character at a time, each a start bit, the data bits, an optional parity bit and
the stop bits; a CAN bus moves one frame at a time, its length set by the bits of ISO 11898-1's
frame format plus the stuff bits the transmitter inserts, and the frame that gets the bus is the
one with the lowest identifier (bitwise arbitration). This module computes those lengths and keeps
one queue per wire, so that the lockstep loop (bridge/runtime/sim_source.py) can hand a frame to
its transport at the first simulation step whose time is at or after the frame's delivery time.

Pure bookkeeping on floats: every time here is a simulated second, never the wall clock.
docs/wire-timing.md explains the model, its sources and what it leaves out.

Sources:
    [ISO] ISO 11898-1:2015 "Road vehicles -- Controller area network (CAN) -- Part 1", and
        Bosch "CAN Specification 2.0" (1991), parts A (11-bit ids) and B (29-bit ids), cited by
        clause name: "Data frame" / "Remote frame" (the fields), "CRC field" (CRC-15, generator
        x^15+x^14+x^10+x^8+x^7+x^4+x^3+1 = 0x4599), "Frame coding" (bit stuffing from SOF to
        the end of the CRC sequence), "Error frame", "Message validation" (valid for receivers
        after the last but one EOF bit), "Bus arbitration".
    [Davis] R. I. Davis, A. Burns, R. J. Bril, J. J. Lukkien, "Controller Area Network (CAN)
        schedulability analysis: Refuted, revisited and revised", Real-Time Systems 35(3),
        2007, eq. (3): worst-case frame length with stuffing, ``g + 8s + 13 + floor((g + 8s -
        1) / 4)`` bits with g = 34 (11-bit id) or 54 (29-bit id), the 13 including the 3-bit
        inter-frame space -- 135 bits for 8 data bytes, 111 without stuffing.
    [CRC] G. Cook, "Catalogue of parametrised CRC algorithms" (reveng): CRC-15/CAN, width 15,
        poly 0x4599, init 0, no reflection, xorout 0, check ("123456789") 0x059E.
    [UART] A character on an asynchronous serial line: 1 start bit, 5-8 data bits, 0 or 1
        parity bit, 1 or 2 stop bits (e.g. TIA/EIA-232 practice; pyserial's bytesize /
        parity / stopbits).
"""

from __future__ import annotations

import heapq
import math
import re
from bisect import bisect_left, bisect_right
from collections import deque
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import can
    from koala_bridge.drivers.kteam import SerialLine

__all__ = [
    "FRAMING_RULE",
    "CanWire",
    "SerialWire",
    "can_crc15",
    "can_error_frame_bits",
    "can_frame_bits",
    "can_unstuffed_bits",
    "can_worst_case_bits",
    "serial_bits_per_byte",
    "serial_time_s",
]

# ------------------------------------------------------------------------------------ UART

#: What a framing string looks like, for error messages (the settings' validator quotes it).
FRAMING_RULE = ("data bits 5..8, parity N/E/O/M/S (none, even, odd, mark, space) and stop bits "
                "1 or 2, like \"8N1\"")
_FRAMING = re.compile(r"([5-8])([NEOMS])([12])")


def serial_bits_per_byte(framing: str) -> int:
    """Bits on the line per character of ``framing`` ("8N1", "8N2", "7E1", ...) [UART]:
    1 start bit + data bits + 1 parity bit unless parity is N + stop bits.

    ``"8N1"`` -> 10, ``"8N2"`` -> 11, ``"8E1"`` -> 11, ``"7E1"`` -> 10. 1.5 stop bits (only
    used with 5 data bits) are not accepted. Raises ValueError naming ``framing``.
    """
    m = _FRAMING.fullmatch(framing) if isinstance(framing, str) else None
    if m is None:
        raise ValueError(f"framing must be {FRAMING_RULE}, got {framing!r}")
    data, parity, stop = m.groups()
    return 1 + int(data) + (parity != "N") + int(stop)


def serial_time_s(n_bytes: int, baud: int, framing: str = "8N1") -> float:
    """Seconds ``n_bytes`` characters take on a UART at ``baud`` bit/s with ``framing``, sent
    back to back: ``n_bytes * serial_bits_per_byte(framing) / baud``. 32 bytes at 115200 8N1:
    320 bits, 2.78 ms."""
    if n_bytes < 0:
        raise ValueError(f"n_bytes must be >= 0, got {n_bytes}")
    return n_bytes * serial_bits_per_byte(framing) / _positive_rate("baud", baud)


def _positive_rate(name: str, value: float) -> float:
    if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be a finite number of bit/s > 0, got {value!r}")
    return float(value)


class SerialWire:
    """One direction of a UART: characters leave in order, one after the other.

    :meth:`submit` queues ``n_bytes`` written at simulated time ``t``; they start when both the
    write happened and the previous write has left the line (a FIFO without a depth limit), and
    the method returns the time their last stop bit ends -- when the reader has every byte.
    """

    __slots__ = ("baud", "framing", "byte_time_s", "busy_until", "_spans")

    def __init__(self, baud: int, framing: str = "8N1") -> None:
        self.baud = baud
        self.framing = framing
        #: seconds per character on the line
        self.byte_time_s = serial_bits_per_byte(framing) / _positive_rate("baud", baud)
        #: when the last submitted character's stop bit ends (-inf: never used)
        self.busy_until = -math.inf
        self._spans: deque[tuple[float, float]] = deque()   # (start, end) of recent writes

    @classmethod
    def from_line(cls, line: SerialLine) -> SerialWire:
        """The wire of a K-Team dialect's port settings (``Dialect.line``: koala1 38400 8N2,
        koala25 115200 8N1)."""
        return cls(line.baudrate, f"{line.bytesize}{line.parity}{line.stopbits:g}")

    def submit(self, t: float, n_bytes: int) -> float:
        """Queue ``n_bytes`` written at ``t``; return when the last of them has arrived."""
        if n_bytes < 0:
            raise ValueError(f"n_bytes must be >= 0, got {n_bytes}")
        start = t if t > self.busy_until else self.busy_until
        self.busy_until = end = start + n_bytes * self.byte_time_s
        if n_bytes:
            self._spans.append((start, end))
            while len(self._spans) > 4096:      # load() looks back one status period at most
                self._spans.popleft()
        return end

    def load(self, window_s: float, now: float) -> float:
        """The fraction of ``[now - window_s, now]`` the line carried characters (1.0:
        saturated), from the writes submitted so far (at most the last 4096)."""
        if not (math.isfinite(window_s) and window_s > 0):
            raise ValueError(f"window_s must be a finite number of seconds > 0, got {window_s}")
        lo = now - window_s
        while self._spans and self._spans[0][1] <= lo:
            self._spans.popleft()
        busy = sum(min(e, now) - max(s, lo) for s, e in self._spans if s < now)
        return min(1.0, max(0.0, busy / window_s))

    def __repr__(self) -> str:
        return f"SerialWire({self.baud}, {self.framing!r}, busy_until={self.busy_until})"


# ------------------------------------------------------------------------------------ CAN

#: After the CRC sequence, never stuffed [ISO]: CRC delimiter 1, ACK slot 1, ACK delimiter 1,
#: end of frame 7, intermission 3.
_TRAILER_BITS = 1 + 1 + 1 + 7 + 3
#: The receivers take the frame as valid after the last but one bit of EOF [ISO "Message
#: validation"]: one EOF bit and the 3-bit intermission before the end of its time on the bus.
_VALID_BEFORE_END_BITS = 1 + 3
_STD_MAX_ID = 0x7FF
_EXT_MAX_ID = 0x1FFFFFFF
_CRC15_POLY = 0x4599


def _crc15_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte << 7
        for _ in range(8):
            crc = ((crc << 1) ^ _CRC15_POLY) if crc & 0x4000 else crc << 1
        table.append(crc & 0x7FFF)
    return tuple(table)


#: CRC-15/CAN, one entry per byte value (MSB first) [CRC].
_CRC15_TABLE = _crc15_table()


def can_crc15(data: bytes, crc: int = 0) -> int:
    """CRC-15/CAN of ``data`` (bits MSB first) [ISO "CRC field"; CRC]: ``can_crc15(b"123456789")
    == 0x059E``. With the initial value 0, leading zero bits do not change the result, so a bit
    sequence is padded on the left to whole bytes."""
    table = _CRC15_TABLE
    for byte in data:
        crc = (table[((crc >> 7) ^ byte) & 0xFF] ^ (crc << 8)) & 0x7FFF
    return crc


def _check_frame(arbitration_id: int, is_extended: bool, n_data: int, dlc: int) -> None:
    top = _EXT_MAX_ID if is_extended else _STD_MAX_ID
    if not 0 <= arbitration_id <= top:
        kind = "29-bit (extended)" if is_extended else "11-bit (standard)"
        raise ValueError(f"arbitration_id must be a {kind} id 0..{top:#x}, got {arbitration_id:#x}")
    if n_data > 8:
        raise ValueError(f"data must be 0..8 bytes on classical CAN (no CAN FD), got {n_data}")
    if not 0 <= dlc <= 15:
        raise ValueError(f"dlc must be 0..15, got {dlc}")


def _frame_head(arbitration_id: int, is_extended: bool, data: bytes, is_remote: bool,
                dlc: int) -> tuple[int, int]:
    """The bits SOF .. end of data [ISO "Data frame"] as ``(value, n_bits)``, MSB first (SOF, a
    dominant 0, is the value's implicit leading zero)."""
    rtr = 1 if is_remote else 0
    if is_extended:
        # SOF, base id (11), SRR = 1, IDE = 1, id extension (18), RTR, r1 = 0, r0 = 0, DLC (4)
        value = (((arbitration_id >> 18) << 2 | 0b11) << 18 | (arbitration_id & 0x3FFFF))
        value = ((value << 1 | rtr) << 2) << 4 | dlc
        n = 1 + 11 + 1 + 1 + 18 + 1 + 2 + 4
    else:
        # SOF, id (11), RTR, IDE = 0, r0 = 0, DLC (4)
        value = ((arbitration_id << 1 | rtr) << 2) << 4 | dlc
        n = 1 + 11 + 1 + 2 + 4
    if data and not is_remote:   # a remote frame has no data field [ISO "Remote frame"]
        value = value << (8 * len(data)) | int.from_bytes(data, "big")
        n += 8 * len(data)
    return value, n


#: Runs of four or more equal bits: shorter runs are never stuffed (a run starts with at most
#: one equal bit already sent, the stuff bit before it).
_LONG_RUNS = re.compile(r"0{4,}|1{4,}")


def _stuff_bits(bits: str) -> int:
    """How many stuff bits a transmitter inserts in ``bits`` (SOF .. CRC sequence) [ISO "Frame
    coding"]: after five consecutive equal bits, one of the opposite value, which itself counts
    in the next run. Counted run by run: a run of ``L`` equal bits reaches five after its first
    five bits -- four if the bit sent just before it was a stuff bit (of this run's value) --
    and then after every further five; a run that ends on a stuff bit passes it on."""
    stuffed = 0
    after_stuff = -1    # where a run that ended on a stuff bit ended
    for m in _LONG_RUNS.finditer(bits):
        start, end = m.span()
        first = 4 if start == after_stuff else 5
        if end - start >= first:
            rest = end - start - first
            stuffed += 1 + rest // 5
            if rest % 5 == 0:
                after_stuff = end
    return stuffed


def can_frame_bits(arbitration_id: int, is_extended: bool, data: bytes,
                   is_remote: bool = False, dlc: int | None = None) -> int:
    """The exact number of bit times a classical CAN 2.0A/2.0B data or remote frame occupies
    the bus, including its stuff bits and the 3-bit intermission that follows it.

    Built as ISO 11898-1 "Data frame" / "Remote frame" lay the frame out: SOF, identifier (11
    bits; or 11 + SRR + IDE + 18), RTR, IDE/r1, r0, DLC, data (none in a remote frame), CRC-15
    over SOF .. data (:func:`can_crc15`); stuffed from SOF to the end of the CRC sequence
    ("Frame coding"); then CRC delimiter, ACK slot, ACK delimiter, 7 EOF bits and 3
    intermission bits, never stuffed. Between :func:`can_unstuffed_bits` (47 + 8n, or 67 + 8n
    with a 29-bit id) and :func:`can_worst_case_bits` [Davis eq. 3].

    ``dlc``: the DLC field, default ``len(data)``; a remote frame's DLC (the length it asks
    for) is its only use. Raises ValueError naming the field for an id out of range or more
    than 8 data bytes.
    """
    data = bytes(data)
    code = len(data) if dlc is None else dlc
    _check_frame(arbitration_id, is_extended, 0 if is_remote else len(data), code)
    if is_remote and data:
        raise ValueError(f"data must be empty in a remote frame, got {len(data)} bytes")
    value, n = _frame_head(arbitration_id, is_extended, data, is_remote, code)
    crc = can_crc15(value.to_bytes((n + 7) // 8, "big"))
    n_crc = n + 15
    return n_crc + _stuff_bits(format(value << 15 | crc, f"0{n_crc}b")) + _TRAILER_BITS


def can_unstuffed_bits(is_extended: bool, n_data: int) -> int:
    """A frame's length without stuff bits, intermission included [ISO; Davis]:
    ``g + 8 n + 13`` with g = 34 (11-bit id) or 54 (29-bit id): 111 / 131 bits for 8 bytes."""
    return (54 if is_extended else 34) + 8 * n_data + _TRAILER_BITS


def can_worst_case_bits(is_extended: bool, n_data: int) -> int:
    """The longest a frame with ``n_data`` data bytes can be once stuffed [Davis eq. 3]:
    ``g + 8n + 13 + floor((g + 8n - 1) / 4)``: 135 bits (11-bit id) or 160 (29-bit id) for 8
    bytes. Of the g + 8n bits stuffing covers, the first stuff bit can follow five, every
    later one four more (a stuff bit opens the next run of equal bits): at most
    ``1 + floor((g + 8n - 5) / 4) = floor((g + 8n - 1) / 4)`` stuff bits."""
    g = 54 if is_extended else 34
    return g + 8 * n_data + _TRAILER_BITS + (g + 8 * n_data - 1) // 4


def can_error_frame_bits(echo_bits: int = 6) -> int:
    """Bit times of an active error frame [ISO "Error frame"]: the 6 dominant bits of the error
    flag, up to 6 more while the other nodes answer with their own flags (``echo_bits``, 0..6; 6 is
    the worst case), the 8 recessive bits of the error delimiter and the 3-bit intermission:
    23 at most, 17 at least. The frame it destroyed is sent again after it (by the fault
    module; this module does not retransmit)."""
    if not 0 <= echo_bits <= 6:
        raise ValueError(f"echo_bits must be 0..6, got {echo_bits}")
    return 6 + echo_bits + 8 + 3


def arbitration_key(arbitration_id: int, is_extended: bool, is_remote: bool = False) -> int:
    """The arbitration field as one 32-bit number; the lower key wins the bus [ISO "Bus
    arbitration"]. The bits as sent, dominant 0 first: base id (11), then RTR and IDE (0 0 for a
    standard data frame) or SRR and IDE (1 1, recessive) and the 18-bit extension and RTR. So an
    11-bit id ranks as ``id << 18`` among 29-bit ids, a standard frame beats an extended one of
    the same base id (its RTR/IDE against the recessive SRR/IDE), and a data frame beats a
    remote frame of the same id (RTR)."""
    rtr = 1 if is_remote else 0
    if is_extended:
        return ((arbitration_id >> 18) << 21 | 0b11 << 19
                | (arbitration_id & 0x3FFFF) << 1 | rtr)
    return arbitration_id << 21 | rtr << 20


class CanWire:
    """One CAN bus in simulated time: the robot's frames and anyone else's, one at a time.

    :meth:`submit` queues a frame written at ``t``. When the bus falls idle, the frames queued by
    then arbitrate and the lowest :func:`arbitration_key` wins (ties between identical
    arbitration fields, which a real bus would answer with an error, go to the one submitted
    first); a frame submitted while another is on the wire waits for the end of that frame's
    intermission (no preemption). :meth:`release` hands out the frames whose receivers have
    them by a given time.

    Submit in time order: a frame's ``t`` may not be earlier than the ``until`` of a previous
    :meth:`release` (the wire has already decided what happened before then). The 10 ms step
    loop submits the step's frames, then releases up to the step's time.
    """

    def __init__(self, bitrate: int, history_s: float = 10.0) -> None:
        self.bitrate = bitrate
        self.bit_time_s = 1.0 / _positive_rate("bitrate", bitrate)
        if not (math.isfinite(history_s) and history_s > 0):
            raise ValueError(f"history_s must be a finite number of seconds > 0, got {history_s}")
        #: how far back :meth:`load` can look
        self.history_s = history_s
        #: when the last released frame's intermission ends: the bus is idle from then on
        self.busy_until = -math.inf
        self._released_until = -math.inf
        self._seq = 0
        # (t, seq, key, bits, msg, tag) submitted, not yet arbitrating, by time
        self._incoming: list[tuple[float, int, int, int, Any, Any]] = []
        # (key, seq, bits, msg, tag) arbitrating at self._arbitration_at
        self._contending: list[tuple[int, int, int, Any, Any]] = []
        self._arbitration_at = -math.inf
        # released transmissions, in wire order: start, end, and the busy seconds before each
        self._starts: list[float] = []
        self._ends: list[float] = []
        self._busy_before: list[float] = []
        self._busy_total = 0.0
        self._bits_cache: dict[tuple[int, bool, bool, int, bytes], int] = {}

    @property
    def pending(self) -> int:
        """Frames submitted and not yet released."""
        return len(self._incoming) + len(self._contending)

    def frame_bits(self, msg: can.Message) -> int:
        """:func:`can_frame_bits` of ``msg``, cached per (id, format, remote, dlc, data)."""
        is_remote = bool(msg.is_remote_frame)
        data = b"" if is_remote else bytes(msg.data)
        key = (msg.arbitration_id, bool(msg.is_extended_id), is_remote, msg.dlc, data)
        bits = self._bits_cache.get(key)
        if bits is None:
            if len(self._bits_cache) >= 4096:   # bounded: payloads of sensor frames vary
                self._bits_cache.clear()
            bits = self._bits_cache[key] = can_frame_bits(
                msg.arbitration_id, key[1], data, is_remote, msg.dlc if is_remote else None)
        return bits

    def submit(self, t: float, msg: can.Message, tag: Any = None) -> None:
        """Queue ``msg`` (a python-can message, classical CAN) written at simulated time ``t``;
        ``tag`` comes back with it from :meth:`release` (which transport, which client...)."""
        if getattr(msg, "is_fd", False):
            raise ValueError("msg: CAN FD frames are not modelled (classical CAN only)")
        if getattr(msg, "is_error_frame", False):
            raise ValueError("msg: an error frame is not queued (it does not arbitrate); "
                             "see can_error_frame_bits")
        if t < self._released_until:
            raise ValueError(
                f"t = {t!r} is before the last release (until = {self._released_until!r}): "
                "submit frames in time order")
        bits = self.frame_bits(msg)
        key = arbitration_key(msg.arbitration_id, bool(msg.is_extended_id),
                              bool(msg.is_remote_frame))
        heapq.heappush(self._incoming, (t, self._seq, key, bits, msg, tag))
        self._seq += 1

    def release(self, until: float) -> list[tuple[float, can.Message, Any]]:
        """The frames the receivers have by ``until``, as ``(time, msg, tag)`` in wire order;
        ``time`` is when the frame became valid for the receivers (after the last but one EOF
        bit [ISO "Message validation"]: 4 bit times before the end of the frame's intermission)."""
        out: list[tuple[float, can.Message, Any]] = []
        incoming, contending = self._incoming, self._contending
        tb = self.bit_time_s
        while True:
            if not contending:
                if not incoming:
                    break
                first = incoming[0][0]
                if first > until:
                    break   # an earlier submission may still come and find the bus idle
                self._arbitration_at = first if first > self.busy_until else self.busy_until
            at = self._arbitration_at
            # everything queued by the moment the bus falls idle takes part
            while incoming and incoming[0][0] <= at:
                _t, seq, key, bits, msg, tag = heapq.heappop(incoming)
                heapq.heappush(contending, (key, seq, bits, msg, tag))
            _key, _seq, bits, msg, tag = contending[0]
            end = at + bits * tb
            valid = end - _VALID_BEFORE_END_BITS * tb
            if valid > until:
                break
            heapq.heappop(contending)
            out.append((valid, msg, tag))
            self._record(at, end)
            self.busy_until = self._arbitration_at = end
        if until > self._released_until:
            self._released_until = until
        return out

    def _record(self, start: float, end: float) -> None:
        self._starts.append(start)
        self._ends.append(end)
        self._busy_before.append(self._busy_total)
        self._busy_total += end - start
        # forget what load() can no longer see, in batches (amortised O(1))
        horizon = end - self.history_s
        if len(self._ends) > 256 and self._ends[len(self._ends) // 2] < horizon:
            drop = bisect_left(self._ends, horizon)
            del self._starts[:drop], self._ends[:drop], self._busy_before[:drop]

    def load(self, window_s: float, now: float) -> float:
        """The fraction of ``[now - window_s, now]`` the bus was busy with released frames (each
        frame's bits, intermission included, at the bit rate): sum(bits) / bitrate / window for
        frames inside the window, partial frames counted in part. 1.0 is a saturated bus."""
        if not (math.isfinite(window_s) and 0 < window_s <= self.history_s):
            raise ValueError(
                f"window_s must be > 0 and <= history_s ({self.history_s} s), got {window_s}")
        lo = now - window_s
        starts, ends = self._starts, self._ends
        i = bisect_right(ends, lo)          # first transmission ending after lo
        j = bisect_left(starts, now)        # first transmission starting at/after now
        if i >= j:
            return 0.0
        after_j = self._busy_before[j] if j < len(starts) else self._busy_total
        busy = after_j - self._busy_before[i]
        busy -= max(0.0, lo - starts[i])             # clip the first at the window's start
        busy -= max(0.0, ends[j - 1] - now)          # and the last at its end
        return busy / window_s

    def __repr__(self) -> str:
        return (f"CanWire({self.bitrate}, busy_until={self.busy_until}, "
                f"pending={self.pending})")
