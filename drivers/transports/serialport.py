"""Serial-port backend: a real device (``/dev/ttyUSB0``) or any pyserial URL, opened as a client.

``serial:PORT`` where PORT is what :func:`serial.serial_for_url` takes: a device path
(``serial:///dev/ttyUSB0`` or ``serial:/dev/ttyUSB0``) or a pyserial URL (``serial:socket://
192.168.1.20:4001``, ``serial:rfc2217://...``, ``serial:loop://``). pyserial's own protocol
handlers parse the rest, as they do for any pyserial program. The bit rate is the ``baudrate``
option (115200 by default).

This is the robot side of a serial link -- the real robot's K-Team and range-frame ports -- where
:class:`koala_bridge.drivers.transports.pty.PtyTransport` is the simulated robot's side.
"""

from __future__ import annotations

from typing import Any, Self

import serial
from koala_bridge.drivers.messages import TransportClosedError, TransportError
from koala_bridge.drivers.transports.base import (
    ByteTransport,
    Endpoint,
    StatsCounter,
    TransportStats,
    split_url,
)

__all__ = ["SerialTransport", "serial_url"]


def serial_url(port: str) -> str:
    """The registry URL of a serial device path or pyserial URL (``/dev/ttyUSB0`` ->
    ``serial:/dev/ttyUSB0``)."""
    return port if port.startswith("serial:") else f"serial:{port}"


class SerialTransport(ByteTransport):
    """A pyserial port behind the :class:`ByteTransport` interface.

    Args:
        port: device path or pyserial URL.
        baudrate: bits per second.
        **kwargs: further :func:`serial.serial_for_url` arguments (bytesize, parity, ...).
    """

    def __init__(self, port: str, baudrate: int = 115200, **kwargs: Any) -> None:
        try:
            self._serial: serial.SerialBase | None = serial.serial_for_url(
                port, baudrate=baudrate, timeout=0, **kwargs
            )
        except (serial.SerialException, ValueError, OSError) as e:
            raise TransportError(f"cannot open serial port {port!r}: {e}") from e
        self._port = port
        self._held = b""  # the byte :meth:`wait` read to learn that input had arrived
        self._stats = StatsCounter()

    @classmethod
    def from_url(cls, url: str, **options: Any) -> Self:
        """``serial:PORT`` (see the module docstring)."""
        rest = split_url(url).rest
        if rest.startswith("///"):  # serial:///dev/ttyUSB0
            rest = rest[2:]
        if not rest:
            raise ValueError(f"{url!r}: expected serial:DEVICE or serial:PYSERIAL_URL")
        options.setdefault("port", rest)
        return cls(**options)

    @property
    def endpoint(self) -> Endpoint:
        return Endpoint("serial", path=self._port)

    @property
    def stats(self) -> TransportStats:
        return self._stats.snapshot(clients=1)

    def read(self, max_bytes: int = 65536) -> bytes:
        port = self._s()
        held, self._held = self._held, b""
        try:
            waiting = min(max_bytes - len(held), port.in_waiting)
            data = held + (bytes(port.read(waiting)) if waiting > 0 else b"")
        except (serial.SerialException, OSError) as e:
            raise TransportError(f"serial read on {self._port!r} failed: {e}") from e
        if data:
            self._stats.add("received")
        return data

    def write(self, data: bytes) -> int:
        port = self._s()
        try:
            port.write(data)
        except (serial.SerialException, OSError) as e:
            raise TransportError(f"serial write on {self._port!r} failed: {e}") from e
        self._stats.add("sent")
        return len(data)

    def wait(self, timeout: float | None) -> bool:
        # pyserial has no portable "wait for input" (URL handlers have no fileno): a one-byte
        # read with a timeout blocks until input arrives, and that byte is kept for read().
        port = self._s()
        if self._held:
            return True
        try:
            port.timeout = timeout
            self._held = bytes(port.read(1))
        except (serial.SerialException, OSError) as e:
            raise TransportError(f"serial read on {self._port!r} failed: {e}") from e
        finally:
            if self._serial is not None:
                self._serial.timeout = 0
        return bool(self._held)

    def close(self) -> None:
        if self._serial is not None:
            self._serial.close()
            self._serial = None

    def _s(self) -> serial.SerialBase:
        if self._serial is None:
            raise TransportClosedError("serial transport is closed")
        return self._serial
