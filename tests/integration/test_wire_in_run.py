"""Wire timing in a running bridge (issue 14 point 4, docs/wire-timing.md): frames reach the
firmware once their bits have crossed the line, in simulated time, with CAN arbitration by id.
Lockstep, paced by K-Team ``D`` from the test thread; CAN read after each ``d``."""

from __future__ import annotations

import can
import pytest
import serial
from _inproc import WAIT_S, ask, bridge, kteam, socketcand
from koala_bridge.drivers.can_codec import KoalaCanCodec
from koala_bridge.drivers.messages import GyroFrame, RangeKind, WheelOdometryFrame
from koala_bridge.drivers.rangeframes import RangeFrameDecoder
from koala_bridge.runtime.wire import can_frame_bits, serial_time_s

CODEC = KoalaCanCodec()


def drain(bus: can.BusABC) -> list[can.Message]:
    out = []
    while (msg := bus.recv(0.05)) is not None:
        out.append(msg)
    return out


def test_can_frames_arrive_a_step_late_and_the_bus_load_is_their_bits_over_the_bitrate() -> None:
    with bridge("buses.can.wire_timing=true", "buses.can.bitrate=125000") as source, \
            socketcand(source) as bus, kteam(source) as port:
        seen: list[can.Message] = []
        for k in range(1, 101):
            assert ask(port, "D,20,-20") == "d"        # spinning: every sample differs
            seen += drain(bus)
            newest = max(m.timestamp for m in seen)
            # a frame sampled at the boundary is still on the wire when the period ends
            assert newest == pytest.approx(0.01 * (k - 1))
        status = source.status(source.port.t)
    # load over the last status period (1 s): the frames released in it, bits / bitrate
    window = [m for m in seen if 0.0 <= m.timestamp < 1.0 - 1e-9 and m.timestamp > 0]
    bits = sum(can_frame_bits(m.arbitration_id, m.is_extended_id, bytes(m.data))
               for m in window)
    assert status["bus_load"]["can"] == pytest.approx(bits / 125000 / 1.0, rel=0.02)


def test_a_saturated_bus_starves_the_higher_id() -> None:
    """At 10 kbit/s the two frames of a step need ~20 ms of a 10 ms step: the queue grows, and
    every time the bus falls idle WheelOdometry (0x110) wins arbitration over Gyro (0x120)."""
    with bridge("buses.can.wire_timing=true", "buses.can.bitrate=10000") as source, \
            socketcand(source) as bus, kteam(source) as port:
        seen: list[can.Message] = []
        for _ in range(100):
            assert ask(port, "D,20,-20") == "d"
            seen += drain(bus)
        status = source.status(source.port.t)
    kinds = [type(CODEC.decode(m)) for m in seen]
    odometry, gyro = kinds.count(WheelOdometryFrame), kinds.count(GyroFrame)
    assert odometry > 40 and gyro <= 1          # step 0's gyro may go before the queue builds
    assert status["bus_load"]["can"] == pytest.approx(1.0, abs=0.01)


def test_range_frames_leave_at_the_baud_rate() -> None:
    """45-byte IR frames at 9600 baud 8N1 take 46.9 ms each, and the sonar frames share the
    line: no frame is read before its last stop bit, and the line stays busy."""
    with bridge("buses.rangefinders.enabled=true", "buses.rangefinders.wire_timing=true",
                "buses.rangefinders.baud=9600") as source, kteam(source) as port:
        assert source.endpoints is not None and source.endpoints.rangefinders is not None
        with serial.Serial(source.endpoints.rangefinders, timeout=0.2) as ranges:
            decoder = RangeFrameDecoder()
            arrivals: list[tuple[float, float]] = []      # (sample time, boundary seen at)
            for _ in range(60):
                assert ask(port, "D,0,0") == "d"
                for frame in decoder.feed(ranges.read(ranges.in_waiting or 0)):
                    if frame.kind == RangeKind.IR:
                        arrivals.append((frame.t_us / 1e6, source.port.t))
            status = source.status(source.port.t)
    ir = [(ts, seen) for ts, seen in arrivals if ts > 0]
    assert ir, "no range frame arrived"
    wire = serial_time_s(45, 9600, "8N1")
    assert wire == pytest.approx(0.046875)
    for ts, seen in ir:
        # written at the first step at or after its last stop bit (never before)
        assert ts + wire - 1e-9 <= seen <= ts + 0.2, (ts, seen)
    assert [ts for ts, _ in ir] == sorted(ts for ts, _ in ir)      # in order, none lost
    assert len(ir) >= 9
    assert status["bus_load"]["rangefinders"] > 0.9           # 20 Hz x 46.9 ms + the sonar


def test_step_zero_crosses_the_wire_while_lockstep_holds() -> None:
    """Held at t = 0 the firmware may wait for a sample before its first command: step 0's
    frames, on a wire that takes less than a step, are there before it."""
    with bridge("buses.can.wire_timing=true", "buses.can.bitrate=125000") as source, \
            socketcand(source) as bus:
        first = bus.recv(WAIT_S)
        assert first is not None and first.timestamp == 0.0
        assert source.port.t == 0.0
