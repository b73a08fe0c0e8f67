"""Byte transports: URL registry, lifecycle, fan-out, and behaviour with absent or slow clients."""

from __future__ import annotations

import os
import socket
from pathlib import Path

import pytest
import serial
from koala_bridge.drivers.messages import TransportClosedError
from koala_bridge.drivers.transports import (
    BYTE_BACKENDS,
    CAN_BACKENDS,
    Endpoint,
    open_byte_transport,
    pymavlink_url,
    pyserial_url,
)
from koala_bridge.drivers.transports.loop import LoopbackTransport
from koala_bridge.drivers.transports.pty import PtyTransport


def test_every_backend_module_imports() -> None:
    import importlib

    for target in [*BYTE_BACKENDS.values(), *CAN_BACKENDS.values()]:
        module, _, name = target.partition(":")
        assert isinstance(getattr(importlib.import_module(module), name), type)


def test_unknown_scheme_lists_the_known_ones() -> None:
    with pytest.raises(ValueError, match="pty"):
        open_byte_transport("rs485:///dev/ttyS0")


@pytest.mark.parametrize("url", ["pty://", "tcp://127.0.0.1:0", "udp://127.0.0.1:9", "loop://"])
def test_lifecycle(url: str) -> None:
    transport = open_byte_transport(url)
    with transport:
        assert transport.read() == b""
        assert transport.wait(0.0) is False
    transport.close()  # idempotent
    with pytest.raises(TransportClosedError):
        transport.read()
    with pytest.raises(TransportClosedError):
        transport.write(b"x")


def test_client_urls() -> None:
    assert pymavlink_url(Endpoint("udp", host="127.0.0.1", port=14550)) == "udpin:127.0.0.1:14550"
    assert pymavlink_url(Endpoint("tcp", host="127.0.0.1", port=5760)) == "tcp:127.0.0.1:5760"
    assert pyserial_url(Endpoint("tcp", host="127.0.0.1", port=5760)) == "socket://127.0.0.1:5760"
    assert pyserial_url(Endpoint("pty", path="/dev/pts/9")) == "/dev/pts/9"
    with pytest.raises(ValueError):
        pymavlink_url(Endpoint("loop"))


def test_pty_is_raw_and_bidirectional(tmp_path: Path) -> None:
    link = tmp_path / "port"
    link.symlink_to("/nonexistent")  # a stale link from an earlier run is replaced
    with open_byte_transport(f"pty://{link}") as port:
        assert isinstance(port, PtyTransport)
        assert os.readlink(link) == port.slave_path
        with serial.serial_for_url(pyserial_url(port.endpoint), timeout=5) as client:
            client.write(b"\x00\x03\x11\r\n\xff")  # no echo, no ^C/XON/CR translation
            received = b""
            while len(received) < 6:
                assert port.wait(5)
                received += port.read()
            assert received == b"\x00\x03\x11\r\n\xff"
            port.write(b"\r\n\x00\xff")
            assert client.read(4) == b"\r\n\x00\xff"
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


def test_udp_without_a_listener_does_not_fail(free_udp_port: int) -> None:
    with open_byte_transport(f"udp://127.0.0.1:{free_udp_port}") as udp:
        for _ in range(5):
            udp.write(b"x" * 10)
            assert udp.read() == b""
        assert udp.stats.sent + udp.stats.dropped == 5


def test_loopback_pair() -> None:
    a, b = LoopbackTransport.pair()
    with a:
        a.write(b"ping")
        assert b.wait(5) and b.read() == b"ping"
        b.write(b"pong")
        assert a.wait(5) and a.read() == b"pong"
    with pytest.raises(TransportClosedError):
        b.read()
