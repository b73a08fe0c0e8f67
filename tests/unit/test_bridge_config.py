"""runtime/settings.py: TOML loading, --set overrides (CLI > file), helpful errors."""

from __future__ import annotations

from pathlib import Path

import pytest
from koala_bridge.runtime.settings import (
    BridgeSettings,
    ConfigError,
    apply_override,
    load_config,
    parse_override,
)

REPO = Path(__file__).resolve().parents[2]


def default() -> dict:
    return load_config(REPO / "config" / "default.toml")


def test_default_config_types() -> None:
    s = BridgeSettings.from_config(default())
    assert s.run.clock == "realtime"
    assert s.zenoh.listen == ("tcp/127.0.0.1:7447",)
    assert s.zenoh.multicast_scouting is False
    assert s.zenoh.prefix == f"koala/{s.robot_name}"
    assert s.buses.mavlink.client_url() == "udpin:127.0.0.1:14550"
    assert s.buses.can.socketcand_host == "127.0.0.1"


@pytest.mark.parametrize(
    ("text", "parts", "value"),
    [
        ("buses.mavlink.port=14551", ["buses", "mavlink", "port"], 14551),
        ('zenoh.listen=["tcp/127.0.0.1:1"]', ["zenoh", "listen"], ["tcp/127.0.0.1:1"]),
        ("robot.name=k2", ["robot", "name"], "k2"),
        ("run.duration_s = 2.5", ["run", "duration_s"], 2.5),
        ("buses.kteam.enabled=false", ["buses", "kteam", "enabled"], False),
    ],
)
def test_parse_override(text: str, parts: list[str], value: object) -> None:
    assert parse_override(text) == (parts, value)


def test_override_wins_over_file_and_does_not_mutate_it() -> None:
    cfg = default()
    out = apply_override(cfg, *parse_override("robot.name=k2"))
    assert BridgeSettings.from_config(out).zenoh.prefix == "koala/k2"
    assert cfg["robot"]["name"] == "koala"


def test_unknown_key_suggests_nearest() -> None:
    cfg = apply_override(default(), *parse_override("zenoh.pose_rate=5"))
    nearest = r"\[zenoh\] unknown key 'pose_rate'; did you mean 'pose_rate_hz'"
    with pytest.raises(ConfigError, match=nearest):
        BridgeSettings.from_config(cfg)


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("run.clock=slow", "'clock' must be one of realtime, fast"),
        ("buses.mavlink.transport=serial", "'transport' must be one of udp, tcp, pty"),
        ("buses.mavlink.port=70000", "port 0..65535"),
        ("buses.can.socketcand=1", "'socketcand' must be bool"),
        ("zenoh.listen=[\"7447\"]", "list of locators"),
        ("zenoh.status_rate_hz=0", "'status_rate_hz' must be > 0"),
        ("run.duration_s=-1", "'duration_s' must be a finite number >= 0"),
        ("run.duration_s=inf", "'duration_s' must be a finite number >= 0"),
        ("run.duration_s=nan", "'duration_s' must be a finite number >= 0"),
        ("robot.name=a/b", "plain word"),
    ],
)
def test_bad_values_are_named(override: str, message: str) -> None:
    cfg = apply_override(default(), *parse_override(override))
    with pytest.raises(ConfigError, match=message):
        BridgeSettings.from_config(cfg)


def test_unknown_section_suggests_nearest() -> None:
    cfg = apply_override(default(), *parse_override("bueses.kteam.enabled=false"))
    with pytest.raises(ConfigError, match=r"unknown section \[bueses\]; did you mean \[buses\]"):
        BridgeSettings.from_config(cfg)
    cfg = apply_override(default(), *parse_override("xyzzy.a=1"))
    with pytest.raises(ConfigError, match=r"unknown section \[xyzzy\]; valid: sim, robot"):
        BridgeSettings.from_config(cfg)
    cfg = apply_override(default(), *parse_override('real.kteam="/dev/ttyUSB0"'))
    BridgeSettings.from_config(cfg)  # [real] is a section of run --source real


def test_missing_key_is_named() -> None:
    cfg = default()
    del cfg["buses"]["mavlink"]["heartbeat_hz"]
    with pytest.raises(ConfigError, match=r"\[buses.mavlink\] missing required key 'heartbeat_hz'"):
        BridgeSettings.from_config(cfg)


def test_file_errors(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="config file not found"):
        load_config(tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[run]\nclock = \n")
    with pytest.raises(ConfigError, match=r"bad.toml: invalid TOML.*line 2"):
        load_config(bad)


def test_override_syntax_errors() -> None:
    with pytest.raises(ConfigError, match="section.key=value"):
        parse_override("buses.mavlink.port")
    with pytest.raises(ConfigError, match="is a value, not a section"):
        apply_override(default(), *parse_override("run.clock.x=1"))


def test_port_zero_where_the_bridge_reports_the_port() -> None:
    """socketcand and MAVLink over TCP listen themselves: 0 = any free port (the endpoints file
    has the real one). Zenoh locators with a port that merely contains 0 are fine."""
    cfg = default()
    for override in (
        "buses.can.socketcand_port=0",
        'buses.mavlink.transport="tcp"',
        "buses.mavlink.port=0",
        'zenoh.listen=["tcp/127.0.0.1:7000", "tcp/[::1]:10"]',
    ):
        cfg = apply_override(cfg, *parse_override(override))
    s = BridgeSettings.from_config(cfg)
    assert s.buses.can.socketcand_port == 0
    assert (s.buses.mavlink.transport, s.buses.mavlink.port) == ("tcp", 0)
    assert s.zenoh.listen == ("tcp/127.0.0.1:7000", "tcp/[::1]:10")


def test_relative_file_paths_are_relative_to_the_config_file(tmp_path: Path) -> None:
    """A config copied with its DBC (``config init``) finds the DBC beside it from any working
    directory; an absolute path and "" (the shipped file) are kept; --set paths stay as given."""
    folder = tmp_path / "mycfg"
    folder.mkdir()
    text = (REPO / "config" / "default.toml").read_text()
    text = text.replace('dbc = ""', 'dbc = "koala.dbc"', 1)
    text = text.replace('config_file = ""', f'config_file = "{tmp_path / "z.json5"}"', 1)
    (folder / "default.toml").write_text(text)
    config = load_config(folder / "default.toml")
    assert config["buses"]["can"]["dbc"] == str(folder / "koala.dbc")
    assert config["zenoh"]["config_file"] == str(tmp_path / "z.json5")
    assert config["buses"]["mavlink"]["signing_key_file"] == ""
    overridden = apply_override(config, *parse_override("buses.can.dbc='other.dbc'"))
    assert overridden["buses"]["can"]["dbc"] == "other.dbc"


def test_kteam_dialect_defaults_to_koala1() -> None:
    assert BridgeSettings.from_config(default()).buses.kteam_dialect == "koala1"


def test_kteam_dialect_is_koala1_or_koala25() -> None:
    cfg = apply_override(default(), ["buses", "kteam", "dialect"], "koala25")
    assert BridgeSettings.from_config(cfg).buses.kteam_dialect == "koala25"
    cfg = apply_override(default(), ["buses", "kteam", "dialect"], "koala2")
    with pytest.raises(ConfigError, match=r"must be one of koala1, koala25, got 'koala2'"):
        BridgeSettings.from_config(cfg)


def test_kteam_dialect_unknown_value_is_an_error() -> None:
    cfg = apply_override(default(), ["buses", "kteam", "dialect"], "koala3")
    with pytest.raises(ConfigError, match="dialect"):
        BridgeSettings.from_config(cfg)
