"""python-can backend: any python-can interface as a bus, e.g. ``virtual`` (in-process, the CAN
loopback used by tests) or ``socketcan`` on hosts that have it.

The bridge's bus object is one node on that bus; clients are other python-can ``Bus`` objects on
the same channel (``can.Bus(interface="virtual", channel=...)`` in the same process), or real
nodes on a real bus.
"""

from __future__ import annotations

import time
from typing import Any, Self
from urllib.parse import quote

import can
from koala_bridge.drivers.messages import TransportClosedError, TransportError
from koala_bridge.drivers.transports.base import (
    CanTransport,
    Endpoint,
    StatsCounter,
    TransportStats,
    split_url,
)

__all__ = ["PythonCanTransport", "VirtualCanTransport", "python_can_url"]

_OFFLINE_POLL_S = 0.05


def python_can_url(interface: str, channel: str) -> str:
    """The registry URL of python-can ``interface`` on ``channel`` (the channel URL-quoted)."""
    return f"python-can://{interface}/{quote(str(channel), safe='')}"


class PythonCanTransport(CanTransport):
    """A python-can ``Bus`` behind the :class:`CanTransport` interface.

    Args:
        interface: python-can interface name (``virtual``, ``socketcan``, ...).
        channel: interface channel (``vcan0``, a virtual channel name, ...).
        **kwargs: passed to :class:`can.Bus` (bitrate, ...).
    """

    def __init__(self, interface: str, channel: str, **kwargs: Any) -> None:
        try:
            self._bus: can.BusABC | None = can.Bus(interface=interface, channel=channel, **kwargs)
        except (can.CanError, OSError, ValueError, ImportError) as e:
            raise TransportError(f"cannot open python-can {interface}:{channel}: {e}") from e
        self._interface = interface
        self._channel = channel
        self._offline = False
        self._stats = StatsCounter()

    @classmethod
    def from_url(cls, url: str, **options: Any) -> Self:
        """``python-can://INTERFACE/CHANNEL`` (:func:`python_can_url`); ``options`` are further
        :class:`can.Bus` arguments (host, port, bitrate, ...)."""
        parts = split_url(url)
        channel = parts.path.lstrip("/")
        if not parts.host or not channel:
            raise ValueError(f"{url!r}: expected python-can://INTERFACE/CHANNEL")
        options.setdefault("interface", parts.host)
        options.setdefault("channel", channel)
        return cls(**options)

    @property
    def endpoint(self) -> Endpoint:
        return Endpoint("python-can", channel=self._channel, interface=self._interface)

    @property
    def stats(self) -> TransportStats:
        return self._stats.snapshot()

    supports_offline = True

    def set_offline(self, offline: bool) -> None:
        self._b()
        self._offline = bool(offline)

    def send(self, msg: can.Message) -> None:
        if self._offline:
            self._b()
            self._stats.add("dropped")
            return
        try:
            self._b().send(msg, timeout=0.0)
        except can.CanOperationError:
            self._stats.add("dropped")
            return
        self._stats.add("sent")

    def recv(self, timeout: float | None = 0.0) -> can.Message | None:
        if self._offline:
            deadline = None if timeout is None else time.monotonic() + timeout
            while self._offline:  # what the other nodes send is lost; look again every 50 ms
                while self._b().recv(0.0) is not None:
                    pass
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    return None
                self._b().recv(_OFFLINE_POLL_S if left is None else min(left, _OFFLINE_POLL_S))
            timeout = None if deadline is None else max(0.0, deadline - time.monotonic())
        msg = self._b().recv(timeout)
        if msg is not None:
            self._stats.add("received")
        return msg

    def close(self) -> None:
        if self._bus is not None:
            self._bus.shutdown()
            self._bus = None

    def _b(self) -> can.BusABC:
        if self._bus is None:
            raise TransportClosedError("python-can transport is closed")
        return self._bus


class VirtualCanTransport(PythonCanTransport):
    """python-can's in-process ``virtual`` bus on ``channel``; clients open the same channel."""

    def __init__(self, channel: str = "koala", **kwargs: Any) -> None:
        super().__init__("virtual", channel, **kwargs)

    @classmethod
    def from_url(cls, url: str, **options: Any) -> Self:
        """``virtual://CHANNEL`` (default ``koala``)."""
        parts = split_url(url)
        options.setdefault("channel", parts.host or parts.path.lstrip("/") or "koala")
        return cls(**options)

    @property
    def endpoint(self) -> Endpoint:
        return Endpoint("virtual", channel=self._channel, interface="virtual")
