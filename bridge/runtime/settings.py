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
import dataclasses
import difflib
import logging
import math
import re
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

from koala_bridge.core.resources import default_dbc_path
from koala_bridge.core.schema import (
    Bool,
    ConfigError,
    NonNegative,
    Positive,
    PositiveInt,
    Str,
    field_names,
    reject_unknown,
    section,
    tuples,
    validate,
)
from koala_bridge.runtime.clock import CLOCK_NAMES
from pydantic import AfterValidator, BeforeValidator, Field, Strict

if TYPE_CHECKING:
    from koala_bridge.drivers.can_codec import KoalaCanCodec

log = logging.getLogger(__name__)

__all__ = [
    "BridgeSettings",
    "BusesSettings",
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
    without quotes, unless it starts like a TOML array, table or quoted string (``[``, ``{``,
    ``"``, ``'``): then it was meant as one, and the error says why it is not (one line). A
    bare word still meets the key's type: ``robot.wheel_base_m=abc`` is refused by the schema
    as "must be a number".
    """
    key, sep, raw = text.partition("=")
    key = key.strip()
    if not sep or not key:
        raise ConfigError(f"override must look like section.key=value, got {text!r}")
    parts = key.split(".")
    if any(not part for part in parts):
        raise ConfigError(f"override key {key!r} has an empty part")
    raw = raw.strip()
    try:
        parsed = tomllib.loads(f"v = {raw}")
    except tomllib.TOMLDecodeError as e:
        if raw[:1] in ("[", "{", '"', "'"):
            reason = str(e).splitlines()[0] if str(e) else "invalid value"
            raise ConfigError(
                f"override {key}: {raw!r} is not a TOML value ({reason}); arrays look like "
                "[1, 2], tables like {a = 1}, strings like \"text\" (quote the whole --set "
                "argument for the shell)"
            ) from None
        return parts, raw
    if set(parsed) != {"v"}:  # "1\nx = 2": a second line is not part of one value
        raise ConfigError(f"override {key}: {raw!r} is more than one TOML value")
    return parts, parsed["v"]


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


def _one_of(choices: tuple[str, ...]) -> Any:
    def check(value: str) -> str:
        if value not in choices:
            raise ValueError(f"must be one of {', '.join(choices)}, got {value!r}")
        return value

    return AfterValidator(check)


def _duration(value: float) -> float:
    if not (math.isfinite(value) and value >= 0):
        raise ValueError(
            f"must be a finite number >= 0 (0 = run until stopped), got {value}"
        )
    return value


def _port(value: int) -> int:
    if not 0 <= value <= 65535:
        raise ValueError(f"must be a TCP/UDP port 0..65535, got {value}")
    return value


#: Any int, checked as a port with the message tests and users know.
_PortKey = Annotated[int, Strict(), AfterValidator(_port)]


@section
class RunSettings:
    """``[run]``: how the loop is paced and for how long."""

    clock: Annotated[Str, _one_of(CLOCK_NAMES)]          # "realtime" | "fast"
    # simulation seconds; 0 = until SIGINT/SIGTERM (inf is refused with the same message)
    duration_s: Annotated[float, Strict(), Field(allow_inf_nan=True), AfterValidator(_duration)]
    endpoints_file: Str         # "" = do not write one

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> RunSettings:
        return validate(cls, d, "run")


@section
class CanSettings:
    """``[buses.can]``: the same CAN bus served on several interfaces at once."""

    channel: Str
    socketcand: Bool
    socketcand_host: Str
    socketcand_port: _PortKey
    slcan: Bool
    virtual: Bool
    virtual_channel: Str
    socketcan: Bool
    socketcan_channel: Str
    # The CAN database: a path (relative to the working directory), or "" for the DBC shipped
    # with koala-bridge (koala_bridge.core.resources.default_dbc_path). Read only when a CAN
    # bus is served, so a missing file does not matter with every CAN bus off. The one key of
    # the bridge's tables with a default (default.toml's ""): configs and recordings from
    # before it existed still load.
    dbc: Str = ""

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> CanSettings:
        return validate(cls, d, "buses.can")

    @property
    def enabled(self) -> bool:
        """Whether any CAN interface is served (only then is the DBC read)."""
        return self.socketcand or self.slcan or self.virtual or self.socketcan

    @property
    def dbc_path(self) -> Path:
        """The DBC file to load: ``dbc``, or the shipped one when ``dbc`` is ""."""
        return Path(self.dbc).expanduser() if self.dbc else default_dbc_path()

    def codec(self, needed: bool | None = None) -> KoalaCanCodec:
        """The CAN codec of :attr:`dbc_path`.

        ``needed`` (default: :attr:`enabled`, whether a CAN bus is served) says whether frames
        go on a CAN bus; then a DBC that cannot be loaded is a :class:`ConfigError` naming the
        key. Otherwise the frames are only recorded and fed to the estimator, and a missing or
        broken ``dbc`` falls back to the shipped database: with every CAN bus off, the key
        does not matter.
        """
        import cantools
        from koala_bridge.drivers.can_codec import KoalaCanCodec, load_koala_dbc
        from koala_bridge.drivers.messages import DriverError

        path = self.dbc_path
        try:
            return KoalaCanCodec(load_koala_dbc(path))
        except (OSError, DriverError, ValueError,
                cantools.database.UnsupportedDatabaseFormatError) as e:
            if needed if needed is not None else self.enabled:
                reason = e.strerror if isinstance(e, OSError) and e.strerror else str(e)
                reason = reason.splitlines()[0] if reason else type(e).__name__
                raise ConfigError(
                    f"[buses.can] 'dbc': cannot load the CAN database {str(path)!r}: {reason}"
                ) from None
            log.debug("[buses.can] dbc %s not loaded (%s); no CAN bus is on", path, e)
            return KoalaCanCodec(load_koala_dbc(default_dbc_path()))


@section
class MavlinkSettings:
    """``[buses.mavlink]``: the compass as a MAVLink 2 component."""

    enabled: Bool
    transport: Annotated[Str, _one_of(MAVLINK_TRANSPORTS)]  # udp (send) | tcp (listen) | pty
    host: Str
    port: _PortKey
    system_id: Annotated[int, Strict(), Field(ge=1, le=255)]
    component_id: Annotated[int, Strict(), Field(ge=1, le=255)]
    heartbeat_hz: Positive

    def __post_init__(self) -> None:
        if self.transport == "udp" and self.port == 0:
            # UDP: host:port is where the CLIENT listens (the bridge sends datagrams there), so
            # the bridge cannot pick it; tcp listens itself and 0 picks a free port.
            raise ConfigError(
                "[buses.mavlink] 'port' 0 is not allowed with transport 'udp': host:port is the "
                "address the client (ground station) listens on and the bridge sends to, so "
                "choose it, e.g. --set buses.mavlink.port=14551 and connect with "
                "udpin:127.0.0.1:14551"
            )

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> MavlinkSettings:
        return validate(cls, d, "buses.mavlink")

    def client_url(self, pty_path: str | None = None, bound_port: int | None = None) -> str:
        """The pymavlink connection string a client uses to receive this stream."""
        if self.transport == "udp":
            return f"udpin:{self.host}:{self.port}"
        if self.transport == "tcp":
            return f"tcp:{self.host}:{bound_port if bound_port is not None else self.port}"
        if pty_path is None:
            raise ValueError("a pty MAVLink link needs its path")
        return pty_path


@section
class KteamSettings:
    """``[buses.kteam]``: the K-Team ASCII protocol server on a pty."""

    enabled: Bool
    max_speed: PositiveInt      # largest |speed| K-Team D accepts, pulses per speed unit


@section
class RangefindersSettings:
    """``[buses.rangefinders]``: binary IR / sonar frames on a pty."""

    enabled: Bool


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
        reject_unknown(d, field_names(_BusesTable) + list(_BUS_TABLES), s)
        top = validate(_BusesTable, {k: v for k, v in d.items() if k not in _BUS_TABLES}, s)
        kteam = validate(KteamSettings, _section(d, "kteam", s), f"{s}.kteam")
        ranges = validate(RangefindersSettings, _section(d, "rangefinders", s),
                          f"{s}.rangefinders")
        return cls(
            motor_watchdog_s=top.motor_watchdog_s,
            kteam=kteam.enabled,
            kteam_max_speed=kteam.max_speed,
            rangefinders=ranges.enabled,
            can=CanSettings.from_dict(_section(d, "can", s)),
            mavlink=MavlinkSettings.from_dict(_section(d, "mavlink", s)),
        )


#: The sub-tables of ``[buses]``, each its own section.
_BUS_TABLES = ("kteam", "rangefinders", "can", "mavlink")


@section
class _BusesTable:
    """``[buses]``'s own keys (its sub-tables are :data:`_BUS_TABLES`)."""

    motor_watchdog_s: NonNegative   # 0 = off


def _locators(value: tuple[str, ...]) -> tuple[str, ...]:
    if not all("/" in e for e in value):
        raise ValueError(
            f"must be a list of locators like \"tcp/127.0.0.1:7447\", got {list(value)!r}"
        )
    return value


_Locators = Annotated[tuple[Str, ...], BeforeValidator(tuples), AfterValidator(_locators)]


def _no_zero_port(value: tuple[str, ...]) -> tuple[str, ...]:
    for locator in value:
        if _ZERO_PORT.search(locator):
            # Zenoh does not report the port it picked, so neither the banner nor the
            # endpoints file could tell clients where to connect.
            raise ValueError(
                f"locator {locator!r}: port 0 is not supported (the bridge could not tell "
                "clients which port Zenoh picked); give a free port, e.g. "
                "--set 'zenoh.listen=[\"tcp/127.0.0.1:7448\"]'"
            )
    return value


def _plain_prefix(value: str) -> str:
    if any(c in value for c in "*$?#"):
        raise ValueError(f"must be a plain key expression, got {value!r}")
    return value


@section
class ZenohSettings:
    """``[zenoh]``: the session and what it publishes."""

    mode: Annotated[Str, _one_of(("peer", "client"))]
    listen: Annotated[_Locators, AfterValidator(_no_zero_port)]
    connect: _Locators
    multicast_scouting: Bool
    prefix: Annotated[Str, AfterValidator(_plain_prefix)]   # "" in the file: koala/<robot name>
    pose_rate_hz: Positive      # truth/pose, in simulation time
    status_rate_hz: Positive    # status, in simulation time

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], robot_name: str) -> ZenohSettings:
        z = validate(cls, d, "zenoh")
        # resolved: "" in the file means koala/<robot name>
        return dataclasses.replace(z, prefix=z.prefix.strip("/") or f"koala/{robot_name}")


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
