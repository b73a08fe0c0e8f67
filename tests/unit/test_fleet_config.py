"""[[robots]] (runtime/fleet_config.py): each robot's configuration, defaults that never clash,
and errors that say what to change."""

from __future__ import annotations

import copy
import tomllib
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
from koala_bridge.core.schema import ConfigError
from koala_bridge.runtime.endpoints import Endpoints, FleetEndpoints
from koala_bridge.runtime.fleet_config import check_clashes, robot_entries
from koala_bridge.runtime.settings import BridgeSettings, load_config

REPO = Path(__file__).resolve().parents[2]


def _config(*robots: dict[str, Any]) -> dict[str, Any]:
    config = load_config(REPO / "config" / "default.toml")
    config["robots"] = list(robots) or [
        {"name": "a", "start": {"x": 1.3, "y": 1.75, "theta_deg": 0.0}},
        {"name": "b", "start": {"x": 2.2, "y": 1.75, "theta_deg": 180.0}},
    ]
    return config


def _settings(config: dict[str, Any]) -> list[BridgeSettings]:
    entries = robot_entries(config)
    assert entries is not None
    return [BridgeSettings.from_config(e.config) for e in entries]


def test_no_robots_is_one_robot() -> None:
    assert robot_entries(load_config(REPO / "config" / "default.toml")) is None


def test_defaults_never_clash() -> None:
    config = _config()
    entries = robot_entries(config)
    assert entries is not None
    a, b = _settings(config)
    assert (a.zenoh.prefix, b.zenoh.prefix) == ("koala/a", "koala/b")
    assert (a.buses.can.socketcand_port, b.buses.can.socketcand_port) == (0, 0)
    assert (a.buses.can.virtual_channel, b.buses.can.virtual_channel) == ("koala-a", "koala-b")
    assert (a.buses.mavlink.port, b.buses.mavlink.port) == (14550, 14551)
    assert (a.buses.mavlink.system_id, b.buses.mavlink.system_id) == (1, 2)
    assert [e.stream_key for e in entries] == [0, 1]
    assert entries[1].config["world"]["start"] == {"x": 2.2, "y": 1.75, "theta_deg": 180.0}
    assert "robots" not in entries[0].config
    check_clashes(entries, [a, b], [0.19, 0.19])


def test_a_mavlink_udp_port_0_is_a_free_port_for_every_robot() -> None:
    """Port 0 is "any free port" (each robot binds its own; the endpoints file names it), not
    a base to count from: robot 1 must not get port 1."""
    config = _config()
    config["buses"]["mavlink"]["port"] = 0
    a, b = _settings(config)
    assert (a.buses.mavlink.port, b.buses.mavlink.port) == (0, 0)


def test_a_robot_sets_its_own_keys_and_a_file_prefix_is_the_parent() -> None:
    config = _config(
        {"name": "a", "start": {"x": 1.3, "y": 1.75}, "seed_offset": 7,
         "buses": {"mavlink": {"port": 15000}, "kteam": {"dialect": "koala25"}},
         "zenoh": {"prefix": "lab/first"}},
        {"name": "b", "start": {"x": 2.2, "y": 1.75}},
    )
    config["zenoh"]["prefix"] = "lab"
    a, b = _settings(config)
    assert a.buses.mavlink.port == 15000 and b.buses.mavlink.port == 14551
    assert (a.buses.kteam_dialect, b.buses.kteam_dialect) == ("koala25", "koala1")
    assert (a.zenoh.prefix, b.zenoh.prefix) == ("lab/first", "lab/b")
    entries = robot_entries(config)
    assert entries is not None and entries[0].stream_key == 7


@pytest.mark.parametrize(("robots", "message"), [
    ([{"name": "a", "start": {"x": 1, "y": 1}, "strat": {}}], "did you mean 'start'"),
    ([{"name": "a"}], "has no 'start': each \\[\\[robots\\]\\] entry needs name"),
    ([{"start": {"x": 1, "y": 1}}], "robots.0\\] has no 'name'"),
    ([{"name": "a", "start": {"y": 1}}], "robots.0.start\\] has no 'x'"),
    ([{"name": "a", "start": {"x": 1, "y": 1, "theta": 0}}], "theta_deg"),
    ([{"name": "a b", "start": {"x": 1, "y": 1}}], "plain word"),
    ([{"name": "a", "start": {"x": 1, "y": 1}}, {"name": "a", "start": {"x": 2, "y": 1}}],
     "taken by another robot"),
    ([{"name": "a", "start": {"x": 1, "y": 1}, "seed_offset": 1},
      {"name": "b", "start": {"x": 2, "y": 1}}], "same noise"),
    ([{"name": "a", "start": {"x": 1, "y": 1}, "world": {}}], "unknown key 'world'"),
    ([{"name": "a", "start": {"x": 1, "y": 1}, "zenoh": {"listen": []}}],
     "the Zenoh session's"),
])
def test_bad_entries_say_what_to_change(robots: list[dict[str, Any]], message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        robot_entries(_config(*robots))


def test_top_level_faults_must_name_their_robot() -> None:
    config = _config()
    config["faults"] = [{"kind": "drop", "target": "can"}]
    with pytest.raises(ConfigError, match=r"\[\[robots.faults\]\]"):
        robot_entries(config)


@pytest.mark.parametrize(("override", "message"), [
    ({"buses": {"mavlink": {"port": 14550}}}, "MAVLink udp port 14550"),
    ({"buses": {"can": {"socketcand_port": 30000}}}, None),
    ({"zenoh": {"prefix": "koala/a"}}, "Zenoh prefix"),
    ({"buses": {"can": {"virtual_channel": "koala-a"}}}, "virtual CAN channel"),
])
def test_clashes_are_refused(override: dict[str, Any], message: str | None) -> None:
    robots = [{"name": "a", "start": {"x": 1.3, "y": 1.75}},
              {"name": "b", "start": {"x": 2.2, "y": 1.75}, **override}]
    if message is None:     # the same socketcand port set for both
        robots[0] = {**robots[0], **copy.deepcopy(override)}
        message = "socketcand port 30000"
    config = _config(*robots)
    entries = robot_entries(config)
    assert entries is not None
    with pytest.raises(ConfigError, match=message):
        check_clashes(entries, _settings(config), [0.19, 0.19])


def test_overlapping_starts_are_refused() -> None:
    config = _config({"name": "a", "start": {"x": 1.3, "y": 1.75}},
                     {"name": "b", "start": {"x": 1.6, "y": 1.75}})
    entries = robot_entries(config)
    assert entries is not None
    with pytest.raises(ConfigError, match="closer than their bodies allow"):
        check_clashes(entries, _settings(config), [0.19, 0.19])


def test_fleet_endpoints_file_names_each_robot() -> None:
    one = Endpoints(kteam="/dev/pts/7", zenoh_prefix="koala/a")
    fleet = FleetEndpoints(robots=(("a", one), ("b", Endpoints(zenoh_prefix="koala/b"))))
    doc = fleet.to_json_dict()
    assert list(doc) == ["robots"] and list(doc["robots"]) == ["a", "b"]
    assert doc["robots"]["a"] == one.to_json_dict()      # each robot: the one-robot format
    assert "Robot b:" in fleet.describe() and "Foxglove" not in fleet.describe()
    # run --foxglove: one server for every robot, its URL beside "robots"
    served = replace(fleet, foxglove_url="ws://127.0.0.1:8765")
    assert served.to_json_dict() == {**doc, "foxglove": {"url": "ws://127.0.0.1:8765"}}
    assert "Foxglove (live view)    ws://127.0.0.1:8765" in served.describe()


def test_example_is_the_default_config_plus_robots() -> None:
    with (REPO / "examples" / "two_robots.toml").open("rb") as f:
        example = tomllib.load(f)
    with (REPO / "config" / "default.toml").open("rb") as f:
        default = tomllib.load(f)
    robots = example.pop("robots")
    assert example == default
    assert [r["name"] for r in robots] == ["alpha", "beta"]
    config = {**load_config(REPO / "examples" / "two_robots.toml")}
    entries = robot_entries(config)
    assert entries is not None
    check_clashes(entries, _settings(config), [0.19, 0.19])


def _fleet(config: dict[str, Any]) -> None:
    from koala_bridge.runtime.fleet_source import FleetSource

    entries = robot_entries(config)
    assert entries is not None
    FleetSource(config, BridgeSettings.from_config(config), entries)


@pytest.mark.parametrize(("start", "message"), [
    ({"x": 3.5, "y": 1.0}, r"^\[robots.1.start\] robot 'b': x = 3.5, y = 1 is outside the world "
                           r"\(x 0..3 m, y 0..3 m\)$"),
    ({"x": 2.2, "y": -0.1}, "outside the world"),
    ({"x": 2.2, "y": 0.1}, r"^\[robots.1.start\] robot 'b': x = 2.2, y = 0.1: the robot's body "
                           r"\(radius 0.19 m\) overlaps the wall"),
])
def test_a_start_outside_the_world_or_in_a_wall_is_refused(start: dict[str, float],
                                                           message: str) -> None:
    config = _config({"name": "a", "start": {"x": 1.3, "y": 1.75}}, {"name": "b", "start": start})
    with pytest.raises(ConfigError, match=message):
        _fleet(config)


def test_an_entry_typo_is_reported_at_the_entry_path() -> None:
    config = _config({"name": "a", "start": {"x": 1.3, "y": 1.75}},
                     {"name": "b", "start": {"x": 2.2, "y": 1.75},
                      "buses": {"kteam": {"dialekt": "koala25"}}})
    with pytest.raises(ConfigError, match=r"^\[robots.1.buses.kteam\] unknown key 'dialekt'; "
                       r"did you mean 'dialect' \(robots.1.buses.kteam.dialect\)\?$"):
        _fleet(config)


def test_a_file_typo_stays_the_files() -> None:
    """A key the entry does not set is the file's: its error keeps the file's path."""
    config = _config({"name": "a", "start": {"x": 1.3, "y": 1.75},
                      "sensors": {"ir": {"rate_hz": 10.0}}})
    config["sensors"]["ir"]["rat_hz"] = 1
    with pytest.raises(ConfigError, match=r"^\[sensors.ir\] unknown key 'rat_hz'"):
        _fleet(config)
