"""UDP backend, both ways round.

``udp://HOST:PORT``: datagrams go to a fixed destination (by default 127.0.0.1:14550, where
MAVLink ground stations listen), and replies arriving on the same socket are returned by
:meth:`UdpTransport.read` -- the bridge serving a ground station.

``udpin://HOST:PORT``: the socket is bound at HOST:PORT and reads what is sent there; writes go
back to whoever sent the last datagram (dropped before the first) -- the bridge listening to a
real robot's MAVLink stream, as pymavlink's ``udpin:`` does.

Each :meth:`UdpTransport.write` is one datagram and each :meth:`UdpTransport.read` returns one.

``udp://HOST:PORT?exclusive=1`` also claims the destination for this transport on this machine:
a second exclusive transport sending to the same address fails to open. UDP itself never
reports it (each sender has its own source port), so two bridges sending MAVLink to one
ground-station port would otherwise interleave their streams silently. The claim is a name
bound in Linux's abstract socket namespace (a lock file's ``flock`` elsewhere): the kernel
releases it when the process ends, even by ``kill -9``.

Offline (:meth:`UdpTransport.set_offline`, the fault ``disconnect``): UDP has no connection to
drop, so the link drops everything: writes are counted ``dropped``, datagrams that arrive are
read and thrown away (not counted ``received``), as on an unplugged radio link.
"""

from __future__ import annotations

import contextlib
import ipaddress
import os
import select
import socket
import sys
import tempfile
from typing import Any, Self
from urllib.parse import parse_qs, urlsplit

from koala_bridge.drivers.messages import TransportClosedError, TransportError
from koala_bridge.drivers.transports.base import (
    ByteTransport,
    Endpoint,
    StatsCounter,
    TransportStats,
    split_url,
)

__all__ = ["UdpTransport"]


class UdpTransport(ByteTransport):
    """One UDP socket bound on loopback, sending to ``(host, port)``.

    Args:
        host / port: destination of every datagram written; ``host=None``: the sender of the
            last datagram read (the ``udpin`` form).
        bind_host / bind_port: local address; port 0 picks a free one.
        exclusive: claim ``(host, port)`` on this machine: a second exclusive transport
            sending there raises :class:`TransportError` (module docstring).
    """

    is_datagram = True

    def __init__(
        self,
        host: str | None = "127.0.0.1",
        port: int = 14550,
        *,
        bind_host: str = "127.0.0.1",
        bind_port: int = 0,
        exclusive: bool = False,
    ) -> None:
        self._claim = _claim_destination(host, port) if exclusive and host is not None else None
        self._sock: socket.socket | None = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self._sock.bind((bind_host, bind_port))
        except OSError as e:
            self._sock.close()
            self._release()
            raise TransportError(f"cannot bind UDP {bind_host}:{bind_port}: {e}") from e
        self._sock.setblocking(False)
        self._dest = None if host is None else (host, port)
        self._stats = StatsCounter()
        self._offline = False
        self.last_peer: tuple[str, int] | None = None

    @classmethod
    def from_url(cls, url: str, **options: Any) -> Self:
        """``udp://HOST:PORT`` sends there (default 127.0.0.1:14550); ``udpin://HOST:PORT``
        (also pymavlink's ``udpin:HOST:PORT``) listens there and answers the last sender."""
        parts = split_url(url)
        if parts.scheme == "udpin":
            host, port = _host_port(parts.host, parts.port, parts.rest, url)
            options.setdefault("host", None)
            options.setdefault("bind_host", host)
            options.setdefault("bind_port", port)
        else:
            options.setdefault("host", parts.host or "127.0.0.1")
            options.setdefault("port", 14550 if parts.port is None else parts.port)
            # a socket bound to loopback cannot send anywhere else (EINVAL)
            if not _is_loopback(options["host"]):
                options.setdefault("bind_host", "0.0.0.0")
            query = parse_qs(urlsplit(url).query)
            if query.get("exclusive", ["0"])[-1] not in ("0", "false", ""):
                options.setdefault("exclusive", True)
        return cls(**options)

    @property
    def endpoint(self) -> Endpoint:
        if self._dest is None:
            host, port = self.local_address
            return Endpoint("udpin", host=host, port=port)
        return Endpoint("udp", host=self._dest[0], port=self._dest[1])

    @property
    def local_address(self) -> tuple[str, int]:
        """The (host, port) datagrams come from; replies are received here."""
        host, port = self._s().getsockname()[:2]
        return host, port

    @property
    def stats(self) -> TransportStats:
        return self._stats.snapshot()

    supports_offline = True

    def set_offline(self, offline: bool) -> None:
        """Drop everything (``True``) or nothing any more (``False``); see the module docstring."""
        self._s()
        self._offline = bool(offline)

    def read(self, max_bytes: int = 65536) -> bytes:
        sock = self._s()
        if self._offline:
            self._discard(sock)
            return b""
        try:
            data, peer = sock.recvfrom(max_bytes)
        except (BlockingIOError, ConnectionRefusedError):
            # Linux reports an earlier datagram's ICMP "port unreachable" on the next call.
            return b""
        self.last_peer = (peer[0], peer[1])
        self._stats.add("received")
        return data

    def write(self, data: bytes) -> int:
        sock = self._s()
        if self._offline:
            self._stats.add("dropped")
            return 0
        dest = self._dest or self.last_peer
        if dest is None:  # udpin before anyone has sent: nobody to answer
            self._stats.add("dropped")
            return 0
        try:
            sent = sock.sendto(data, dest)
        except (BlockingIOError, ConnectionRefusedError):
            self._stats.add("dropped")
            return 0
        except OSError as e:
            raise TransportError(f"UDP send to {dest} failed: {e}") from e
        self._stats.add("sent")
        return sent

    def wait(self, timeout: float | None) -> bool:
        if self._offline:  # what arrives is thrown away: wait out the timeout, no spin
            self._discard(self._s())
            select.select([], [], [], timeout)
            self._discard(self._s())
            return False
        readable, _, _ = select.select([self._s()], [], [], timeout)
        return bool(readable)

    @staticmethod
    def _discard(sock: socket.socket) -> None:
        """Read and throw away every datagram waiting (offline)."""
        while True:
            try:
                sock.recvfrom(65536)
            except (BlockingIOError, ConnectionRefusedError):
                return
            except OSError:
                return

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
        self._release()

    def _release(self) -> None:
        if self._claim is not None:
            self._claim.close()
            self._claim = None

    def _s(self) -> socket.socket:
        if self._sock is None:
            raise TransportClosedError("udp transport is closed")
        return self._sock


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def _claim_destination(host: str, port: int) -> Any:
    """Hold a machine-wide claim on sending to ``host:port`` (an open socket or file; closing
    it releases the claim); :class:`TransportError` if another process holds it."""
    try:
        ip = socket.getaddrinfo(host, port, socket.AF_INET, socket.SOCK_DGRAM)[0][4][0]
    except OSError:
        ip = host
    name = f"koala-bridge/udp-destination/{ip}:{port}"
    taken = TransportError(
        f"another koala-bridge (or exclusive UDP transport) on this machine already sends to "
        f"{ip}:{port}; two senders would interleave their streams there"
    )
    if sys.platform.startswith("linux"):
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        try:
            sock.bind("\0" + name)
        except OSError as e:
            sock.close()
            raise taken from e
        return sock
    import fcntl  # POSIX without an abstract namespace (macOS)

    path = os.path.join(tempfile.gettempdir(), name.replace("/", "-") + ".lock")
    lock = open(path, "a+b")  # noqa: SIM115 - held open until close()
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as e:
        with contextlib.suppress(OSError):
            lock.close()
        raise taken from e
    return lock


def _host_port(
    host: str | None, port: int | None, rest: str, url: str
) -> tuple[str, int]:
    """HOST:PORT of ``udpin://HOST:PORT`` or of pymavlink's ``udpin:HOST:PORT``."""
    if host and port is not None:
        return host, port
    h, _, p = rest.lstrip("/").rpartition(":")
    if not h or not p.isdigit():
        raise ValueError(f"{url!r}: expected udpin://HOST:PORT")
    return h, int(p)
