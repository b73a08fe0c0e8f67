"""A raw socketcand client for tests: the TCP socket and the ``< ... >`` elements, by hand (no
python-can), so a test can send what a well-behaved client never would."""

from __future__ import annotations

import socket

from koala_bridge.drivers.transports.socketcand import SocketcandServer


def raw_client(server: SocketcandServer, rcvbuf: int | None = None,
               timeout: float = 10.0) -> socket.socket:
    """A connected socket past the server's ``< hi >``; ``rcvbuf`` is set before connecting, so
    the TCP window stays that small."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    if rcvbuf is not None:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
    sock.settimeout(timeout)
    sock.connect((server.endpoint.host, server.endpoint.port))
    assert read_element(sock) == b"< hi >"
    return sock


def read_element(sock: socket.socket) -> bytes:
    """The next ``< ... >`` element the server sends, stripped."""
    buf = b""
    while not buf.endswith(b">"):
        chunk = sock.recv(1)
        assert chunk, "server closed the connection"
        buf += chunk
    return buf.strip()
