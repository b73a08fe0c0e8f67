"""Write a PNG of the world, the truth and estimated poses, and any published grid.

Queries `<prefix>/world` (walls, blocked cells, landmarks, magnetic sources), listens for a moment
to `truth/pose`, `estimate/pose`, `estimate/grid` (belief) and `map/occupancy`, and draws them
with matplotlib. Works against a bridge in another process or host (docs/multihost.md).

examples:
  koala-bridge snapshot --out /tmp/koala.png
  koala-bridge snapshot --out /tmp/koala.png --endpoints-file /tmp/koala.json --listen 3
"""

from __future__ import annotations

import argparse
import logging
import sys

from koala_bridge.cli.main import seconds
from koala_bridge.cli.monitor import add_target_arguments, resolve_target
from koala_bridge.tools.snapshot import collect_scene, render_scene

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", metavar="FILE.png", required=True, help="PNG to write")
    add_target_arguments(parser)
    parser.add_argument(
        "--listen",
        type=seconds,
        default=1.0,
        metavar="S",
        help="seconds to collect poses (the trail) before drawing (default: 1)",
    )
    parser.add_argument(
        "--timeout", type=seconds, default=5.0, metavar="S", help="give up after S seconds"
    )


def run(args: argparse.Namespace) -> int:
    try:
        connect, prefix = resolve_target(args)
        scene = collect_scene(connect, prefix, args.listen, max(args.timeout, args.listen))
    except OSError as e:
        print(f"koala-bridge snapshot: {e}", file=sys.stderr)
        return 2
    if scene.world is None:
        print(
            f"koala-bridge snapshot: no answer from {prefix}/world via {', '.join(connect)} "
            "(is the bridge running, with this prefix?)",
            file=sys.stderr,
        )
        return 1
    out = render_scene(scene, args.out)
    log.info(
        "wrote %s (%d truth poses, %d estimates%s%s)",
        out,
        len(scene.truth),
        len(scene.estimate),
        ", belief" if scene.belief is not None else "",
        ", occupancy" if scene.occupancy is not None else "",
    )
    return 0
