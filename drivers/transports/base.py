"""The two transport interfaces -- byte streams and CAN -- and their shared bookkeeping.

A transport moves bytes or CAN frames and nothing else; which codec reads them is the caller's
business. Every transport that serves clients binds to 127.0.0.1 by default; the robot-side
ones (``serial``, ``tcp-client``, ``udpin``) open what their URL names. Each has :meth:`close`, is a
context manager, reports counters through :attr:`stats` (for the bridge's ``status``), and is
opened from its URL by its own :meth:`from_url` (through the registry,
:func:`koala_bridge.drivers.transports.open_byte_transport` / ``open_can_transport``).
"""

from __future__ import annotations

import socket
import threading
from abc import ABC, abstractmethod
from dataclasses import dataclass
from types import TracebackType
from typing import Any, Self
from urllib.parse import unquote, urlsplit

import can

__all__ = [
    "listen_tcp",
    "ByteTransport",
    "CanTransport",
    "Endpoint",
    "StatsCounter",
    "TransportStats",
    "UrlParts",
    "split_url",
]


@dataclass(frozen=True, slots=True)
class UrlParts:
    """A transport URL split into what backends read from it (``scheme://host:port/path``).

    ``rest`` is everything after ``scheme:`` unparsed, for backends whose address is not a
    network location (a pyserial URL behind ``serial:``, a device path).
    """

    scheme: str
    host: str | None
    port: int | None
    path: str
    rest: str


def split_url(url: str) -> UrlParts:
    """Split ``url``; a bad port (not a number, out of range) raises :class:`ValueError`."""
    parts = urlsplit(url)
    scheme, _, rest = url.partition(":")
    try:
        port = parts.port
    except ValueError as e:
        raise ValueError(f"{url!r}: {e}") from e
    return UrlParts(parts.scheme.lower(), parts.hostname, port, unquote(parts.path), rest)


def listen_tcp(host: str, port: int, backlog: int) -> socket.socket:
    """A non-blocking IPv4 socket listening on ``host:port`` (``SO_REUSEADDR``, so that a port
    just given up -- the fault ``disconnect`` going back online -- binds again at once).
    :class:`OSError` if it cannot listen; nothing is left open then."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((host, port))
        sock.listen(backlog)
        sock.setblocking(False)
    except OSError:
        sock.close()
        raise
    return sock


@dataclass(frozen=True, slots=True)
class TransportStats:
    """A snapshot of a transport's counters.

    Attributes:
        sent: writes (byte transports) or frames (CAN) handed to clients.
        received: reads / datagrams (byte transports) or frames (CAN) received from clients.
        rejected: malformed input the transport itself refused (protocol-level garbage; codec
            rejects are counted by the codec's caller).
        dropped: outgoing data thrown away because no client was connected or a client could not
            keep up, and incoming frames dropped because the receive queue was full.
        clients: clients currently connected and receiving what is sent, where the transport
            can tell (else 0): a pty with its slave open, a TCP connection, a socketcand client
            in raw mode, an slcan channel opened with ``O``.
    """

    sent: int = 0
    received: int = 0
    rejected: int = 0
    dropped: int = 0
    clients: int = 0


class StatsCounter:
    """Thread-safe mutable counters behind :class:`TransportStats`."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._values = {"sent": 0, "received": 0, "rejected": 0, "dropped": 0}

    def add(self, name: str, n: int = 1) -> None:
        """Increase counter ``name`` (``sent``, ``received``, ``rejected`` or ``dropped``)."""
        with self._lock:
            self._values[name] += n

    def snapshot(self, clients: int = 0) -> TransportStats:
        """A consistent copy of the counters."""
        with self._lock:
            return TransportStats(clients=clients, **self._values)


@dataclass(frozen=True, slots=True)
class Endpoint:
    """Where a client connects to a transport.

    Attributes:
        kind: backend name, the URL scheme that opened it (``pty``, ``tcp``, ``tcp-client``,
            ``udp``, ``udpin``, ``serial``, ``loop``, ``socketcand``, ``slcan``, ``virtual``,
            ``python-can``).
        path: device path for pty-based backends (the stable symlink if one was asked for);
            the device or pyserial URL of a ``serial`` port.
        host / port: socket address for network backends (for ``udp``, where datagrams are sent).
        channel: CAN channel name (socketcand bus name, python-can channel).
        interface: python-can interface name for the ``python-can`` and ``virtual`` backends.
    """

    kind: str
    path: str | None = None
    host: str | None = None
    port: int | None = None
    channel: str | None = None
    interface: str | None = None


class _Closable(ABC):
    #: Whether :meth:`set_offline` is implemented (fault ``disconnect``, docs/faults.md).
    supports_offline: bool = False
    _offline: bool = False  # a backend's set_offline keeps it (or it overrides :attr:`offline`)

    @property
    def offline(self) -> bool:
        """True between :meth:`set_offline` ``(True)`` and ``(False)``; always False for a
        backend that cannot go offline."""
        return self._offline

    def set_offline(self, offline: bool) -> None:
        """Take the bus away (``True``) or give it back (``False``), as a cable pulled and
        plugged in again: the fault ``disconnect`` (bridge/runtime/faults.py, docs/faults.md).
        While offline nothing is sent or received and writes are counted ``dropped``; what a
        client sees depends on the backend (its docstring). Idempotent.

        The default raises :class:`NotImplementedError`: a backend that cannot model a
        disconnect says so (:attr:`supports_offline` is False) rather than ignoring the fault
        and letting a firmware test pass that should not."""
        raise NotImplementedError(f"{type(self).__name__} cannot go offline")

    @classmethod
    def from_url(cls, url: str, **options: Any) -> Self:
        """Open the backend named by ``url`` (its own URL syntax, see the module docstring of
        :mod:`koala_bridge.drivers.transports`); ``options`` go to the constructor and win over
        what the URL says. The default reads no URL at all."""
        return cls(**options)

    @abstractmethod
    def close(self) -> None:
        """Release every resource; idempotent; joins any thread the transport started."""

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


class ByteTransport(_Closable):
    """A byte stream (pty, TCP, loopback) or datagram link (UDP) to one or more clients.

    :meth:`read` and :meth:`write` never block. On a datagram transport (``is_datagram``) each
    :meth:`read` returns one whole datagram and each :meth:`write` sends one.
    """

    is_datagram: bool = False

    @property
    @abstractmethod
    def endpoint(self) -> Endpoint:
        """Where clients connect."""

    @property
    @abstractmethod
    def stats(self) -> TransportStats:
        """Counters snapshot."""

    @abstractmethod
    def read(self, max_bytes: int = 65536) -> bytes:
        """Bytes (or one datagram) received from a client; ``b""`` if none are waiting."""

    @abstractmethod
    def write(self, data: bytes) -> int:
        """Send ``data`` to the client(s); returns the bytes accepted (0 if dropped).

        ``data`` is delivered whole or not at all (and then counted in ``dropped``), so a
        message is never cut in half by a slow or absent client.
        """

    @abstractmethod
    def wait(self, timeout: float | None) -> bool:
        """Block until :meth:`read` may return data or ``timeout`` s pass; True if readable."""

    @property
    def client_session(self) -> int:
        """On a link that serves one client at a time (a pty), which client's bytes :meth:`read`
        returns: grows by one when the next client's begin, so a reader keeping per-client state
        (a half-received line) resets it. 0 where the transport cannot tell clients apart."""
        return 0


class CanTransport(_Closable):
    """A CAN bus endpoint: frames from the bridge go to every client, frames from clients queue up
    for :meth:`recv`."""

    @property
    @abstractmethod
    def endpoint(self) -> Endpoint:
        """Where clients connect."""

    @property
    @abstractmethod
    def stats(self) -> TransportStats:
        """Counters snapshot."""

    @abstractmethod
    def send(self, msg: can.Message) -> None:
        """Put ``msg`` on the bus for every client; never blocks on a slow client."""

    @abstractmethod
    def recv(self, timeout: float | None = 0.0) -> can.Message | None:
        """Next frame from a client, waiting up to ``timeout`` s (None: forever); None if none."""
