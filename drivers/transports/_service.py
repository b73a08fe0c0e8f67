"""A stoppable I/O thread for the transports that must answer clients on their own (socketcand
handshakes, slcan adapter commands), plus the bounded receive queue they share."""

from __future__ import annotations

import logging
import queue
import socket
import threading
from collections.abc import Callable

import can
from koala_bridge.drivers.transports.base import StatsCounter

__all__ = ["FrameQueue", "ServiceThread", "Waker"]

log = logging.getLogger(__name__)


class Waker:
    """A socketpair whose read end wakes a ``select`` loop from another thread.

    Wakes are coalesced: while one is pending (written, not yet drained) another costs no system
    call. The loop must :meth:`drain` *before* it looks at the work it was woken for: work queued
    after the drain sets the flag again and wakes the loop once more.
    """

    def __init__(self) -> None:
        self._r, self._w = socket.socketpair()
        self._r.setblocking(False)
        self._w.setblocking(False)
        self._pending = False

    def fileno(self) -> int:
        return self._r.fileno()

    def wake(self) -> None:
        if self._pending:  # the loop has not drained the last wake yet: it will see this work
            return
        self._pending = True
        try:
            self._w.send(b"\0")
        except (BlockingIOError, OSError):
            pass  # already pending, or closing: either way the loop will wake

    def drain(self) -> None:
        self._pending = False  # first: a wake from now on writes again
        try:
            while self._r.recv(4096):
                pass
        except (BlockingIOError, OSError):
            pass

    def close(self) -> None:
        self._r.close()
        self._w.close()


class ServiceThread:
    """Runs ``step(stop_event)`` repeatedly in a daemon thread until :meth:`stop`.

    ``step`` must return within a bounded time (it selects on the waker as well as its sockets),
    so :meth:`stop` -- set the event, wake, join -- always finishes.
    """

    def __init__(self, name: str, step: Callable[[threading.Event], None], waker: Waker) -> None:
        self._stop = threading.Event()
        self._step = step
        self._waker = waker
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self, timeout: float = 5.0) -> None:
        self._stop.set()
        self._waker.wake()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout)
            if self._thread.is_alive():
                log.error("%s did not stop within %.1f s", self._thread.name, timeout)

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self._step(self._stop)
            except Exception:  # a bug in one step must not silently kill the bus
                log.exception("%s: unexpected error; continuing", self._thread.name)


class FrameQueue:
    """Bounded queue of frames received from clients; overflow drops the new frame and counts it."""

    def __init__(self, maxsize: int, stats: StatsCounter) -> None:
        self._q: queue.Queue[can.Message] = queue.Queue(maxsize)
        self._stats = stats

    def put(self, msg: can.Message) -> None:
        try:
            self._q.put_nowait(msg)
            self._stats.add("received")
        except queue.Full:
            self._stats.add("dropped")

    def get(self, timeout: float | None) -> can.Message | None:
        try:
            if timeout is not None and timeout <= 0:
                return self._q.get_nowait()
            return self._q.get(timeout=timeout)
        except queue.Empty:
            return None
