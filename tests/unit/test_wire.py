"""Wire timing (bridge/runtime/wire.py, docs/wire-timing.md): UART character times, the exact
length of a classical CAN frame, arbitration and load of a CAN bus -- all in simulated time.

The CAN lengths are checked three ways: against the standard's unstuffed field counts and
Davis et al. 2007's worst case, against frames written out bit by bit here from ISO 11898-1's
layout, and against a bit-level reference built in this file from the Bosch CAN 2.0
specification's own CRC shift-register pseudocode and stuffing rule (independent of the
table-driven, run-counting production code).
"""

from __future__ import annotations

import random
import re

import can
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from koala_bridge.core.resources import default_config_path
from koala_bridge.core.schema import ConfigError
from koala_bridge.drivers.dialects import DIALECTS
from koala_bridge.runtime.settings import (
    BridgeSettings,
    apply_override,
    load_config,
    parse_override,
)
from koala_bridge.runtime.wire import (
    CanWire,
    SerialWire,
    arbitration_key,
    can_crc15,
    can_error_frame_bits,
    can_frame_bits,
    can_unstuffed_bits,
    can_worst_case_bits,
    serial_bits_per_byte,
    serial_time_s,
)

DEFAULT = default_config_path()

# ---------------------------------------------------------------------------- reference (test)


def _bits(value: int, n: int) -> list[int]:
    return [(value >> (n - 1 - i)) & 1 for i in range(n)]


def reference_crc15(bits: list[int]) -> int:
    """Bosch CAN Specification 2.0, "CRC field": CRC_RG = 0; per bit CRCNXT = NXTBIT xor
    CRC_RG(14); shift left by one; if CRCNXT, CRC_RG ^= 4599h."""
    crc = 0
    for bit in bits:
        nxt = bit ^ ((crc >> 14) & 1)
        crc = (crc << 1) & 0x7FFF
        if nxt:
            crc ^= 0x4599
    return crc


def reference_stuff(bits: list[int]) -> list[int]:
    """ISO 11898-1 / Bosch CAN 2.0, "Frame coding": after five consecutive equal bits, insert
    their complement (which counts in the following run)."""
    out: list[int] = []
    run, last = 0, None
    for bit in bits:
        out.append(bit)
        run = run + 1 if bit == last else 1
        last = bit
        if run == 5:
            out.append(1 - bit)
            run, last = 1, 1 - bit
    return out


def reference_frame(can_id: int, extended: bool, data: bytes, remote: bool = False,
                    dlc: int | None = None) -> list[int]:
    """The frame's bits on the wire, SOF to the end of the intermission."""
    dlc = len(data) if dlc is None else dlc
    head = [0]                                                  # SOF
    if extended:
        head += _bits(can_id >> 18, 11) + [1, 1] + _bits(can_id & 0x3FFFF, 18)  # SRR, IDE
        head += [int(remote), 0, 0]                             # RTR, r1, r0
    else:
        head += _bits(can_id, 11) + [int(remote), 0, 0]         # RTR, IDE, r0
    head += _bits(dlc, 4)
    if not remote:
        for byte in data:
            head += _bits(byte, 8)
    head += _bits(reference_crc15(head), 15)
    # CRC delimiter, ACK slot (recessive as sent), ACK delimiter, EOF, intermission
    return reference_stuff(head) + [1, 1, 1] + [1] * 7 + [1] * 3


# ---------------------------------------------------------------------------- UART


@pytest.mark.parametrize(("framing", "bits"), [
    ("8N1", 10), ("8N2", 11), ("8E1", 11), ("8O2", 12), ("7E1", 10), ("7N1", 9), ("5N1", 7),
    ("8M1", 11), ("8S1", 11),
])
def test_serial_bits_per_byte(framing: str, bits: int) -> None:
    assert serial_bits_per_byte(framing) == bits


@pytest.mark.parametrize("bad", ["8N", "9N1", "4N1", "8X1", "8N3", "8n1", "8N1.5", "", " 8N1"])
def test_bad_framing_names_the_field(bad: str) -> None:
    with pytest.raises(ValueError, match=r"^framing must be .*like \"8N1\""):
        serial_bits_per_byte(bad)


def test_serial_time_of_the_issue_figure() -> None:
    # issue 14: 32 bytes at 115200 baud 8N1 take 2.78 ms (320 bits)
    assert serial_time_s(32, 115200, "8N1") == pytest.approx(320 / 115200)
    assert round(serial_time_s(32, 115200) * 1e3, 2) == 2.78
    assert serial_time_s(0, 9600) == 0.0
    # the classic Koala's line: 38400 8N2, 11 bits a character
    assert serial_time_s(12, 38400, "8N2") == pytest.approx(12 * 11 / 38400)
    with pytest.raises(ValueError, match="baud"):
        serial_time_s(1, 0)


def test_serial_wire_queues_back_to_back() -> None:
    wire = SerialWire(115200, "8N1")
    byte = 10 / 115200
    assert wire.submit(0.0, 10) == pytest.approx(10 * byte)
    # written at the same time, it waits for the first
    assert wire.submit(0.0, 10) == pytest.approx(20 * byte)
    # written while the line is still busy: starts at the end of the previous write
    assert wire.submit(15 * byte, 5) == pytest.approx(25 * byte)
    assert wire.busy_until == pytest.approx(25 * byte)
    # written after the line fell idle: starts when written
    assert wire.submit(1.0, 32) == pytest.approx(1.0 + 320 / 115200)
    assert wire.submit(2.0, 0) == 2.0


def test_serial_wire_of_each_dialect_line() -> None:
    koala1 = SerialWire.from_line(DIALECTS["koala1"].line)
    koala25 = SerialWire.from_line(DIALECTS["koala25"].line)
    assert (koala1.baud, koala1.framing) == (38400, "8N2")
    assert (koala25.baud, koala25.framing) == (115200, "8N1")
    assert koala1.submit(0.0, 1) == pytest.approx(11 / 38400)


# ---------------------------------------------------------------------------- CAN frame length


def test_crc15_catalogue_check_value() -> None:
    # reveng catalogue, CRC-15/CAN: check = 0x059E over ASCII "123456789"
    assert can_crc15(b"123456789") == 0x059E
    bits = [b for byte in b"123456789" for b in _bits(byte, 8)]
    assert reference_crc15(bits) == 0x059E


@pytest.mark.parametrize("n", range(9))
def test_unstuffed_lengths_from_the_standard(n: int) -> None:
    # ISO 11898-1 field counts: 44 + 8n + 3 (11-bit id), 64 + 8n + 3 (29-bit id), IFS included
    assert can_unstuffed_bits(False, n) == 44 + 8 * n + 3
    assert can_unstuffed_bits(True, n) == 64 + 8 * n + 3
    # the reference frame without its stuff bits has that length
    for extended in (False, True):
        frame = reference_frame(0, extended, bytes(n))
        stuffed = can_frame_bits(0, extended, bytes(n)) - can_unstuffed_bits(extended, n)
        assert len(frame) == can_unstuffed_bits(extended, n) + stuffed


def test_published_figures() -> None:
    # Davis et al. 2007: a standard 8-byte frame is 111 bits unstuffed, 135 at worst (eq. 3);
    # 131 and 160 with a 29-bit id
    assert (can_unstuffed_bits(False, 8), can_worst_case_bits(False, 8)) == (111, 135)
    assert (can_unstuffed_bits(True, 8), can_worst_case_bits(True, 8)) == (131, 160)
    assert can_error_frame_bits() == 23 and can_error_frame_bits(0) == 17


def test_all_zero_frame_written_out_by_hand() -> None:
    # id 0x000, no data: SOF, 11 id bits, RTR, IDE, r0 and DLC 0000 are 19 dominant bits; the
    # CRC of zeros is zero: 34 zeros, a stuff bit (1) after every five of them -> 6 stuff bits
    on_wire = ("00000" "1") * 6 + "0000" + "111" + "1111111" + "111"
    assert len(on_wire) == 53
    assert can_frame_bits(0x000, False, b"") == 53
    assert "".join(map(str, reference_frame(0x000, False, b""))) == on_wire


#: A standard frame with no five equal bits anywhere from SOF to the end of the CRC (found by a
#: search with the reference above; its fields are written out below).
NO_STUFF_ID, NO_STUFF_DATA = 0x555, bytes.fromhex("d2662d6655693399")


def test_frame_without_stuff_bits_against_all_zero_data() -> None:
    fields = ("0" "10101010101" "0" "0" "0" "1000"        # SOF, id 0x555, RTR, IDE, r0, DLC 8
              + "".join(f"{b:08b}" for b in NO_STUFF_DATA))
    crc = reference_crc15([int(c) for c in fields])
    stuffed_part = fields + f"{crc:015b}"
    assert not re.search("00000|11111", stuffed_part)      # nothing to stuff
    assert len(stuffed_part) + 13 == 111
    assert can_frame_bits(NO_STUFF_ID, False, NO_STUFF_DATA) == 111
    # the same id with eight zero bytes: the data field alone is a run of 64 dominant bits
    zeros = can_frame_bits(NO_STUFF_ID, False, bytes(8))
    assert zeros == len(reference_frame(NO_STUFF_ID, False, bytes(8)))
    assert zeros >= 111 + 64 // 5


def test_stuff_count_of_every_14_bit_sequence() -> None:
    """The run-by-run count (wire._stuff_bits) equals bit-by-bit stuffing for every sequence of
    14 bits: every way runs, stuff bits and the runs they open can meet."""
    from koala_bridge.runtime.wire import _stuff_bits

    for value in range(1 << 14):
        bits = _bits(value, 14)
        assert _stuff_bits("".join(map(str, bits))) == len(reference_stuff(bits)) - 14, value


def test_remote_frame_has_no_data_field() -> None:
    # a remote frame asking for 8 bytes: RTR recessive, DLC 8, no data
    bits = can_frame_bits(0x123, False, b"", is_remote=True, dlc=8)
    assert bits == len(reference_frame(0x123, False, b"", remote=True, dlc=8))
    assert can_unstuffed_bits(False, 0) <= bits <= can_worst_case_bits(False, 0)
    with pytest.raises(ValueError, match="remote"):
        can_frame_bits(0x123, False, b"\x00", is_remote=True)


@pytest.mark.parametrize(("kwargs", "field"), [
    ({"arbitration_id": 0x800, "is_extended": False, "data": b""}, "arbitration_id"),
    ({"arbitration_id": 1 << 29, "is_extended": True, "data": b""}, "arbitration_id"),
    ({"arbitration_id": -1, "is_extended": False, "data": b""}, "arbitration_id"),
    ({"arbitration_id": 1, "is_extended": False, "data": bytes(9)}, "data"),
])
def test_bad_frames_name_the_field(kwargs: dict, field: str) -> None:
    with pytest.raises(ValueError, match=f"^{field} "):
        can_frame_bits(**kwargs)


@settings(max_examples=400, deadline=None, derandomize=True)
@given(st.booleans(), st.integers(0, 0x1FFFFFFF), st.binary(min_size=0, max_size=8),
       st.booleans())
def test_frame_bits_match_the_reference_and_stay_within_the_bounds(
    extended: bool, can_id: int, data: bytes, remote: bool
) -> None:
    can_id = can_id if extended else can_id & 0x7FF
    if remote:
        bits = can_frame_bits(can_id, extended, b"", True, len(data))
        reference = reference_frame(can_id, extended, b"", True, len(data))
        n = 0
    else:
        bits = can_frame_bits(can_id, extended, data)
        reference = reference_frame(can_id, extended, data)
        n = len(data)
    assert bits == len(reference)
    assert can_unstuffed_bits(extended, n) <= bits <= can_worst_case_bits(extended, n)


@settings(max_examples=200, deadline=None, derandomize=True)
@given(st.lists(st.sampled_from([0x00, 0xFF, 0x0F, 0xF0, 0x07, 0xE0, 0x83, 0x3E, 0x7C, 0xC1]),
                min_size=8, max_size=8),
       st.sampled_from([0x000, 0x7FF, 0x3E0, 0x01F, 0x783, 0x07C, 0x555, 0x421]),
       st.booleans(), st.integers(0, 0x3FFFF))
def test_stuff_heavy_payloads_stay_within_the_worst_case(
    payload: list[int], base: int, extended: bool, extension: int
) -> None:
    """Payloads and ids of long runs (where stuff bits pile up, and a stuff bit starts the next
    run) match the reference and never exceed Davis et al.'s bound."""
    data = bytes(payload)
    can_id = base << 18 | extension if extended else base
    bits = can_frame_bits(can_id, extended, data)
    assert bits == len(reference_frame(can_id, extended, data))
    assert bits <= can_worst_case_bits(extended, 8) == (160 if extended else 135)


# ---------------------------------------------------------------------------- CAN bus


def msg(can_id: int, data: bytes = bytes(8), extended: bool = False,
        remote: bool = False) -> can.Message:
    return can.Message(arbitration_id=can_id, data=b"" if remote else data,
                       is_extended_id=extended, is_remote_frame=remote,
                       dlc=len(data) if remote else None)


BITRATE = 500_000
TB = 1 / BITRATE


def ids(released: list) -> list[int]:
    return [m.arbitration_id for _, m, _ in released]


def test_three_frames_queued_together_leave_lowest_id_first() -> None:
    wire = CanWire(BITRATE)
    frames = [msg(0x300), msg(0x100), msg(0x200)]
    for i, m in enumerate(frames):
        wire.submit(0.0, m, tag=i)
    assert wire.pending == 3
    out = wire.release(1.0)
    assert ids(out) == [0x100, 0x200, 0x300]
    assert [tag for _, _, tag in out] == [1, 2, 0]
    # back to back; each valid for the receivers 4 bit times (last EOF bit + IFS) before its end
    end = 0.0
    for (t, m, _) in out:
        end += wire.frame_bits(m) * TB
        assert t == pytest.approx(end - 4 * TB)
    assert wire.busy_until == pytest.approx(end)
    assert wire.pending == 0


def test_arbitration_by_the_bits_of_the_arbitration_field() -> None:
    # an 11-bit id ranks as id << 18 among 29-bit ids; same base id: standard before extended;
    # same id: data before remote
    wire = CanWire(BITRATE)
    for m in (msg(0x101), msg(0x100 << 18 | 0x3FFFF, extended=True), msg(0x100, remote=True),
              msg(0x100 << 18, extended=True), msg(0x100)):
        wire.submit(0.0, m)
    out = wire.release(1.0)
    assert [(m.arbitration_id, m.is_extended_id, m.is_remote_frame) for _, m, _ in out] == [
        (0x100, False, False), (0x100, False, True), (0x100 << 18, True, False),
        (0x100 << 18 | 0x3FFFF, True, False), (0x101, False, False)]
    assert arbitration_key(0x100, False) < arbitration_key(0x100 << 18, True)
    assert arbitration_key(0x0FF << 18 | 0x3FFFF, True) < arbitration_key(0x100, False)


def test_frame_submitted_during_a_transmission_waits() -> None:
    wire = CanWire(BITRATE)
    slow = msg(0x300)
    wire.submit(0.0, slow)
    half = wire.frame_bits(slow) * TB / 2
    assert wire.release(half) == []            # still on the wire
    urgent = msg(0x001)
    wire.submit(half, urgent)                  # lower id, but the bus is taken: no preemption
    out = wire.release(1.0)
    assert ids(out) == [0x300, 0x001]
    first_end = wire.frame_bits(slow) * TB
    assert out[1][0] == pytest.approx(first_end + (wire.frame_bits(urgent) - 4) * TB)


def test_idle_bus_starts_a_frame_when_written() -> None:
    wire = CanWire(BITRATE)
    m = msg(NO_STUFF_ID, NO_STUFF_DATA)
    wire.submit(0.25, m)
    assert wire.release(0.25) == []
    ((t, _, _),) = wire.release(0.5)
    assert t == pytest.approx(0.25 + (111 - 4) * TB)


def test_worked_example_of_the_docs() -> None:
    """docs/wire-timing.md "Worked example": 500 kbit/s, four 111-bit frames."""
    payload = bytes.fromhex("a5cc335a96cc994b")
    assert {can_frame_bits(i, False, payload) for i in (0x355, 0x155, 0x2AA, 0x0AA)} == {111}
    wire = CanWire(BITRATE)
    for can_id in (0x355, 0x155, 0x2AA):
        wire.submit(0.0, msg(can_id, payload))
    assert wire.release(100e-6) == []
    wire.submit(100e-6, msg(0x0AA, payload))
    out = wire.release(1.0)
    assert ids(out) == [0x155, 0x0AA, 0x2AA, 0x355]
    assert [round(t * 1e6, 6) for t, _, _ in out] == [214, 436, 658, 880]


def test_identical_arbitration_fields_go_in_submission_order() -> None:
    wire = CanWire(BITRATE)
    for tag in range(4):
        wire.submit(0.0, msg(0x42), tag=tag)
    assert [tag for _, _, tag in wire.release(1.0)] == [0, 1, 2, 3]


def _traffic(seed: int, n: int) -> list[tuple[float, can.Message]]:
    rng = random.Random(seed)
    out = []
    t = 0.0
    for _ in range(n):
        t += rng.choice([0.0, 0.0, rng.uniform(0, 0.004)])
        ext = rng.random() < 0.3
        out.append((t, msg(rng.randrange(1 << 29) if ext else rng.randrange(0x800),
                           rng.randbytes(rng.randrange(9)), extended=ext)))
    return out


def _run(traffic: list[tuple[float, can.Message]], step: float | None) -> list:
    wire = CanWire(BITRATE)
    out: list = []
    if step is None:                           # everything submitted, then one release
        for i, (t, m) in enumerate(traffic):
            wire.submit(t, m, tag=i)
        return wire.release(1e9)
    now, i = 0.0, 0
    while i < len(traffic) or wire.pending:    # the lockstep loop: submit the step's, release
        while i < len(traffic) and traffic[i][0] <= now:
            wire.submit(traffic[i][0], traffic[i][1], tag=i)
            i += 1
        out += wire.release(now)
        now += step
    return out


def test_stepping_the_wire_changes_nothing_and_runs_are_deterministic() -> None:
    traffic = _traffic(seed=14, n=600)
    once = _run(traffic, None)
    assert [(t, tag) for t, _, tag in once] == [(t, tag) for t, _, tag in _run(traffic, None)]
    for step in (0.01, 0.001, 0.0003):
        stepped = _run(traffic, step)
        assert [tag for _, _, tag in stepped] == [tag for _, _, tag in once]
        assert [t for t, _, _ in stepped] == pytest.approx([t for t, _, _ in once], abs=1e-12)
    assert sorted(tag for _, _, tag in once) == list(range(len(traffic)))
    # each frame started when the bus fell idle or when it was written, and beat every frame
    # written by then and sent later (the lowest arbitration field wins; ties by submission)
    bits = CanWire(BITRATE).frame_bits
    end = -1.0
    for k, (t, m, tag) in enumerate(once):
        start = t + 4 * TB - bits(m) * TB
        assert start == pytest.approx(max(end, traffic[tag][0]), abs=1e-12)
        mine = (arbitration_key(m.arbitration_id, m.is_extended_id), tag)
        for _, later, later_tag in once[k + 1:]:
            if traffic[later_tag][0] <= start + 1e-12:
                assert mine < (arbitration_key(later.arbitration_id, later.is_extended_id),
                               later_tag)
        end = start + bits(m) * TB


def test_submitting_into_the_decided_past_is_refused() -> None:
    wire = CanWire(BITRATE)
    wire.release(0.02)
    with pytest.raises(ValueError, match=r"^t = .* before the last release"):
        wire.submit(0.01, msg(1))
    with pytest.raises(ValueError, match="CAN FD"):
        wire.submit(0.02, can.Message(arbitration_id=1, data=bytes(12), is_fd=True))
    with pytest.raises(ValueError, match="bitrate"):
        CanWire(0)


def test_load_is_the_busy_fraction_of_the_window() -> None:
    wire = CanWire(BITRATE)
    frames = [msg(0x100 + i, bytes([i]) * (i % 9)) for i in range(20)]
    for m in frames:
        wire.submit(0.0, m)
    wire.release(1.0)
    total_bits = sum(wire.frame_bits(m) for m in frames)
    assert wire.load(1.0, 1.0) == pytest.approx(total_bits / BITRATE / 1.0)
    assert wire.load(0.1, 0.1) == pytest.approx(total_bits / BITRATE / 0.1)
    # a window inside the busy period is fully busy, one after it idle
    busy = total_bits / BITRATE
    assert wire.load(busy / 2, busy * 0.75) == pytest.approx(1.0)
    assert wire.load(0.5, 1.0) == 0.0
    # half of the window overlaps the busy period
    assert wire.load(busy, busy * 1.5) == pytest.approx(0.5)
    with pytest.raises(ValueError, match="window_s"):
        wire.load(20.0, 1.0)


def test_saturated_bus_carries_bitrate_over_frame_bits_frames_a_second() -> None:
    # docs/wire-timing.md's worked example: 500 kbit/s, 8-byte standard frames of 111 bits
    # (no stuff bits): a frame every 222 us, 4504 complete in the first second
    wire = CanWire(BITRATE, history_s=2.0)
    for _ in range(5000):
        wire.submit(0.0, msg(NO_STUFF_ID, NO_STUFF_DATA))
    out = wire.release(1.0)
    assert len(out) == int((1.0 + 4 * TB) / (111 * TB)) == 4504
    assert wire.pending == 5000 - 4504
    assert wire.load(1.0, 1.0) == pytest.approx(4504 * 111 / BITRATE)
    # the history is pruned as the bus runs, and what load can see is kept
    for k in range(1, 4):
        for _ in range(4600):
            wire.submit(float(k), msg(NO_STUFF_ID, NO_STUFF_DATA))
        wire.release(k + 1.0)
    assert len(wire._ends) < 2 * 4600 * 2 + 300
    assert wire.load(1.0, 4.0) == pytest.approx(1.0, abs=2 * 111 / BITRATE)


# ---------------------------------------------------------------------------- settings


def test_wire_keys_default_off_and_reach_the_settings() -> None:
    buses = BridgeSettings.from_config(load_config(DEFAULT)).buses
    assert (buses.kteam_wire_timing, buses.rangefinders_wire_timing) == (False, False)
    assert (buses.rangefinders_baud, buses.rangefinders_framing) == (115200, "8N1")
    assert (buses.can.wire_timing, buses.can.bitrate) == (False, 500_000)
    assert (buses.mavlink.wire_timing, buses.mavlink.baud, buses.mavlink.framing) == (
        False, 57600, "8N1")
    assert str(buses.kteam_line) == "38400 8N2"
    cfg = load_config(DEFAULT)
    for override in ("buses.can.wire_timing=true", "buses.can.bitrate=125000",
                     "buses.kteam.wire_timing=true", "buses.kteam.dialect=koala25",
                     'buses.mavlink.framing="8E1"', "buses.rangefinders.baud=9600"):
        cfg = apply_override(cfg, *parse_override(override))
    buses = BridgeSettings.from_config(cfg).buses
    assert (buses.can.wire_timing, buses.can.bitrate, buses.kteam_wire_timing) == (
        True, 125000, True)
    assert (buses.mavlink.framing, buses.rangefinders_baud) == ("8E1", 9600)
    assert str(buses.kteam_line) == "115200 8N1"


@pytest.mark.parametrize(("override", "message"), [
    ('buses.rangefinders.framing="8X1"', r"\[buses.rangefinders\] 'framing' must be data bits"),
    ('buses.mavlink.framing="9N1"', r"\[buses.mavlink\] 'framing' must be data bits"),
    ("buses.can.bitrate=2000000", r"\[buses.can\] 'bitrate' must be a classical CAN bit rate"),
    ("buses.can.bitrate=500000.0", r"\[buses.can\] 'bitrate'"),
    ("buses.mavlink.baud=0", r"\[buses.mavlink\] 'baud'"),
    ("buses.kteam.wire_timing=1", r"\[buses.kteam\] 'wire_timing' must be"),
    ("buses.can.wire_timeing=true", r"did you mean 'wire_timing'"),
])
def test_bad_wire_keys_are_one_line_errors(override: str, message: str) -> None:
    cfg = apply_override(load_config(DEFAULT), *parse_override(override))
    with pytest.raises(ConfigError, match=message) as e:
        BridgeSettings.from_config(cfg)
    assert "\n" not in str(e.value)
