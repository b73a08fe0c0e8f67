"""Pseudo-terminal backend: the bridge holds the master side, a client opens the slave path with
pyserial (or any serial library) exactly as it opens a USB-serial adapter.

The slave is set to raw mode (no echo, no line editing, 8 bits) before any client opens it. The
bridge does not keep the slave open itself, so it can tell whether a client is connected: while
none is, written data is dropped and counted -- as on a real UART with nobody listening -- instead
of piling up and reaching the next client stale.

One client at a time: when the transport sees the slave closed (the master reports hang-up), the
client's session ends. Output held back for it (:attr:`PtyTransport.pending`) and what it left
unread in the kernel are thrown away. What it wrote that the bridge has not read yet is still
returned by :meth:`PtyTransport.read` (a last ``D,0,0`` still stops the robot) up to what the
kernel had handed over (4 KiB; a flood beyond that is discarded), and replies to it are dropped;
then :attr:`PtyTransport.client_session` grows by one, so a reader that keeps per-client state
(a half-received line) can start afresh for the next client.
The hang-up is seen by :meth:`~PtyTransport.read`, :meth:`~PtyTransport.write`,
:meth:`~PtyTransport.wait`, :meth:`~PtyTransport.has_client` and :attr:`~PtyTransport.stats`;
a client that reopens the port before any of them runs (a reader waiting on the port runs
within milliseconds) is taken for the same client: the kernel keeps no trace of the gap.

Offline (:meth:`PtyTransport.set_offline`, the fault ``disconnect``): the master is closed, so the
client sees a hang-up (a read returns EOF / EIO, pyserial raises ``SerialException``) as when a
USB-serial adapter is unplugged; the symlink, if any, is removed meanwhile, and nothing is read
or written (writes are counted ``dropped``). Back online, the port is a **new** pty (a new
``/dev/pts/N``) and the symlink points to it: the client reopens the same path. Without a
symlink the path changes (:attr:`PtyTransport.endpoint`). The master's file descriptor number
stays the same throughout (a pipe stands in for it while offline), so whoever polls
:meth:`PtyTransport.fileno` keeps polling the right descriptor; a poll already blocked on the
old master holds it open until that poll returns (the hang-up is seen then).
"""

from __future__ import annotations

import errno
import logging
import os
import select
import termios
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

log = logging.getLogger(__name__)

_HUP_POLL_S = 0.02
_MAX_STALE = 65536  # bytes of a gone client's input still returned by read (the kernel holds 4 KiB)


def _open_raw_pty() -> tuple[int, str]:
    """A new pty pair: its master (non-blocking) and the slave's path, the slave in raw mode
    (and closed here: the client opens it by its path)."""
    try:
        master, slave = os.openpty()
    except OSError as e:
        raise TransportError(f"cannot open a pty: {e}") from e
    try:
        tty.setraw(slave)
        name = os.ttyname(slave)
    finally:
        os.close(slave)
    os.set_blocking(master, False)
    return master, name


class PtyTransport(ByteTransport):
    """A pty pair; the slave path (or a stable symlink to it) is the client's serial port.

    Args:
        link: optional path of a symlink to create pointing at the slave device (replaced
            atomically if it exists; removed on :meth:`close` if it still points to this pty).
        max_pending: bytes kept while a connected client is slower than the writer; a write that
            would exceed it is dropped whole.
    """

    def __init__(self, link: str | Path | None = None, *, max_pending: int = 65536) -> None:
        master, self._slave_name = _open_raw_pty()
        self._master: int | None = master
        self._poll = select.poll()
        self._poll.register(master, select.POLLIN)
        self._pending = bytearray()
        self._max_pending = max_pending
        # Client sessions (module docstring): _in_session while a client is known to be there;
        # when it goes, _stale holds its last input, and the session number grows at
        # the first read after them (_boundary). _answering_gone: what read() returned last
        # came from a client that has gone, so replies to it are dropped.
        self._in_session = False
        self._stale = bytearray()
        self._answering_gone = False
        self._last_read_data = False
        self._boundary = False
        self._sessions = 0
        self._offline_pipe: int | None = None   # write end of the stand-in while offline
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

    supports_offline = True

    @property
    def offline(self) -> bool:
        """True between :meth:`set_offline` ``(True)`` and ``(False)``."""
        return self._offline_pipe is not None

    def set_offline(self, offline: bool) -> None:
        """Close the port under the client (``True``) or open a new one at the same symlink
        (``False``); see the module docstring. The client's session ends at once:
        :attr:`client_session` grows, what it left unread or unanswered is dropped."""
        fd = self._fd()
        if offline == self.offline:
            return
        if offline:
            r, w = os.pipe()
            os.dup2(r, fd, inheritable=False)  # closes the master: the client sees a hang-up
            os.close(r)
            self._offline_pipe = w
            if self._link is not None:
                self._unlink_if_mine()
            if self._pending:
                self._pending.clear()
                self._stats.add("dropped")
            self._in_session = self._answering_gone = self._last_read_data = False
            self._boundary = False
            self._stale.clear()
            self._sessions += 1
            log.debug("%s: offline", self._slave_name)
            return
        master, name = _open_raw_pty()
        os.dup2(master, fd, inheritable=False)  # the same fd number, now the new master
        os.close(master)
        stand_in, self._offline_pipe = self._offline_pipe, None
        if stand_in is not None:
            os.close(stand_in)
        self._slave_name = name
        if self._link is not None:
            self._make_link(self._link)
        log.debug("%s: online again", self._slave_name)

    def fileno(self) -> int:
        """The master fd, readable when the client has written something."""
        return self._fd()

    @property
    def client_session(self) -> int:
        """Grows by one at the first :meth:`read` after a client has gone (and its last input
        has been read): from then on, bytes read are the next client's."""
        return self._sessions

    def has_client(self) -> bool:
        """True while some process has the slave open (the master reports no hang-up). Seeing
        the hang-up ends the client's session; seeing a client begins one, unless what the
        bridge is answering is still the last client's input."""
        if self.offline:
            return False
        present = self._slave_open()
        if not present and self._in_session:
            self._end_session()
        elif present and not self._in_session and not self._stale and not self._answering_gone:
            self._in_session = True
        return present

    def read(self, max_bytes: int = 65536) -> bytes:
        self._fd()
        if self.offline:
            return b""
        self._answering_gone = self._last_read_data = False
        self.has_client()
        if self._stale:  # the last input of a client that has gone
            data = bytes(self._stale[:max_bytes])
            del self._stale[:max_bytes]
            self._answering_gone = True
            self._stats.add("received")
            return data
        if self._boundary:
            self._boundary = False
            self._sessions += 1
        self._flush()
        data = self._os_read(max_bytes)
        if data:
            self._stats.add("received")
            self._in_session = self._last_read_data = True  # a client wrote: its session...
            if not self._slave_open():  # ...which may be over already
                self._end_session()
        return data

    def write(self, data: bytes) -> int:
        self._fd()
        self.has_client()
        if not self._in_session:  # (never while offline)
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
        if not self.offline:
            self._flush()

    @property
    def pending(self) -> int:
        """Bytes accepted but not yet taken by the kernel."""
        return len(self._pending)

    def wait(self, timeout: float | None) -> bool:
        self._fd()  # closed: refused, as read and write are
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            if self._stale:  # a gone client's last input, taken from the kernel
                return True
            if self.offline:  # the stand-in pipe never becomes readable
                self._poll.poll(None if timeout is None else int(max(0.0, timeout) * 1000))
                return False
            remaining = None if deadline is None else max(0.0, deadline - time.monotonic())
            events = self._poll.poll(None if remaining is None else int(remaining * 1000))
            if any(ev & select.POLLIN for _, ev in events):
                return True
            if remaining is not None and remaining <= 0:
                return False
            if events:  # hang-up (no client) is reported at once: re-check every _HUP_POLL_S
                if not self.has_client() and self._stale:  # (ends the gone client's session)
                    return True
                time.sleep(_HUP_POLL_S if remaining is None else min(_HUP_POLL_S, remaining))

    def close(self) -> None:
        if self._master is None:
            return
        fd, self._master = self._master, None
        os.close(fd)
        if self._offline_pipe is not None:
            os.close(self._offline_pipe)
            self._offline_pipe = None
        if self._link is not None:
            self._unlink_if_mine()

    # ----------------------------------------------------------------- internals

    def _fd(self) -> int:
        if self._master is None:
            raise TransportClosedError("pty transport is closed")
        return self._master

    def _unlink_if_mine(self) -> None:
        assert self._link is not None
        try:
            if os.readlink(self._link) == self._slave_name:
                self._link.unlink()
        except OSError:
            pass

    def _slave_open(self) -> bool:
        # Its own poll object: ``wait`` may be blocked in ``self._poll`` on another thread, and
        # a poll object refuses concurrent use.
        poller = select.poll()
        poller.register(self._fd(), select.POLLIN)
        events = poller.poll(0)
        return not any(ev & select.POLLHUP for _, ev in events)

    def _end_session(self) -> None:
        """The client has closed the slave: nothing meant for it may reach the next one."""
        log.debug("%s: the client closed the port; its session ends", self._slave_name)
        self._in_session = False
        self._boundary = True
        self._answering_gone = self._last_read_data  # replies to it must not reach the next
        if self._pending:
            self._pending.clear()
            self._stats.add("dropped")
        self._stale = self._take_unread_input()
        self._discard_unread_output()

    def _take_unread_input(self) -> bytearray:
        """What the gone client wrote and the bridge has not read: what the kernel holds for
        reading now (<= 4 KiB), returned; the rest of a flood, discarded (from here on, whatever
        arrives is the next client's)."""
        taken = bytearray()
        while len(taken) < _MAX_STALE and (chunk := self._os_read(_MAX_STALE - len(taken))):
            taken += chunk
        try:
            termios.tcflush(self._fd(), termios.TCIFLUSH)
        except termios.error as e:
            log.debug("cannot flush the pty master: %s", e)
        return taken

    def _discard_unread_output(self) -> None:
        """Flush what the gone client left unread in the slave's input queue (pyserial flushes
        it when it opens a port; other clients may not)."""
        try:
            fd = os.open(self._slave_name, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        except OSError as e:  # a client that opens the port later sees at most 4 KiB stale
            log.debug("cannot open %s to flush it: %s", self._slave_name, e)
            return
        try:
            termios.tcflush(fd, termios.TCIFLUSH)
        except termios.error as e:
            log.debug("cannot flush %s: %s", self._slave_name, e)
        finally:
            os.close(fd)

    def _os_read(self, max_bytes: int) -> bytes:
        try:
            return os.read(self._fd(), max_bytes)
        except BlockingIOError:
            return b""
        except OSError as e:
            if e.errno == errno.EIO:  # no client has the slave open
                return b""
            raise TransportError(f"pty read failed: {e}") from e

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
