"""CAN: the shipped DBC, the codec, and the socketcand / slcan / virtual transports driven by
python-can's own clients, plus malformed input on each."""

from __future__ import annotations

import random
import threading
from collections.abc import Iterator
from pathlib import Path

import can
import cantools
import pytest
import serial
from _can import recv, wait_for
from _socketcand_client import raw_client, read_element
from koala_bridge.drivers.can_codec import (
    DEFAULT_DBC_PATH,
    KoalaCanCodec,
    load_koala_dbc,
    wrap_int32,
)
from koala_bridge.drivers.messages import (
    FrameError,
    GyroFrame,
    MotorCommandFrame,
    Reject,
    RejectReason,
    WheelOdometryFrame,
)
from koala_bridge.drivers.transports import open_can_transport, python_can_config
from koala_bridge.drivers.transports.base import CanTransport
from koala_bridge.drivers.transports.slcan import SlcanAdapter
from koala_bridge.drivers.transports.socketcand import SocketcandServer

GOLDEN = Path(__file__).parents[1] / "data" / "drivers" / "can_frames.txt"
FRAME_TYPES = {
    "MotorCommandFrame": MotorCommandFrame,
    "WheelOdometryFrame": WheelOdometryFrame,
    "GyroFrame": GyroFrame,
}


@pytest.fixture(scope="module")
def codec() -> KoalaCanCodec:
    return KoalaCanCodec()


def _golden() -> list[tuple[object, int, bytes]]:
    cases = []
    for line in GOLDEN.read_text().splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        left, right = line.split("|")
        name, *assignments = left.split()
        values = {k: float(v) for k, v in (a.split("=") for a in assignments)}
        if name == "WheelOdometryFrame":
            values = {k: int(v) for k, v in values.items()}
        can_id, _dlc, data = right.split()
        cases.append((FRAME_TYPES[name](**values), int(can_id, 16), bytes.fromhex(data)))
    return cases


# --------------------------------------------------------------------------- DBC + codec


def test_dbc_loads_strictly_and_has_the_documented_layout() -> None:
    db = load_koala_dbc()
    ids = {m.name: (m.frame_id, m.length, m.senders) for m in db.messages}
    assert ids == {
        "MotorCommand": (0x100, 4, ["Firmware"]),
        "WheelOdometry": (0x110, 8, ["KoalaBase"]),
        "Gyro": (0x120, 4, ["KoalaBase"]),
    }
    assert db.get_message_by_name("Gyro").get_signal_by_name("yaw_rate").unit == "rad/s"
    # cantools' own DBC writer re-reads it identically (a proxy for other tools' parsers).
    again = cantools.database.load_string(db.as_dbc_string(), database_format="dbc")
    assert [m.name for m in again.messages] == [m.name for m in db.messages]
    assert DEFAULT_DBC_PATH.is_absolute()


@pytest.mark.parametrize(("frame", "can_id", "data"), _golden())
def test_golden_frames(codec: KoalaCanCodec, frame: object, can_id: int, data: bytes) -> None:
    msg = codec.encode(frame)  # type: ignore[arg-type]
    assert (msg.arbitration_id, bytes(msg.data), msg.is_extended_id) == (can_id, data, False)
    decoded = codec.decode(msg)
    assert type(decoded) is type(frame)
    for name in frame.__slots__:  # type: ignore[attr-defined]
        assert getattr(decoded, name) == pytest.approx(getattr(frame, name), abs=1e-9)
    # A third party decoding with cantools and the shipped DBC sees the same physical values.
    db = cantools.database.load_file(str(DEFAULT_DBC_PATH))
    values = db.decode_message(can_id, data)
    for name in frame.__slots__:  # type: ignore[attr-defined]
        assert values[name] == pytest.approx(getattr(frame, name), abs=1e-9)


def test_encoder_counters_wrap_and_out_of_range_values_are_refused(codec: KoalaCanCodec) -> None:
    assert wrap_int32(2**31) == -(2**31)
    decoded = codec.decode(codec.encode(WheelOdometryFrame(2**31 + 5, -(2**31) - 1)))
    assert decoded == WheelOdometryFrame(-(2**31) + 5, 2**31 - 1)
    with pytest.raises(FrameError):
        codec.encode(MotorCommandFrame(2.5, 0.0))
    with pytest.raises(FrameError):
        codec.encode(GyroFrame(-25.0))


@pytest.mark.parametrize(
    ("msg", "reason"),
    [
        (can.Message(arbitration_id=0x7FF, data=b"\0" * 8, is_extended_id=False), "unknown_id"),
        (can.Message(arbitration_id=0x110, data=b"\0" * 8, is_extended_id=True), "unknown_id"),
        (can.Message(arbitration_id=0x110, data=b"\0" * 7, is_extended_id=False), "wrong_dlc"),
        (can.Message(arbitration_id=0x100, data=b"\0" * 5, is_extended_id=False), "wrong_dlc"),
        (
            can.Message(arbitration_id=0x100, data=b"\xff\x7f\0\0", is_extended_id=False),
            "out_of_range",
        ),
        (
            can.Message(arbitration_id=0x120, data=b"\0\0\0\x80", is_extended_id=False),
            "out_of_range",
        ),
        (
            can.Message(arbitration_id=0x100, is_remote_frame=True, dlc=4, is_extended_id=False),
            "unsupported",
        ),
    ],
)
def test_bad_frames_are_rejected(codec: KoalaCanCodec, msg: can.Message, reason: str) -> None:
    result = codec.decode(msg)
    assert isinstance(result, Reject)
    assert result.reason is RejectReason(reason)


# --------------------------------------------------------------------------- transports


@pytest.fixture
def socketcand() -> Iterator[SocketcandServer]:
    with SocketcandServer(channel="koala0") as server:
        yield server
    assert not [t for t in threading.enumerate() if t.name.startswith("socketcand:")]


@pytest.fixture
def slcan() -> Iterator[SlcanAdapter]:
    with SlcanAdapter() as adapter:
        yield adapter
    assert not [t for t in threading.enumerate() if t.name.startswith("slcan:")]


def _exchange(codec: KoalaCanCodec, server: CanTransport, client: can.BusABC) -> None:
    """Bridge -> client odometry and gyro; client -> bridge motor command; all decoded."""
    server.send(codec.encode(WheelOdometryFrame(1000, -1000)))
    server.send(codec.encode(GyroFrame(0.5)))
    assert codec.decode(recv(client)) == WheelOdometryFrame(1000, -1000)
    assert codec.decode(recv(client)) == GyroFrame(0.5)
    client.send(codec.encode(MotorCommandFrame(0.2, -0.2)))
    assert codec.decode(recv(server)) == MotorCommandFrame(0.2, -0.2)


def test_socketcand_with_python_can_clients(
    codec: KoalaCanCodec, socketcand: SocketcandServer
) -> None:
    config = python_can_config(socketcand.endpoint)
    with can.Bus(**config) as first, can.Bus(**config) as second:
        wait_for(lambda: socketcand.stats.clients == 2)
        _exchange(codec, socketcand, first)
        # Broadcast: the second client saw the bridge's frames and the first client's command.
        seen = [codec.decode(recv(second)) for _ in range(3)]
        assert seen == [
            WheelOdometryFrame(1000, -1000),
            GyroFrame(0.5),
            MotorCommandFrame(0.2, -0.2),
        ]
        extended = can.Message(arbitration_id=0x1ABCDEF, data=b"\x01", is_extended_id=True)
        second.send(extended)
        got = recv(socketcand)
        assert (got.arbitration_id, got.is_extended_id, bytes(got.data)) == (
            0x1ABCDEF,
            True,
            b"\x01",
        )
        assert isinstance(codec.decode(got), Reject)  # unknown id: the bridge counts it
    stats = socketcand.stats
    assert stats.sent == 2 and stats.received == 2 and stats.rejected == 0


def test_socketcand_counts_a_client_once_it_receives_frames(
    codec: KoalaCanCodec, socketcand: SocketcandServer
) -> None:
    # What `replay --wait-clients` waits on: a frame sent before `rawmode` never reaches the
    # client, so a client still in its handshake is not counted yet.
    with raw_client(socketcand) as raw:
        raw.sendall(b"< open koala0 >")
        assert read_element(raw) == b"< ok >"
        assert socketcand.stats.clients == 0
        raw.sendall(b"< rawmode >")
        assert read_element(raw) == b"< ok >"
        wait_for(lambda: socketcand.stats.clients == 1)
        socketcand.send(codec.encode(GyroFrame(0.5)))
        assert read_element(raw).startswith(b"< frame ")
    wait_for(lambda: socketcand.stats.clients == 0)


def test_socketcand_rejects_bad_input_and_keeps_serving(
    codec: KoalaCanCodec, socketcand: SocketcandServer
) -> None:
    rng = random.Random(11)
    with raw_client(socketcand) as raw:
        raw.sendall(b"< open wrongbus >")
        assert read_element(raw) == b"< error could not open bus >"
        raw.sendall(b"< open koala0 >< rawmode >")
        assert read_element(raw) == b"< ok >"
        assert read_element(raw) == b"< ok >"
        bad_inputs = [
            b"< bogus >",
            b"< send 100 4 1 2 >",  # dlc says 4, two bytes
            b"< send 800 0 >",  # 11-bit id out of range
            b"< send 100 9 0 0 0 0 0 0 0 0 0 >",  # dlc > 8
            b"< send 10x 1 00 >",
            b"< send 100 1 100 >",  # not a byte
            b"< subscribe 0 0 100 >",  # BCM command, unsupported here
        ]
        # In raw mode a rejected element is counted and not answered: there "< error ... >" is
        # an error frame, which python-can would parse (and choke on). The echo right after
        # each one proves that nothing was sent before it.
        for n, bad in enumerate(bad_inputs, start=1):
            raw.sendall(bad + b"< echo >")
            assert read_element(raw) == b"< echo >", bad
            assert socketcand.stats.rejected == 1 + n, bad  # 1: the wrong bus above
        raw.sendall(
            bytes(rng.randrange(256) for _ in range(200)).replace(b"<", b"").replace(b">", b"")
        )
        raw.sendall(b"< " + b"x" * 300)  # an element that never ends
        raw.sendall(b">< echo >")  # (the stray '>' closes nothing: junk)
        assert read_element(raw) == b"< echo >"
        assert socketcand.stats.rejected >= 1 + len(bad_inputs) + 2
        # The same connection still sends valid frames, and a python-can client still works.
        raw.sendall(b"< send 100 4 c8 0 38 ff >")
        assert codec.decode(recv(socketcand)) == MotorCommandFrame(0.2, -0.2)
        with can.Bus(**python_can_config(socketcand.endpoint)) as client:
            _exchange(codec, socketcand, client)
        assert socketcand.stats.rejected >= len(bad_inputs) + 3


def test_slcan_with_python_can_client(codec: KoalaCanCodec, slcan: SlcanAdapter) -> None:
    with can.Bus(
        **python_can_config(slcan.endpoint), sleep_after_open=0, bitrate=500_000
    ) as client:
        assert client.get_version(5) == (10, 13)
        assert client.get_serial_number(5) == "KOAL"
        wait_for(lambda: slcan.is_open)
        _exchange(codec, slcan, client)
    wait_for(lambda: not slcan.is_open)  # python-can sent "C" on shutdown
    assert slcan.stats.rejected == 0


def test_slcan_rejects_bad_input_and_keeps_serving(
    codec: KoalaCanCodec, slcan: SlcanAdapter
) -> None:
    rng = random.Random(12)
    with serial.Serial(slcan.endpoint.path, timeout=5) as port:

        def ask(line: bytes) -> bytes:
            port.write(line + b"\r")
            reply = b""
            while not reply.endswith((b"\r", b"\a")):
                byte = port.read(1)
                assert byte, f"no reply to {line!r}"
                reply += byte
            return reply

        assert ask(b"t1004C8003") == b"\a"  # channel closed
        assert ask(b"O") == b"\r"
        assert ask(b"S6") == b"\a"  # bit rate while open
        for bad in [
            b"t10",
            b"t1004C800",
            b"t1009" + b"00" * 9,
            b"tXYZ0",
            b"t8000",
            b"d1001AA",
            b"Q",
            b"\xff\xfe",
        ]:
            assert ask(bad) == b"\a", bad
        garbage = (
            bytes(rng.randrange(256) for _ in range(300)).replace(b"\r", b"").replace(b"\n", b"")
        )
        assert ask(garbage) == b"\a"  # one over-long line, one BELL
        assert ask(b"t1004C80038FF") == b"z\r"
        assert codec.decode(recv(slcan)) == MotorCommandFrame(0.2, -0.2)
        assert ask(b"T01ABCDEF1FF") == b"Z\r"
        assert isinstance(codec.decode(recv(slcan)), Reject)
        assert ask(b"Z1") == b"\r"
        slcan.send(codec.encode(GyroFrame(0.5)))
        line = port.read_until(b"\r")
        assert line.startswith(b"t1204") and len(line) == 1 + 3 + 1 + 8 + 4 + 1  # + time stamp
        assert ask(b"C") == b"\r"
    assert slcan.stats.rejected >= 11
    with can.Bus(**python_can_config(slcan.endpoint), sleep_after_open=0) as client:
        wait_for(lambda: slcan.is_open)
        _exchange(codec, slcan, client)


def test_virtual_bus_through_the_url_registry(codec: KoalaCanCodec) -> None:
    with open_can_transport("virtual://koala-test") as bridge_side:
        with can.Bus(**python_can_config(bridge_side.endpoint)) as client:
            _exchange(codec, bridge_side, client)
            client.send(can.Message(arbitration_id=0x100, data=b"\0", is_extended_id=False))
            assert codec.decode(recv(bridge_side)).reason is RejectReason.WRONG_DLC  # type: ignore[union-attr]
            _exchange(codec, bridge_side, client)


def test_url_registry_opens_each_can_backend() -> None:
    with open_can_transport("socketcand://127.0.0.1:0/vcan9") as server:
        assert server.endpoint.channel == "vcan9" and server.endpoint.port
    with open_can_transport("slcan://") as adapter:
        assert Path(adapter.endpoint.path or "").exists()
    with pytest.raises(ValueError, match="unknown transport"):
        open_can_transport("canbus://x")
    with pytest.raises(ValueError):
        open_can_transport("python-can://virtual")


def test_socketcand_frame_time_is_the_senders_time_stamp(
    codec: KoalaCanCodec, socketcand: SocketcandServer
) -> None:
    # The bridge stamps its frames with the sample's simulation time (docs/protocols.md,
    # "Time"); the first step's frames are at t = 0 and must say 0, not the host's clock.
    with raw_client(socketcand) as raw:
        raw.sendall(b"< open koala0 >< rawmode >")
        assert read_element(raw) == b"< ok >"
        assert read_element(raw) == b"< ok >"
        wait_for(lambda: socketcand.stats.clients == 1)
        for t in (0.0, 0.01, 12.34):
            msg = codec.encode(GyroFrame(0.5))
            msg.timestamp = t
            socketcand.send(msg)
            assert read_element(raw) == f"< frame 120 {t:.6f} 50C30000 >".encode()
