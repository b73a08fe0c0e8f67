"""The transports' offline hook (fault ``disconnect``) and CAN error frames, with real clients:
pyserial on a pty, python-can's socketcand and virtual interfaces, raw TCP and UDP sockets
(bridge/runtime/faults.py, docs/faults.md)."""

from __future__ import annotations

import os
import socket
from collections.abc import Iterator
from pathlib import Path

import can
import pytest
import serial
from _can import recv, wait_for
from _socketcand_client import raw_client, read_element
from koala_bridge.drivers.transports.loop import LoopbackTransport
from koala_bridge.drivers.transports.pty import PtyTransport
from koala_bridge.drivers.transports.pythoncan import VirtualCanTransport
from koala_bridge.drivers.transports.slcan import SlcanAdapter
from koala_bridge.drivers.transports.socketcand import SocketcandServer
from koala_bridge.drivers.transports.tcp import TcpServerTransport
from koala_bridge.drivers.transports.udp import UdpTransport
from koala_bridge.runtime.buses import LockedByteLink
from koala_bridge.runtime.faults import (
    CAN_ERR_BUSERROR,
    CAN_ERR_BUSOFF,
    CAN_ERR_PROT,
    FaultInjector,
    faults_from_config,
)

# ----------------------------------------------------------------------------- pty


def client_read_fails(client: serial.Serial) -> bool:
    """Whether the client's port reports the hang-up (pyserial raises on a read)."""
    try:
        client.read(1)
    except serial.SerialException:
        return True
    return False


def test_pty_offline_hangs_up_and_a_new_pty_returns_at_the_same_path(tmp_path: Path) -> None:
    link = tmp_path / "kteam"
    with PtyTransport(link) as port:
        fd = port.fileno()
        client = serial.Serial(str(link), timeout=1.0)
        try:
            assert port.write(b"hello") == 5
            assert client.read(5) == b"hello"
            session = port.client_session
            port.set_offline(True)
            port.set_offline(True)              # idempotent
            assert port.offline
            assert client_read_fails(client)
            assert not link.exists()            # nobody opens a stale or reused /dev/pts/N
            assert port.write(b"lost") == 0 and port.stats.dropped == 1
            assert not port.wait(0.05) and port.read() == b""
            assert not port.has_client() and port.stats.clients == 0
            assert port.client_session == session + 1   # readers start afresh
        finally:
            client.close()
        port.set_offline(False)
        assert not port.offline
        assert os.readlink(link) == port.slave_path
        assert port.fileno() == fd              # whoever polls it polls the new master
        client = serial.Serial(str(link), timeout=1.0)
        try:
            wait_for(port.has_client)
            assert port.write(b"back") == 4
            assert client.read(4) == b"back"
            client.write(b"D,1,1\n")
            assert port.wait(5.0)
            assert port.read() == b"D,1,1\n"
        finally:
            client.close()
    assert not link.exists()


def test_pty_offline_through_the_locked_link(tmp_path: Path) -> None:
    """The bridge's wrapper keeps polling the same descriptor: offline it waits out its timeout
    (no spin), back online it sees the new client's bytes."""
    link = LockedByteLink(PtyTransport(tmp_path / "rf"))
    try:
        link.set_offline(True)
        assert not link.wait(0.1) and link.read() == b""
        link.set_offline(False)
        with serial.Serial(str(tmp_path / "rf"), timeout=1.0) as client:
            client.write(b"x")
            assert link.wait(5.0) and link.read() == b"x"
    finally:
        link.close()


def test_slcan_goes_offline_and_sends_no_error_frames(tmp_path: Path) -> None:
    path = tmp_path / "slcan"
    adapter = SlcanAdapter(path)
    try:
        client = serial.Serial(str(path), timeout=1.0)
        try:
            client.write(b"O\r")
            assert client.read(1) == b"\r"
            wait_for(lambda: adapter.is_open)
            err = FaultInjector(faults_from_config({}, ["bus_off:can"]), 0)
            assert err.bus_off("can", 0.0)
            adapter.send(err.can_error_frames(0.0)[0])   # LAWICEL has no error frames: skipped
            adapter.send(can.Message(arbitration_id=0x101, data=b"\x01", is_extended_id=False))
            assert client.read_until(b"\r") == b"t101101\r"
            assert adapter.stats.sent == 1
            adapter.set_offline(True)
            assert adapter.offline
            assert client_read_fails(client)
            assert not adapter.is_open
        finally:
            client.close()
        adapter.set_offline(False)
        assert not adapter.offline
        with serial.Serial(str(path), timeout=1.0) as client:
            client.write(b"V\r")
            assert client.read_until(b"\r") == b"V1013\r"
    finally:
        adapter.close()


# ----------------------------------------------------------------------------- socketcand


@pytest.fixture
def server() -> Iterator[SocketcandServer]:
    srv = SocketcandServer(handshake_grace_s=0.0)
    yield srv
    srv.close()


def python_can_client(srv: SocketcandServer) -> can.BusABC:
    ep = srv.endpoint
    bus = can.Bus(interface="socketcand", host=ep.host, port=ep.port, channel=ep.channel)
    wait_for(lambda: srv.stats.clients >= 1)
    return bus


def test_error_frames_reach_a_python_can_socketcand_client(server: SocketcandServer) -> None:
    """A corrupted CAN frame is an error frame and then the frame (the retransmission); a
    bus-off window opens with CAN_ERR_BUSOFF. socketcand sends '< error CLASS SECS.USECS >'."""
    inj = FaultInjector(faults_from_config({}, ["corrupt:can:end_s=1", "bus_off:can:start_s=2,"
                                                                       "end_s=3"]), 0)
    bus = python_can_client(server)
    try:
        frame = can.Message(arbitration_id=0x101, data=b"\x01\x02", is_extended_id=False,
                            timestamp=0.5)
        deliveries = inj.on_frame("can", 0.5, bytes(frame.data), frame.arbitration_id)
        for err in inj.can_error_frames(0.5):           # first the error frames...
            server.send(err)
        for t, data in deliveries:                       # ...then the frame
            server.send(can.Message(arbitration_id=frame.arbitration_id, data=data,
                                    is_extended_id=False, timestamp=t))
        got = recv(bus)
        assert got.is_error_frame
        assert got.arbitration_id == CAN_ERR_PROT | CAN_ERR_BUSERROR
        assert got.timestamp == 0.5
        again = recv(bus)
        assert not again.is_error_frame and bytes(again.data) == b"\x01\x02"
        assert inj.bus_off("can", 2.0)
        (off,) = inj.can_error_frames(2.0)
        server.send(off)
        got = recv(bus)
        assert got.is_error_frame and got.arbitration_id == CAN_ERR_BUSOFF
        assert got.timestamp == 2.0
    finally:
        bus.shutdown()


def test_socketcand_offline_drops_clients_and_refuses_new_ones(server: SocketcandServer) -> None:
    ep = server.endpoint
    raw = raw_client(server)
    try:
        raw.sendall(b"< open " + ep.channel.encode() + b" >")
        assert read_element(raw) == b"< ok >"
        server.set_offline(True)
        assert server.offline
        assert raw.recv(100) == b""                      # the connection dropped
    finally:
        raw.close()
    with pytest.raises(ConnectionRefusedError), socket.create_connection(
            (ep.host, ep.port), timeout=5.0):
        pass
    server.send(can.Message(arbitration_id=0x101, data=b"\x01", is_extended_id=False))
    assert server.stats.dropped == 1 and server.stats.clients == 0
    server.set_offline(False)
    server.set_offline(False)                            # idempotent
    assert not server.offline
    bus = python_can_client(server)                      # the same port again
    try:
        server.send(can.Message(arbitration_id=0x102, data=b"\x03", is_extended_id=False,
                                timestamp=1.0))
        assert bytes(recv(bus).data) == b"\x03"
    finally:
        bus.shutdown()


# ----------------------------------------------------------------------------- TCP, UDP, virtual


def test_tcp_server_offline_drops_clients_and_refuses_new_ones() -> None:
    with TcpServerTransport() as srv:
        ep = srv.endpoint
        with socket.create_connection((ep.host, ep.port), timeout=5.0) as client:
            wait_for(lambda: srv.read() == b"" and srv.stats.clients == 1)
            assert srv.write(b"hi") == 2 and client.recv(2) == b"hi"
            srv.set_offline(True)
            assert srv.offline
            assert client.recv(10) == b""
        with pytest.raises(ConnectionRefusedError), socket.create_connection(
                (ep.host, ep.port), timeout=5.0):
            pass
        assert srv.write(b"lost") == 0 and srv.read() == b"" and not srv.wait(0.01)
        srv.set_offline(False)
        assert not srv.offline
        with socket.create_connection((ep.host, ep.port), timeout=5.0) as client:
            client.sendall(b"up")
            assert srv.wait(5.0) and srv.read() == b"up"


def test_udp_offline_drops_everything() -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as ground:
        ground.bind(("127.0.0.1", 0))
        ground.settimeout(5.0)
        host, port = ground.getsockname()
        with UdpTransport(host, port) as link:
            link.set_offline(True)
            assert link.offline
            assert link.write(b"lost") == 0 and link.stats.dropped == 1
            ground.sendto(b"ignored", link.local_address)   # loopback: queued at once
            assert not link.wait(0.05) and link.read() == b""
            link.set_offline(False)
            assert not link.offline
            assert link.write(b"up") == 2 and ground.recv(10) == b"up"
            ground.sendto(b"heard", link.local_address)
            assert link.wait(5.0) and link.read() == b"heard"  # not the one sent offline


def test_virtual_can_offline_drops_both_ways() -> None:
    with VirtualCanTransport("faults-test") as node:
        other = can.Bus(interface="virtual", channel="faults-test")
        try:
            node.set_offline(True)
            assert node.offline
            node.send(can.Message(arbitration_id=1, data=b"\x01", is_extended_id=False))
            assert other.recv(0.05) is None and node.stats.dropped == 1
            other.send(can.Message(arbitration_id=2, data=b"\x02", is_extended_id=False))
            assert node.recv(0.1) is None
            node.set_offline(False)
            assert not node.offline
            assert node.recv(0.05) is None                 # lost while offline
            other.send(can.Message(arbitration_id=3, data=b"\x03", is_extended_id=False))
            assert recv(node).arbitration_id == 3
        finally:
            other.shutdown()


def test_a_backend_without_offline_says_so() -> None:
    a, b = LoopbackTransport.pair()
    try:
        assert not a.supports_offline and not a.offline
        with pytest.raises(NotImplementedError, match="LoopbackTransport cannot go offline"):
            a.set_offline(True)
    finally:
        a.close()
        b.close()
    assert PtyTransport.supports_offline and SocketcandServer.supports_offline
