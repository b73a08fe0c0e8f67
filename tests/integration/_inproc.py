"""The bridge in this process, for tests that play its firmware from the test thread: a
:class:`SimulatedRobotSource` whose loop runs in a thread, clients on its real transports
(pyserial on the K-Team pty, python-can's ``socketcand`` interface, zenoh-python), and a tap
that keeps what the bridge published and put on its buses."""

from __future__ import annotations

import json
import threading
from collections.abc import Iterable, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Protocol, TypeVar

import can
import serial
import zenoh
from conftest import free_port
from koala_bridge.runtime.settings import (
    BridgeSettings,
    apply_override,
    load_config,
    parse_override,
)
from koala_bridge.runtime.sim_source import SimulatedRobotSource


class _Served(Protocol):
    def open(self) -> Any: ...
    def run(self, stop: threading.Event, duration_s: float | None = None) -> Any: ...
    def close(self) -> None: ...


S = TypeVar("S", bound=_Served)

REPO = Path(__file__).resolve().parents[2]
WAIT_S = 10.0


class ListTap:
    """A recorder in memory: ``messages`` (channel, t, payload), ``frames`` (bus, dir, t, data,
    fields)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.messages: list[tuple[str, float, Mapping[str, Any]]] = []
        self.frames: list[tuple[str, str, float, bytes, dict[str, object]]] = []

    def declare(self, keys: Iterable[str] = (), buses: Iterable[str] = ()) -> None:
        pass

    def record(self, channel: str, t: float, payload: Mapping[str, Any]) -> None:
        with self.lock:
            self.messages.append((channel, t, payload))

    def record_frame(self, bus: str, direction: str, t: float, data: bytes,
                     **fields: object) -> None:
        with self.lock:
            self.frames.append((bus, direction, t, data, fields))

    def on(self, channel: str) -> list[tuple[float, Mapping[str, Any]]]:
        with self.lock:
            return [(t, m) for c, t, m in self.messages if c == channel]


def lockstep_config(*overrides: str, faults: list[dict[str, Any]] | None = None
                    ) -> dict[str, Any]:
    config = load_config(REPO / "config" / "default.toml")
    for text in ("run.clock=\"lockstep\"", "buses.can.socketcand_port=0",
                 "buses.can.slcan=false", "buses.rangefinders.enabled=false",
                 f"buses.mavlink.port={free_port('udp')}",
                 # port 0: the bridge binds a free one and names it in its endpoints (a port
                 # picked free here could be taken by another connection before it binds)
                 'zenoh.listen=["tcp/127.0.0.1:0"]', *overrides):
        config = apply_override(config, *parse_override(text))
    if faults:
        config["faults"] = faults
    return config


@contextmanager
def bridge(*overrides: str, duration_s: float = 0.0, faults: list[dict[str, Any]] | None = None,
           tap: ListTap | None = None) -> Iterator[SimulatedRobotSource]:
    """The bridge (lockstep unless overridden), its loop in a thread; stopped and closed on
    exit."""
    config = lockstep_config(*overrides, faults=faults)
    source = SimulatedRobotSource(config, BridgeSettings.from_config(config), tap=tap)
    with serving(source, duration_s):
        yield source


@contextmanager
def serving(source: S, duration_s: float = 0.0) -> Iterator[S]:
    """``source`` opened, its loop in a thread for ``duration_s`` (0: until the exit); stopped,
    closed and the loop joined on exit."""
    source.open()
    stop = threading.Event()
    loop = threading.Thread(target=source.run, args=(stop, duration_s), daemon=True)
    loop.start()
    try:
        yield source
    finally:
        stop.set()
        source.close()
        loop.join(WAIT_S)
        assert not loop.is_alive()


def kteam(source: SimulatedRobotSource, timeout: float = WAIT_S) -> serial.Serial:
    assert source.endpoints is not None and source.endpoints.kteam is not None
    return serial.Serial(source.endpoints.kteam, 115200, timeout=timeout)


def ask(port: serial.Serial, command: str) -> str:
    port.write(command.encode() + b"\n")
    line = port.readline().decode().strip()
    assert line, f"no reply to {command!r}"
    return line


def socketcand(source: SimulatedRobotSource) -> can.BusABC:
    assert source.endpoints is not None
    sc = source.endpoints.socketcand
    assert sc is not None
    return can.Bus(interface="socketcand", host=sc.host, port=sc.port, channel=sc.channel)


def zenoh_session(source: SimulatedRobotSource) -> zenoh.Session:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    assert source.endpoints is not None and source.endpoints.zenoh_endpoints
    conf.insert_json5("connect/endpoints", json.dumps(list(source.endpoints.zenoh_endpoints)))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(conf)
