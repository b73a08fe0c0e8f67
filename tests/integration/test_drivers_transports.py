"""The transport registry and one contract run against every backend through it.

As python-can's back-to-back tests do, each backend is opened by URL through the registry and
paired with a client on its own transport (pyserial on a pty, a socket, python-can, or another
backend of the registry), then the same tests run on every pair: bytes (frames) both ways,
counters, close idempotent, use after close refused. Backend-specific behaviour (slow and absent
clients, fan-out) follows.
"""

from __future__ import annotations

import importlib
import os
import socket
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import can
import pytest
import serial
from _can import wait_for
from koala_bridge.drivers.messages import TransportClosedError
from koala_bridge.drivers.transports import (
    BYTE_BACKENDS,
    CAN_BACKENDS,
    ByteTransport,
    CanTransport,
    Endpoint,
    mavlink_connection_options,
    mavlink_connection_url,
    open_byte_transport,
    open_can_transport,
    pymavlink_url,
    pyserial_url,
    python_can_config,
)
from koala_bridge.drivers.transports.loop import LoopbackTransport
from koala_bridge.drivers.transports.pty import PtyTransport
from koala_bridge.drivers.transports.serialport import SerialTransport, serial_url
from koala_bridge.drivers.transports.tcp import TcpClientTransport
from koala_bridge.drivers.transports.udp import UdpTransport

# ----------------------------------------------------------------------------- registry


def test_every_backend_module_imports() -> None:
    for target in [*BYTE_BACKENDS.values(), *CAN_BACKENDS.values()]:
        module, _, name = target.partition(":")
        assert isinstance(getattr(importlib.import_module(module), name), type)


def test_every_backend_parses_its_own_url() -> None:
    """Each class in the tables has its own ``from_url`` (pyserial's ``protocol_<scheme>``)."""
    for target in [*BYTE_BACKENDS.values(), *CAN_BACKENDS.values()]:
        module, _, name = target.partition(":")
        cls = getattr(importlib.import_module(module), name)
        assert "from_url" in vars(cls) or cls is LoopbackTransport, target


def test_every_bus_kind_has_a_loopback_backend() -> None:
    assert "loop" in BYTE_BACKENDS and "virtual" in CAN_BACKENDS


def test_unknown_scheme_lists_the_known_ones() -> None:
    with pytest.raises(ValueError, match="pty"):
        open_byte_transport("rs485:///dev/ttyS0")
    with pytest.raises(ValueError, match="socketcand"):
        open_can_transport("canbus://x")


@pytest.mark.parametrize(
    "url", ["tcp-client://127.0.0.1", "udpin:nowhere", "serial:", "python-can://virtual"]
)
def test_malformed_urls_are_refused_by_their_backend(url: str) -> None:
    with pytest.raises(ValueError, match="expected"):
        if url.startswith("python-can"):
            open_can_transport(url)
        else:
            open_byte_transport(url)


def test_client_urls() -> None:
    assert pymavlink_url(Endpoint("udp", host="127.0.0.1", port=14550)) == "udpin:127.0.0.1:14550"
    assert pymavlink_url(Endpoint("udpin", host="127.0.0.1", port=14550)) == (
        "udpout:127.0.0.1:14550"
    )
    assert pymavlink_url(Endpoint("tcp", host="127.0.0.1", port=5760)) == "tcp:127.0.0.1:5760"
    assert pyserial_url(Endpoint("tcp", host="127.0.0.1", port=5760)) == "socket://127.0.0.1:5760"
    assert pyserial_url(Endpoint("pty", path="/dev/pts/9")) == "/dev/pts/9"
    with pytest.raises(ValueError):
        pymavlink_url(Endpoint("loop"))


def test_mavlink_connection_strings_map_to_registry_urls() -> None:
    assert mavlink_connection_url("udpin:0.0.0.0:14550") == "udpin://0.0.0.0:14550"
    assert mavlink_connection_url("udp:127.0.0.1:14551") == "udpin://127.0.0.1:14551"
    assert mavlink_connection_url("tcp:192.168.1.2:5760") == "tcp-client://192.168.1.2:5760"
    assert mavlink_connection_url("/dev/ttyACM0,57600") == "serial:/dev/ttyACM0"
    assert mavlink_connection_url("socket://10.0.0.1:4001") == "serial:socket://10.0.0.1:4001"
    assert mavlink_connection_url("udpin://0.0.0.0:14550") == "udpin://0.0.0.0:14550"
    assert mavlink_connection_url("serial:/dev/ttyACM0,9600") == "serial:/dev/ttyACM0"
    assert mavlink_connection_options("serial:/dev/ttyACM0,9600") == {"baudrate": 9600}
    assert mavlink_connection_options("/dev/ttyACM0,57600") == {"baudrate": 57600}
    assert mavlink_connection_options("/dev/ttyACM0") == {"baudrate": 115200}
    assert mavlink_connection_options("udpin:0.0.0.0:14550") == {}
    with pytest.raises(ValueError, match="baud"):
        mavlink_connection_options("/dev/ttyACM0,fast")


def test_serial_urls() -> None:
    assert serial_url("/dev/ttyUSB0") == "serial:/dev/ttyUSB0"
    assert serial_url("loop://") == "serial:loop://"
    assert serial_url("serial:loop://") == "serial:loop://"


# ----------------------------------------------------------------------------- byte contract


@dataclass
class BytePair:
    """A backend opened through the registry and a client on its other side."""

    bridge: ByteTransport
    send: Callable[[bytes], None]          # the client sends bytes to the bridge
    receive: Callable[[int], bytes]        # the client receives n bytes (or a datagram)
    close_client: Callable[[], None]


def _pty_pair() -> BytePair:
    bridge = open_byte_transport("pty://")
    client = serial.serial_for_url(pyserial_url(bridge.endpoint), timeout=5)
    return BytePair(bridge, client.write, client.read, client.close)


def _tcp_pair() -> BytePair:
    bridge = open_byte_transport("tcp://127.0.0.1:0")
    ep = bridge.endpoint
    client = socket.create_connection((ep.host, ep.port), timeout=5)
    deadline = time.monotonic() + 5
    while bridge.stats.clients == 0 and time.monotonic() < deadline:
        bridge.wait(0.05)  # accepts the connection

    def receive(n: int) -> bytes:
        out = b""
        while len(out) < n:
            out += client.recv(n - len(out))
        return out

    return BytePair(bridge, client.sendall, receive, client.close)


def _tcp_client_pair() -> BytePair:
    server = open_byte_transport("tcp://127.0.0.1:0")  # the registry's own server, back to back
    ep = server.endpoint
    bridge = open_byte_transport(f"tcp-client://{ep.host}:{ep.port}")
    deadline = time.monotonic() + 5
    while server.stats.clients == 0 and time.monotonic() < deadline:
        server.wait(0.05)

    def receive(n: int) -> bytes:
        out = b""
        deadline = time.monotonic() + 5
        while len(out) < n and time.monotonic() < deadline:
            if server.wait(0.1):
                out += server.read()
        return out

    return BytePair(bridge, server.write, receive, server.close)


def _udp_pair() -> BytePair:
    client = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    client.bind(("127.0.0.1", 0))
    client.settimeout(5)
    bridge = open_byte_transport(f"udp://127.0.0.1:{client.getsockname()[1]}")
    assert isinstance(bridge, UdpTransport)
    local = bridge.local_address
    return BytePair(
        bridge, lambda data: client.sendto(data, local), lambda n: client.recv(65536), client.close
    )


def _udpin_pair() -> BytePair:
    bridge = open_byte_transport("udpin://127.0.0.1:0")
    ep = bridge.endpoint
    sender = open_byte_transport(f"udp://{ep.host}:{ep.port}")  # back to back
    assert isinstance(sender, UdpTransport)

    def receive(n: int) -> bytes:
        return sender.read() if sender.wait(5) else b""

    return BytePair(bridge, sender.write, receive, sender.close)


def _serial_pair() -> BytePair:
    pty = open_byte_transport("pty://")  # the robot's port, as the simulated robot serves it
    bridge = open_byte_transport(serial_url(str(pty.endpoint.path)), baudrate=115200)
    assert isinstance(bridge, SerialTransport)

    def receive(n: int) -> bytes:
        out = b""
        deadline = time.monotonic() + 5
        while len(out) < n and time.monotonic() < deadline:
            if pty.wait(0.1):
                out += pty.read()
        return out

    return BytePair(bridge, pty.write, receive, pty.close)


def _loop_pair() -> BytePair:
    bridge = open_byte_transport("loop://")
    assert isinstance(bridge, LoopbackTransport)
    peer = bridge.peer

    def receive(n: int) -> bytes:
        return peer.read(n) if peer.wait(5) else b""

    return BytePair(bridge, peer.write, receive, lambda: None)


BYTE_PAIRS: dict[str, Callable[[], BytePair]] = {
    "pty": _pty_pair,
    "tcp": _tcp_pair,
    "tcp-client": _tcp_client_pair,
    "udp": _udp_pair,
    "udpin": _udpin_pair,
    "serial": _serial_pair,
    "loop": _loop_pair,
}


def test_the_byte_contract_covers_every_byte_backend() -> None:
    assert set(BYTE_PAIRS) == set(BYTE_BACKENDS)


@pytest.fixture(params=sorted(BYTE_PAIRS))
def byte_pair(request: pytest.FixtureRequest) -> Iterator[BytePair]:
    pair = BYTE_PAIRS[request.param]()
    try:
        yield pair
    finally:
        pair.bridge.close()
        pair.close_client()


def _read_all(transport: ByteTransport, n: int, timeout: float = 5.0) -> bytes:
    out = b""
    deadline = time.monotonic() + timeout
    while len(out) < n and time.monotonic() < deadline:
        if transport.wait(0.1):
            out += transport.read()
    return out


def test_bytes_both_ways(byte_pair: BytePair) -> None:
    bridge = byte_pair.bridge
    # udpin answers whoever spoke last, so the client speaks first on every backend.
    byte_pair.send(b"\x00\x03\x11\r\n\xff")
    assert _read_all(bridge, 6) == b"\x00\x03\x11\r\n\xff"  # raw: no ^C/XON/CR translation
    assert bridge.write(b"\r\n\x00\xff") == 4
    assert byte_pair.receive(4) == b"\r\n\x00\xff"
    assert bridge.read() == b""  # and no echo
    stats = bridge.stats
    assert stats.sent >= 1 and stats.received >= 1 and stats.dropped == 0


def test_nothing_waiting_reads_empty(byte_pair: BytePair) -> None:
    assert byte_pair.bridge.read() == b""
    assert byte_pair.bridge.wait(0.0) is False


def test_endpoint_names_the_backend(byte_pair: BytePair) -> None:
    kind = byte_pair.bridge.endpoint.kind
    assert kind in BYTE_BACKENDS
    assert byte_pair.bridge.is_datagram == (kind in ("udp", "udpin"))


def test_close_is_idempotent_and_use_after_close_is_refused(byte_pair: BytePair) -> None:
    bridge = byte_pair.bridge
    with bridge:
        pass
    bridge.close()
    with pytest.raises(TransportClosedError):
        bridge.read()
    with pytest.raises(TransportClosedError):
        bridge.write(b"x")
    with pytest.raises(TransportClosedError):
        bridge.wait(0.0)


# ----------------------------------------------------------------------------- CAN contract


@dataclass
class CanPair:
    bridge: CanTransport
    client: can.BusABC
    client_open: bool = True

    def close_client(self) -> None:
        """Once: python-can's slcan ``shutdown`` is not idempotent (it writes to the port)."""
        if self.client_open:
            self.client_open = False
            self.client.shutdown()


def _can_client(bridge: CanTransport) -> can.BusABC:
    config = python_can_config(bridge.endpoint)
    if config["interface"] == "slcan":
        config["sleep_after_open"] = 0
    return can.Bus(**config)


CAN_URLS = {
    "socketcand": "socketcand://127.0.0.1:0/koala-contract",
    "slcan": "slcan://",
    "virtual": "virtual:///koala-contract-v",
    "python-can": "python-can://virtual/koala-contract-p",
}


def test_the_can_contract_covers_every_can_backend() -> None:
    assert set(CAN_URLS) == set(CAN_BACKENDS)


@pytest.fixture(params=sorted(CAN_URLS))
def can_pair(request: pytest.FixtureRequest) -> Iterator[CanPair]:
    bridge = open_can_transport(CAN_URLS[request.param])
    try:
        client = _can_client(bridge)
    except BaseException:
        bridge.close()
        raise
    pair = CanPair(bridge, client)
    try:
        yield pair
    finally:
        pair.close_client()
        bridge.close()


def _wait_for_raw_client(bridge: CanTransport) -> None:
    if bridge.endpoint.kind in ("socketcand", "slcan"):  # the client's handshake must be done
        # (frames sent during socketcand's handshake grace are held back for the client, not lost)
        wait_for(lambda: bridge.stats.clients > 0, timeout=5.0)


def test_frames_both_ways(can_pair: CanPair) -> None:
    bridge, client = can_pair.bridge, can_pair.client
    _wait_for_raw_client(bridge)
    bridge.send(can.Message(arbitration_id=0x101, is_extended_id=False, data=b"\x01\x02"))
    got = client.recv(5)
    assert got is not None and got.arbitration_id == 0x101 and bytes(got.data) == b"\x01\x02"
    client.send(can.Message(arbitration_id=0x1ABCDE, is_extended_id=True, data=b"\xff"))
    msg = bridge.recv(5)
    assert msg is not None and msg.arbitration_id == 0x1ABCDE and msg.is_extended_id
    assert bytes(msg.data) == b"\xff"
    assert bridge.stats.sent >= 1 and bridge.stats.received >= 1


def test_can_endpoint_names_the_backend(can_pair: CanPair) -> None:
    assert can_pair.bridge.endpoint.kind in CAN_BACKENDS
    assert can_pair.bridge.recv(0.0) is None


def test_can_close_is_idempotent_and_use_after_close_is_refused(can_pair: CanPair) -> None:
    bridge = can_pair.bridge
    can_pair.close_client()  # first: python-can's slcan client writes to the pty on shutdown
    bridge.close()
    bridge.close()
    with pytest.raises(TransportClosedError):
        bridge.send(can.Message(arbitration_id=1, data=b""))
    with pytest.raises(TransportClosedError):
        bridge.recv(0.0)


# ----------------------------------------------------------------------------- backend specifics


def test_pty_symlink_from_the_url(tmp_path: Path) -> None:
    link = tmp_path / "port"
    link.symlink_to("/nonexistent")  # a stale link from an earlier run is replaced
    with open_byte_transport(f"pty://{link}") as port:
        assert isinstance(port, PtyTransport)
        assert os.readlink(link) == port.slave_path
        with serial.serial_for_url(pyserial_url(port.endpoint), timeout=5):
            assert port.stats.clients == 1
    assert not link.exists()


def test_pty_slow_client_gets_whole_writes_or_none() -> None:
    with PtyTransport(max_pending=1000) as port:
        with serial.Serial(port.endpoint.path, timeout=0.5) as client:
            message = bytes(range(100))
            accepted = sum(1 for _ in range(2000) if port.write(message))  # client reads nothing
            assert port.stats.dropped > 0
            assert port.pending <= 1000
            total = b""
            while chunk := client.read(65536):
                total += chunk
                port.flush()
            assert len(total) == accepted * len(message)  # no torn message
            assert total == message * accepted


def test_tcp_fans_out_to_every_client_and_survives_disconnects() -> None:
    with open_byte_transport("tcp://127.0.0.1:0") as server:
        address = (server.endpoint.host, server.endpoint.port)
        with (
            socket.create_connection(address, timeout=5) as a,
            socket.create_connection(address, timeout=5) as b,
        ):
            server.wait(0.5)
            assert server.write(b"hello") == 5
            assert a.recv(5) == b"hello" and b.recv(5) == b"hello"
            a.sendall(b"from-a")
            assert server.wait(5)
            assert server.read() == b"from-a"
            b.close()
            for _ in range(3):
                server.write(b"again")  # the closed client is noticed and dropped
            assert a.recv(15).startswith(b"again")
        server.write(b"nobody")
        server.read()
        assert server.stats.clients == 0


def test_tcp_client_reads_silence_after_the_server_goes() -> None:
    server = open_byte_transport("tcp://127.0.0.1:0")
    ep = server.endpoint
    with open_byte_transport(f"tcp-client://{ep.host}:{ep.port}") as client:
        assert isinstance(client, TcpClientTransport)
        server.wait(0.2)
        server.close()
        deadline = time.monotonic() + 5
        while client.stats.clients and time.monotonic() < deadline:
            client.wait(0.1)
            client.read()
        assert client.stats.clients == 0
        assert client.read() == b"" and client.write(b"x") == 0
        assert client.stats.dropped == 1


def test_tcp_client_to_nobody_fails_to_open(free_tcp_port: int) -> None:
    with pytest.raises(OSError, match="cannot connect"):
        open_byte_transport(f"tcp-client://127.0.0.1:{free_tcp_port}")


def test_udp_without_a_listener_does_not_fail(free_udp_port: int) -> None:
    with open_byte_transport(f"udp://127.0.0.1:{free_udp_port}") as udp:
        for _ in range(5):
            udp.write(b"x" * 10)
            assert udp.read() == b""
        assert udp.stats.sent + udp.stats.dropped == 5


def test_udpin_drops_writes_before_anyone_has_sent() -> None:
    with open_byte_transport("udpin:127.0.0.1:0") as udp:  # pymavlink's spelling works too
        assert udp.endpoint.kind == "udpin" and udp.endpoint.port
        assert udp.write(b"hello") == 0
        assert udp.stats.dropped == 1


def test_serial_on_pyserial_loop_url() -> None:
    with open_byte_transport("serial:loop://", baudrate=9600) as port:
        assert port.endpoint == Endpoint("serial", path="loop://")
        port.write(b"echo")
        assert _read_all(port, 4) == b"echo"


def test_serial_to_a_missing_device_fails_to_open(tmp_path: Path) -> None:
    with pytest.raises(OSError, match="cannot open serial port"):
        open_byte_transport(serial_url(str(tmp_path / "ttyNONE")))


def test_loopback_pair() -> None:
    a, b = LoopbackTransport.pair()
    with a:
        a.write(b"ping")
        assert b.wait(5) and b.read() == b"ping"
        b.write(b"pong")
        assert a.wait(5) and a.read() == b"pong"
    with pytest.raises(TransportClosedError):
        b.read()
