"""Run the simulated Koala and serve it on every bus and over Zenoh.

On start it prints where each client connects and, with --endpoints-file, writes the same as
JSON once every endpoint accepts clients. SIGINT (Ctrl-C) or SIGTERM stops it cleanly (exit 0);
--duration stops it after that many simulation seconds.

examples:
  koala-bridge run                                  # config/default.toml, real time
  koala-bridge run --clock fast --duration 30 --seed 7
  koala-bridge run --config "$(koala-bridge config path)/koala25.toml"   # a Koala 2.5 (libkoala)
  koala-bridge run --endpoints-file /tmp/koala.json --set buses.mavlink.port=14551
  koala-bridge run --set 'zenoh.listen=["tcp/127.0.0.1:7500"]' --set robot.name=k2
  koala-bridge run --clock fast --duration 60 --record /tmp/run.mcap   # docs/recording.md
  koala-bridge run --source real --config robot.toml --record /tmp/real.mcap
  koala-bridge run --set localisation.enabled=false     # no estimate/* (docs/localisation.md)
  koala-bridge run --set localisation.grid_prior=uniform  # no known start: the grid filter finds it
  koala-bridge run --clock lockstep --endpoints-file ep.json  # paced by the firmware (protocols.md)
  koala-bridge run --clock lockstep --fault drop:can:start_s=5,end_s=10,probability=0.3
  koala-bridge run --fault kidnap:robot:start_s=20,x=1.0,y=0.5   # docs/faults.md
  koala-bridge run --set buses.can.wire_timing=true --set buses.can.bitrate=125000
  koala-bridge run --config examples/two_robots.toml --endpoints-file ep.json  # [[robots]]:
                    # several Koalas in one world, each with its own buses (docs/multirobot.md)
  koala-bridge run --foxglove                       # live view in Foxglove (docs/foxglove.md)
  koala-bridge run --clock fast --foxglove 127.0.0.1:0 --record /tmp/run.mcap

lockstep is set in the config's [lockstep] table (cycle_bus, cycle_message, period_s, on_quiet,
quiet_timeout_s); --set zenoh.remote_commands=true adds the lockstep/step and faults/schedule
queryables; each bus's wire_timing key paces its frames (docs/wire-timing.md). The docs/ files
named here are in the source repository (README.md "Documentation").
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path
from typing import Any

from koala_bridge.cli.main import seconds
from koala_bridge.core.resources import default_config_path
from koala_bridge.runtime.clock import CLOCK_NAMES
from koala_bridge.runtime.faults import FAULT_HELP, faults_from_config, parse_fault_option
from koala_bridge.runtime.settings import (
    BridgeSettings,
    ConfigError,
    apply_override,
    load_config,
    parse_override,
)

log = logging.getLogger(__name__)

# The shipped default config (a package resource, core/resources.py), wherever the command runs.
DEFAULT_CONFIG = default_config_path()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--config", type=Path, default=DEFAULT_CONFIG,
        help="TOML configuration (default: config/default.toml of this installation)",
    )
    parser.add_argument(
        "--clock", choices=CLOCK_NAMES,
        help="realtime: one simulation second per wall second; fast: as fast as possible; "
        "lockstep: one [lockstep] period per cycle message of the firmware, held at t = 0 "
        "until its first (docs/protocols.md §6) (default: [run] clock)",
    )
    parser.add_argument(
        "--duration", type=seconds, metavar="S",
        help="stop after S simulation seconds; 0 = until stopped (default: [run] duration_s)",
    )
    parser.add_argument("--seed", type=int, help="random seed (default: [sim] seed)")
    parser.add_argument(
        "--endpoints-file", type=Path, metavar="F",
        help="write where clients connect, as JSON, to F (default: [run] endpoints_file)",
    )
    parser.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE", dest="overrides",
        help="override a config key, e.g. --set buses.mavlink.port=14551 (repeatable; "
        "VALUE is TOML)",
    )
    parser.add_argument(
        "--fault", action="append", default=[], metavar="KIND:TARGET[:K=V,...]", dest="faults",
        help=FAULT_HELP.replace("%", "%%"),
    )
    parser.add_argument(
        "--source", choices=("sim", "real"), default="sim",
        help="sim: the simulated Koala (default); real: read the robot's ports named in the "
        "config's [real] section and publish/record them as in simulation (docs/recording.md)",
    )
    parser.add_argument(
        "--record", type=Path, metavar="FILE.mcap",
        help="record every Zenoh message and raw bus frame to an MCAP file, and the scene in "
        "Foxglove's standard schemas beside them (docs/recording.md)",
    )
    parser.add_argument(
        "--foxglove", nargs="?", const="", metavar="HOST:PORT",
        help="serve a live view on a Foxglove WebSocket: the map, the robot, its sensors and "
        "estimate, plots and logs (default 127.0.0.1:8765; port 0: any free port, named in the "
        "banner and the endpoints file; a non-loopback host needs [run] allow_non_loopback; "
        "docs/foxglove.md)",
    )


def resolve_config(args: argparse.Namespace) -> dict[str, Any]:
    """The file's configuration with the command line applied on top (CLI > file)."""
    config = load_config(args.config)
    for text in args.overrides:
        key, value = parse_override(text)
        if key == ["robot", "name"] and "robots" in config:
            raise ConfigError(
                f"--set {text}: with [[robots]] each robot's name is its entry's 'name' "
                "([[robots]] name = \"...\"), not [robot] name: rename it there")
        config = apply_override(config, key, value)
    flags = {
        ("run", "clock"): args.clock,
        ("run", "duration_s"): args.duration,
        ("sim", "seed"): args.seed,
        ("run", "endpoints_file"): (
            None if args.endpoints_file is None else str(args.endpoints_file)
        ),
    }
    for key, value in flags.items():
        if value is not None:
            config = apply_override(config, list(key), value)
    if args.faults:
        # validated here, so that an error names the --fault option; then [[faults]] tables
        faults_from_config(config, args.faults)
        config = {**config, "faults": [*config.get("faults", []),
                                       *(parse_fault_option(text) for text in args.faults)]}
    return config


def run(args: argparse.Namespace) -> int:
    # Imported here so that `koala-bridge --help` does not load the simulator and Zenoh.
    from koala_bridge.runtime.session import make_source, run_session

    # A bad configuration raises ConfigError: cli/main.py prints it, with a hint.
    config = resolve_config(args)
    settings = BridgeSettings.from_config(config)
    foxglove_io, address = _foxglove(args, settings)
    source = make_source(args.source, config, settings)

    after_close = None
    recorder = None
    if args.record is not None:
        from koala_bridge.recording.mcap_file import Recorder, RecordingError, run_metadata

        metadata = run_metadata(
            args.source, config, args.config,
            # the K-Team frames' dialect: the real robot's, else the simulated pty's
            getattr(source, "kteam_dialect", settings.buses.kteam_dialect),
        )
        robots = getattr(source, "robots_metadata", None)
        if robots is not None:
            # [[robots]]: each robot's keys and buses are recorded under its name
            metadata["robots"] = json.dumps(robots())
        try:
            recorder = Recorder(
                args.record,
                metadata=metadata,
                world=source.world_answer(),
            )
        except RecordingError as e:
            print(f"koala-bridge run: {e}", file=sys.stderr)
            return 1
        source.tap = recorder

        def after_close() -> str:
            recorder.close()
            return f"Recorded {recorder.written} messages to {recorder.path}."

    if foxglove_io is not None and (address is not None or args.record is not None):
        # the scene in Foxglove's schemas: live and/or into the recording (docs/foxglove.md);
        # [[robots]]: every robot's, on one server and in one recording (docs/multirobot.md)
        from koala_bridge.runtime.fleet_source import FleetSource

        robots = (list(zip(source.names, source.robots, strict=True))
                  if isinstance(source, FleetSource) else [])
        source = foxglove_io.attach_foxglove(
            source, ", ".join(n for n, _ in robots) or settings.robot_name, address=address,
            recorder=recorder, robots=robots,
        )

    return run_session(
        source,
        prog="koala-bridge run",
        endpoints_file=settings.run.endpoints_file or None,
        after_close=after_close,
        # A live line on a terminal only: simulated time, real-time factor, ETA.
        sim_time=(lambda: source.sim.t) if args.source == "sim" else None,
        duration_s=settings.run.duration_s,
    )


def _foxglove(args: argparse.Namespace, settings: BridgeSettings) -> tuple[Any, Any]:
    """The Foxglove module and the live server's ``(host, port)`` (None: no server). Without
    the foxglove-sdk package, --foxglove is an error and a recording has no scene channels."""
    try:
        from koala_bridge.runtime import foxglove_io
    except ImportError as e:
        if args.foxglove is not None:
            raise ConfigError(f"--foxglove needs the foxglove-sdk package ({e}); install it "
                              "with: pip install 'foxglove-sdk>=0.30'") from None
        if args.record is not None:
            log.warning("foxglove-sdk is not installed: the recording has no Foxglove scene "
                        "channels (%s)", e)
        return None, None
    if args.foxglove is None:
        return foxglove_io, None
    return foxglove_io, foxglove_io.parse_address(args.foxglove,
                                                  settings.run.allow_non_loopback)
