"""Replay a recording's raw bus frames on the buses, with their original timing.

Puts back what the robot sent, recorded by `run --record` (simulated or real robot): range frames
on the rangefinders pty, CAN frames on socketcand/slcan/virtual, MAVLink on its UDP/TCP/pty link,
each at its recorded time (or --speed times faster). K-Team commands are answered with the
recorded reply to the same letter at the current replay time. The recorded Zenoh messages
(truth, sensors, status, estimates) are published again at their times, and the `world`
queryable answers, so `koala-bridge monitor` and `snapshot` work during a replay (--no-zenoh:
buses only). The buses are those of the recording's configuration (`--config` replaces it,
`--set` overrides a key), and the start banner and --endpoints-file say where clients connect,
as for `run`. A recording that cannot be replayed (other format version, no bus channel) is
refused with the reason. A recording of several robots (`[[robots]]`, docs/multirobot.md) is
replayed one robot at a time: --robot NAME picks it, and it is replayed as a one-robot recording
on that robot's buses and Zenoh prefix (of the recorded configuration).

examples:
  koala-bridge run --clock fast --duration 60 --record /tmp/run.mcap   # make a recording
  koala-bridge replay /tmp/run.mcap
  koala-bridge replay /tmp/run.mcap --speed 4 --endpoints-file /tmp/replay.json
  koala-bridge replay /tmp/run.mcap --wait-clients 30 --set buses.mavlink.port=14551
  koala-bridge replay /tmp/run.mcap --set 'zenoh.listen=["tcp/127.0.0.1:7500"]' &
  koala-bridge monitor --connect tcp/127.0.0.1:7500                     # watch the replay
  koala-bridge replay /tmp/two.mcap --robot beta   # one robot of a recording of [[robots]]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from koala_bridge.cli.main import positive, seconds


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("recording", metavar="FILE.mcap", help="a recording of `run --record`")
    parser.add_argument(
        "--robot", metavar="NAME",
        help="the robot to replay of a recording of [[robots]] (required for one)",
    )
    parser.add_argument(
        "--speed",
        type=positive,
        default=1.0,
        metavar="X",
        help="replay X times faster than recorded (default: 1, real time)",
    )
    parser.add_argument(
        "--config",
        type=Path,
        help="take [buses] from this TOML file instead of the recording's configuration",
    )
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        dest="overrides",
        help="override a config key, e.g. --set buses.mavlink.port=14551 (repeatable)",
    )
    parser.add_argument(
        "--endpoints-file",
        type=Path,
        metavar="F",
        help="write where clients connect, as JSON, to F (as `run` does)",
    )
    parser.add_argument(
        "--bus",
        action="append",
        dest="buses",
        metavar="BUS",
        choices=("serial/kteam", "serial/rangefinders", "can", "mavlink"),
        help="replay only this bus (repeatable; default: every recorded bus)",
    )
    parser.add_argument(
        "--no-zenoh",
        action="store_true",
        help="do not publish the recorded Zenoh messages (no Zenoh session is opened)",
    )
    parser.add_argument(
        "--fifo-priority",
        type=int,
        default=0,
        metavar="P",
        help="run under SCHED_FIFO real-time priority P (1-99; needs CAP_SYS_NICE): the replay "
        "then sends within 0.5 ms of each frame's time at p99 on a busy host; a client at normal "
        "priority may still wait for a CPU (docs/recording.md, Timing)",
    )
    parser.add_argument(
        "--linger",
        type=seconds,
        default=0.5,
        metavar="S",
        help="keep the buses open S seconds after the last frame (default: 0.5)",
    )
    parser.add_argument(
        "--wait-clients",
        type=seconds,
        default=0.0,
        metavar="S",
        help="before starting, wait up to S seconds for a client on each pty/TCP/socketcand bus",
    )


def run(args: argparse.Namespace) -> int:
    from koala_bridge.core.resources import default_config_path
    from koala_bridge.recording.mcap_file import RecordingError, open_recording
    from koala_bridge.runtime.fleet_config import robot_entries
    from koala_bridge.runtime.replay import ReplaySource, plan_replay
    from koala_bridge.runtime.session import run_session
    from koala_bridge.runtime.settings import (
        BridgeSettings,
        apply_override,
        load_config,
        parse_override,
    )

    # A bad recording or configuration raises the project's errors: cli/main.py prints them.
    rec = open_recording(args.recording).robot(args.robot)
    plan = plan_replay(rec, tuple(args.buses) if args.buses else None, zenoh=not args.no_zenoh)
    if args.config is not None:
        config = load_config(args.config)
    else:
        text = rec.metadata.get("koala-bridge", {}).get("config")
        try:
            config = json.loads(text) if text else load_config(default_config_path())
        except json.JSONDecodeError as e:
            raise RecordingError(
                f"{args.recording}: the recorded configuration is not JSON ({e}); "
                "give one with --config"
            ) from e
    if args.robot is not None and args.config is None:
        # the robot's own configuration: the recorded file's with its entry laid over it
        entry = next((e for e in robot_entries(config) or [] if e.name == args.robot), None)
        if entry is not None:
            config = entry.config
    for o in args.overrides:
        config = apply_override(config, *parse_override(o))
    settings = BridgeSettings.from_config(config)
    speed = float(args.speed)  # > 0: argparse's `positive`

    source = ReplaySource(
        rec, plan, settings, speed=speed, linger_s=args.linger, zenoh=not args.no_zenoh,
        wait_clients_s=args.wait_clients, fifo_priority=args.fifo_priority,
        say=lambda line: print(line, flush=True),
    )
    return run_session(source, prog="koala-bridge replay", endpoints_file=args.endpoints_file)
