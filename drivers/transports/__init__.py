"""Transports: one interface per bus, backends chosen by URL.

Byte streams (:class:`ByteTransport`) -- :func:`open_byte_transport`::

    pty://                    a pty pair; clients open Endpoint.path with pyserial
    pty:///tmp/koala-kteam    ... plus a stable symlink at that path
    tcp://127.0.0.1:0         TCP server on loopback (port 0 = a free port)
    udp://127.0.0.1:14550     UDP datagrams to that address, replies read on the same socket
    loop://                   in-process loopback pair (the other end is ``transport.peer``)

CAN buses (:class:`CanTransport`) -- :func:`open_can_transport`::

    socketcand://127.0.0.1:0/can0   socketcand server (python-can interface "socketcand")
    slcan://  or  slcan:///tmp/koala-slcan   LAWICEL adapter on a pty (python-can "slcan")
    virtual://koala                 python-can in-process virtual bus, channel "koala"
    python-can://socketcan/vcan0    any python-can interface/channel (here socketcan, vcan0)

Backends are imported lazily from the tables below, as python-can's interface table does, so
adding one is adding one module and one line.
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from types import MappingProxyType
from typing import Any
from urllib.parse import unquote, urlsplit

from koala_bridge.drivers.transports.base import (
    ByteTransport,
    CanTransport,
    Endpoint,
    StatsCounter,
    TransportStats,
)

__all__ = [
    "BYTE_BACKENDS",
    "CAN_BACKENDS",
    "ByteTransport",
    "CanTransport",
    "Endpoint",
    "StatsCounter",
    "TransportStats",
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
        "udp": "koala_bridge.drivers.transports.udp:UdpTransport",
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
    scheme, host, port, path = _split(url, BYTE_BACKENDS)
    cls = _load(BYTE_BACKENDS[scheme])
    if scheme == "pty" or scheme == "loop":
        if scheme == "pty" and path:
            options.setdefault("link", path)
    elif scheme == "tcp":
        options.setdefault("host", host or "127.0.0.1")
        options.setdefault("port", 0 if port is None else port)
    elif scheme == "udp":
        options.setdefault("host", host or "127.0.0.1")
        options.setdefault("port", 14550 if port is None else port)
    transport = cls(**options)
    assert isinstance(transport, ByteTransport)
    return transport


def open_can_transport(url: str, **options: Any) -> CanTransport:
    """Open the CAN transport named by ``url``; ``options`` go to the backend's constructor."""
    scheme, host, port, path = _split(url, CAN_BACKENDS)
    cls = _load(CAN_BACKENDS[scheme])
    if scheme == "socketcand":
        options.setdefault("host", host or "127.0.0.1")
        options.setdefault("port", 0 if port is None else port)
        options.setdefault("channel", path.lstrip("/") or "can0")
    elif scheme == "slcan":
        if path:
            options.setdefault("link", path)
    elif scheme == "virtual":
        options.setdefault("channel", host or path.lstrip("/") or "koala")
    else:  # python-can://INTERFACE/CHANNEL
        if not host or not path.lstrip("/"):
            raise ValueError(f"{url!r}: expected python-can://INTERFACE/CHANNEL")
        options.setdefault("interface", host)
        options.setdefault("channel", path.lstrip("/"))
    transport = cls(**options)
    assert isinstance(transport, CanTransport)
    return transport


def pymavlink_url(endpoint: Endpoint) -> str:
    """The pymavlink connection string a client uses to receive from a byte transport.

    ``udp`` -> ``udpin:HOST:PORT`` (the client listens where the bridge sends);
    ``tcp`` -> ``tcp:HOST:PORT``; ``pty`` -> the device path.
    """
    if endpoint.kind == "udp":
        return f"udpin:{endpoint.host}:{endpoint.port}"
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


def _split(url: str, table: Mapping[str, str]) -> tuple[str, str | None, int | None, str]:
    parts = urlsplit(url)
    scheme = parts.scheme.lower()
    if scheme not in table:
        raise ValueError(f"unknown transport {scheme!r} in {url!r}; known: {sorted(table)}")
    return scheme, parts.hostname, parts.port, unquote(parts.path)


def _load(target: str) -> type:
    module_name, _, attr = target.partition(":")
    cls = getattr(importlib.import_module(module_name), attr)
    assert isinstance(cls, type)
    return cls
