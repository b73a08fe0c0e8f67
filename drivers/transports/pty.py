"""Pseudo-terminal backend: the bridge holds the master side, a client opens the slave path with
pyserial (or any serial library) exactly as it opens a USB-serial adapter.

The slave is set to raw mode (no echo, no line editing, 8 bits) before any client opens it. The
bridge does not keep the slave open itself, so it can tell whether a client is connected: while
none is, written data is dropped and counted -- as on a real UART with nobody listening -- instead
of piling up and reaching the next client stale.
"""

from __future__ import annotations

import errno
import os
import select
import time
import tty
from pathlib import Path
from typing import Any, Self

from koala_bridge.drivers.messages import TransportClosedError, TransportError
from koala_bridge.drivers.transports.base import (
    ByteTransport,
    Endpoint,
    StatsCounter,
    TransportStats,
    split_url,
)

__all__ = ["PtyTransport"]

_HUP_POLL_S = 0.02


class PtyTransport(ByteTransport):
    """A pty pair; the slave path (or a stable symlink to it) is the client's serial port.

    Args:
        link: optional path of a symlink to create pointing at the slave device (replaced
            atomically if it exists; removed on :meth:`close` if it still points to this pty).
        max_pending: bytes kept while a connected client is slower than the writer; a write that
            would exceed it is dropped whole.
    """

    def __init__(self, link: str | Path | None = None, *, max_pending: int = 65536) -> None:
        try:
            master, slave = os.openpty()
        except OSError as e:
            raise TransportError(f"cannot open a pty: {e}") from e
        try:
            tty.setraw(slave)
            self._slave_name = os.ttyname(slave)
        finally:
            os.close(slave)
        os.set_blocking(master, False)
        self._master: int | None = master
        self._poll = select.poll()
        self._poll.register(master, select.POLLIN)
        self._pending = bytearray()
        self._max_pending = max_pending
        self._stats = StatsCounter()
        self._link: Path | None = None
        if link is not None:
            self._link = Path(link)
            self._make_link(self._link)

    @classmethod
    def from_url(cls, url: str, **options: Any) -> Self:
        """``pty://`` (a new pty) or ``pty:///PATH`` (plus a symlink at PATH to its slave)."""
        path = split_url(url).path
        if path:
            options.setdefault("link", path)
        return cls(**options)

    # ----------------------------------------------------------------- ByteTransport

    @property
    def endpoint(self) -> Endpoint:
        return Endpoint("pty", path=str(self._link) if self._link else self._slave_name)

    @property
    def slave_path(self) -> str:
        """The ``/dev/pts/N`` device path (the symlink, if any, points here)."""
        return self._slave_name

    @property
    def stats(self) -> TransportStats:
        return self._stats.snapshot(
            clients=1 if self._master is not None and self.has_client() else 0
        )

    def fileno(self) -> int:
        """The master fd, readable when the client has written something."""
        return self._fd()

    def has_client(self) -> bool:
        """True while some process has the slave open (the master reports no hang-up).

        Uses its own poll object: ``wait`` may be blocked in ``self._poll`` on another thread,
        and a poll object refuses concurrent use.
        """
        poller = select.poll()
        poller.register(self._fd(), select.POLLIN)
        events = poller.poll(0)
        return not any(ev & select.POLLHUP for _, ev in events)

    def read(self, max_bytes: int = 65536) -> bytes:
        fd = self._fd()
        self._flush()
        try:
            data = os.read(fd, max_bytes)
        except BlockingIOError:
            return b""
        except OSError as e:
            if e.errno == errno.EIO:  # no client has the slave open
                return b""
            raise TransportError(f"pty read failed: {e}") from e
        if data:
            self._stats.add("received")
        return data

    def write(self, data: bytes) -> int:
        self._fd()
        if not self.has_client():
            self._pending.clear()
            self._stats.add("dropped")
            return 0
        self._flush()
        if self._pending:
            if len(self._pending) + len(data) > self._max_pending:
                self._stats.add("dropped")
                return 0
            self._pending += data
        else:
            written = self._os_write(data)
            if written < len(data):
                self._pending += data[written:]
        self._stats.add("sent")
        return len(data)

    def flush(self) -> None:
        """Push data held back by a slow client; called by :meth:`read` and :meth:`write` too."""
        self._fd()
        self._flush()

    @property
    def pending(self) -> int:
        """Bytes accepted but not yet taken by the kernel."""
        return len(self._pending)

    def wait(self, timeout: float | None) -> bool:
        self._fd()  # closed: refused, as read and write are
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            remaining = None if deadline is None else max(0.0, deadline - time.monotonic())
            events = self._poll.poll(None if remaining is None else int(remaining * 1000))
            if any(ev & select.POLLIN for _, ev in events):
                return True
            if remaining is not None and remaining <= 0:
                return False
            if events:  # hang-up (no client) is reported at once: re-check every _HUP_POLL_S
                time.sleep(_HUP_POLL_S if remaining is None else min(_HUP_POLL_S, remaining))

    def close(self) -> None:
        if self._master is None:
            return
        fd, self._master = self._master, None
        os.close(fd)
        if self._link is not None:
            try:
                if os.readlink(self._link) == self._slave_name:
                    self._link.unlink()
            except OSError:
                pass

    # ----------------------------------------------------------------- internals

    def _fd(self) -> int:
        if self._master is None:
            raise TransportClosedError("pty transport is closed")
        return self._master

    def _flush(self) -> None:
        if self._pending:
            written = self._os_write(bytes(self._pending))
            del self._pending[:written]

    def _os_write(self, data: bytes) -> int:
        try:
            return os.write(self._fd(), data)
        except BlockingIOError:
            return 0
        except OSError as e:
            if e.errno == errno.EIO:
                return 0
            raise TransportError(f"pty write failed: {e}") from e

    def _make_link(self, link: Path) -> None:
        tmp = link.with_name(f".{link.name}.{os.getpid()}.tmp")
        try:
            tmp.unlink(missing_ok=True)
            os.symlink(self._slave_name, tmp)
            os.replace(tmp, link)
        except OSError as e:
            self.close()
            raise TransportError(f"cannot create symlink {link}: {e}") from e
