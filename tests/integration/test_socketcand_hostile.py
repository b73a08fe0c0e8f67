"""The socketcand server under hostile or careless clients, checked with python-can's own
``socketcand`` interface: a rejected frame or a garbage element does not wedge the client; a client
that floods and never reads is disconnected and counted while the others keep receiving; idle
connections do not lock everyone out; 50 connect/disconnect rounds leak nothing. And the slcan
adapter counts the replies a client that never reads cannot get."""

from __future__ import annotations

import os
import socket
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import can
import cantools
import pytest
import serial
from _can import recv, wait_for
from _socketcand_client import raw_client, read_element
from koala_bridge.drivers.transports import python_can_config
from koala_bridge.drivers.transports.slcan import SlcanAdapter
from koala_bridge.drivers.transports.socketcand import SocketcandServer

CHANNEL = "koala0"


def _frame(i: int) -> can.Message:
    return can.Message(arbitration_id=0x110, is_extended_id=False, data=i.to_bytes(4, "little"),
                       timestamp=float(i))


def _bus(server: SocketcandServer) -> can.BusABC:
    return can.Bus(**python_can_config(server.endpoint))


def _assert_both_ways(server: SocketcandServer, client: can.BusABC, i: int) -> None:
    """A bridge frame reaches ``client`` as a data frame; a frame from ``client`` reaches the
    bridge."""
    server.send(_frame(i))
    got = recv(client)
    assert not got.is_error_frame
    assert (got.arbitration_id, bytes(got.data)) == (0x110, i.to_bytes(4, "little"))
    client.send(can.Message(arbitration_id=0x100, is_extended_id=False, data=bytes([i % 256] * 4)))
    got = recv(server)
    assert (got.arbitration_id, bytes(got.data)) == (0x100, bytes([i % 256] * 4))


def _raw_mode(sock: socket.socket) -> None:
    sock.sendall(f"< open {CHANNEL} >< rawmode >".encode())
    assert read_element(sock) == b"< ok >"
    assert read_element(sock) == b"< ok >"


def _closed_by_server(sock: socket.socket) -> bool:
    """Blocks until the server closes ``sock`` (True) or sends something (False)."""
    try:
        return sock.recv(1) == b""
    except ConnectionResetError:
        return True


@pytest.fixture
def server_factory() -> Iterator[Callable[..., SocketcandServer]]:
    opened: list[SocketcandServer] = []

    def start(**options: object) -> SocketcandServer:
        opened.append(SocketcandServer(channel=CHANNEL, **options))  # type: ignore[arg-type]
        return opened[-1]

    yield start
    for server in opened:
        server.close()


# ------------------------------------------------------------------ 1. rejected input, no wedge


def test_python_can_keeps_working_after_a_remote_frame_and_a_garbage_element(
    server_factory: Callable[..., SocketcandServer],
) -> None:
    server = server_factory()
    with _bus(server) as client, _bus(server) as bystander:
        wait_for(lambda: server.stats.clients == 2)
        _assert_both_ways(server, client, 1)
        # python-can sends a remote frame as "< send 100 4  >": no data bytes for a DLC of 4,
        # a syntax error for socketcand (the daemon drops it too).
        client.send(can.Message(arbitration_id=0x100, is_remote_frame=True, dlc=4))
        client._tcp_send("< bogus >")  # and an element no socketcand knows
        client._tcp_send("< send 100 4 1 2 >")
        wait_for(lambda: server.stats.rejected == 3)
        # Answering "< error ... >" here made every later recv() raise in python-can 4.6.
        for i in range(2, 12):
            _assert_both_ways(server, client, i)
        assert server.stats.rejected == 3
        # The other client saw only frames, none of the rejects, and no error frame.
        seen = []
        while (msg := bystander.recv(0.5)) is not None:
            seen.append(msg)
        assert seen and not any(m.is_error_frame for m in seen)
        assert all(m.arbitration_id in (0x100, 0x110) for m in seen)
        assert not any(m.arbitration_id == 0x100 and len(m.data) != 4 for m in seen)


def test_errors_before_rawmode_are_still_answered(
    server_factory: Callable[..., SocketcandServer],
) -> None:
    # The handshake is a dialogue (python-can's constructor compares each reply): an error
    # there is answered as the daemon does, and python-can reports it.
    server = server_factory()
    with raw_client(server) as raw:
        raw.sendall(b"<x>")
        assert read_element(raw) == b"< error open a bus first >"
        raw.sendall(b"< open can9 >")
        assert read_element(raw) == b"< error could not open bus >"
        raw.sendall(f"< open {CHANNEL} >< bogus >".encode())
        assert read_element(raw) == b"< ok >"
        assert read_element(raw) == b"< error unknown command >"
    config = {**python_can_config(server.endpoint), "channel": "can9"}
    with pytest.raises(can.CanError, match="could not open bus"):
        can.Bus(**config)


# ------------------------------------------------------------------ 2. bounded memory, slots


@pytest.mark.parametrize(
    ("handshake", "flood"),
    [(False, b"<x>"), (True, b"< echo >")],
    ids=["garbage-before-open", "echo-in-raw-mode"],
)
def test_a_client_that_floods_and_never_reads_is_dropped_and_counted(
    server_factory: Callable[..., SocketcandServer], handshake: bool, flood: bytes
) -> None:
    max_pending = 4096
    server = server_factory(max_pending=max_pending, handshake_timeout_s=600.0)
    with _bus(server) as listener, raw_client(server, rcvbuf=4096) as flooder:
        if handshake:
            _raw_mode(flooder)
        wait_for(lambda: server.stats.clients == 1 + handshake)
        sent, limit, i = 0, 64 << 20, 0
        try:
            while sent < limit:  # every element gets a reply the flooder never reads
                flooder.sendall(flood * 512)
                sent += len(flood) * 512
                i += 1
                if i % 16 == 0:  # meanwhile the well-behaved client is served
                    server.send(_frame(i))
                    assert bytes(recv(listener).data) == i.to_bytes(4, "little")
        except (ConnectionResetError, BrokenPipeError):
            pass  # the server disconnected the flooder
        assert sent < limit, f"flooder still connected after {sent} bytes"
        wait_for(lambda: server.stats.dropped >= 1 and server.stats.clients == 1)
        if not handshake:  # no frame is ever queued for it: the one drop is the disconnection
            assert server.stats.dropped == 1
        # Memory bound: never more than max_pending bytes queued for one client.
        assert 0 < server.peak_pending <= max_pending
        for j in range(3):
            _assert_both_ways(server, listener, 1000 + j)


def test_rejected_elements_in_raw_mode_queue_nothing(
    server_factory: Callable[..., SocketcandServer],
) -> None:
    server = server_factory(max_pending=4096)
    with raw_client(server, rcvbuf=4096) as raw:
        _raw_mode(raw)
        raw.sendall(b"<x>" * 20_000)
        raw.sendall(b"< echo >")
        assert read_element(raw) == b"< echo >"  # nothing came before it
        assert server.stats.rejected == 20_000
    assert server.peak_pending <= len(b"< echo >")  # the largest reply it was sent


def test_a_connection_that_never_opens_the_bus_is_closed(
    server_factory: Callable[..., SocketcandServer],
) -> None:
    server = server_factory(max_clients=1, handshake_timeout_s=0.2)
    with raw_client(server) as idle:
        assert _closed_by_server(idle)
    assert server.stats.rejected == 1
    with _bus(server) as client:  # the slot is free again
        wait_for(lambda: server.stats.clients == 1)
        _assert_both_ways(server, client, 1)


def test_at_the_client_limit_a_newcomer_evicts_the_client_idle_longest(
    server_factory: Callable[..., SocketcandServer],
) -> None:
    idle_timeout_s = 0.2
    server = server_factory(max_clients=2, idle_timeout_s=idle_timeout_s)
    with raw_client(server) as oldest, raw_client(server) as other:
        _raw_mode(oldest)
        _raw_mode(other)
        time.sleep(1.5 * idle_timeout_s)  # both idle now (a precondition, not the oracle)
        with _bus(server) as client:
            assert _closed_by_server(oldest)
            other.sendall(b"< echo >")  # the other idle client was left alone
            assert read_element(other) == b"< echo >"
            wait_for(lambda: server.stats.clients == 2)
            _assert_both_ways(server, client, 1)
            assert read_element(other).startswith(b"< frame 110 ")
    assert server.stats.rejected == 1


def test_at_the_client_limit_working_clients_are_kept_and_the_newcomer_refused(
    server_factory: Callable[..., SocketcandServer],
) -> None:
    server = server_factory(max_clients=2)  # default idle_timeout_s: nobody has idled that long
    with _bus(server) as first, _bus(server) as second:
        wait_for(lambda: server.stats.clients == 2)
        with pytest.raises(can.CanError, match="< hi >") as refused:
            _bus(server)
        assert "too many clients" in str(refused.value)  # python-can's error says why
        del refused  # its traceback holds python-can's half-made bus and so its socket
        assert server.stats.rejected == 1
        _assert_both_ways(server, first, 1)
        assert bytes(recv(second).data) == (1).to_bytes(4, "little")


def test_keep_alives_do_not_hold_a_slot_against_a_python_can_newcomer(
    server_factory: Callable[..., SocketcandServer],
) -> None:
    """Clients that open the bus and only send ``< echo >`` (never read, never send a frame) are
    idle: a python-can newcomer takes the place of one of them."""
    server = server_factory(max_clients=2, idle_timeout_s=0.2)
    squatters = [raw_client(server), raw_client(server)]
    stop = threading.Event()

    def keep_alive(sock: socket.socket) -> None:
        sock.sendall(f"< open {CHANNEL} >".encode())
        while not stop.wait(0.01):
            try:
                sock.sendall(b"< echo >")
            except OSError:  # evicted
                return

    threads = [threading.Thread(target=keep_alive, args=(s,), daemon=True) for s in squatters]
    for thread in threads:
        thread.start()
    newcomer: list[can.BusABC] = []

    def newcomer_admitted() -> bool:
        try:
            newcomer.append(_bus(server))
        except can.CanError:
            return False
        return True

    try:
        wait_for(newcomer_admitted, timeout=15.0)
        with newcomer[0] as client:
            wait_for(lambda: server.stats.clients == 1)  # the squatters never entered raw mode
            _assert_both_ways(server, client, 1)
    finally:
        stop.set()
        for thread in threads:
            thread.join()
        for sock in squatters:
            sock.close()


# ------------------------------------------------------------------ 3. reconnect rounds


def test_fifty_python_can_reconnect_rounds(
    server_factory: Callable[..., SocketcandServer],
) -> None:
    server = server_factory()
    for i in range(50):
        with _bus(server) as client:
            wait_for(lambda: server.stats.clients == 1)
            _assert_both_ways(server, client, i)
        wait_for(lambda: server.stats.clients == 0)
    stats = server.stats
    assert (stats.sent, stats.received, stats.rejected, stats.dropped) == (50, 50, 0, 0)
    # (conftest's leak check fails this test on a leaked thread or socket)


def _open_sockets(pid: int) -> int:
    fd_dir = Path(f"/proc/{pid}/fd")
    count = 0
    for fd in fd_dir.iterdir():
        try:
            count += os.readlink(fd).startswith("socket:")
        except OSError:
            continue  # closed meanwhile
    return count


@pytest.mark.skipif(not Path("/proc/self/fd").is_dir(), reason="needs /proc")
def test_fifty_reconnect_rounds_against_the_bridge(bridge, zenoh_watch) -> None:
    b = bridge(clock="realtime")
    watch = zenoh_watch(b)
    sc = b.endpoints["can"]["socketcand"]
    db = cantools.database.load_file(b.endpoints["can"]["dbc"])
    odometry = db.get_message_by_name("WheelOdometry").frame_id
    motor = db.get_message_by_name("MotorCommand")
    stop = can.Message(arbitration_id=motor.frame_id, is_extended_id=False,
                       data=db.encode_message("MotorCommand",
                                              {"left_speed": 0.0, "right_speed": 0.0}))
    watch.wait_for("status")
    baseline = _open_sockets(b.proc.pid)  # listeners, Zenoh (this test's session included)
    for _ in range(50):
        with can.Bus(interface="socketcand", host=sc["host"], port=sc["port"],
                     channel=sc["channel"]) as client:
            deadline = time.monotonic() + 10
            while (msg := recv(client)).arbitration_id != odometry:  # every round gets frames
                assert time.monotonic() < deadline, "no odometry frame"
            assert not msg.is_error_frame
            client.send(stop)
    wait_for(lambda: _open_sockets(b.proc.pid) <= baseline)
    status = watch.wait_for("status", lambda m: m["buses"]["can.socketcand"]["received"] >= 50)
    assert status["buses"]["can.socketcand"]["rejected"] == 0
    assert b.proc.poll() is None


# ------------------------------------------------------------------ slcan: the same rule


def test_an_slcan_client_that_never_reads_its_replies_is_counted() -> None:
    with SlcanAdapter() as slcan, serial.Serial(slcan.endpoint.path, timeout=0.5) as port:
        sent, limit = 0, 16 << 20
        while slcan.stats.dropped == 0:  # replies past the pty's 64 KiB cap are dropped
            assert sent < limit, f"no reply dropped after {sent} bytes of commands"
            port.write(b"V\r" * 1024)
            sent += 2048
        assert slcan.stats.rejected == 0
        # What it does get is whole replies, and the port still answers.
        stream = b""
        while chunk := port.read(65536):
            stream += chunk
        assert stream and stream == b"V1013\r" * (len(stream) // 6)
        port.write(b"V\r")
        assert port.read_until(b"\r") == b"V1013\r"
