"""Hostile configuration files and ``--set`` values (issue 12, item 4): each one ends
``koala-bridge run`` with exit 2 and one line on stderr, never a traceback, a hang or a run that
dies later; a value that means something runs.

Every numeric key of ``config/default.toml`` is walked (arrays: their first number) with nan,
inf, 1e300, 0, -1 and 1e-9. nan and 1e300 are always refused, inf everywhere but where a key
says "infinitely long"; 0, -1 and 1e-9 are refused where the schema's declared range excludes
them and must RUN where it does not (e.g. a hard-iron offset of -1 uT). The bridge runs
in-process (``koala_bridge.cli.main.main``), on free loopback ports.
"""

from __future__ import annotations

import copy
import logging
import math
import subprocess
import tomllib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import tomli_w
from conftest import DEFAULT_CONFIG, bridge_command, free_port
from koala_bridge.cli.main import main

BASE: dict[str, Any] = tomllib.loads(DEFAULT_CONFIG.read_text(encoding="utf-8"))

#: Keys whose meaning has an "infinitely long" (core.schema.FloatOrInf).
INF_ALLOWED = {"sensors.gyro.bias_correlation_time_s"}
VALUES = (math.nan, math.inf, 1e300, 0.0, -1.0, 1e-9)


def numeric_keys(node: Any, path: tuple[str | int, ...] = ()) -> Iterator[tuple[str | int, ...]]:
    """The path of every number of ``node``; of an array, only its first element's."""
    if isinstance(node, bool):
        return
    if isinstance(node, int | float):
        yield path
    elif isinstance(node, dict):
        for key, value in node.items():
            yield from numeric_keys(value, (*path, key))
    elif isinstance(node, list):
        for i, value in enumerate(node):
            if i == 0 or isinstance(value, dict):  # tables of arrays: each one's keys
                yield from numeric_keys(value, (*path, i))


KEYS = list(numeric_keys(BASE))


def dotted(path: tuple[str | int, ...]) -> str:
    return ".".join(map(str, path))


def set_at(config: dict[str, Any], path: tuple[str | int, ...], value: float) -> None:
    node: Any = config
    for part in path[:-1]:
        node = node[part]
    # an integer key gets an integer where the value is one (-1, 0; not 1e300, beyond TOML's
    # 64-bit integers): the type is not what is tested
    if isinstance(node[path[-1]], int) and math.isfinite(value) and value == int(value) and (
            abs(value) < 2**63):
        value = int(value)
    node[path[-1]] = value


def on_free_ports(config: dict[str, Any]) -> dict[str, Any]:
    """``config`` on free loopback ports, written in the file (not --set, which would win over
    a walked key)."""
    out = copy.deepcopy(config)
    out["zenoh"]["listen"] = [f"tcp/127.0.0.1:{free_port()}"]
    out["buses"]["mavlink"]["port"] = free_port("udp")
    out["buses"]["can"]["socketcand_port"] = 0
    out["buses"]["can"]["virtual_channel"] = f"bad-config-{free_port()}"
    return out


@pytest.fixture
def run(tmp_path: Path, capsys: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture):
    """``run(config_or_bytes, *args)`` -> (exit status, stderr lines); a dict is written as TOML
    on free ports (the ports of the walk are set after that, so a walked port key wins)."""
    caplog.set_level(logging.ERROR)

    def go(config: dict[str, Any] | bytes | str | Path, *args: str,
           duration: bool = True) -> tuple[int, list[str]]:
        if isinstance(config, Path):
            path = config
        else:
            path = tmp_path / "hostile.toml"
            if isinstance(config, dict):
                config = tomli_w.dumps(config)
            path.write_bytes(config.encode() if isinstance(config, str) else config)
        argv = ["run", "--config", str(path), "--clock", "fast", "--log-level", "ERROR"]
        if duration:
            argv += ["--duration", "0.1"]
        caplog.clear()
        code = main([*argv, *args])  # an exception here is the traceback the test forbids
        errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
        assert not errors, [r.getMessage() for r in errors]  # no thread died along the way
        return code, capsys.readouterr().err.strip().splitlines()

    return go


def assert_refused(result: tuple[int, list[str]], *needles: str) -> None:
    code, lines = result
    assert code == 2 and len(lines) == 1, (code, lines)
    assert lines[0].startswith("koala-bridge run: ") and "Traceback" not in lines[0]
    for needle in needles:
        assert needle in lines[0], lines[0]


# --------------------------------------------------------------------------- every numeric key

@pytest.mark.parametrize("path", KEYS, ids=[dotted(p) for p in KEYS])
def test_every_numeric_key(run, path: tuple[str | int, ...]) -> None:
    name = dotted(path)
    ported = on_free_ports(BASE)
    for value in VALUES:
        if name == "run.duration_s" and value == 0:
            continue  # 0 = until stopped: meaningful, and a test must not wait for a signal
        config = copy.deepcopy(ported)
        set_at(config, path, value)
        # --duration would override the walked [run] duration_s
        code, lines = run(config, duration=name != "run.duration_s")
        must_refuse = math.isnan(value) or value == 1e300 or (
            math.isinf(value) and name not in INF_ALLOWED)
        if must_refuse or code != 0:
            assert_refused((code, lines))
            key = str(path[-1]) if isinstance(path[-1], str) else str(path[-2])
            if must_refuse:  # the line names the key (arrays: the key holding it)
                assert key in lines[0] or str(path[0]) in lines[0], (name, value, lines)


# --------------------------------------------------------------------------- hostile files

def text_with(section_line: str, replace: str, by: str) -> str:
    text = DEFAULT_CONFIG.read_text(encoding="utf-8")
    assert section_line in text and replace in text
    return text.replace(replace, by, 1)


DEEP = 10_000


@pytest.mark.parametrize(("content", "needles"), [
    (bytes(range(256)) * 4, ["not a UTF-8 text file"]),
    (b"\x89PNG\r\n\x1a\n" + bytes(200), ["not a UTF-8 text file"]),
    (DEFAULT_CONFIG.read_text().encode("utf-16"), ["UTF-16", "save it as UTF-8"]),
    (DEFAULT_CONFIG.read_text().encode("utf-16-le"), ["not a UTF-8 text file"]),
    (b"\xef\xbb\xbf" + DEFAULT_CONFIG.read_bytes(), ["invalid TOML"]),      # UTF-8 BOM
    (b"[run]\nclock = \"fast\x00\"\n", ["invalid TOML"]),
    (b"", ["missing required key"]),
    (b"a = " + b"[" * DEEP + b"]" * DEEP, ["nested more than"]),
    (b"a = " + b"{b = " * DEEP + b"1" + b"}" * DEEP, ["nested more than"]),
    (("[" + ".".join(["run"] * DEEP) + "]\nx = 1\n").encode(), ["nested more than"]),
    (("[" + ".".join(["deep"] * DEEP) + "]\nx = 1\n").encode(), ["nested more than"]),
    (b"x = 1\n" * (1 << 20), ["is not a configuration"]),
    (b"run = [1, 2]\n", ["[run] must be a table"]),
])
def test_hostile_files(run, content: bytes, needles: list[str]) -> None:
    assert_refused(run(content), *needles)


def test_a_directory_is_not_a_config(run, tmp_path: Path) -> None:
    assert_refused(run(tmp_path), "cannot read config file")


# --------------------------------------------------------------------------- values and types

@pytest.mark.parametrize(("old", "new", "needles"), [
    ("horizontal_uT = 20.0", "horizontal_uT = nan", ["'horizontal_uT' must be a finite"]),
    ("dt_s = 0.01", "dt_s = 1e-9", ["[sim] 'dt_s' must be >="]),
    ("wheel_base_m = 0.285", 'wheel_base_m = "0.285"',
     ["[robot] 'wheel_base_m' must be a number, got '0.285'"]),
    ("port = 14550", 'port = "14550"', ["[buses.mavlink] 'port' must be"]),
    ("heartbeat_hz = 1.0", "heartbeat_hz = true", ["'heartbeat_hz' must be a number"]),
    ("max_speed = 127", "max_speed = 127.5", ["'max_speed' must be an integer"]),
    ("seed = 1 ", "seed = 1e300 ", ["'seed'"]),
])
def test_bad_values_in_the_file(run, old: str, new: str, needles: list[str]) -> None:
    text = DEFAULT_CONFIG.read_text(encoding="utf-8")
    assert old in text
    assert_refused(run(text.replace(old, new, 1)), *needles)


@pytest.fixture
def default_on_free_ports(tmp_path: Path) -> Path:
    path = tmp_path / "ports.toml"
    path.write_text(tomli_w.dumps(on_free_ports(BASE)))
    return path


@pytest.mark.parametrize(("override", "needles"), [
    ("robot.wheel_base_m=true", ["[robot] 'wheel_base_m' must be a number, got True"]),
    ('robot.wheel_base_m="0.285"', ["must be a number, got '0.285'"]),
    ("robot.wheel_base_m=abc", ["must be a number, got 'abc'"]),
    ("robot.wheel_base_m=[0.285", ["is not a TOML value"]),
    ("zenoh.listen=[\"tcp/127.0.0.1:7447\"", ["is not a TOML value"]),
    ("robot.name={a = ", ["is not a TOML value"]),
    ('robot.name="unterminated', ["is not a TOML value"]),
    ("robot.wheel_base_m=" + "[" * DEEP + "]" * DEEP, ["nested too deeply"]),
    ("robot.wheel_base_m=1\nx = 2", ["more than one TOML value"]),
    ("world.earth_field.horizontal_uT=nan", ["'horizontal_uT' must be a finite"]),
    ("sim.dt_s=1e-9", ["'dt_s' must be >="]),
    ("buses.mavlink.port=14550.0", ["'port' must be"]),
    ("buses.can.socketcand_port=-1", ["'socketcand_port'"]),
])
def test_bad_overrides(run, default_on_free_ports: Path, override: str,
                       needles: list[str]) -> None:
    assert_refused(run(default_on_free_ports, "--set", override), *needles)


# --------------------------------------------------------------------------- names and endpoints

@pytest.mark.parametrize("prefix", ["*", "koala/*", "koala/**", "$*", "a$b", "a//b", "/koala",
                                    "koala/", "/", "a b", "a?b", "a#b", "tab\there"])
def test_invalid_zenoh_prefix(run, default_on_free_ports: Path, prefix: str) -> None:
    assert_refused(run(default_on_free_ports, "--set", f"zenoh.prefix={tomli_w_str(prefix)}"),
                   "[zenoh] 'prefix' must be")


def tomli_w_str(text: str) -> str:
    return tomli_w.dumps({"v": text})[4:].strip()


@pytest.mark.parametrize("prefix", ["", "lab/koala1"])
def test_valid_zenoh_prefix_runs(run, default_on_free_ports: Path, prefix: str) -> None:
    code, lines = run(default_on_free_ports, "--set", f"zenoh.prefix={tomli_w_str(prefix)}")
    assert code == 0, lines


@pytest.mark.parametrize("key", ["listen", "connect"])
@pytest.mark.parametrize("locator", [
    "", "tcp", "tcp/", "tcp/127.0.0.1", "tcp/:7447", "127.0.0.1:7447", "tcp/127.0.0.1:99999",
    "tcp/127.0.0.1:abc", "foo/127.0.0.1:7447", "tcp/[::1:7447", "tcp/127.0.0.1:7447 x",
    "tcp//127.0.0.1:7447",
])
def test_invalid_zenoh_endpoints(run, default_on_free_ports: Path, key: str,
                                 locator: str) -> None:
    assert_refused(run(default_on_free_ports, "--set", f"zenoh.{key}=[{tomli_w_str(locator)}]"),
                   f"[zenoh] '{key}' must be a list of locators")


@pytest.mark.parametrize("key", ["listen", "connect"])
def test_zenoh_endpoints_must_be_a_list(run, default_on_free_ports: Path, key: str) -> None:
    assert_refused(run(default_on_free_ports, "--set", f'zenoh.{key}="tcp/127.0.0.1:7447"'),
                   f"[zenoh] '{key}' must be a list")


@pytest.mark.parametrize(("key", "value"), [
    ("channel", ""), ("channel", "koala 0"), ("channel", "<koala>"), ("channel", "a/b"),
    ("channel", "k\u00f6ala"), ("channel", "x" * 65), ("channel", "a\\b"),
    ("socketcan_channel", ""), ("socketcan_channel", "vcan0/x"), ("socketcan_channel", "x" * 16),
    ("socketcan_channel", "can 0"), ("virtual_channel", ""), ("virtual_channel", "a\nb"),
])
def test_invalid_can_channel_names(run, default_on_free_ports: Path, key: str,
                                   value: str) -> None:
    assert_refused(run(default_on_free_ports, "--set", f"buses.can.{key}={tomli_w_str(value)}"),
                   f"[buses.can] '{key}' must be a")


@pytest.mark.parametrize("name", ["", "koala 1", "a/b", "k*", "tab\tname"])
def test_invalid_robot_name(run, default_on_free_ports: Path, name: str) -> None:
    assert_refused(run(default_on_free_ports, "--set", f"robot.name={tomli_w_str(name)}"),
                   "[robot] 'name' must be a plain word")


# --------------------------------------------------------------------------- the real entry point

@pytest.mark.parametrize("content", [
    bytes(range(256)),
    b"a = " + b"[" * DEEP + b"]" * DEEP,
    ("[" + ".".join(["run"] * DEEP) + "]\n").encode(),
], ids=["binary", "deep-arrays", "deep-headers"])
def test_in_a_subprocess(tmp_path: Path, content: bytes) -> None:
    """The installed entry point (its own interpreter, stack and logging) says the same."""
    path = tmp_path / "hostile.toml"
    path.write_bytes(content)
    p = subprocess.run(bridge_command("run", "--config", str(path), "--duration", "0.1",
                                      "--clock", "fast"),
                       cwd=tmp_path, capture_output=True, text=True, timeout=120,
                       stdin=subprocess.DEVNULL)
    assert "Traceback" not in p.stderr + p.stdout
    lines = p.stderr.strip().splitlines()
    assert p.returncode == 2 and len(lines) == 1, (p.returncode, p.stderr)
    assert str(path) in lines[0]
