"""Live terminal dashboard of a running bridge, over Zenoh.

Shows, per key under the prefix, the message count, rate (per wall and per simulation second),
the last value; the truth pose against the estimate; the bus counters and the real-time factor
from `status`. Connects as a Zenoh client (multicast scouting off) to the bridge's endpoint, or to
a router in front of it (docs/multihost.md). Ctrl-C quits.

examples:
  koala-bridge monitor                                   # tcp/127.0.0.1:7447, koala/koala
  koala-bridge monitor --endpoints-file /tmp/koala.json  # endpoint and prefix of a running bridge
  koala-bridge monitor --connect tcp/10.0.0.5:7447 --prefix koala/koala
  koala-bridge monitor --once --duration 2               # print one frame after 2 s, exit
"""

from __future__ import annotations

import argparse
import logging
import sys
import time

from koala_bridge.cli.main import positive, seconds
from koala_bridge.tools.monitor import (
    DEFAULT_CONNECT,
    DEFAULT_PREFIX,
    MonitorState,
    ZenohWatch,
    render,
    target_from_endpoints_file,
    wait_for,
)
from rich.console import Console
from rich.live import Live

log = logging.getLogger(__name__)


def add_target_arguments(parser: argparse.ArgumentParser) -> None:
    """``--connect``, ``--prefix``, ``--endpoints-file`` (shared with snapshot)."""
    parser.add_argument(
        "--connect",
        metavar="ENDPOINT",
        action="append",
        help=f"Zenoh endpoint to connect to, repeatable (default: {DEFAULT_CONNECT})",
    )
    parser.add_argument("--prefix", help=f"key prefix of the robot (default: {DEFAULT_PREFIX})")
    parser.add_argument(
        "--endpoints-file",
        metavar="F",
        help="take endpoint and prefix from a bridge's endpoints file (--connect/--prefix win)",
    )


def resolve_target(args: argparse.Namespace) -> tuple[list[str], str]:
    connect, prefix = [DEFAULT_CONNECT], DEFAULT_PREFIX
    if args.endpoints_file:
        connect, prefix = target_from_endpoints_file(args.endpoints_file)
    return (args.connect or connect), (args.prefix or prefix).strip("/")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_target_arguments(parser)
    parser.add_argument(
        "--duration",
        type=seconds,
        metavar="S",
        help="exit after S seconds (default: run until Ctrl-C)",
    )
    parser.add_argument(
        "--once",
        action="store_true",
        help="no live view: collect for --duration (default 2 s) and print one frame",
    )
    parser.add_argument(
        "--timeout",
        type=seconds,
        default=10.0,
        metavar="S",
        help="with --once: wait up to S seconds for the first message (default: 10)",
    )
    parser.add_argument("--refresh-hz", type=positive, default=4.0, help="redraws per second")


def run(args: argparse.Namespace) -> int:
    try:
        connect, prefix = resolve_target(args)
    except OSError as e:
        print(f"koala-bridge monitor: {e}", file=sys.stderr)
        return 2
    header = f"koala-bridge monitor — {prefix} via {', '.join(connect)}"
    state = MonitorState()
    console = Console()
    try:
        watch = ZenohWatch(connect, prefix, state.on_message)
    except OSError as e:
        print(f"koala-bridge monitor: {e}", file=sys.stderr)
        return 2
    with watch:
        if args.once:
            # Collect for --duration from the first message on (the session may take a moment
            # to reach the bridge, through a router in particular).
            wait_for(lambda: state.total() > 0, args.timeout)
            time.sleep(args.duration if args.duration is not None else 2.0)
            console.print(render(state, header))
            if not state.total():
                print(
                    f"koala-bridge monitor: no message under {prefix}/ in {args.timeout:g} s "
                    f"via {', '.join(connect)} (is the bridge running, with this prefix?)",
                    file=sys.stderr,
                )
                return 1
            return 0
        deadline = None if args.duration is None else time.monotonic() + args.duration
        period = 1.0 / max(args.refresh_hz, 0.1)
        try:
            with Live(render(state, header), console=console, auto_refresh=False) as live:
                while deadline is None or time.monotonic() < deadline:
                    time.sleep(period)
                    live.update(render(state, header), refresh=True)
        except KeyboardInterrupt:
            pass
    return 0
