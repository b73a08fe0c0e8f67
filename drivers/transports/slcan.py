"""An slcan (LAWICEL CAN-USB ASCII) adapter emulated on a pty, so python-can's ``slcan``
interface -- or slcand, or any LAWICEL tool -- opens the pty path as it opens a USB-CAN adapter.

Commands end with CR; a successful command is answered CR (plus data for queries), a refused one
BELL (0x07)::

    O / L / C       open / open listen-only / close the channel      -> CR
    Sn / sXXYY      bit rate (n = 0..9) / BTR registers, channel closed -> CR (BELL if open)
    V / v / N       hardware+software version / version / serial number -> "V1013" CR ...
    F               status flags                                       -> "F00" CR
    Zn              receive time stamps off (0) / on (1)               -> CR
    Mxxxxxxxx / mxxxxxxxx  acceptance code / mask (accepted, ignored)   -> CR
    tIIILDD..       standard frame, L = 0..8 data bytes in hex          -> "z" CR
    TIIIIIIIILDD..  extended frame                                      -> "Z" CR
    rIIIL / RIIIIIIIIL  remote frames                                   -> "z" / "Z" CR

Frames on the bus reach the client as ``tIIILDD..`` / ``TIIIIIIIILDD..`` (+ 4 hex digits of
milliseconds when time stamps are on) and CR, only while the channel is open. CAN FD commands
(``d``, ``D``, ``b``, ``B``) and anything else are refused with BELL and counted as rejected.
Output a client does not read (frames and replies alike) is dropped whole past the pty's 64 KiB
and counted as dropped. The LAWICEL protocol has no error frames: :meth:`SlcanAdapter.send`
skips a python-can error frame (``is_error_frame``), counted neither sent nor dropped (the fault
injector counts the faults, docs/faults.md). :meth:`SlcanAdapter.set_offline` is the pty's
(:class:`PtyTransport`): the port hangs up and comes back as a new pty at the same symlink,
with the channel closed, as a re-plugged adapter.
"""

from __future__ import annotations

import re
import select
import threading
import time
from pathlib import Path
from typing import Any, Self

import can
from koala_bridge.drivers.kteam import LineSplitter
from koala_bridge.drivers.messages import Reject, TransportClosedError
from koala_bridge.drivers.transports._service import FrameQueue, ServiceThread, Waker
from koala_bridge.drivers.transports.base import (
    CanTransport,
    Endpoint,
    StatsCounter,
    TransportStats,
    split_url,
)
from koala_bridge.drivers.transports.pty import PtyTransport

__all__ = ["SlcanAdapter", "format_slcan_frame", "parse_slcan_frame"]

OK = b"\r"
BELL = b"\a"
_FRAME = re.compile(r"(?P<kind>[tTrR])(?P<id>[0-9A-Fa-f]+)")
_HEXDIGITS = re.compile(r"[0-9A-Fa-f]*")
_NO_CLIENT_POLL_S = 0.02


def format_slcan_frame(msg: can.Message, timestamp_ms: int | None = None) -> bytes:
    """``tIIILDD..`` / ``TIIIIIIIILDD..`` (``r``/``R`` for remote) + optional time stamp + CR."""
    if msg.is_remote_frame:
        head = f"R{msg.arbitration_id:08X}" if msg.is_extended_id else f"r{msg.arbitration_id:03X}"
        text = f"{head}{msg.dlc:d}"
    else:
        head = f"T{msg.arbitration_id:08X}" if msg.is_extended_id else f"t{msg.arbitration_id:03X}"
        text = f"{head}{msg.dlc:d}{bytes(msg.data[: msg.dlc]).hex().upper()}"
    if timestamp_ms is not None:
        text += f"{timestamp_ms % 60000:04X}"
    return text.encode("ascii") + OK


def parse_slcan_frame(line: str) -> can.Message | str:
    """Parse a client's ``t``/``T``/``r``/``R`` transmit; returns the reason if malformed."""
    kind = line[:1]
    if kind not in ("t", "T", "r", "R"):  # not `in "tTrR"`: "" is in every string
        return "not a frame command"
    id_len = 8 if kind in "TR" else 3
    if len(line) < 1 + id_len + 1 or not _HEXDIGITS.fullmatch(line[1:]):
        return "malformed frame command"
    can_id = int(line[1 : 1 + id_len], 16)
    if can_id > (0x1FFFFFFF if id_len == 8 else 0x7FF):
        return "id out of range"
    dlc_char = line[1 + id_len]
    if not dlc_char.isdigit() or int(dlc_char) > 8:
        return "dlc must be 0..8"
    dlc = int(dlc_char)
    payload = line[2 + id_len :]
    remote = kind in "rR"
    if (remote and payload) or (not remote and len(payload) != 2 * dlc):
        return f"dlc {dlc} does not match {len(payload) // 2} data bytes"
    return can.Message(
        arbitration_id=can_id,
        is_extended_id=id_len == 8,
        is_remote_frame=remote,
        dlc=dlc,
        data=None if remote else bytes.fromhex(payload),
    )


class SlcanAdapter(CanTransport):
    """A LAWICEL adapter on a pty.

    Args:
        link: optional stable symlink to the pty slave (see :class:`PtyTransport`).
        version: the 4 digits answered to ``V`` (hardware 2 + software 2).
        serial_number: the 4 characters answered to ``N``.
        rx_queue: client frames waiting for :meth:`recv`; beyond it they are dropped.
    """

    def __init__(
        self,
        link: str | Path | None = None,
        *,
        version: str = "1013",
        serial_number: str = "KOAL",
        rx_queue: int = 1024,
    ) -> None:
        if len(version) != 4 or not version.isdigit() or len(serial_number) != 4:
            raise ValueError("version must be 4 digits and serial_number 4 characters")
        self._pty = PtyTransport(link)
        self._version = version
        self._serial = serial_number
        self._stats = StatsCounter()
        self._rx = FrameQueue(rx_queue, self._stats)
        self._lines = LineSplitter(max_line=64)
        self._session = self._pty.client_session
        self._lock = threading.Lock()  # guards channel state and pty writes across threads
        self._open = False
        self._listen_only = False
        self._timestamps = False
        self._epoch = time.monotonic()
        self._closed = False
        self._waker = Waker()
        self._thread = ServiceThread(f"slcan:{self._pty.slave_path}", self._step, self._waker)
        self._thread.start()

    # ----------------------------------------------------------------- CanTransport

    @classmethod
    def from_url(cls, url: str, **options: Any) -> Self:
        """``slcan://`` (a new pty) or ``slcan:///PATH`` (plus a symlink at PATH)."""
        path = split_url(url).path
        if path:
            options.setdefault("link", path)
        return cls(**options)

    @property
    def endpoint(self) -> Endpoint:
        return Endpoint("slcan", path=self._pty.endpoint.path)

    @property
    def stats(self) -> TransportStats:
        return self._stats.snapshot(clients=1 if self._open else 0)

    @property
    def is_open(self) -> bool:
        """True while the client has the CAN channel open (after ``O`` or ``L``)."""
        return self._open

    supports_offline = True

    @property
    def offline(self) -> bool:
        return self._pty.offline

    def set_offline(self, offline: bool) -> None:
        if self._closed:
            raise TransportClosedError("slcan adapter is closed")
        with self._lock:
            self._pty.set_offline(offline)
            self._client_gone()
            self._session = self._pty.client_session
        self._waker.wake()

    def send(self, msg: can.Message) -> None:
        if self._closed:
            raise TransportClosedError("slcan adapter is closed")
        if msg.is_error_frame:  # LAWICEL has none (module docstring)
            return
        with self._lock:
            if not self._open:
                self._stats.add("dropped")
                return
            stamp = int((time.monotonic() - self._epoch) * 1000) if self._timestamps else None
            accepted = self._pty.write(format_slcan_frame(msg, stamp))
        self._stats.add("sent" if accepted else "dropped")

    def recv(self, timeout: float | None = 0.0) -> can.Message | None:
        if self._closed:
            raise TransportClosedError("slcan adapter is closed")
        return self._rx.get(timeout)

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
        self._thread.stop()
        self._pty.close()
        self._waker.close()

    # ----------------------------------------------------------------- service thread

    def _step(self, stop: threading.Event) -> None:
        if not self._pty.has_client():
            # A pty master reports hang-up continuously while no client has the port open, so
            # wait on the waker alone and look again shortly.
            with self._lock:
                self._client_gone()
            if select.select([self._waker], [], [], _NO_CLIENT_POLL_S)[0]:
                self._waker.drain()
            return
        fd = self._pty.fileno()
        timeout = _NO_CLIENT_POLL_S if self._pty.pending else None
        readable, _, _ = select.select([fd, self._waker.fileno()], [], [], timeout)
        if self._waker.fileno() in readable:
            self._waker.drain()
        if stop.is_set():
            return
        with self._lock:
            self._pty.flush()
            if fd in readable:
                data = self._pty.read()
                if self._pty.client_session != self._session:  # the last client's input is read
                    self._session = self._pty.client_session
                    self._client_gone()
                for item in self._lines.feed(data):
                    if not self._pty.write(self._on_command(item)):
                        # Past the pty's cap: the client sends commands and does not read.
                        self._stats.add("dropped")

    def _client_gone(self) -> None:
        # The port was closed (with or without "C"): forget the session, as a re-plugged
        # adapter would.
        self._open = False
        self._timestamps = False
        self._lines.reset()

    def _on_command(self, item: bytes | Reject) -> bytes:
        if isinstance(item, Reject):
            return self._refuse()
        try:
            line = item.decode("ascii")
        except UnicodeDecodeError:
            return self._refuse()
        cmd, arg = line[:1], line[1:]
        if cmd in "tTrR":
            return self._on_frame(line)
        if cmd in ("O", "L") and not arg:
            self._open, self._listen_only = True, cmd == "L"
            return OK
        if cmd == "C" and not arg:
            self._open = False
            return OK
        if cmd == "S" and arg.isdigit() and len(arg) == 1:
            return OK if not self._open else self._refuse()
        if cmd == "s" and len(arg) == 4 and _HEXDIGITS.fullmatch(arg):
            return OK if not self._open else self._refuse()
        if cmd == "V" and not arg:
            return f"V{self._version}".encode("ascii") + OK
        if cmd == "v" and not arg:
            return f"v{self._version}".encode("ascii") + OK
        if cmd == "N" and not arg:
            return f"N{self._serial}".encode("ascii") + OK
        if cmd == "F" and not arg:
            return b"F00" + OK
        if cmd == "Z" and arg in ("0", "1"):
            self._timestamps = arg == "1"
            return OK
        if cmd in ("M", "m") and len(arg) == 8 and _HEXDIGITS.fullmatch(arg):
            return OK
        return self._refuse()

    def _on_frame(self, line: str) -> bytes:
        if not self._open or self._listen_only:
            return self._refuse()
        result = parse_slcan_frame(line)
        if isinstance(result, str):
            return self._refuse()
        result.timestamp = time.time()
        result.channel = self.endpoint.path
        self._rx.put(result)
        return (b"Z" if result.is_extended_id else b"z") + OK

    def _refuse(self) -> bytes:
        self._stats.add("rejected")
        return BELL
