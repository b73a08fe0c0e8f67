"""In-process loopback backend: two connected ends, what one writes the other reads.

Used by tests and by the bridge's own self-checks, the way pyserial offers ``loop://``.
"""

from __future__ import annotations

import select
import socket

from drivers.messages import TransportClosedError
from drivers.transports.base import ByteTransport, Endpoint, StatsCounter, TransportStats

__all__ = ["LoopbackTransport"]


class LoopbackTransport(ByteTransport):
    """One end of a connected pair; the other end is :attr:`peer`."""

    def __init__(self, _sock: socket.socket | None = None, _peer: LoopbackTransport | None = None):
        if _sock is None:
            a, b = socket.socketpair()
            _sock = a
            _peer = LoopbackTransport(b, self)
        assert _peer is not None
        _sock.setblocking(False)
        self._sock: socket.socket | None = _sock
        self.peer: LoopbackTransport = _peer
        self._stats = StatsCounter()

    @classmethod
    def pair(cls) -> tuple[LoopbackTransport, LoopbackTransport]:
        """Two connected ends."""
        end = cls()
        return end, end.peer

    @property
    def endpoint(self) -> Endpoint:
        return Endpoint("loop")

    @property
    def stats(self) -> TransportStats:
        return self._stats.snapshot(clients=1)

    def read(self, max_bytes: int = 65536) -> bytes:
        try:
            data = self._s().recv(max_bytes)
        except BlockingIOError:
            return b""
        if data:
            self._stats.add("received")
        return data

    def write(self, data: bytes) -> int:
        try:
            self._s().sendall(data)
        except (BlockingIOError, BrokenPipeError):
            self._stats.add("dropped")
            return 0
        self._stats.add("sent")
        return len(data)

    def wait(self, timeout: float | None) -> bool:
        readable, _, _ = select.select([self._s()], [], [], timeout)
        return bool(readable)

    def close(self) -> None:
        """Close this end and its peer."""
        if self._sock is not None:
            self._sock.close()
            self._sock = None
            self.peer.close()

    def _s(self) -> socket.socket:
        if self._sock is None:
            raise TransportClosedError("loopback transport is closed")
        return self._sock
