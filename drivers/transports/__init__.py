"""Transports: one interface per bus, backends chosen by URL -- the one way koala-bridge opens a
bus, whether it serves the simulated robot's buses or reads a real robot's ports.

Byte streams (:class:`ByteTransport`) -- :func:`open_byte_transport`::

    pty://                    a pty pair; clients open Endpoint.path with pyserial
    pty:///tmp/koala-kteam    ... plus a stable symlink at that path
    tcp://127.0.0.1:0         TCP server on loopback (port 0 = a free port)
    tcp-client://HOST:PORT    TCP connection to a server (a robot's MAVLink TCP port)
    udp://127.0.0.1:14550     UDP datagrams to that address, replies read on the same socket
    udpin://0.0.0.0:14550     UDP socket bound there, reading what is sent to it
    serial:/dev/ttyUSB0       a serial device or pyserial URL (serial:socket://..., serial:loop://)
    loop://                   in-process loopback pair (the other end is ``transport.peer``)

CAN buses (:class:`CanTransport`) -- :func:`open_can_transport`::

    socketcand://127.0.0.1:0/can0   socketcand server (python-can interface "socketcand")
    slcan://  or  slcan:///tmp/koala-slcan   LAWICEL adapter on a pty (python-can "slcan")
    virtual://koala                 python-can in-process virtual bus (the CAN loopback)
    python-can://socketcan/vcan0    any python-can interface/channel (here socketcan, vcan0)

The scheme picks the backend from the tables below, imported lazily as python-can's interface
table is; the backend's ``from_url`` parses the rest of the URL, as pyserial's
``protocol_<scheme>`` handlers do. Adding a backend is adding one module and one line. Every bus
has a loopback backend: ``loop://`` for byte streams, ``virtual://`` for CAN.

:func:`mavlink_connection_url` turns a pymavlink connection string (``udpin:HOST:PORT``,
``tcp:HOST:PORT``, a device) into a URL of this registry; :func:`pymavlink_url`,
:func:`pyserial_url` and :func:`python_can_config` go the other way, for the clients of a bus
the bridge serves.
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from types import MappingProxyType
from typing import Any

from koala_bridge.drivers.transports.base import (
    ByteTransport,
    CanTransport,
    Endpoint,
    StatsCounter,
    TransportStats,
    split_url,
)

__all__ = [
    "BYTE_BACKENDS",
    "CAN_BACKENDS",
    "ByteTransport",
    "CanTransport",
    "Endpoint",
    "StatsCounter",
    "TransportStats",
    "mavlink_connection_options",
    "mavlink_connection_url",
    "open_byte_transport",
    "open_can_transport",
    "pymavlink_url",
    "pyserial_url",
    "python_can_config",
]

BYTE_BACKENDS: Mapping[str, str] = MappingProxyType(
    {
        "pty": "koala_bridge.drivers.transports.pty:PtyTransport",
        "tcp": "koala_bridge.drivers.transports.tcp:TcpServerTransport",
        "tcp-client": "koala_bridge.drivers.transports.tcp:TcpClientTransport",
        "udp": "koala_bridge.drivers.transports.udp:UdpTransport",
        "udpin": "koala_bridge.drivers.transports.udp:UdpTransport",
        "serial": "koala_bridge.drivers.transports.serialport:SerialTransport",
        "loop": "koala_bridge.drivers.transports.loop:LoopbackTransport",
    }
)
CAN_BACKENDS: Mapping[str, str] = MappingProxyType(
    {
        "socketcand": "koala_bridge.drivers.transports.socketcand:SocketcandServer",
        "slcan": "koala_bridge.drivers.transports.slcan:SlcanAdapter",
        "virtual": "koala_bridge.drivers.transports.pythoncan:VirtualCanTransport",
        "python-can": "koala_bridge.drivers.transports.pythoncan:PythonCanTransport",
    }
)


def open_byte_transport(url: str, **options: Any) -> ByteTransport:
    """Open the byte transport named by ``url``; ``options`` go to the backend's constructor."""
    transport = _load(url, BYTE_BACKENDS).from_url(url, **options)
    assert isinstance(transport, ByteTransport)
    return transport


def open_can_transport(url: str, **options: Any) -> CanTransport:
    """Open the CAN transport named by ``url``; ``options`` go to the backend's constructor."""
    transport = _load(url, CAN_BACKENDS).from_url(url, **options)
    assert isinstance(transport, CanTransport)
    return transport


def mavlink_connection_url(connection: str) -> str:
    """The registry URL of a pymavlink-style connection string, for reading a robot's MAVLink:
    ``udpin:HOST:PORT`` and ``udp:HOST:PORT`` listen there (``udpin://``), ``tcp:HOST:PORT``
    connects (``tcp-client://``), anything else is a serial device or pyserial URL with an
    optional ``,BAUD`` (``serial:``; the rate is an option, see
    :func:`mavlink_connection_options`). A URL of this registry's robot-side backends
    (``udpin://``, ``tcp-client://``, ``serial:``) is taken as it is."""
    if connection.startswith(("udpin://", "tcp-client://", "serial:")):
        return connection.partition(",")[0] if connection.startswith("serial:") else connection
    kind, sep, rest = connection.partition(":")
    if sep and rest and not rest.startswith("//"):
        if kind in ("udpin", "udp"):
            return f"udpin://{rest}"
        if kind == "tcp":
            return f"tcp-client://{rest}"
    path, _, _ = connection.partition(",")
    return f"serial:{path}"


def mavlink_connection_options(connection: str) -> dict[str, Any]:
    """The options that go with :func:`mavlink_connection_url`: the ``baudrate`` of a serial
    connection string (``/dev/ttyACM0,57600``; 115200 without one), nothing for a socket."""
    if not mavlink_connection_url(connection).startswith("serial:"):
        return {}
    _, sep, baud = connection.partition(",")
    if sep and not baud.isdigit():
        raise ValueError(f"{connection!r}: the baud rate after ',' must be a number")
    return {"baudrate": int(baud) if sep else 115200}


def pymavlink_url(endpoint: Endpoint) -> str:
    """The pymavlink connection string a client uses to receive from a byte transport.

    ``udp`` -> ``udpin:HOST:PORT`` (the client listens where the bridge sends);
    ``udpin`` -> ``udpout:HOST:PORT`` (the client sends where the bridge listens);
    ``tcp`` -> ``tcp:HOST:PORT``; ``pty`` -> the device path.
    """
    if endpoint.kind == "udp":
        return f"udpin:{endpoint.host}:{endpoint.port}"
    if endpoint.kind == "udpin":
        return f"udpout:{endpoint.host}:{endpoint.port}"
    if endpoint.kind == "tcp":
        return f"tcp:{endpoint.host}:{endpoint.port}"
    if endpoint.kind == "pty" and endpoint.path:
        return endpoint.path
    raise ValueError(f"no pymavlink connection string for a {endpoint.kind} endpoint")


def pyserial_url(endpoint: Endpoint) -> str:
    """The ``serial.serial_for_url`` string for a byte transport (pty path or ``socket://``)."""
    if endpoint.kind == "pty" and endpoint.path:
        return endpoint.path
    if endpoint.kind == "tcp":
        return f"socket://{endpoint.host}:{endpoint.port}"
    raise ValueError(f"no pyserial URL for a {endpoint.kind} endpoint")


def python_can_config(endpoint: Endpoint) -> dict[str, Any]:
    """Keyword arguments for ``can.Bus(**config)`` that open a CAN transport from a client."""
    if endpoint.kind == "socketcand":
        return {
            "interface": "socketcand",
            "host": endpoint.host,
            "port": endpoint.port,
            "channel": endpoint.channel,
        }
    if endpoint.kind == "slcan":
        return {"interface": "slcan", "channel": endpoint.path}
    if endpoint.kind in ("virtual", "python-can"):
        return {"interface": endpoint.interface, "channel": endpoint.channel}
    raise ValueError(f"no python-can configuration for a {endpoint.kind} endpoint")


def _load(url: str, table: Mapping[str, str]) -> Any:
    scheme = split_url(url).scheme
    if scheme not in table:
        raise ValueError(f"unknown transport {scheme!r} in {url!r}; known: {sorted(table)}")
    module_name, _, attr = table[scheme].partition(":")
    cls = getattr(importlib.import_module(module_name), attr)
    assert isinstance(cls, type)
    return cls
