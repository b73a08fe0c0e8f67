"""Clients that come and go, and clients that never read, on the bridge's serial (pty) buses and its
MAVLink UDP/TCP links (issue 12): nothing one client leaves behind reaches the next, and nothing a
client fails to read grows the bridge's memory.

The bridge runs in-process (runtime.sim_source, fast clock); the clients are the libraries a
firmware team uses: pyserial on the ptys, pymavlink on MAVLink.
"""

from __future__ import annotations

import socket
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
import serial
from conftest import _wait_until
from koala_bridge.drivers.kteam import parse_reply
from koala_bridge.drivers.messages import KteamReply, RangeFrame
from koala_bridge.drivers.rangeframes import SYNC, RangeFrameDecoder
from koala_bridge.drivers.transports.pty import PtyTransport
from koala_bridge.drivers.transports.slcan import SlcanAdapter
from koala_bridge.drivers.transports.tcp import TcpServerTransport
from koala_bridge.runtime.buses import LockedByteLink
from koala_bridge.runtime.endpoints import Endpoints
from koala_bridge.runtime.robot_io import VERSION_TEXT
from koala_bridge.runtime.settings import (
    BridgeSettings,
    apply_override,
    load_config,
    parse_override,
)
from koala_bridge.runtime.sim_source import SimulatedRobotSource

REPO = Path(__file__).resolve().parents[2]
ROUNDS = 50
BANNER = f"b,{VERSION_TEXT}\r\n".encode()


@contextmanager
def running_bridge(
    zenoh_port: int, *overrides: str
) -> Iterator[tuple[SimulatedRobotSource, Endpoints]]:
    """The simulated robot, fast clock, CAN off; stopped and closed on exit."""
    config = load_config(REPO / "config" / "default.toml")
    for text in (
        "run.clock=fast",
        f'zenoh.listen=["tcp/127.0.0.1:{zenoh_port}"]',
        "buses.can.socketcand=false",
        "buses.can.slcan=false",
        "buses.can.virtual=false",
        *overrides,
    ):
        config = apply_override(config, *parse_override(text))
    service = SimulatedRobotSource(config, BridgeSettings.from_config(config))
    stop = threading.Event()
    with service:
        endpoints = service.open()
        runner = threading.Thread(target=service.run, args=(stop,), kwargs={"duration_s": 0})
        runner.start()
        try:
            yield service, endpoints
        finally:
            stop.set()
            runner.join(60)
    assert not runner.is_alive()


def _bus(service: SimulatedRobotSource, name: str) -> dict[str, int]:
    counts: dict[str, int] = service.status(service.port.t)["buses"][name]
    return counts


def _ask(path: str, command: bytes) -> bytes:
    """One client session: open, send ``command``, return the first line read, close."""
    with serial.Serial(path, 115200, timeout=10) as client:
        client.write(command)
        return client.read_until(b"\r\n")


def _kteam_link(service: SimulatedRobotSource) -> LockedByteLink:
    assert service.buses.kteam is not None
    return service.buses.kteam


def _wait_gone(link: LockedByteLink, read_before: int | None = None) -> None:
    """Wait until the bridge has read what the client sent after ``read_before`` reads and has
    seen it close the port -- as it does well before another program can open it; a client
    reopening within microseconds may still be taken for the same one (docs/protocols.md)."""
    if read_before is not None:
        assert _wait_until(lambda: link.stats.received > read_before, 30)
    assert _wait_until(lambda: link.stats.clients == 0, 30)


# ----------------------------------------------------------------------------- K-Team pty


@pytest.fixture
def kteam(free_tcp_port: int, free_udp_port: int) -> Iterator[tuple[SimulatedRobotSource, str]]:
    with running_bridge(
        free_tcp_port, f"buses.mavlink.port={free_udp_port}", "buses.rangefinders.enabled=false"
    ) as (service, endpoints):
        assert endpoints.kteam is not None
        yield service, endpoints.kteam


def test_a_half_sent_command_is_not_glued_to_the_next_clients(
    kteam: tuple[SimulatedRobotSource, str],
) -> None:
    service, path = kteam
    link = _kteam_link(service)
    read_before = link.stats.received
    with serial.Serial(path, 115200, timeout=10) as first:
        first.write(b"D,1")  # no terminator: the client gives up half-way
        first.flush()
    _wait_gone(link, read_before)
    reply = parse_reply(_ask(path, b"H\r").rstrip())
    assert isinstance(reply, KteamReply) and reply.letter == "h" and len(reply.fields) == 2
    assert _bus(service, "kteam")["rejected"] == 0  # nothing was taken for "D,1H"


def test_replies_a_client_never_read_do_not_reach_the_next(
    kteam: tuple[SimulatedRobotSource, str],
) -> None:
    service, path = kteam
    link = _kteam_link(service)
    with serial.Serial(path, 115200, timeout=10, write_timeout=60) as first:
        # ~350 KiB of replies (16 IR counts each): more than the kernel and the 64 KiB queue hold.
        first.write(b"N\r" * 10_000)
        first.flush()
        assert _wait_until(lambda: _bus(service, "kteam")["dropped"] > 0, 60)
    _wait_gone(link)
    assert _ask(path, b"B\r") == BANNER


def test_fifty_clients_in_turn_each_get_their_own_reply(
    kteam: tuple[SimulatedRobotSource, str],
) -> None:
    service, path = kteam
    link = _kteam_link(service)
    for i in range(ROUNDS):
        read_before = None
        with serial.Serial(path, 115200, timeout=10) as client:
            client.write(b"G,%d,0\r" % i)
            assert client.read_until(b"\r\n") == b"g\r\n"
            client.write(b"B\r")
            assert client.read_until(b"\r\n") == BANNER
            if i % 3:
                read_before = link.stats.received
                # Left behind: replies never read, or a command half-sent.
                client.write(b"N\r" * 50 if i % 3 == 1 else b"L,0,")
                client.flush()
        _wait_gone(link, read_before)
    assert _ask(path, b"B\r") == BANNER
    # Every command was answered in order and nothing was taken as garbage.
    assert _bus(service, "kteam")["rejected"] == 0
    assert _bus(service, "kteam")["received"] >= 2 * ROUNDS + 1


def test_pty_transport_counts_client_sessions() -> None:
    with PtyTransport() as port:
        link = LockedByteLink(port)
        assert link.client_session == 0
        with serial.Serial(port.endpoint.path, timeout=10) as client:
            client.write(b"D,1")
            assert port.wait(10) and port.read() == b"D,1"
        assert not port.has_client()  # the bridge sees it go
        assert port.client_session == 0  # ...and the next read is the next client's
        with serial.Serial(port.endpoint.path, timeout=10) as client:
            client.write(b"H\r")
            data = b""
            while not data:
                assert port.wait(10)
                data = port.read()
            assert data == b"H\r"
        assert port.client_session == link.client_session == 1


def test_pty_drops_replies_to_a_client_that_has_gone() -> None:
    with PtyTransport() as port:
        with serial.Serial(port.endpoint.path, timeout=10) as client:
            client.write(b"B\r")
            assert port.wait(10) and port.read() == b"B\r"
        assert not port.has_client()
        with serial.Serial(port.endpoint.path, timeout=0.2) as client:
            # The first client's answer, written after it left: not for this client.
            assert port.write(b"b,late\r\n") == 0
            client.write(b"B\r")
            assert port.wait(10) and port.read() == b"B\r"
            assert port.write(b"b,mine\r\n") > 0
            assert client.read_until(b"\r\n") == b"b,mine\r\n"


def test_pty_flushes_what_a_gone_client_left_unread() -> None:
    """A client that does not flush its input at open (``os.open``, unlike pyserial) still gets
    nothing stale: the bridge flushes it when the previous client goes."""
    import os

    with PtyTransport() as port:
        fd = os.open(port.endpoint.path, os.O_RDWR | os.O_NOCTTY)
        assert port.write(b"x" * 3000) == 3000  # never read
        os.close(fd)
        assert not port.has_client()
        fd = os.open(port.endpoint.path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        try:
            assert port.write(b"fresh") == 5
            assert os.read(fd, 10000) == b"fresh"
        finally:
            os.close(fd)


def test_slcan_a_half_sent_line_is_not_glued_to_the_next_clients() -> None:
    with SlcanAdapter() as adapter:
        with serial.Serial(adapter.endpoint.path, timeout=10) as first:
            first.write(b"O\r")
            assert first.read_until(b"\r") == b"\r"
            first.write(b"t100")  # half a frame line, then the client goes
            first.flush()
        assert _wait_until(lambda: not adapter.is_open, 10)
        with serial.Serial(adapter.endpoint.path, timeout=10) as second:
            second.write(b"V\r")
            assert second.read_until(b"\r") == b"V1013\r"
        assert adapter.stats.rejected == 0


# ----------------------------------------------------------------------------- range-frame pty


def _first_frames(path: str, n: int) -> tuple[list[RangeFrame], int, bytes]:
    """The first ``n`` frames a new client reads, the decoder's rejects, and its first bytes."""
    decoder = RangeFrameDecoder()
    frames: list[RangeFrame] = []
    head = b""
    with serial.Serial(path, 115200, timeout=10) as client:
        while len(frames) < n:
            chunk = client.read(max(1, client.in_waiting))
            assert chunk, "no range frames"
            head = (head + chunk)[:2]
            frames += decoder.feed(chunk)
    return frames, decoder.rejected, head


def test_range_frames_a_client_never_reads_are_bounded_and_not_passed_on(
    free_tcp_port: int, free_udp_port: int
) -> None:
    with running_bridge(
        free_tcp_port, f"buses.mavlink.port={free_udp_port}", "buses.kteam.enabled=false"
    ) as (service, endpoints):
        assert endpoints.rangefinders is not None and service.buses.rangefinders is not None
        transport = service.buses.rangefinders.transport
        assert isinstance(transport, PtyTransport)
        for _ in range(3):
            dropped = _bus(service, "rangefinders")["dropped"]
            with serial.Serial(endpoints.rangefinders, 115200, timeout=10):
                # The client reads nothing; the bridge queues up to its limit, then drops.
                assert _wait_until(
                    lambda d=dropped: _bus(service, "rangefinders")["dropped"] > d + 100, 120
                )
                assert transport.pending <= 65536
            _wait_gone(service.buses.rangefinders)
            frames, rejected, head = _first_frames(endpoints.rangefinders, 20)
            assert head == SYNC and rejected == 0  # whole frames from the first byte
            for a, b in zip(frames, frames[1:], strict=False):
                if a.kind == b.kind:
                    assert b.t_us > a.t_us


# ----------------------------------------------------------------------------- MAVLink


def _mavlink_rounds(url: str) -> None:
    from pymavlink import mavutil

    for _ in range(ROUNDS):
        link = mavutil.mavlink_connection(url, source_system=255)
        try:
            msg = link.recv_match(type=["HEARTBEAT", "SCALED_IMU"], blocking=True, timeout=30)
            assert msg is not None, f"nothing received on {url}"
        finally:
            link.close()


def test_mavlink_pty_a_half_sent_packet_is_not_glued_to_the_next_clients(
    free_tcp_port: int,
) -> None:
    from pymavlink.dialects.v20 import common as mavlink2

    gcs = mavlink2.MAVLink(None, 255, 190)
    heartbeat = bytes(gcs.heartbeat_encode(6, 8, 0, 0, 4).pack(gcs))
    with running_bridge(
        free_tcp_port,
        'buses.mavlink.transport="pty"',
        "buses.kteam.enabled=false",
        "buses.rangefinders.enabled=false",
    ) as (service, endpoints):
        assert endpoints.mavlink_url is not None and service.buses.mavlink is not None
        link = service.buses.mavlink
        read_before = link.stats.received
        with serial.Serial(endpoints.mavlink_url, 115200, timeout=10) as first:
            first.write(heartbeat[:7])  # the client gives up half-way through a packet
            first.flush()
        _wait_gone(link, read_before)
        with serial.Serial(endpoints.mavlink_url, 115200, timeout=10) as second:
            second.write(heartbeat)
            second.flush()
            assert _wait_until(lambda: _bus(service, "mavlink")["received"] == 1, 30)
        assert _bus(service, "mavlink")["rejected"] == 0


def test_mavlink_udp_fifty_listeners_in_turn(free_tcp_port: int, free_udp_port: int) -> None:
    with running_bridge(
        free_tcp_port,
        f"buses.mavlink.port={free_udp_port}",
        "buses.kteam.enabled=false",
        "buses.rangefinders.enabled=false",
    ) as (service, _):
        _mavlink_rounds(f"udpin:127.0.0.1:{free_udp_port}")
        assert _bus(service, "mavlink")["sent"] > 0


def test_mavlink_tcp_fifty_clients_in_turn(free_tcp_port: int) -> None:
    with running_bridge(
        free_tcp_port,
        'buses.mavlink.transport="tcp"',
        "buses.mavlink.port=0",
        "buses.kteam.enabled=false",
        "buses.rangefinders.enabled=false",
    ) as (service, endpoints):
        assert endpoints.mavlink_url is not None
        _mavlink_rounds(endpoints.mavlink_url)
        assert _wait_until(lambda: service.buses.stats()["mavlink"].clients == 0, 30)


def _reader(sock: socket.socket, into: bytearray) -> Callable[[], None]:
    """Read what ``sock`` has now, without waiting."""
    sock.setblocking(False)

    def read_some() -> None:
        try:
            while chunk := sock.recv(65536):
                into.extend(chunk)
        except BlockingIOError:
            pass

    return read_some


def test_tcp_client_that_never_reads_is_bounded_and_others_lose_nothing() -> None:
    message = bytes(range(250)) * 4
    with TcpServerTransport(max_pending=20_000) as server:
        address = (server.endpoint.host, server.endpoint.port)
        with socket.socket() as stuck, socket.create_connection(address, timeout=10) as reader:
            stuck.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
            stuck.connect(address)
            assert _wait_until(lambda: _clients(server) == 2, 10)
            received = bytearray()
            read_some = _reader(reader, received)
            sent = 0
            while server.stats.dropped < 200:  # the stuck client's writes are dropped...
                assert server.write(message) == len(message)
                sent += 1
                read_some()
                assert server.pending <= 2 * 20_000  # ...after at most 20 kB queued for it
                assert sent < 100_000, "a client that never reads was never cut off"
            for _ in range(1000):
                if len(received) >= sent * len(message):
                    break
                server.wait(0.02)  # flushes what is queued for the reader
                read_some()
            assert received == message * sent  # the client that reads loses nothing
            assert server.stats.clients == 2


def test_tcp_a_stalled_client_gives_its_place_to_a_new_one() -> None:
    with TcpServerTransport(max_clients=1, max_pending=1000) as server:
        address = (server.endpoint.host, server.endpoint.port)
        with socket.socket() as stuck:
            stuck.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
            stuck.connect(address)
            assert _wait_until(lambda: _clients(server) == 1, 10)
            while server.stats.dropped == 0:  # it reads nothing: its queue fills
                server.write(bytes(1000))
            with socket.create_connection(address, timeout=10) as fresh:
                # The stalled client is closed and the new one takes its place.
                assert _wait_until(lambda: _clients(server) == 1 and server.pending == 0, 10)
                assert server.write(b"hello") == 5
                assert fresh.recv(5) == b"hello"
                with socket.create_connection(address, timeout=10) as third:
                    # A place held by a client that keeps up is not taken.
                    assert _wait_until(lambda: _clients(server) and server.stats.rejected == 1, 10)
                    assert third.recv(1) == b""
                assert server.write(b"again") == 5
                assert fresh.recv(5) == b"again"
            stuck.settimeout(10)
            while stuck.recv(65536):  # what it had, then the end of the stream
                pass


def _clients(server: TcpServerTransport) -> int:
    server.wait(0.01)  # accepts waiting connections, notices closed ones
    server.read()
    return server.stats.clients
