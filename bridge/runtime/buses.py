"""Open the transports the configuration asks for, and close them all again.

:func:`bus_urls` maps ``[buses]`` settings to transport URLs (pty, UDP, TCP, socketcand,
slcan-on-a-pty, python-can), and the transport registry (:mod:`koala_bridge.drivers.transports`)
opens them -- the same registry the real-robot source and the tests open their ports with.
:class:`OpenBuses` holds what was opened; if opening one fails, everything opened before it is
closed and the error names the bus.

Byte transports are not safe to use from two threads at once (a write may flush data held back
for a slow client while a read does the same), so each is wrapped in :class:`LockedByteLink`:
the simulation loop writes while a reader thread reads.
"""

from __future__ import annotations

import errno
import logging
import select
import threading
import time
from dataclasses import dataclass, field
from urllib.parse import quote

from koala_bridge.drivers.messages import TransportError
from koala_bridge.drivers.transports import open_byte_transport, open_can_transport
from koala_bridge.drivers.transports.base import ByteTransport, CanTransport, TransportStats
from koala_bridge.drivers.transports.pythoncan import python_can_url
from koala_bridge.runtime.settings import BusesSettings

log = logging.getLogger(__name__)

HANGUP_RETRY_S = 0.02   # how often a reader re-checks a pty nobody has opened yet


class BusOpenError(TransportError):
    """A bus could not be opened; the message names the bus and the cause."""


class LockedByteLink:
    """A :class:`ByteTransport` used by several threads: every call into it is serialised.

    :meth:`wait` does not hold the lock while it blocks: where the transport has a ``fileno``
    it polls that descriptor with a poll object of its own (a transport's internal poll object
    may not be used by two threads at once), so the simulation loop can write and read counters
    while a reader thread waits for input.
    """

    def __init__(self, transport: ByteTransport) -> None:
        self.transport = transport
        self._lock = threading.Lock()
        fileno = getattr(transport, "fileno", None)
        self._poll: select.poll | None = None
        if fileno is not None:
            self._poll = select.poll()
            self._poll.register(fileno(), select.POLLIN)

    @property
    def is_datagram(self) -> bool:
        return self.transport.is_datagram

    @property
    def client_session(self) -> int:
        """The transport's :attr:`ByteTransport.client_session` (an int: read without the lock)."""
        return self.transport.client_session

    def read(self, max_bytes: int = 65536) -> bytes:
        with self._lock:
            return self.transport.read(max_bytes)

    def write(self, data: bytes) -> int:
        with self._lock:
            return self.transport.write(data)

    def has_client(self) -> bool:
        """Whether a client is connected, where the transport can tell (a pty); True where it
        cannot (UDP, TCP servers count their own clients)."""
        probe = getattr(self.transport, "has_client", None)
        if probe is None:
            return True
        with self._lock:
            return bool(probe())

    def wait(self, timeout: float) -> bool:
        """Block until input may be waiting or ``timeout`` s pass; True if readable."""
        if self._poll is None:
            with self._lock:
                return self.transport.wait(timeout)
        events = self._poll.poll(int(timeout * 1000))
        if any(ev & select.POLLIN for _, ev in events):
            return True
        if events:  # a pty with no client reports hang-up at once: do not spin on it,
            has_client = getattr(self.transport, "has_client", None)
            if has_client is not None:  # but let it see the hang-up now (the session ends)
                with self._lock:
                    has_client()
            time.sleep(min(timeout, HANGUP_RETRY_S))
        return False

    @property
    def stats(self) -> TransportStats:
        with self._lock:
            return self.transport.stats

    def set_offline(self, offline: bool) -> None:
        """The transport's ``set_offline`` (fault ``disconnect``, runtime/faults.py), under the
        lock. A pty keeps its descriptor number, so the poll above stays valid."""
        with self._lock:
            self.transport.set_offline(offline)

    def close(self) -> None:
        with self._lock:
            self.transport.close()


@dataclass
class OpenBuses:
    """Every transport the bridge serves, by bus name (the names used in ``status``)."""

    kteam: LockedByteLink | None = None
    rangefinders: LockedByteLink | None = None
    mavlink: LockedByteLink | None = None
    can: dict[str, CanTransport] = field(default_factory=dict)

    def byte_links(self) -> dict[str, LockedByteLink]:
        links = {"kteam": self.kteam, "rangefinders": self.rangefinders, "mavlink": self.mavlink}
        return {name: link for name, link in links.items() if link is not None}

    def stats(self) -> dict[str, TransportStats]:
        out = {name: link.stats for name, link in self.byte_links().items()}
        out.update({name: t.stats for name, t in self.can.items()})
        return out

    def close(self) -> None:
        """Close every transport (each one even if another fails)."""
        closables: list[tuple[str, LockedByteLink | CanTransport]] = [
            *self.byte_links().items(),
            *self.can.items(),
        ]
        for name, closable in closables:
            try:
                closable.close()
            except Exception:  # closing must go on for the others
                log.exception("closing %s failed", name)
        self.kteam = self.rangefinders = self.mavlink = None
        self.can.clear()


#: The configuration key that moves a bus to another port, for the "port in use" hint.
PORT_KEYS = {"mavlink": "buses.mavlink.port", "can.socketcand": "buses.can.socketcand_port"}


def address_in_use(e: BaseException) -> bool:
    """Whether ``e`` (or an exception it was raised from) says the address is already in use."""
    seen: BaseException | None = e
    while seen is not None:
        if isinstance(seen, OSError) and seen.errno == errno.EADDRINUSE:
            return True
        if "address already in use" in str(seen).lower():
            return True
        seen = seen.__cause__
    return False


def bus_urls(settings: BusesSettings) -> dict[str, str]:
    """The transport URL of every enabled bus of ``settings``, by bus name, in opening order
    (:mod:`koala_bridge.drivers.transports` opens them)."""
    urls: dict[str, str] = {}
    if settings.kteam:
        urls["kteam"] = "pty://"
    if settings.rangefinders:
        urls["rangefinders"] = "pty://"
    mav = settings.mavlink
    if mav.enabled:
        urls["mavlink"] = (
            "pty://" if mav.transport == "pty" else f"{mav.transport}://{mav.host}:{mav.port}"
        )
        if mav.transport == "udp" and mav.port == 0:
            # a free port the bridge listens on; it answers the client that sends to it
            urls["mavlink"] = f"udpin://{mav.host}:0"
        elif mav.transport == "udp":  # one bridge per ground-station port (docs/security.md)
            urls["mavlink"] += "?exclusive=1"
    can = settings.can
    if can.socketcand:
        urls["can.socketcand"] = (
            f"socketcand://{can.socketcand_host}:{can.socketcand_port}/{quote(can.channel)}"
        )
    if can.slcan:
        urls["can.slcan"] = "slcan://"
    if can.virtual:
        urls["can.virtual"] = f"virtual:///{quote(can.virtual_channel)}"
    if can.socketcan:
        urls["can.socketcan"] = python_can_url("socketcan", can.socketcan_channel)
    return urls


def open_bus(name: str, url: str) -> ByteTransport | CanTransport:
    """Open bus ``name`` at ``url`` through the transport registry; a failure raises
    :class:`BusOpenError` naming the bus (and, for a port in use, the key that moves it)."""
    try:
        if name.startswith("can."):
            return open_can_transport(url)
        return open_byte_transport(url)
    except (TransportError, OSError) as e:
        hint = ""
        if name in PORT_KEYS and address_in_use(e):
            hint = (
                f" (another koala-bridge running? --set {PORT_KEYS[name]}=N picks another "
                "port, 0 any free one)"
            )
        raise BusOpenError(f"cannot open bus {name}: {e}{hint}") from e


def open_buses(settings: BusesSettings) -> OpenBuses:
    """Open every enabled bus of ``settings``; on failure close what was opened and raise."""
    buses = OpenBuses()
    for what in settings.exposure():  # refused unless [run] allow_non_loopback (settings.py)
        log.warning("%s, reachable from the network ([run] allow_non_loopback)", what)
    try:
        for name, url in bus_urls(settings).items():
            transport = open_bus(name, url)
            if isinstance(transport, CanTransport):
                buses.can[name] = transport
            else:
                setattr(buses, name, LockedByteLink(transport))
    except BaseException:
        buses.close()
        raise
    return buses
