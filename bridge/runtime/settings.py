"""Configuration: read a TOML file, apply command-line overrides, type the bridge's sections.

Precedence is explicit: command line > file. Nothing is read from the environment or the home
directory, and every default a run uses is written in ``config/default.toml``. This module types
the sections the bridge owns — ``[run]``, ``[buses]`` and ``[zenoh]`` — and leaves ``[sim]``,
``[robot]``, ``[world]`` and the sensor sections to ``sim/`` (which validates them the same way).
Unknown keys are errors that name the section and suggest the nearest valid key.

Command-line overrides use dotted keys and TOML values, e.g.
``--set buses.mavlink.port=14551 --set 'zenoh.listen=["tcp/127.0.0.1:7500"]'``.
"""

from __future__ import annotations

import copy
import difflib
import math
import re
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from koala_bridge.core.schema import ConfigError, reject_unknown
from koala_bridge.runtime.clock import CLOCK_NAMES

__all__ = [
    "BridgeSettings",
    "CanSettings",
    "ConfigError",
    "MavlinkSettings",
    "RunSettings",
    "ZenohSettings",
    "apply_override",
    "load_config",
    "parse_override",
]

MAVLINK_TRANSPORTS = ("udp", "tcp", "pty")

#: A Zenoh locator whose port is 0 (``tcp/127.0.0.1:0``, ``udp/[::1]:0#iface=lo``, ...).
_ZERO_PORT = re.compile(r":0+(?:[?#].*)?$")

#: The top-level tables of a configuration: sim/ reads the first four (sim/config.py), the bridge
#: the others (``[real]``: runtime/real_source.py, for ``run --source real``; ``[localisation]``:
#: bridge/runtime/localisation.py, the estimator node).
SECTIONS = ("sim", "robot", "sensors", "world", "run", "buses", "zenoh", "real", "localisation")


def load_config(path: str | Path) -> dict[str, Any]:
    """Read the TOML file ``path``; errors name the file and, for syntax errors, the line."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError as e:
        raise ConfigError(f"config file not found: {p}") from e
    except OSError as e:
        raise ConfigError(f"cannot read config file {p}: {e.strerror}") from e
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{p}: invalid TOML: {e}") from e


def parse_override(text: str) -> tuple[list[str], Any]:
    """Split ``"a.b.c=VALUE"`` into ``(["a", "b", "c"], value)``; VALUE is a TOML value.

    A VALUE that is not valid TOML is taken as a plain string, so ``robot.name=k2`` works
    without quotes.
    """
    key, sep, raw = text.partition("=")
    key = key.strip()
    if not sep or not key:
        raise ConfigError(f"override must look like section.key=value, got {text!r}")
    parts = key.split(".")
    if any(not part for part in parts):
        raise ConfigError(f"override key {key!r} has an empty part")
    try:
        value = tomllib.loads(f"v = {raw.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw.strip()
    return parts, value


def apply_override(config: Mapping[str, Any], parts: list[str], value: Any) -> dict[str, Any]:
    """A deep copy of ``config`` with ``value`` set at the dotted key ``parts``."""
    out = copy.deepcopy(dict(config))
    node: dict[str, Any] = out
    for i, part in enumerate(parts[:-1]):
        child = node.setdefault(part, {})
        if not isinstance(child, dict):
            where = ".".join(parts[: i + 1])
            raise ConfigError(f"override {'.'.join(parts)}: {where} is a value, not a section")
        node = child
    node[parts[-1]] = value
    return out


def _section(config: Mapping[str, Any], name: str, parent: str = "") -> Mapping[str, Any]:
    """The table at dotted ``name`` below ``config`` (whose own name is ``parent``)."""
    where = f"{parent}.{name}" if parent else name
    node: Any = config
    for part in name.split("."):
        if not isinstance(node, Mapping):
            raise ConfigError(f"[{where}] must be a table")
        node = node.get(part, {})
    if not isinstance(node, Mapping):
        raise ConfigError(f"[{where}] must be a table, got {node!r}")
    return node


def _get(d: Mapping[str, Any], key: str, section: str, kind: type | tuple[type, ...]) -> Any:
    if key not in d:
        raise ConfigError(f"[{section}] missing required key '{key}'")
    value = d[key]
    # bool is an int in Python; a number key must not silently accept true/false.
    if isinstance(value, bool) and bool not in (kind if isinstance(kind, tuple) else (kind,)):
        raise ConfigError(f"[{section}] '{key}' must be a number, got {value!r}")
    if not isinstance(value, kind):
        names = " or ".join(k.__name__ for k in (kind if isinstance(kind, tuple) else (kind,)))
        raise ConfigError(f"[{section}] '{key}' must be {names}, got {value!r}")
    return value


def _port(d: Mapping[str, Any], key: str, section: str) -> int:
    port = _get(d, key, section, int)
    if not 0 <= port <= 65535:
        raise ConfigError(f"[{section}] '{key}' must be a TCP/UDP port 0..65535, got {port}")
    return int(port)


def _rate(d: Mapping[str, Any], key: str, section: str) -> float:
    rate = float(_get(d, key, section, (int, float)))
    if not rate > 0:
        raise ConfigError(f"[{section}] '{key}' must be > 0, got {rate}")
    return rate


@dataclass(frozen=True)
class RunSettings:
    """``[run]``: how the loop is paced and for how long."""

    clock: str                  # "realtime" | "fast"
    duration_s: float           # simulation seconds; 0 = until SIGINT/SIGTERM
    endpoints_file: str         # "" = do not write one

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> RunSettings:
        s = "run"
        reject_unknown(d, ("clock", "duration_s", "endpoints_file"), s)
        clock = _get(d, "clock", s, str)
        if clock not in CLOCK_NAMES:
            choices = ", ".join(CLOCK_NAMES)
            raise ConfigError(f"[{s}] 'clock' must be one of {choices}, got {clock!r}")
        duration = float(_get(d, "duration_s", s, (int, float)))
        if not (math.isfinite(duration) and duration >= 0):
            raise ConfigError(
                f"[{s}] 'duration_s' must be a finite number >= 0 (0 = run until stopped), "
                f"got {duration}"
            )
        return cls(clock, duration, _get(d, "endpoints_file", s, str))


@dataclass(frozen=True)
class CanSettings:
    """``[buses.can]``: the same CAN bus served on several interfaces at once."""

    channel: str
    socketcand: bool
    socketcand_host: str
    socketcand_port: int
    slcan: bool
    virtual: bool
    virtual_channel: str
    socketcan: bool
    socketcan_channel: str

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> CanSettings:
        s = "buses.can"
        reject_unknown(d, [f for f in cls.__dataclass_fields__], s)
        return cls(
            channel=_get(d, "channel", s, str),
            socketcand=_get(d, "socketcand", s, bool),
            socketcand_host=_get(d, "socketcand_host", s, str),
            socketcand_port=_port(d, "socketcand_port", s),
            slcan=_get(d, "slcan", s, bool),
            virtual=_get(d, "virtual", s, bool),
            virtual_channel=_get(d, "virtual_channel", s, str),
            socketcan=_get(d, "socketcan", s, bool),
            socketcan_channel=_get(d, "socketcan_channel", s, str),
        )


@dataclass(frozen=True)
class MavlinkSettings:
    """``[buses.mavlink]``: the compass as a MAVLink 2 component."""

    enabled: bool
    transport: str              # "udp" (send to host:port) | "tcp" (listen) | "pty"
    host: str
    port: int
    system_id: int
    component_id: int
    heartbeat_hz: float

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> MavlinkSettings:
        s = "buses.mavlink"
        reject_unknown(d, [f for f in cls.__dataclass_fields__], s)
        transport = _get(d, "transport", s, str)
        if transport not in MAVLINK_TRANSPORTS:
            choices = ", ".join(MAVLINK_TRANSPORTS)
            raise ConfigError(f"[{s}] 'transport' must be one of {choices}, got {transport!r}")
        ids = {}
        for key in ("system_id", "component_id"):
            v = _get(d, key, s, int)
            if not 1 <= v <= 255:
                raise ConfigError(f"[{s}] '{key}' must be 1..255, got {v}")
            ids[key] = v
        port = _port(d, "port", s)
        if transport == "udp" and port == 0:
            # UDP: host:port is where the CLIENT listens (the bridge sends datagrams there), so
            # the bridge cannot pick it; tcp listens itself and 0 picks a free port.
            raise ConfigError(
                f"[{s}] 'port' 0 is not allowed with transport 'udp': host:port is the address "
                "the client (ground station) listens on and the bridge sends to, so choose it, "
                "e.g. --set buses.mavlink.port=14551 and connect with udpin:127.0.0.1:14551"
            )
        return cls(
            enabled=_get(d, "enabled", s, bool),
            transport=transport,
            host=_get(d, "host", s, str),
            port=port,
            system_id=ids["system_id"],
            component_id=ids["component_id"],
            heartbeat_hz=_rate(d, "heartbeat_hz", s),
        )

    def client_url(self, pty_path: str | None = None, bound_port: int | None = None) -> str:
        """The pymavlink connection string a client uses to receive this stream."""
        if self.transport == "udp":
            return f"udpin:{self.host}:{self.port}"
        if self.transport == "tcp":
            return f"tcp:{self.host}:{bound_port if bound_port is not None else self.port}"
        if pty_path is None:
            raise ValueError("a pty MAVLink link needs its path")
        return pty_path


@dataclass(frozen=True)
class BusesSettings:
    """``[buses]``: which buses are served, and the motor command watchdog."""

    motor_watchdog_s: float     # 0 = off: a wheel command holds until the next one
    kteam: bool
    kteam_max_speed: int        # largest |speed| K-Team D accepts, pulses per speed unit
    rangefinders: bool
    can: CanSettings
    mavlink: MavlinkSettings

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> BusesSettings:
        s = "buses"
        reject_unknown(d, ("motor_watchdog_s", "kteam", "rangefinders", "can", "mavlink"), s)
        watchdog = float(_get(d, "motor_watchdog_s", s, (int, float)))
        if watchdog < 0:
            raise ConfigError(f"[{s}] 'motor_watchdog_s' must be >= 0 (0 = off)")
        flags = {}
        for name, keys in (("kteam", ("enabled", "max_speed")), ("rangefinders", ("enabled",))):
            sub = _section(d, name, s)
            reject_unknown(sub, keys, f"{s}.{name}")
            flags[name] = _get(sub, "enabled", f"{s}.{name}", bool)
        max_speed = _get(_section(d, "kteam", s), "max_speed", f"{s}.kteam", int)
        if max_speed < 1:
            raise ConfigError(f"[{s}.kteam] 'max_speed' must be >= 1, got {max_speed}")
        return cls(
            motor_watchdog_s=watchdog,
            kteam=flags["kteam"],
            kteam_max_speed=max_speed,
            rangefinders=flags["rangefinders"],
            can=CanSettings.from_dict(_section(d, "can", s)),
            mavlink=MavlinkSettings.from_dict(_section(d, "mavlink", s)),
        )


@dataclass(frozen=True)
class ZenohSettings:
    """``[zenoh]``: the session and what it publishes."""

    mode: str
    listen: tuple[str, ...]
    connect: tuple[str, ...]
    multicast_scouting: bool
    prefix: str                 # resolved: "" in the file means koala/<robot name>
    pose_rate_hz: float         # truth/pose, in simulation time
    status_rate_hz: float       # status, in simulation time

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], robot_name: str) -> ZenohSettings:
        s = "zenoh"
        reject_unknown(d, [f for f in cls.__dataclass_fields__], s)
        mode = _get(d, "mode", s, str)
        if mode not in ("peer", "client"):
            raise ConfigError(f"[{s}] 'mode' must be 'peer' or 'client', got {mode!r}")
        endpoints = {}
        for key in ("listen", "connect"):
            v = _get(d, key, s, list)
            if not all(isinstance(e, str) and "/" in e for e in v):
                raise ConfigError(
                    f"[{s}] '{key}' must be a list of locators like "
                    f"\"tcp/127.0.0.1:7447\", got {v!r}"
                )
            endpoints[key] = tuple(v)
        for locator in endpoints["listen"]:
            if _ZERO_PORT.search(locator):
                # Zenoh does not report the port it picked, so neither the banner nor the
                # endpoints file could tell clients where to connect.
                raise ConfigError(
                    f"[{s}] 'listen' locator {locator!r}: port 0 is not supported (the bridge "
                    "could not tell clients which port Zenoh picked); give a free port, e.g. "
                    "--set 'zenoh.listen=[\"tcp/127.0.0.1:7448\"]'"
                )
        prefix = _get(d, "prefix", s, str).strip("/") or f"koala/{robot_name}"
        if any(c in prefix for c in "*$?#"):
            raise ConfigError(f"[{s}] 'prefix' must be a plain key expression, got {prefix!r}")
        return cls(
            mode=mode,
            listen=endpoints["listen"],
            connect=endpoints["connect"],
            multicast_scouting=_get(d, "multicast_scouting", s, bool),
            prefix=prefix,
            pose_rate_hz=_rate(d, "pose_rate_hz", s),
            status_rate_hz=_rate(d, "status_rate_hz", s),
        )


@dataclass(frozen=True)
class BridgeSettings:
    """The bridge's typed sections of one configuration."""

    run: RunSettings
    buses: BusesSettings
    zenoh: ZenohSettings
    robot_name: str

    @classmethod
    def from_config(cls, config: Mapping[str, Any]) -> BridgeSettings:
        reject_unknown_sections(config)
        robot = _section(config, "robot")
        name = robot.get("name", "koala")
        if not isinstance(name, str) or not name or any(c in name for c in "/*$?# "):
            raise ConfigError(f"[robot] 'name' must be a plain word, got {name!r}")
        return cls(
            run=RunSettings.from_dict(_section(config, "run")),
            buses=BusesSettings.from_dict(_section(config, "buses")),
            zenoh=ZenohSettings.from_dict(_section(config, "zenoh"), name),
            robot_name=name,
        )


def reject_unknown_sections(config: Mapping[str, Any]) -> None:
    """Raise :class:`ConfigError` for a top-level key that is not one of :data:`SECTIONS`,
    suggesting the nearest (a misspelt ``[bueses]`` must not be ignored silently), or that is
    not a table."""
    for key, value in config.items():
        if key not in SECTIONS:
            near = difflib.get_close_matches(key, SECTIONS, n=1)
            hint = f"did you mean [{near[0]}]?" if near else f"valid: {', '.join(SECTIONS)}"
            raise ConfigError(f"unknown section [{key}]; {hint}")
        if not isinstance(value, Mapping):
            raise ConfigError(f"[{key}] must be a table, got {value!r}")
