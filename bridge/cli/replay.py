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
refused with the reason.

examples:
  koala-bridge run --clock fast --duration 60 --record /tmp/run.mcap   # make a recording
  koala-bridge replay /tmp/run.mcap
  koala-bridge replay /tmp/run.mcap --speed 4 --endpoints-file /tmp/replay.json
  koala-bridge replay /tmp/run.mcap --wait-clients 30 --set buses.mavlink.port=14551
  koala-bridge replay /tmp/run.mcap --set 'zenoh.listen=["tcp/127.0.0.1:7500"]' &
  koala-bridge monitor --connect tcp/127.0.0.1:7500                     # watch the replay
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import sys
import threading
import time
from pathlib import Path
from types import FrameType

from koala_bridge.cli.main import positive, seconds

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("recording", metavar="FILE.mcap", help="a recording of `run --record`")
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
    from koala_bridge.cli.run import DEFAULT_CONFIG
    from koala_bridge.recording.mcap_file import RecordingError, open_recording
    from koala_bridge.runtime.buses import open_buses
    from koala_bridge.runtime.endpoints import endpoints_of, write_endpoints_file
    from koala_bridge.runtime.replay import SWITCH_INTERVAL_S, Replayer, ReplayStats, plan_replay
    from koala_bridge.runtime.settings import (
        BridgeSettings,
        ConfigError,
        apply_override,
        load_config,
        parse_override,
    )
    from koala_bridge.runtime.zenoh_io import ZenohLink

    try:
        rec = open_recording(args.recording)
        plan = plan_replay(
            rec, tuple(args.buses) if args.buses else None, zenoh=not args.no_zenoh
        )
    except RecordingError as e:
        print(f"koala-bridge replay: cannot replay: {e}", file=sys.stderr)
        return 2
    try:
        if args.config is not None:
            config = load_config(args.config)
        else:
            text = rec.metadata.get("koala-bridge", {}).get("config")
            config = json.loads(text) if text else load_config(DEFAULT_CONFIG)
        for o in args.overrides:
            config = apply_override(config, *parse_override(o))
        settings = BridgeSettings.from_config(config)
        replayer_speed = float(args.speed)
        if not replayer_speed > 0:
            raise ConfigError(f"--speed must be > 0, got {args.speed}")
    except (ConfigError, ValueError) as e:
        print(f"koala-bridge replay: configuration error: {e}", file=sys.stderr)
        return 2

    stop = threading.Event()

    def on_signal(signum: int, frame: FrameType | None) -> None:
        stop.set()

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    if args.fifo_priority:
        _set_fifo_priority(args.fifo_priority)
    buses = None
    zenoh = None
    world = rec.world or {}
    try:
        try:
            buses = open_buses(settings.buses)
            if not args.no_zenoh:
                zenoh = ZenohLink(settings.zenoh, lambda: world)
        except OSError as e:
            print(f"koala-bridge replay: {e}", file=sys.stderr)
            return 1
        endpoints = endpoints_of(buses, settings, zenoh=zenoh is not None)
        print(endpoints.describe(), flush=True)
        if args.endpoints_file:
            try:
                path = write_endpoints_file(args.endpoints_file, endpoints)
            except OSError as e:
                print(
                    f"koala-bridge replay: cannot write the endpoints file {args.endpoints_file}: "
                    f"{e.strerror or e}",
                    file=sys.stderr,
                )
                return 1
            print(f"  Endpoints file          {path}")
        counts = ", ".join(f"{b} {n}" for b, n in sorted(plan.counts.items()))
        span = plan.t_end - plan.t0
        print(
            f"Replaying {rec.path.name}: {counts} frames over {span:.3f} s at speed "
            f"{replayer_speed:g}.",
            flush=True,
        )
        if args.wait_clients > 0:
            _wait_clients(buses, plan.counts, args.wait_clients, stop)
        # The replay thread and the transports' I/O threads hand the GIL over every 0.5 ms
        # instead of 5 ms: a frame queued for socketcand leaves within a millisecond.
        sys.setswitchinterval(SWITCH_INTERVAL_S)
        linger_s = max(0.0, args.linger)

        def on_sent_all(stats: ReplayStats) -> None:
            print(
                f"Every frame sent; the buses stay open {linger_s:g} s more (Ctrl-C ends).",
                flush=True,
            )

        replayer = Replayer(
            plan, buses, speed=replayer_speed, linger_s=linger_s, zenoh=zenoh,
            on_sent_all=on_sent_all,
        )
        stats = replayer.run(stop)
        sent = ", ".join(f"{b} {n}" for b, n in sorted(stats.sent.items()))
        p99 = stats.lateness_quantile(0.99) * 1e3
        print(
            f"Replay {'stopped' if stats.stopped_early else 'done'}: sent {sent}; "
            f"K-Team answers {stats.kteam_answered}; lateness p99 {p99:.3f} ms.",
            flush=True,
        )
    finally:
        if zenoh is not None:
            zenoh.close()
        if buses is not None:
            buses.close()
        for s, handler in previous.items():
            signal.signal(s, handler)
    return 0


def _wait_clients(buses, counts, timeout: float, stop: threading.Event) -> None:  # type: ignore[no-untyped-def]
    """Wait until every connection-oriented bus to be replayed has a client (or timeout)."""
    links = []
    if "serial/rangefinders" in counts and buses.rangefinders is not None:
        links.append(("rangefinders", buses.rangefinders))
    if "serial/kteam" in counts and buses.kteam is not None:
        links.append(("kteam", buses.kteam))
    if "mavlink" in counts and buses.mavlink is not None and not buses.mavlink.is_datagram:
        links.append(("mavlink", buses.mavlink))
    if "can" in counts:
        links += [(n, t) for n, t in buses.can.items() if n in ("can.socketcand", "can.slcan")]
    deadline = time.monotonic() + timeout
    waiting = [n for n, link in links if link.stats.clients == 0]
    while waiting and time.monotonic() < deadline and not stop.is_set():
        time.sleep(0.02)
        waiting = [n for n, link in links if link.stats.clients == 0]
    if waiting:
        log.warning("no client on %s after %.1f s: starting anyway", ", ".join(waiting), timeout)


def _set_fifo_priority(priority: int) -> None:
    """SCHED_FIFO for this thread and the threads it starts later (the transports' I/O threads)."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (OSError, ValueError) as e:
        log.warning(
            "cannot run under SCHED_FIFO %d (%s): replaying at normal priority", priority, e
        )
