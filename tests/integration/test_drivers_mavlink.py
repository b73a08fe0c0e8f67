"""MAVLink compass codec: frames and units, pymavlink (mavutil, as a ground station uses it)
receiving over UDP / TCP / pty, and garbage datagrams."""

from __future__ import annotations

import math
import random
import socket
from collections.abc import Iterator

import pytest
from koala_bridge.drivers.mavlink_codec import (
    CompassDecoder,
    CompassEncoder,
    MavlinkIdentity,
    flu_ut_to_frd_mgauss,
    frd_mgauss_to_flu_ut,
    heading_from_frd,
)
from koala_bridge.drivers.messages import CompassSample, MavlinkHeartbeat
from koala_bridge.drivers.transports import open_byte_transport, pymavlink_url
from koala_bridge.drivers.transports.base import ByteTransport
from pymavlink.dialects.v20 import common as mavlink2


@pytest.fixture
def mavutil(monkeypatch: pytest.MonkeyPatch) -> Iterator[object]:
    """pymavlink's mavutil set up for MAVLink 2, as a ground station would run it."""
    monkeypatch.setenv("MAVLINK20", "1")
    from pymavlink import mavutil as module

    module.set_dialect("common")
    yield module


def _earth_field_in_body(yaw_cw_from_north: float) -> tuple[float, float, float]:
    """FLU field (uT) of a level robot whose heading is ``yaw`` clockwise from magnetic north,
    in a field of 20 uT north and 40 uT down."""
    north, down = 20.0, 40.0
    # Robot frame: x forward; the north vector is at angle -yaw from forward, CCW positive.
    return (north * math.cos(yaw_cw_from_north), north * math.sin(yaw_cw_from_north), -down)


@pytest.mark.parametrize("heading_deg", [0, 45, 90, 135, 180, 270, 359])
def test_heading_formula_matches_the_physical_heading(heading_deg: float) -> None:
    yaw = math.radians(heading_deg)
    xmag, ymag, zmag = flu_ut_to_frd_mgauss(*_earth_field_in_body(yaw))
    assert zmag == 400  # FRD z is down: the downward field component is positive
    assert math.degrees(heading_from_frd(xmag, ymag)) == pytest.approx(heading_deg, abs=0.5)


def test_unit_and_axis_conversion() -> None:
    assert flu_ut_to_frd_mgauss(1.0, 2.0, 3.0) == (10, -20, -30)
    assert frd_mgauss_to_flu_ut(10, -20, -30) == (1.0, 2.0, 3.0)
    assert flu_ut_to_frd_mgauss(1e6, -1e6, 0.04) == (32767, 32767, 0)  # int16 saturation


def test_encoded_bytes_are_mavlink2_with_the_documented_ids() -> None:
    encoder = CompassEncoder(MavlinkIdentity(system_id=7, component_id=200))
    parser = mavlink2.MAVLink(None)
    wire = encoder.heartbeat() + encoder.scaled_imu(CompassSample(1500, 20.0, 5.0, -40.0))
    assert wire[0] == 0xFD  # MAVLink 2 magic
    hb, imu = parser.parse_buffer(wire)
    assert (hb.get_msgId(), imu.get_msgId()) == (0, 26)
    assert (hb.get_srcSystem(), hb.get_srcComponent()) == (7, 200)
    assert hb.autopilot == mavlink2.MAV_AUTOPILOT_INVALID
    assert (imu.xmag, imu.ymag, imu.zmag, imu.time_boot_ms) == (200, -50, 400, 1500)
    assert (imu.get_seq() - hb.get_seq()) % 256 == 1


def test_decoder_counts_garbage_and_recovers() -> None:
    rng = random.Random(3)
    encoder, decoder = CompassEncoder(), CompassDecoder()
    sample = CompassSample(10, 1.5, -2.5, 30.0)
    good = encoder.scaled_imu(sample)
    corrupted = bytearray(good)
    corrupted[-3] ^= 0xFF
    assert decoder.feed_datagram(bytes(rng.randrange(256) for _ in range(100))) == []
    assert decoder.feed_datagram(good[:-5]) == []  # truncated
    assert decoder.feed_datagram(bytes(corrupted)) == []  # CRC fails
    assert decoder.rejected >= 3
    assert decoder.feed_datagram(good) == [sample]
    # As a byte stream, a packet may arrive split in any two pieces.
    for cut in range(len(good) + 1):
        assert decoder.feed(good[:cut]) + decoder.feed(good[cut:]) == [sample]


def test_decoder_filters_by_source() -> None:
    mine = CompassEncoder(MavlinkIdentity(system_id=1))
    other = CompassEncoder(MavlinkIdentity(system_id=2))
    decoder = CompassDecoder(system_id=1)
    out = decoder.feed(other.heartbeat() + mine.heartbeat())
    assert out == [
        MavlinkHeartbeat(1, 200, mavlink2.MAV_TYPE_GROUND_ROVER, mavlink2.MAV_AUTOPILOT_INVALID)
    ]
    assert decoder.ignored == 1


def _stream_to_ground_station(transport: ByteTransport, gcs: object, datagrams: bool) -> None:
    encoder = CompassEncoder()
    sample = CompassSample(1234, *_earth_field_in_body(math.radians(90)))
    received: dict[str, object] = {}
    for _ in range(200):
        if datagrams:
            transport.write(bytes(random.Random(1).randrange(256) for _ in range(40)))  # garbage
        transport.write(encoder.heartbeat())
        transport.write(encoder.scaled_imu(sample))
        msg = gcs.recv_match(type=["HEARTBEAT", "SCALED_IMU"], blocking=True, timeout=0.2)  # type: ignore[attr-defined]
        while msg is not None:
            received[msg.get_type()] = msg
            msg = gcs.recv_match(type=["HEARTBEAT", "SCALED_IMU"], blocking=False)  # type: ignore[attr-defined]
        if len(received) == 2:
            break
    assert set(received) == {"HEARTBEAT", "SCALED_IMU"}
    imu = received["SCALED_IMU"]
    assert math.degrees(heading_from_frd(imu.xmag, imu.ymag)) == pytest.approx(90, abs=0.5)  # type: ignore[attr-defined]


def test_pymavlink_ground_station_over_udp(mavutil: object, free_udp_port: int) -> None:
    with open_byte_transport(f"udp://127.0.0.1:{free_udp_port}") as udp:
        url = pymavlink_url(udp.endpoint)
        assert url == f"udpin:127.0.0.1:{free_udp_port}"
        gcs = mavutil.mavlink_connection(url, source_system=255)  # type: ignore[attr-defined]
        try:
            _stream_to_ground_station(udp, gcs, datagrams=True)
            # The ground station's own heartbeat comes back on the bridge's socket.
            gcs.mav.heartbeat_send(mavlink2.MAV_TYPE_GCS, mavlink2.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            assert udp.wait(5)
            replies = CompassDecoder().feed_datagram(udp.read())
            assert (
                replies and isinstance(replies[0], MavlinkHeartbeat) and replies[0].system_id == 255
            )
        finally:
            gcs.close()


def test_pymavlink_ground_station_over_tcp(mavutil: object) -> None:
    with open_byte_transport("tcp://127.0.0.1:0") as tcp:
        gcs = mavutil.mavlink_connection(pymavlink_url(tcp.endpoint))  # type: ignore[attr-defined]
        try:
            _stream_to_ground_station(tcp, gcs, datagrams=False)
        finally:
            gcs.close()


def test_pymavlink_ground_station_over_a_pty(mavutil: object) -> None:
    with open_byte_transport("pty://") as pty:
        gcs = mavutil.mavlink_connection(pymavlink_url(pty.endpoint), baud=115200)  # type: ignore[attr-defined]
        try:
            _stream_to_ground_station(pty, gcs, datagrams=False)
        finally:
            gcs.close()


def test_udp_garbage_from_a_client_is_counted_by_the_decoder(free_udp_port: int) -> None:
    rng = random.Random(8)
    with open_byte_transport(f"udp://127.0.0.1:{free_udp_port}") as udp:
        decoder = CompassDecoder()
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sender:
            for _ in range(5):
                sender.sendto(bytes(rng.randrange(256) for _ in range(64)), udp.local_address)
            sender.sendto(CompassEncoder().heartbeat(), udp.local_address)
            out: list[object] = []
            for _ in range(6):
                assert udp.wait(5)
                out += decoder.feed_datagram(udp.read())
        assert len(out) == 1 and decoder.rejected >= 5
        assert udp.stats.received == 6
