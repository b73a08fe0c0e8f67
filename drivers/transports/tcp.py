"""TCP server backend: clients connect to 127.0.0.1:<port>; what the bridge writes goes to every
connected client, what any client sends is returned by :meth:`TcpServerTransport.read`.

No thread: connections are accepted and data moved whenever :meth:`read`, :meth:`write` or
:meth:`wait` is called (the kernel completes the TCP handshake from the listen backlog meanwhile).

Limits (docs/security.md): at most ``max_clients`` connections; each client has its own queue of
``max_pending`` bytes for what it has not read yet, past which writes to that client are dropped
whole and counted (``dropped``) -- the others are not slowed. A client whose queue overflowed is
*stalled* until it has read its queue empty; when all places are taken, a new connection replaces
the longest-stalled client (closed), or is closed at once (``rejected``) if none is stalled.

Offline (:meth:`TcpServerTransport.set_offline`, the fault ``disconnect``): every connection is
closed and so is the listening socket, so a reconnect is refused, until the server listens again
on the same port. Meanwhile reads return nothing and writes are dropped (counted).
"""

from __future__ import annotations

import select
import socket
from typing import Any, Self

from koala_bridge.drivers.messages import TransportClosedError, TransportError
from koala_bridge.drivers.transports.base import (
    ByteTransport,
    Endpoint,
    StatsCounter,
    TransportStats,
    listen_tcp,
    split_url,
)

__all__ = ["TcpClientTransport", "TcpServerTransport"]


class _Client:
    __slots__ = ("sock", "pending", "stalled_since")

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self.pending = bytearray()
        self.stalled_since: int | None = None  # write count when its queue first overflowed


class TcpServerTransport(ByteTransport):
    """A listening TCP socket fanning bytes out to all its clients.

    Args:
        host: address to bind; loopback by default.
        port: port to bind; 0 picks a free one (see :attr:`endpoint`).
        max_clients: further connections replace a stalled client, or are accepted and closed at
            once (module docstring).
        max_pending: per-client bytes kept while that client is slow; beyond it writes to that
            client are dropped whole.
    """

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 0,
        *,
        max_clients: int = 8,
        max_pending: int = 65536,
    ) -> None:
        try:
            self._listener: socket.socket | None = listen_tcp(host, port, max_clients)
        except OSError as e:
            raise TransportError(f"cannot listen on {host}:{port}: {e}") from e
        self._host, self._port = self._listener.getsockname()[:2]
        self._offline = False
        self._clients: list[_Client] = []
        self._max_clients = max_clients
        self._max_pending = max_pending
        self._stats = StatsCounter()
        self._next = 0
        self._writes = 0

    @classmethod
    def from_url(cls, url: str, **options: Any) -> Self:
        """``tcp://HOST:PORT`` listens there (host 127.0.0.1 and port 0, a free one, if left
        out)."""
        parts = split_url(url)
        options.setdefault("host", parts.host or "127.0.0.1")
        options.setdefault("port", 0 if parts.port is None else parts.port)
        return cls(**options)

    @property
    def endpoint(self) -> Endpoint:
        return Endpoint("tcp", host=self._host, port=self._port)

    @property
    def stats(self) -> TransportStats:
        return self._stats.snapshot(clients=len(self._clients))

    @property
    def pending(self) -> int:
        """Bytes accepted but not yet taken by the kernel, all clients together (at most
        ``max_clients * max_pending``)."""
        return sum(len(c.pending) for c in self._clients)

    supports_offline = True

    def set_offline(self, offline: bool) -> None:
        """Drop every client and stop listening (``True``), or listen again on the same port
        (``False``; :class:`TransportError` if it cannot be bound again)."""
        listener = self._sock()
        if offline == self._offline:
            return
        if offline:
            for client in list(self._clients):
                self._drop_client(client)
            listener.close()
            self._offline = True
            return
        try:
            self._listener = listen_tcp(self._host, self._port, self._max_clients)
        except OSError as e:
            raise TransportError(f"cannot listen on {self._host}:{self._port} again: {e}") from e
        self._offline = False

    def read(self, max_bytes: int = 65536) -> bytes:
        if self._offline_now():
            return b""
        self._service()
        # Round-robin so one chatty client cannot starve the others.
        for _ in range(len(self._clients)):
            client = self._clients[self._next % len(self._clients)]
            self._next += 1
            try:
                data = client.sock.recv(max_bytes)
            except BlockingIOError:
                continue
            except OSError:
                data = b""
            if not data:
                self._drop_client(client)
                return b""
            self._stats.add("received")
            return data
        return b""

    def write(self, data: bytes) -> int:
        if self._offline_now():
            self._stats.add("dropped")
            return 0
        self._service()
        if not self._clients:
            self._stats.add("dropped")
            return 0
        self._writes += 1
        for client in list(self._clients):
            if client.pending:
                if len(client.pending) + len(data) > self._max_pending:
                    self._stats.add("dropped")
                    if client.stalled_since is None:
                        client.stalled_since = self._writes
                    continue
                client.pending += data
                continue
            sent = self._send(client, data)
            if sent < len(data):
                client.pending += data[sent:]
        self._stats.add("sent")
        return len(data)

    def wait(self, timeout: float | None) -> bool:
        if self._offline_now():  # nothing can arrive: wait out the timeout, no spin
            select.select([], [], [], timeout)
            return False
        listener = self._sock()
        self._service()
        readable, _, _ = select.select(
            [listener, *(c.sock for c in self._clients)], [], [], timeout
        )
        if listener in readable:
            self._service()
        return any(s is not listener for s in readable)

    def close(self) -> None:
        if self._listener is None:
            return
        for client in self._clients:
            client.sock.close()
        self._clients.clear()
        self._listener.close()
        self._listener = None

    # ----------------------------------------------------------------- internals

    def _sock(self) -> socket.socket:
        if self._listener is None:
            raise TransportClosedError("tcp transport is closed")
        return self._listener

    def _offline_now(self) -> bool:
        """Whether offline (raises if closed)."""
        self._sock()
        return self._offline

    def _service(self) -> None:
        """Accept waiting connections and flush pending output."""
        listener = self._sock()
        while True:
            try:
                sock, _ = listener.accept()
            except (BlockingIOError, OSError):
                break
            if len(self._clients) >= self._max_clients and not self._evict_stalled():
                sock.close()
                self._stats.add("rejected")
                continue
            sock.setblocking(False)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._clients.append(_Client(sock))
        for client in list(self._clients):
            if client.pending:
                sent = self._send(client, bytes(client.pending))
                del client.pending[:sent]
                if not client.pending:
                    client.stalled_since = None  # it caught up

    def _send(self, client: _Client, data: bytes) -> int:
        try:
            return client.sock.send(data)
        except BlockingIOError:
            return 0
        except OSError:
            self._drop_client(client)
            return len(data)

    def _evict_stalled(self) -> bool:
        """Close the client stalled longest, if any, to make room for a new one."""
        stalled = [c for c in self._clients if c.stalled_since is not None]
        if not stalled:
            return False
        self._drop_client(min(stalled, key=lambda c: c.stalled_since or 0))
        return True

    def _drop_client(self, client: _Client) -> None:
        if client in self._clients:
            self._clients.remove(client)
        client.sock.close()


class TcpClientTransport(ByteTransport):
    """A TCP connection to a server (a robot's MAVLink TCP port, a serial-to-TCP bridge).

    When the server closes the connection, :meth:`read` returns ``b""`` and :meth:`write` drops,
    and ``stats.clients`` is 0: a dead link reads as silence, as an unplugged serial cable does.

    Args:
        host / port: the server's address.
        connect_timeout_s: how long connecting may take.
    """

    def __init__(self, host: str, port: int, *, connect_timeout_s: float = 5.0) -> None:
        try:
            sock = socket.create_connection((host, port), timeout=connect_timeout_s)
        except OSError as e:
            raise TransportError(f"cannot connect to {host}:{port}: {e}") from e
        sock.setblocking(False)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._sock: socket.socket | None = sock
        self._host, self._port = host, port
        self._connected = True
        self._stats = StatsCounter()

    @classmethod
    def from_url(cls, url: str, **options: Any) -> Self:
        """``tcp-client://HOST:PORT`` connects there."""
        parts = split_url(url)
        if not parts.host or parts.port is None:
            raise ValueError(f"{url!r}: expected tcp-client://HOST:PORT")
        options.setdefault("host", parts.host)
        options.setdefault("port", parts.port)
        return cls(**options)

    @property
    def endpoint(self) -> Endpoint:
        return Endpoint("tcp-client", host=self._host, port=self._port)

    @property
    def stats(self) -> TransportStats:
        return self._stats.snapshot(clients=1 if self._connected else 0)

    def read(self, max_bytes: int = 65536) -> bytes:
        sock = self._s()
        if not self._connected:
            return b""
        try:
            data = sock.recv(max_bytes)
        except BlockingIOError:
            return b""
        except OSError:
            data = b""
        if not data:
            self._connected = False
            return b""
        self._stats.add("received")
        return data

    def write(self, data: bytes) -> int:
        sock = self._s()
        if not self._connected:
            self._stats.add("dropped")
            return 0
        try:
            sock.sendall(data)
        except BlockingIOError:  # the server does not keep up: drop, the link stays
            self._stats.add("dropped")
            return 0
        except OSError:
            self._connected = False
            self._stats.add("dropped")
            return 0
        self._stats.add("sent")
        return len(data)

    def wait(self, timeout: float | None) -> bool:
        sock = self._s()
        if not self._connected:  # nothing will ever arrive: wait out the timeout, no spin
            select.select([], [], [], timeout)
            return False
        readable, _, _ = select.select([sock], [], [], timeout)
        return bool(readable)

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def _s(self) -> socket.socket:
        if self._sock is None:
            raise TransportClosedError("tcp client transport is closed")
        return self._sock
