"""``[[robots]]``: several Koalas in one world, each with its own configuration.

A configuration without ``[[robots]]`` is one robot, as always. With it, each entry is one robot::

    [[robots]]
    name = "alpha"                                   # required: a plain word, unique
    start = { x = 1.3, y = 1.75, theta_deg = 0.0 }   # required: its start pose
    seed_offset = 0                                  # optional: its random streams (default: index)
    [robots.buses.mavlink]                           # optional: any key of these sections
    port = 14560

and the robot's configuration is the file's, with the entry's own sections laid over it (tables
merge key by key, a value replaces). An entry may hold ``robot``, ``sensors``, ``buses``,
``localisation``, ``lockstep``, ``faults`` (its own ``[[faults]]``) and, of ``zenoh``, the keys
``prefix``, ``pose_rate_hz`` and ``status_rate_hz``; ``sim``, ``world`` and ``run`` are the
world's and the clock's, one for all, and the Zenoh session (``listen``, ``connect``, ...) is one
for all.

Defaults chosen so that no two robots clash (an entry that sets a key keeps its value):

- Zenoh prefix: ``koala/<name>``, or ``<[zenoh] prefix>/<name>`` when the file sets a prefix;
- ``[buses.can] socketcand_port = 0`` (a free port, named in the endpoints file) and
  ``virtual_channel = "<virtual_channel>-<name>"``;
- ``[buses.mavlink]``: with ``transport = "udp"`` the port is the file's plus the robot's index
  (14550, 14551, ...: the ground station's ports; a file's 0 stays 0, a free port each), with
  ``"tcp"`` 0 (a free port); ``system_id``
  is the file's plus the index (a ground station tells vehicles apart by it);
- the ptys (K-Team, range frames, slcan) are new devices for each robot anyway.

What still clashes (two robots on one port, one prefix, one SocketCAN interface; bodies that
overlap at the start) is a :class:`ConfigError`. Random streams: robot ``i`` draws from
``SeedSequence(seed, spawn_key=(seed_offset_i,))`` (sim/fleet.py).
"""

from __future__ import annotations

import copy
import math
import re
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

from koala_bridge.core.schema import ConfigError, reject_unknown

__all__ = ["ROBOT_ENTRY_KEYS", "RobotEntry", "check_clashes", "entry_errors", "robot_entries"]

#: The keys of one ``[[robots]]`` entry.
ROBOT_ENTRY_KEYS = ("name", "start", "seed_offset", "robot", "sensors", "buses", "zenoh",
                    "localisation", "lockstep", "faults")
#: The ``[zenoh]`` keys a robot may set for itself (the session is one for all robots).
ZENOH_ROBOT_KEYS = ("prefix", "pose_rate_hz", "status_rate_hz")
_START_KEYS = ("x", "y", "theta_deg")


@dataclass(frozen=True)
class RobotEntry:
    """One robot of ``[[robots]]``: its name, index, random-stream key and whole configuration
    (the file's with the entry laid over it, without ``[[robots]]``)."""

    name: str
    index: int
    stream_key: int
    config: dict[str, Any]
    own: Mapping[str, Any] = field(default_factory=dict)
    """The entry as the file writes it (its errors are reported at its path:
    :func:`entry_errors`)."""


def robot_entries(config: Mapping[str, Any]) -> list[RobotEntry] | None:
    """The robots of ``[[robots]]`` (module docstring), or None when the file has none."""
    entries = config.get("robots")
    if entries is None:
        return None
    if not isinstance(entries, list) or not entries or not all(
            isinstance(e, Mapping) for e in entries):
        raise ConfigError("[[robots]] must be an array of tables, one per robot "
                          "([[robots]] name = \"a\" start = {x = 1.0, y = 1.0, theta_deg = 0})")
    if config.get("faults"):
        raise ConfigError("[[faults]] (and --fault) with [[robots]]: put each robot's faults in "
                          "its entry ([[robots.faults]]), so that each names its robot")
    base = {k: copy.deepcopy(v) for k, v in config.items() if k not in ("robots", "faults")}
    out: list[RobotEntry] = []
    names: set[str] = set()
    keys: set[int] = set()
    for i, entry in enumerate(entries):
        where = f"robots.{i}"
        reject_unknown(entry, ROBOT_ENTRY_KEYS, where)
        for needed in ("name", "start"):
            if needed not in entry:
                raise ConfigError(
                    f"[{where}] has no '{needed}': each [[robots]] entry needs name = \"...\" "
                    "(a plain word, unique) and start = {x = .., y = .., theta_deg = ..} (the "
                    "robot's start pose in the world); the rest is optional (docs/multirobot.md)")
        name = entry["name"]
        if (not isinstance(name, str) or not name or not name.isprintable()
                or any(c.isspace() or c in "/*$?#\\" for c in name)):
            raise ConfigError(f"[{where}] 'name' must be a plain word, got {name!r}")
        if name in names:
            raise ConfigError(f"[{where}] 'name' {name!r} is taken by another robot")
        names.add(name)
        key = entry.get("seed_offset", i)
        if isinstance(key, bool) or not isinstance(key, int) or not 0 <= key < 2**32:
            raise ConfigError(f"[{where}] 'seed_offset' must be an integer 0..2^32-1, got {key!r}")
        if key in keys:
            raise ConfigError(f"[{where}] 'seed_offset' {key} is another robot's: two robots "
                              "would draw the same noise")
        keys.add(key)
        start = entry["start"]
        if not isinstance(start, Mapping):
            raise ConfigError(f"[{where}] 'start' must be a table {{x = .., y = .., "
                              f"theta_deg = ..}}, got {start!r}")
        reject_unknown(start, _START_KEYS, f"{where}.start")
        for k in ("x", "y"):
            if k not in start:
                raise ConfigError(f"[{where}.start] has no '{k}': a robot's start is "
                                  "{x = .., y = .., theta_deg = ..} (m, m, degrees)")
        zenoh = entry.get("zenoh", {})
        if isinstance(zenoh, Mapping):
            for k in zenoh:
                if k not in ZENOH_ROBOT_KEYS:
                    raise ConfigError(
                        f"[{where}.zenoh] '{k}' is the Zenoh session's, one for every robot: set "
                        f"it in [zenoh]; a robot sets only {', '.join(ZENOH_ROBOT_KEYS)}")
        out.append(RobotEntry(name, i, key, _robot_config(base, entry, i, name), dict(entry)))
    return out


@contextmanager
def entry_errors(entry: RobotEntry) -> Iterator[None]:
    """Report a :class:`ConfigError` raised while robot ``entry``'s configuration is built
    (typed sections, simulator) at the entry's path when the entry set the key at fault:
    ``[robots.1.buses.kteam] unknown key 'dialekt'`` rather than ``[buses.kteam] ...``, which
    a reader looks for in the file's top-level tables; its start pose as ``[robots.1.start]``.
    An error in a key the entry does not set is the file's and stays as it is."""
    try:
        yield
    except ConfigError as e:
        text = str(e)
        found = _ERROR_PLACE.match(text)
        if found is None:
            raise
        path, rest = found.group(1), found.group(2)
        where = f"robots.{entry.index}"
        if path == "world.start":
            raise ConfigError(f"[{where}.start] robot {entry.name!r}: "
                              f"{rest.strip()}") from e
        key = _ERROR_KEY.search(rest)
        table: Any = entry.own
        for part in path.split("."):
            table = table.get(part) if isinstance(table, Mapping) else None
        if key is None or not isinstance(table, Mapping) or key.group(1) not in table:
            raise
        rest = rest.replace(f"({path}.", f"({where}.{path}.")
        raise ConfigError(f"[{where}.{path}]{rest}") from e


#: ``[section.path] the rest`` of a :class:`ConfigError` message (core/schema.py), and the key
#: it names first (``unknown key 'dialekt'``, ``'port' must be ...``).
_ERROR_PLACE = re.compile(r"^\[([\w.]+)\](.*)$", re.DOTALL)
_ERROR_KEY = re.compile(r"'([^']+)'")


def _robot_config(base: Mapping[str, Any], entry: Mapping[str, Any], index: int,
                  name: str) -> dict[str, Any]:
    cfg = copy.deepcopy(dict(base))
    own = {k: v for k, v in entry.items() if k not in ("name", "start", "seed_offset")}
    _merge(cfg, own)
    cfg.setdefault("robot", {})["name"] = name
    cfg.setdefault("world", {})["start"] = dict(entry["start"])
    buses_in = _table(own, "buses")
    can_in, mav_in = _table(buses_in, "can"), _table(buses_in, "mavlink")
    can = cfg.setdefault("buses", {}).setdefault("can", {})
    if "socketcand_port" not in can_in:
        can["socketcand_port"] = 0
    if "virtual_channel" not in can_in:
        can["virtual_channel"] = f"{can.get('virtual_channel', 'koala')}-{name}"
    mav = cfg["buses"].setdefault("mavlink", {})
    if "port" not in mav_in and isinstance(mav.get("port"), int):
        if mav.get("transport") == "udp" and mav["port"] != 0:
            # (port 0 stays 0: each robot gets a free port of its own, in the endpoints file)
            mav["port"] = mav["port"] + index
        elif mav.get("transport") == "tcp":
            mav["port"] = 0
    if "system_id" not in mav_in and isinstance(mav.get("system_id"), int):
        mav["system_id"] = mav["system_id"] + index
        if mav["system_id"] > 255:
            raise ConfigError(f"[robots.{index}] MAVLink system_id {mav['system_id']} > 255: "
                              "set [robots.buses.mavlink] system_id for this robot")
    zenoh = cfg.setdefault("zenoh", {})
    if "prefix" not in _table(own, "zenoh"):
        base_prefix = _table(base, "zenoh").get("prefix", "")
        zenoh["prefix"] = f"{base_prefix}/{name}" if base_prefix else ""
    return cfg


def _table(d: Mapping[str, Any], key: str) -> Mapping[str, Any]:
    v = d.get(key, {})
    return v if isinstance(v, Mapping) else {}


def _merge(into: dict[str, Any], over: Mapping[str, Any]) -> None:
    """Lay ``over`` on ``into``: tables merge key by key, any other value replaces."""
    for k, v in over.items():
        if isinstance(v, Mapping) and isinstance(into.get(k), dict):
            _merge(into[k], v)
        else:
            into[k] = copy.deepcopy(v)


def check_clashes(entries: list[RobotEntry], settings: list[Any], radii: list[float]) -> None:
    """:class:`ConfigError` when two robots would share a Zenoh prefix, a port, a CAN channel,
    or overlap at the start (``settings``: each robot's :class:`BridgeSettings`)."""
    seen: dict[tuple[str, ...], str] = {}

    def claim(what: tuple[str, ...], name: str, text: str) -> None:
        other = seen.get(what)
        if other is not None:
            raise ConfigError(f"[[robots]] {other!r} and {name!r} share {text}: set it in one "
                              "robot's entry")
        seen[what] = name

    for e, s in zip(entries, settings, strict=True):
        claim(("zenoh", s.zenoh.prefix), e.name, f"the Zenoh prefix {s.zenoh.prefix!r}")
        can = s.buses.can
        if can.socketcand and can.socketcand_port:
            claim(("tcp", can.socketcand_host, str(can.socketcand_port)), e.name,
                  f"the socketcand port {can.socketcand_port}")
        if can.virtual:
            claim(("virtual", can.virtual_channel), e.name,
                  f"the virtual CAN channel {can.virtual_channel!r}")
        if can.socketcan:
            claim(("socketcan", can.socketcan_channel), e.name,
                  f"the SocketCAN interface {can.socketcan_channel!r}")
        mav = s.buses.mavlink
        if mav.enabled and mav.transport != "pty" and mav.port:
            claim((mav.transport, mav.host, str(mav.port)), e.name,
                  f"the MAVLink {mav.transport} port {mav.port}")
    for i, a in enumerate(entries):
        for j in range(i):
            b = entries[j]
            sa, sb = a.config["world"]["start"], b.config["world"]["start"]
            d = math.hypot(float(sa["x"]) - float(sb["x"]), float(sa["y"]) - float(sb["y"]))
            if d < radii[i] + radii[j]:
                raise ConfigError(
                    f"[[robots]] {b.name!r} and {a.name!r} start {d:.3f} m apart, closer than "
                    f"their bodies allow ({radii[i] + radii[j]:.3f} m): move one 'start'")
