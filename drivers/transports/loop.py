"""In-process loopback backend: two connected ends, what one writes the other reads.

Used by tests and by the bridge's own self-checks, the way pyserial offers ``loop://``.
"""

from __future__ import annotations

import select
import socket

from koala_bridge.drivers.messages import TransportClosedError
from koala_bridge.drivers.transports.base import (
    ByteTransport,
    Endpoint,
    StatsCounter,
    TransportStats,
)

__all__ = ["LoopbackTransport"]


class LoopbackTransport(ByteTransport):
    """One end of a connected pair; the other end is :attr:`peer`."""

    def __init__(
        self,
        _sock: socket.socket | None = None,
        _peer: LoopbackTransport | None = None,
        *,
        max_pending: int = 65536,
    ) -> None:
        if _sock is None:
            a, b = socket.socketpair()
            _sock = a
            _peer = LoopbackTransport(b, self)
        assert _peer is not None
        _sock.setblocking(False)
        self._sock: socket.socket | None = _sock
        self.peer: LoopbackTransport = _peer
        self._stats = StatsCounter()
        self._pending = bytearray()
        self._max_pending = max_pending

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
        sock = self._s()
        self._flush()
        try:
            data = sock.recv(max_bytes)
        except BlockingIOError:
            return b""
        if data:
            self._stats.add("received")
        return data

    def write(self, data: bytes) -> int:
        self._s()
        self._flush()
        if self._pending:
            if len(self._pending) + len(data) > self._max_pending:
                self._stats.add("dropped")
                return 0
            self._pending += data
        else:
            sent = self._send(data)
            if sent < 0:
                self._stats.add("dropped")
                return 0
            self._pending += data[sent:]
        self._stats.add("sent")
        return len(data)

    def _flush(self) -> None:
        if self._pending:
            sent = self._send(bytes(self._pending))
            del self._pending[: sent if sent >= 0 else len(self._pending)]

    def _send(self, data: bytes) -> int:
        """Bytes taken by the socket; -1 if the other end is gone."""
        try:
            return self._s().send(data)
        except BlockingIOError:
            return 0
        except (BrokenPipeError, ConnectionResetError):
            return -1

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
