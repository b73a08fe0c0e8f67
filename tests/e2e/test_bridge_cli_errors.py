"""What a new user meets first: every mistake on the command line or in the configuration, and a
port another program holds, ends `koala-bridge` with one clear line on stderr and a non-zero exit
(2: the request is wrong; 1: the machine refused), never a traceback; every `--help` teaches
with examples. Each case runs the real entry point in a subprocess, from outside the repository.
"""

from __future__ import annotations

import socket
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest
from conftest import DEFAULT_CONFIG, bridge_command, free_port
from koala_bridge.cli.main import SUBCOMMANDS


def koala(cwd: Path, *args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    return subprocess.run(bridge_command(*args), cwd=cwd, capture_output=True, text=True,
                          timeout=timeout, stdin=subprocess.DEVNULL)


def free_ports() -> list[str]:
    """--set overrides that keep a run off the default ports (a bridge may be running)."""
    return ["--set", f'zenoh.listen=["tcp/127.0.0.1:{free_port()}"]',
            "--set", f"buses.mavlink.port={free_port('udp')}",
            "--set", "buses.can.socketcand_port=0"]


def assert_one_line_error(p: subprocess.CompletedProcess[str], code: int, *needles: str) -> str:
    assert "Traceback" not in p.stderr + p.stdout, p.stderr
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1, p.stderr
    assert p.returncode == code, (p.returncode, p.stderr)
    for needle in needles:
        assert needle in lines[0], lines[0]
    return lines[0]


@pytest.fixture
def held_tcp_port() -> Iterator[int]:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        yield int(s.getsockname()[1])


@pytest.mark.parametrize("args, needles", [
    (["--config", "nonexistent.toml"], ["config file not found: nonexistent.toml"]),
    (["--set", "buses.mavlink.prot=1"], ["[buses.mavlink] unknown key 'prot'",
                                         "did you mean 'port'"]),
    (["--set", "sensors.gyro.idael=true"], ["did you mean 'ideal'"]),
    (["--set", "bueses.kteam.enabled=false"], ["unknown section [bueses]",
                                               "did you mean [buses]"]),
    (["--set", "run.clock=bogus"], ["'clock' must be one of realtime, fast"]),
    (["--set", "sensors=3"], ["[sensors] must be a table"]),
    (["--set", "buses.can=false"], ["[buses.can] must be a table"]),
    (["--duration", "-1"], ["--duration", ">= 0", "--help"]),
    (["--duration", "inf"], ["--duration", "finite"]),
    (["--clock", "bogus"], ["--clock", "invalid choice: 'bogus'", "--help"]),
    (["--seed", "x"], ["--seed", "invalid int value"]),
    (["--set", "novalue"], ["override must look like section.key=value"]),
    # the schema's policy (config/README.md "Policy"): strict types, finite ranges, full names
    (["--set", "robot.wheel_base_m=true"], ["[robot] 'wheel_base_m' must be a number"]),
    (["--set", 'robot.wheel_base_m="0.285"'], ["'wheel_base_m' must be a number, got '0.285'"]),
    (["--set", "sim.dt_s=1e-9"], ["[sim] 'dt_s' must be >= 0.0001"]),
    (["--set", "world.earth_field.horizontal_uT=nan"], ["'horizontal_uT' must be a finite"]),
    (["--set", "sensors.sonar.late_echo_probabilty=0.3"],
     ["did you mean 'late_echo_probability' (sensors.sonar.late_echo_probability)"]),
    (["--set", 'zenoh.listen=["tcp/127.0.0.1:7447"'], ["override zenoh.listen:",
                                                       "is not a TOML value"]),
    (["--set", 'buses.can.dbc="nonexistent.dbc"'], ["[buses.can] 'dbc': cannot load",
                                                    "nonexistent.dbc"]),
    (["--bogus"], ["unrecognized arguments: --bogus", "koala-bridge run --help"]),
    # a start the robot cannot leave (a new user's first edit of [world] start)
    (["--set", "world.start.x=7"], ["[world.start] x = 7, y = ", "is outside the world"]),
    (["--set", "world.start.x=0.05"], ["[world.start] x = 0.05", "overlaps the wall",
                                       "0.050 m from its centre"]),
])
def test_run_mistakes_are_one_line_exit_2(tmp_path: Path, args: list[str],
                                          needles: list[str]) -> None:
    p = koala(tmp_path, "run", "--duration", "0.1", *free_ports(), *args)
    assert_one_line_error(p, 2, "koala-bridge run", *needles)
    assert "is serving" not in p.stdout


def test_toml_syntax_error_names_file_and_line(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text(DEFAULT_CONFIG.read_text() + "\n[run\nclock = 'fast'\n")
    p = koala(tmp_path, "run", "--config", str(bad))
    assert_one_line_error(p, 2, "bad.toml", "invalid TOML", "line")


def test_unknown_section_in_the_file(tmp_path: Path) -> None:
    cfg = tmp_path / "k.toml"
    cfg.write_text(DEFAULT_CONFIG.read_text() + "\n[zenho]\nmode = 'peer'\n")
    p = koala(tmp_path, "run", "--config", str(cfg))
    assert_one_line_error(p, 2, "unknown section [zenho]", "did you mean [zenoh]")


def test_a_config_fragment_says_where_to_start(tmp_path: Path) -> None:
    """A file with a few keys (what `calibrate --write-config` writes without --config) is not a
    bridge config: the error says which key is missing and what to start from."""
    cfg = tmp_path / "fragment.toml"
    cfg.write_text("[sensors.gyro]\nbias_rad_s = 0.0196\n")
    p = koala(tmp_path, "run", "--config", str(cfg))
    assert_one_line_error(p, 2, "missing required key", "config/default.toml")


def test_zenoh_port_in_use(tmp_path: Path, held_tcp_port: int) -> None:
    p = koala(tmp_path, "run", "--clock", "fast", "--duration", "0.1", *free_ports(),
              "--set", f'zenoh.listen=["tcp/127.0.0.1:{held_tcp_port}"]')
    line = assert_one_line_error(p, 1, f"tcp/127.0.0.1:{held_tcp_port} is already in use",
                                 "--set 'zenoh.listen=")
    assert ".rs:" not in line  # no Rust source locations


@pytest.mark.parametrize("bus, sets", [
    ("can.socketcand", ["buses.can.socketcand_port={port}"]),
    ("mavlink", ['buses.mavlink.transport="tcp"', "buses.mavlink.port={port}"]),
])
def test_bus_port_in_use(tmp_path: Path, held_tcp_port: int, bus: str, sets: list[str]) -> None:
    args = [a for s in sets for a in ("--set", s.format(port=held_tcp_port))]
    p = koala(tmp_path, "run", "--clock", "fast", "--duration", "0.1", *free_ports(), *args)
    assert_one_line_error(p, 1, f"cannot open bus {bus}", "Address already in use", "--set buses.")


def test_a_ground_station_on_the_mavlink_udp_port_is_not_an_error(tmp_path: Path) -> None:
    # UDP 14550 "in use" is the normal case: the bridge sends to where a ground station listens.
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as gcs:
        gcs.bind(("127.0.0.1", 0))
        gcs.settimeout(10)
        port = gcs.getsockname()[1]
        p = koala(tmp_path, "run", "--clock", "fast", "--duration", "1", *free_ports(),
                  "--set", f"buses.mavlink.port={port}")
        assert p.returncode == 0, p.stderr
        assert gcs.recv(4096)[0] == 0xFD  # a MAVLink 2 packet
    # Run from outside the repository: the default config is the installation's.
    assert "Stopped at t = 1.000 s" in p.stdout


def test_a_missing_dbc_does_not_matter_with_every_can_bus_off(tmp_path: Path) -> None:
    p = koala(tmp_path, "run", "--clock", "fast", "--duration", "0.1", *free_ports(),
              "--set", 'buses.can.dbc="nonexistent.dbc"', "--set", "buses.can.socketcand=false",
              "--set", "buses.can.slcan=false", "--set", "buses.can.virtual=false")
    assert p.returncode == 0, p.stderr
    assert "CAN database (DBC)" in p.stdout and "nonexistent.dbc" not in p.stdout


def test_unwritable_endpoints_file(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("")
    p = koala(tmp_path, "run", "--clock", "fast", "--duration", "0.1", *free_ports(),
              "--endpoints-file", str(blocker / "koala.json"))
    assert_one_line_error(p, 1, "cannot write the endpoints file")


@pytest.mark.parametrize("args, code, needles", [
    (["replay", "nonexistent.mcap"], 2, ["cannot read nonexistent.mcap"]),
    (["replay", "x.mcap", "--speed", "0"], 2, ["--speed", "> 0"]),
    (["export", "nonexistent.mcap", "--bundle", "b"], 2, ["cannot read nonexistent.mcap"]),
    (["monitor", "--endpoints-file", "nonexistent.json"], 2, ["cannot read the endpoints file"]),
    (["monitor", "--duration", "-1"], 2, ["--duration"]),
    (["snapshot", "--out", "x.png", "--connect", "tcp/127.0.0.1:{port}", "--timeout", "0.5"],
     2, ["cannot reach a Zenoh peer", "is the bridge running"]),
    (["bogus"], 2, ["invalid choice: 'bogus'"]),
    ([], 2, ["required: SUBCOMMAND"]),
])
def test_other_subcommands_fail_in_one_line(tmp_path: Path, args: list[str], code: int,
                                            needles: list[str]) -> None:
    port = str(free_port())
    p = koala(tmp_path, *[a.replace("{port}", port) for a in args])
    assert_one_line_error(p, code, *needles)


@pytest.mark.parametrize("sub", ["replay", "export"])
def test_a_file_that_is_not_mcap_is_named_so(tmp_path: Path, sub: str) -> None:
    (tmp_path / "notes.txt").write_text("abc\n")  # shorter than the MCAP magic
    p = koala(tmp_path, sub, "notes.txt", *(["--bundle", "b"] if sub == "export" else []))
    line = assert_one_line_error(p, 2, f"koala-bridge {sub}", "notes.txt is not an MCAP file")
    assert "unpack" not in line


def test_an_unknown_option_names_its_subcommand(tmp_path: Path) -> None:
    p = koala(tmp_path, "snapshot", "--out", "x.png", "--bogus")
    assert_one_line_error(p, 2, "koala-bridge snapshot: error: unrecognized arguments: --bogus")


@pytest.mark.parametrize("sub", [None, *SUBCOMMANDS])
def test_help_teaches_with_examples(tmp_path: Path, sub: str | None) -> None:
    p = koala(tmp_path, *([sub] if sub else []), "--help")
    assert p.returncode == 0 and not p.stderr, p.stderr
    assert "example" in p.stdout
    examples = p.stdout[p.stdout.index("example"):]
    assert f"koala-bridge {sub or 'run'} " in examples, p.stdout


FLEET = Path(__file__).resolve().parents[2] / "examples" / "two_robots.toml"


@pytest.mark.parametrize("entry, needles, absent", [
    ('[[robots]]\nstart = { x = 0.5, y = 0.5 }\n',
     ["[robots.2] has no 'name'", "each [[robots]] entry needs name ="], "config init"),
    ('[[robots]]\nname = "g"\nstart = { x = 9.5, y = 0.5 }\n',
     ["[robots.2.start] robot 'g': x = 9.5, y = 0.5 is outside the world"], "[world"),
    ('[[robots]]\nname = "g"\nstart = { x = 0.1, y = 0.5 }\n',
     ["[robots.2.start] robot 'g': x = 0.1, y = 0.5: the robot's body", "overlaps the wall"],
     "[world"),
    ('[[robots]]\nname = "g"\nstart = { x = 0.5, y = 0.5 }\n[robots.sensors.ir]\nrat_hz = 5\n',
     ["[robots.2.sensors.ir] unknown key 'rat_hz'", "(robots.2.sensors.ir.rate_hz)"],
     "[sensors.ir]"),
])
def test_a_robots_entry_mistake_names_the_entry(tmp_path: Path, entry: str,
                                                needles: list[str], absent: str) -> None:
    config = tmp_path / "fleet.toml"
    config.write_text(FLEET.read_text() + "\n" + entry)
    p = koala(tmp_path, "run", "--config", str(config), "--duration", "0.1", *free_ports())
    line = assert_one_line_error(p, 2, "koala-bridge run: configuration error:", *needles)
    assert absent not in line


def test_a_typo_in_a_robots_sub_table_names_the_entry(tmp_path: Path) -> None:
    config = tmp_path / "fleet.toml"
    config.write_text(FLEET.read_text().replace('dialect = "koala25"', 'dialekt = "koala25"'))
    p = koala(tmp_path, "run", "--config", str(config), "--duration", "0.1", *free_ports())
    assert_one_line_error(p, 2, "[robots.1.buses.kteam] unknown key 'dialekt'; did you mean "
                          "'dialect' (robots.1.buses.kteam.dialect)?")


def test_set_robot_name_with_robots_is_refused(tmp_path: Path) -> None:
    p = koala(tmp_path, "run", "--config", str(FLEET), "--duration", "0.1", *free_ports(),
              "--set", "robot.name=x")
    assert_one_line_error(p, 2, "--set robot.name=x: with [[robots]] each robot's name is its "
                          "entry's 'name'")
