"""A socketcand server on loopback, so python-can's ``socketcand`` interface (and any socketcand
client) opens the simulated CAN bus unchanged.

Protocol subset (https://github.com/linux-can/socketcand, doc/protocol.md), ASCII over TCP, every
element ``< ... >``::

    server: < hi >                              on connect
    client: < open CHANNEL >     server: < ok >  (or < error could not open bus >)
    client: < rawmode >          server: < ok >
    server: < frame ID SECS.USECS DATA >        every bus frame, to every raw-mode client
                                                (SECS.USECS: the frame's ``timestamp`` as given
                                                to :meth:`SocketcandServer.send` -- the bridge
                                                gives simulation seconds, 0 included; frames
                                                from clients: host wall clock at reception)
    client: < send ID DLC B0 B1 ... >           a frame onto the bus (no reply when valid)
    client: < echo >             server: < echo >
    client: < bcmmode >          server: < ok >  (stops frame delivery to that client)

``ID`` is hex, 3 digits for a standard id and 8 for an extended one; ``DATA`` in ``frame`` is hex
without spaces; ``DLC`` and the bytes of ``send`` are hex. Malformed or unsupported elements are
counted as rejected and the connection stays open. Before ``rawmode`` they are answered
``< error TEXT >``, as the daemon does; in raw mode they get **no reply**: there ``< error ... >``
is an error *frame* (``< error CLASS SECS.USECS >``, socketcand's doc/protocol.md), and python-can
(4.6) parses every such element as one -- ``< error syntax ... >`` raised in its ``recv`` and,
left in its buffer, in every later ``recv``. The real daemon is silent about a malformed ``send``
too (state_raw.c logs it on its side only); it answers an unknown command ``< error unknown
command >``, which wedges python-can, so here that is silent as well.

Limits, so that no client can hold memory or slots the others need:

- everything queued for one client (frames and replies) is capped at ``max_pending`` bytes. A bus
  frame that does not fit is dropped for that client (counted ``dropped``; the client keeps its
  connection, as a CAN node that falls behind loses frames -- a python-can script that only
  sends never reads). A *reply* that does not fit means the client sends commands and does not
  read the answers: it is disconnected, counted ``dropped``, and logged.
- a connection that has not opened the bus within ``handshake_timeout_s`` is closed, counted
  ``rejected``.
- with ``max_clients`` connected, a new connection takes the place of the client idle longest if
  that one has been idle for ``idle_timeout_s``; the evicted client is counted ``rejected``. Idle
  means: it has neither put a frame on the bus (a valid ``< send >``) nor taken bus frames queued
  for it. An ``< echo >`` or any other chatter is not activity, so keep-alives cannot hold a slot.
  Else the newcomer gets ``< error too many clients >`` instead of ``< hi >`` and is closed
  (counted ``rejected``; python-can's ``CanError`` shows the element). Working clients never lose
  their connection to a newcomer.

python-can reads the handshake replies with one ``recv`` each, so after ``< ok >`` to
``rawmode`` frames for that client are held back for ``handshake_grace_s`` lest they arrive in
the same segment as the ``< ok >``.

Error frames: a python-can message with ``is_error_frame`` given to :meth:`SocketcandServer.send`
reaches raw-mode clients as ``< error CLASS SECS.USECS >`` -- what the daemon sends for a
SocketCAN error frame (src/state_raw.c: ``CLASS`` = ``can_id & CAN_EFF_MASK`` in hex, at least 3
digits, no data) and what python-can's socketcand client (4.6) turns back into a message with
``is_error_frame`` and the class in ``arbitration_id``. The error's data bytes do not travel.

Offline (:meth:`SocketcandServer.set_offline`, the fault ``disconnect``): every connection is
closed and the listening socket too, so a client sees its connection drop and a reconnect
refused (python-can's client retries connecting for 10 s) until the server is back online on
the same port.
"""

from __future__ import annotations

import logging
import re
import selectors
import socket
import threading
import time
from collections import deque
from typing import Any, Self

import can
from koala_bridge.drivers.messages import TransportClosedError, TransportError
from koala_bridge.drivers.transports._service import FrameQueue, ServiceThread, Waker
from koala_bridge.drivers.transports.base import (
    CanTransport,
    Endpoint,
    StatsCounter,
    TransportStats,
    listen_tcp,
    split_url,
)

__all__ = ["SocketcandServer", "format_error_element", "format_frame_element",
           "parse_send_element"]

log = logging.getLogger(__name__)

_HEX = re.compile(r"[0-9A-Fa-f]+")
_UNSUPPORTED = frozenset(
    {"add", "update", "delete", "filter", "subscribe", "unsubscribe", "controlmode", "isotpmode",
     "statistics", "muxfilter"}
)  # fmt: skip


def format_frame_element(msg: can.Message, timestamp: float) -> bytes:
    """``< frame ID SECS.USECS DATA >`` for one bus frame, as socketcand's raw mode sends it."""
    if msg.is_extended_id:
        can_id = f"{msg.arbitration_id & 0x1FFFFFFF:08X}"
    else:
        can_id = f"{msg.arbitration_id & 0x7FF:03X}"
    secs, usecs = _secs_usecs(timestamp)
    data = bytes(msg.data[: msg.dlc]).hex().upper()
    return f"< frame {can_id} {secs}.{usecs:06d} {data} >".encode("ascii")


def format_error_element(msg: can.Message, timestamp: float) -> bytes:
    """``< error CLASS SECS.USECS >`` for an error frame (``msg.is_error_frame``; the SocketCAN
    error class in ``arbitration_id``), as socketcand's raw mode sends it (module docstring)."""
    secs, usecs = _secs_usecs(timestamp)
    return f"< error {msg.arbitration_id & 0x1FFFFFFF:03X} {secs}.{usecs:06d} >".encode("ascii")


def _secs_usecs(timestamp: float) -> tuple[int, int]:
    secs = int(timestamp)
    usecs = int(round((timestamp - secs) * 1e6))
    if usecs >= 1_000_000:
        secs, usecs = secs + 1, usecs - 1_000_000
    return secs, usecs


def parse_send_element(words: list[str]) -> can.Message | str:
    """``["send", ID, DLC, B0, ...]`` -> a message, or the reason it is malformed."""
    if len(words) < 3:
        return "send needs an id and a dlc"
    id_s, dlc_s, byte_s = words[1], words[2], words[3:]
    if not _HEX.fullmatch(id_s) or len(id_s) > 8:
        return f"bad id {id_s!r}"
    extended = len(id_s) == 8  # socketcand's rule: 8 hex digits mean an extended id
    can_id = int(id_s, 16)
    if can_id > (0x1FFFFFFF if extended else 0x7FF):
        return f"id {id_s} out of range"
    if not _HEX.fullmatch(dlc_s) or int(dlc_s, 16) > 8:
        return f"bad dlc {dlc_s!r}"
    dlc = int(dlc_s, 16)
    if len(byte_s) != dlc or not all(_HEX.fullmatch(b) and len(b) <= 2 for b in byte_s):
        return f"dlc {dlc} needs {dlc} hex bytes, got {byte_s}"
    return can.Message(
        arbitration_id=can_id, is_extended_id=extended, data=bytes(int(b, 16) for b in byte_s)
    )


class _Client:
    __slots__ = ("sock", "mode", "inbuf", "outbuf", "held", "hold_until", "in_garbage", "events",
                 "open_deadline", "last_active", "frame_bytes", "closed", "blocked")  # fmt: skip

    def __init__(self, sock: socket.socket, now: float, handshake_timeout_s: float) -> None:
        self.sock = sock
        self.mode = "new"  # new -> bcm (after open) -> raw (after rawmode)
        self.inbuf = bytearray()
        self.outbuf = bytearray()
        self.held = bytearray()  # frames waiting for the end of the handshake grace period
        self.hold_until: float | None = None
        self.in_garbage = False
        self.events = selectors.EVENT_READ
        self.open_deadline: float | None = now + handshake_timeout_s  # None once the bus is open
        # Last frame it put on the bus or bus frames its socket took: chatter is not activity.
        self.last_active = now
        self.frame_bytes = 0  # bytes of bus frames in outbuf (approximate order with replies)
        self.closed = False
        self.blocked = False  # its socket refused the last send (it is not reading)

    @property
    def queued(self) -> int:
        """Bytes waiting to be sent to this client."""
        return len(self.outbuf) + len(self.held)


class SocketcandServer(CanTransport):
    """socketcand server for one CAN channel.

    Args:
        host / port: listening address; port 0 picks a free port (see :attr:`endpoint`).
        channel: the bus name clients must ``open`` (python-can's ``channel=``).
        max_clients: further connections are closed at once and counted as rejected.
        rx_queue: frames from clients waiting for :meth:`recv`; beyond it they are dropped.
        max_pending: per-client output bytes (frames and replies) kept for a slow client; beyond
            it frames are dropped, and a client whose reply does not fit is disconnected.
        max_element: longest ``< ... >`` element accepted, in bytes.
        handshake_grace_s: delay between ``< ok >`` to ``rawmode`` and the first frame.
        handshake_timeout_s: a connection that has not opened the bus by then is closed.
        idle_timeout_s: with ``max_clients`` connected, a newcomer evicts the client idle longest
            if it has been idle this long (see the module's docstring).
    """

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 0,
        channel: str = "can0",
        *,
        max_clients: int = 16,
        rx_queue: int = 1024,
        max_pending: int = 1 << 20,
        max_element: int = 256,
        handshake_grace_s: float = 0.05,
        handshake_timeout_s: float = 10.0,
        idle_timeout_s: float = 60.0,
    ) -> None:
        if not channel or any(c.isspace() or c in "<>" for c in channel):
            raise ValueError(f"invalid channel name {channel!r}")
        try:
            listener = listen_tcp(host, port, max_clients)
        except OSError as e:
            raise TransportError(f"cannot listen on {host}:{port}: {e}") from e
        self._listener = listener
        self._host, self._port = listener.getsockname()[:2]
        self.channel = channel
        self._max_clients = max_clients
        self._max_pending = max_pending
        self._max_element = max_element
        self._grace = handshake_grace_s
        self._handshake_timeout = handshake_timeout_s
        self._idle_timeout = idle_timeout_s
        self._peak_pending = 0
        self._stats = StatsCounter()
        self._rx = FrameQueue(rx_queue, self._stats)
        self._outbox: deque[tuple[bytes, _Client | None]] = deque()
        self._clients: dict[socket.socket, _Client] = {}
        # Whether any client is in raw mode (the service thread keeps it): without one a bus
        # frame goes to nobody, so send() neither formats it nor wakes the thread.
        self._any_raw = False
        self._waker = Waker()
        self._sel = selectors.DefaultSelector()
        self._sel.register(listener, selectors.EVENT_READ, None)
        self._sel.register(self._waker, selectors.EVENT_READ, self._waker)
        self._closed = False
        self._close_lock = threading.Lock()
        self._stepped = threading.Condition()   # notified after every service-thread step
        self._offline = False           # applied by the service thread (_apply_offline)
        self._want_offline = False
        # Client state (buffers, modes, the client table) is changed by the service thread and,
        # for bus frames, by send(): one lock for both (never held while waiting in select).
        self._io_lock = threading.Lock()
        self._thread = ServiceThread(f"socketcand:{self._port}", self._step, self._waker)
        self._thread.start()

    @classmethod
    def from_url(cls, url: str, **options: Any) -> Self:
        """``socketcand://HOST:PORT/CHANNEL`` (defaults 127.0.0.1, 0 = a free port, ``can0``)."""
        parts = split_url(url)
        options.setdefault("host", parts.host or "127.0.0.1")
        options.setdefault("port", 0 if parts.port is None else parts.port)
        options.setdefault("channel", parts.path.lstrip("/") or "can0")
        return cls(**options)

    # ----------------------------------------------------------------- CanTransport

    @property
    def endpoint(self) -> Endpoint:
        return Endpoint("socketcand", host=self._host, port=self._port, channel=self.channel)

    @property
    def stats(self) -> TransportStats:
        """Counters; ``clients`` counts the clients in raw mode, the ones that receive the bus's
        frames: a client that has connected but not yet sent ``open`` and ``rawmode`` would miss
        every frame sent meanwhile (``replay --wait-clients`` waits on this)."""
        clients = list(self._clients.values())  # a copy: the service thread adds and drops
        return self._stats.snapshot(clients=sum(1 for c in clients if c.mode == "raw"))

    @property
    def peak_pending(self) -> int:
        """The most bytes ever queued for one client at once; never above ``max_pending``."""
        return self._peak_pending

    supports_offline = True

    def set_offline(self, offline: bool) -> None:
        """Drop every client and stop listening (``True``), or listen again on the same port
        (``False``); returns once the service thread has done it. :class:`TransportError` if
        the port cannot be bound again."""
        if self._closed:
            raise TransportClosedError("socketcand server is closed")
        self._want_offline = offline
        deadline = time.monotonic() + 5.0
        with self._stepped:  # held from the check to the wait: no step's notify is missed
            while self._offline != offline and self._want_offline == offline:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    break
                self._waker.wake()
                self._stepped.wait(remaining)
        if self._offline != offline:
            raise TransportError(f"socketcand: cannot listen on {self._host}:{self._port} "
                                 "again")

    def send(self, msg: can.Message) -> None:
        if self._closed:
            raise TransportClosedError("socketcand server is closed")
        if self._offline or self._want_offline:
            self._stats.add("dropped")
            return
        self._stats.add("sent")
        if not self._any_raw:  # nobody receives bus frames (the thread would discard it)
            return
        # The sender's time stamp as it is: the bridge's frames carry their sample's simulation
        # time, which is 0.0 at the first step (a wall-clock fallback for 0 made those frames
        # jump to the epoch time).
        line = (format_error_element if msg.is_error_frame else format_frame_element)(
            msg, msg.timestamp)
        # Straight onto the clients' sockets from the sender's thread: handing the frame to the
        # service thread cost a thread switch, and the sender usually holds the GIL on (the
        # bridge's loop goes on encoding), so the frame waited for it. What a socket does not
        # take at once stays queued for the service thread, which is woken for it.
        with self._io_lock:
            if self._closed:
                raise TransportClosedError("socketcand server is closed")
            self._outbox.append((line, None))
            self._distribute()
            backlog = False
            for client in list(self._clients.values()):
                # A socket error is left to the service thread: it reads what the client sent
                # before it went (a last < send >) and then drops it.
                self._flush(client, drop_on_error=False)
                backlog = backlog or bool(client.outbuf)
        if backlog:
            self._waker.wake()

    def sync(self, timeout: float) -> bool:
        """Block until every frame sent so far has been handed to the clients' sockets (or
        could not be: a client that does not read keeps its queue); False on ``timeout``. In
        lockstep the bridge calls this before it answers the firmware's cycle message, so that
        every frame of the cycle is readable when the answer is."""
        deadline = time.monotonic() + timeout
        with self._stepped:
            while True:
                if self._closed:
                    return False
                clients = list(self._clients.values())
                if not self._outbox and not any(
                        c.outbuf and not c.blocked for c in clients if c.mode == "raw"):
                    return True
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                self._waker.wake()
                self._stepped.wait(min(remaining, 0.05))

    def recv(self, timeout: float | None = 0.0) -> can.Message | None:
        if self._closed:
            raise TransportClosedError("socketcand server is closed")
        return self._rx.get(timeout)

    def close(self) -> None:
        with self._close_lock:
            if self._closed:
                return
            self._closed = True
        self._thread.stop()
        with self._io_lock:
            for client in list(self._clients.values()):
                client.sock.close()
            self._clients.clear()
        self._sel.close()
        self._listener.close()
        self._waker.close()

    # ----------------------------------------------------------------- service thread

    def _step(self, stop: threading.Event) -> None:
        with self._io_lock:
            timeout = self._timeout()
        events = self._sel.select(timeout)
        with self._io_lock:
            if not self._closed:
                self._handle(events, stop)

    def _handle(self, events: list[tuple[selectors.SelectorKey, int]],
                stop: threading.Event) -> None:
        for key, mask in events:
            if stop.is_set():
                return
            if key.fileobj is self._listener:
                self._accept()
            elif key.data is self._waker:
                self._waker.drain()
            else:
                client: _Client = key.data
                if client.closed:  # evicted by an accept earlier in this batch
                    continue
                if mask & selectors.EVENT_READ:
                    self._on_readable(client)
                if mask & selectors.EVENT_WRITE and client.sock in self._clients:
                    self._flush(client)
        self._distribute()
        self._release_held()
        self._expire_handshakes()
        for client in list(self._clients.values()):
            self._flush(client)
            self._update_interest(client)
        if self._want_offline != self._offline:
            self._apply_offline(self._want_offline)
        with self._stepped:
            self._stepped.notify_all()

    def _apply_offline(self, offline: bool) -> None:
        if offline:
            for client in list(self._clients.values()):
                self._drop(client)
            self._outbox.clear()
            self._sel.unregister(self._listener)
            self._listener.close()
            self._offline = True
            log.info("socketcand %s:%d: offline", self._host, self._port)
            return
        try:
            listener = listen_tcp(self._host, self._port, self._max_clients)
        except OSError as e:
            self._want_offline = True  # stays offline; set_offline reports it
            log.error("socketcand: cannot listen on %s:%d again: %s", self._host, self._port, e)
            return
        self._listener = listener
        self._sel.register(listener, selectors.EVENT_READ, None)
        self._offline = False
        log.info("socketcand %s:%d: online again", self._host, self._port)

    def _timeout(self) -> float | None:
        deadlines = [
            t
            for c in self._clients.values()
            for t in (c.hold_until, c.open_deadline)
            if t is not None
        ]
        return max(0.0, min(deadlines) - time.monotonic()) if deadlines else None

    def _accept(self) -> None:
        while True:
            try:
                sock, _ = self._listener.accept()
            except (BlockingIOError, OSError):
                return
            if len(self._clients) >= self._max_clients and not self._evict_idle():
                self._stats.add("rejected")  # before the reply: the client may look at once
                try:  # a fresh socket's buffer is empty: this does not block
                    sock.setblocking(False)
                    sock.send(b"< error too many clients >")
                except OSError:
                    pass
                sock.close()
                log.warning("socketcand: %d clients connected, refused one more",
                            len(self._clients))
                continue
            sock.setblocking(False)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            client = _Client(sock, time.monotonic(), self._handshake_timeout)
            self._clients[sock] = client
            self._sel.register(sock, selectors.EVENT_READ, client)
            self._reply(client, b"< hi >")

    def _on_readable(self, client: _Client) -> None:
        try:
            data = client.sock.recv(4096)
        except BlockingIOError:
            return
        except OSError:
            data = b""
        if not data:
            self._drop(client)
            return
        client.inbuf += data
        self._parse(client)

    def _parse(self, client: _Client) -> None:
        buf = client.inbuf
        while buf and not client.closed:
            start = buf.find(b"<")
            junk = buf if start < 0 else buf[:start]
            if junk.strip():
                self._reject(client, "data outside < >")
            if start < 0:
                buf.clear()
                return
            del buf[:start]
            end = buf.find(b">")
            if end < 0:
                if len(buf) > self._max_element:
                    buf.clear()
                    self._error(client, "element too long")
                return
            element = bytes(buf[1:end])
            del buf[: end + 1]
            nested = element.rfind(b"<")
            if nested >= 0:  # "< sen< send ... >": the first element was cut short
                self._reject(client, "unterminated element")
                element = element[nested + 1 :]
            client.in_garbage = False
            self._on_element(client, element)

    def _on_element(self, client: _Client, element: bytes) -> None:
        try:
            words = element.decode("ascii").split()
        except UnicodeDecodeError:
            words = []
        if not words:
            self._error(client, "syntax error")
            return
        command = words[0]
        if client.mode == "new":
            if command == "open" and len(words) == 2 and words[1] == self.channel:
                client.mode = "bcm"
                client.open_deadline = None
                self._reply(client, b"< ok >")
            elif command == "open":
                self._error(client, "could not open bus")
            else:
                self._error(client, "open a bus first")
        elif command == "send":
            result = parse_send_element(words)
            if isinstance(result, str):
                self._error(client, f"syntax error: {result}")
                return
            client.last_active = time.monotonic()
            result.timestamp = time.time()
            result.channel = self.channel
            self._rx.put(result)
            # Other nodes on a CAN bus see the frame too.
            self._outbox.append((format_frame_element(result, result.timestamp), client))
        elif command == "rawmode" and len(words) == 1:
            client.mode = "raw"
            client.hold_until = time.monotonic() + self._grace
            self._any_raw = True
            self._reply(client, b"< ok >")
        elif command == "bcmmode" and len(words) == 1:
            client.mode = "bcm"
            client.held.clear()
            client.hold_until = None
            self._recount_raw()
            self._reply(client, b"< ok >")
        elif command == "echo" and len(words) == 1:
            self._reply(client, b"< echo >")
        elif command in _UNSUPPORTED:
            self._error(client, f"{command} not supported")
        else:
            self._error(client, "unknown command")

    def _distribute(self) -> None:
        while self._outbox:
            line, origin = self._outbox.popleft()
            for client in self._clients.values():
                if client is origin or client.mode != "raw":
                    continue
                target = client.held if client.hold_until is not None else client.outbuf
                if client.queued + len(line) > self._max_pending:
                    self._stats.add("dropped")
                    continue
                target += line
                if target is client.outbuf:
                    client.frame_bytes += len(line)
                self._peak_pending = max(self._peak_pending, client.queued)

    def _release_held(self) -> None:
        now = time.monotonic()
        for client in self._clients.values():
            if client.hold_until is not None and now >= client.hold_until:
                client.outbuf += client.held
                client.frame_bytes += len(client.held)
                client.held.clear()
                client.hold_until = None

    def _expire_handshakes(self) -> None:
        now = time.monotonic()
        for client in list(self._clients.values()):
            if client.open_deadline is not None and now >= client.open_deadline:
                log.warning("socketcand client %s: bus not opened within %.3g s; disconnected",
                            client.sock.fileno(), self._handshake_timeout)
                self._stats.add("rejected")
                self._drop(client)

    def _evict_idle(self) -> bool:
        """Disconnect the client idle longest if idle for ``idle_timeout_s``; True if one was."""
        if not self._clients:
            return False
        idlest = min(self._clients.values(), key=lambda c: c.last_active)
        idle_s = time.monotonic() - idlest.last_active
        if idle_s < self._idle_timeout:
            return False
        log.warning("socketcand: %d clients connected; client %s, idle for %.3g s, disconnected "
                    "for a new one", len(self._clients), idlest.sock.fileno(), idle_s)
        self._stats.add("rejected")
        self._drop(idlest)
        return True

    def _reply(self, client: _Client, element: bytes) -> None:
        if client.closed:
            return
        if client.queued + len(element) > self._max_pending:
            # It sends commands and does not read the answers: its queue would grow forever.
            log.warning("socketcand client %s: %d bytes of output not read; disconnected",
                        client.sock.fileno(), client.queued)
            self._stats.add("dropped")
            self._drop(client)
            return
        client.outbuf += element
        self._peak_pending = max(self._peak_pending, client.queued)
        self._flush(client)

    def _error(self, client: _Client, text: str) -> None:
        self._reject(client, text)
        if client.mode != "raw":  # in raw mode "< error ... >" is an error frame: see the top
            self._reply(client, f"< error {text} >".encode("ascii", "replace"))

    def _reject(self, client: _Client, why: str) -> None:
        if client.in_garbage and why == "data outside < >":
            return  # one run of junk is one reject
        client.in_garbage = why == "data outside < >"
        self._stats.add("rejected")
        log.debug("socketcand client %s: rejected input (%s)", client.sock.fileno(), why)

    def _flush(self, client: _Client, drop_on_error: bool = True) -> None:
        if not client.outbuf or client.sock not in self._clients:
            return
        try:
            sent = client.sock.send(client.outbuf)
        except BlockingIOError:
            client.blocked = True       # its socket is full: it is not reading
            return
        except OSError:
            if drop_on_error:
                self._drop(client)
            return
        client.blocked = False
        if sent and client.frame_bytes:
            client.last_active = time.monotonic()
            client.frame_bytes = max(0, client.frame_bytes - sent)
        del client.outbuf[:sent]

    def _update_interest(self, client: _Client) -> None:
        if client.sock not in self._clients:
            return
        want = selectors.EVENT_READ | (selectors.EVENT_WRITE if client.outbuf else 0)
        if want != client.events:
            self._sel.modify(client.sock, want, client)
            client.events = want

    def _recount_raw(self) -> None:
        self._any_raw = any(c.mode == "raw" for c in self._clients.values())

    def _drop(self, client: _Client) -> None:
        client.closed = True
        if self._clients.pop(client.sock, None) is not None:
            self._sel.unregister(client.sock)
            self._recount_raw()
        client.sock.close()
        client.inbuf.clear()
        client.outbuf.clear()
        client.held.clear()
