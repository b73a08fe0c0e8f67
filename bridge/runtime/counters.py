"""Per-bus frame counters: sent, received, rejected. Published in ``status`` on Zenoh.

A bus is counted under a stable name (``kteam``, ``rangefinders``, ``can.socketcand``,
``can.slcan``, ``can.virtual``, ``mavlink``, ...). Transports and readers on several threads
count into one :class:`BusCounters`; every method is thread-safe.

- ``sent``: frames (or replies) the bridge wrote to the bus;
- ``received``: well-formed frames read from the bus and acted upon;
- ``rejected``: input that was read and discarded — bytes that are not a frame, a frame with a bad
  checksum or length, an unknown command or CAN id. A rejected input changes nothing else.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

KINDS = ("sent", "received", "rejected")


@dataclass
class _Count:
    sent: int = 0
    received: int = 0
    rejected: int = 0


class BusCounters:
    """Thread-safe counters of frames sent, received and rejected, per bus name."""

    def __init__(self, buses: tuple[str, ...] | list[str] = ()) -> None:
        self._lock = threading.Lock()
        self._counts: dict[str, _Count] = {name: _Count() for name in buses}

    def add(self, bus: str, kind: str, n: int = 1) -> None:
        """Add ``n`` to counter ``kind`` (one of :data:`KINDS`) of ``bus``."""
        if kind not in KINDS:
            raise ValueError(f"counter kind must be one of {KINDS}, got {kind!r}")
        with self._lock:
            count = self._counts.setdefault(bus, _Count())
            setattr(count, kind, getattr(count, kind) + n)

    def sent(self, bus: str, n: int = 1) -> None:
        self.add(bus, "sent", n)

    def received(self, bus: str, n: int = 1) -> None:
        self.add(bus, "received", n)

    def rejected(self, bus: str, n: int = 1) -> None:
        self.add(bus, "rejected", n)

    def snapshot(self) -> dict[str, dict[str, int]]:
        """A copy: ``{bus: {"sent": n, "received": n, "rejected": n}}``, buses sorted by name."""
        with self._lock:
            return {
                name: {"sent": c.sent, "received": c.received, "rejected": c.rejected}
                for name, c in sorted(self._counts.items())
            }
