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

from bridge.cli.monitor import add_target_arguments, resolve_target
from bridge.snapshot import collect_scene, render_scene

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", metavar="FILE.png", required=True, help="PNG to write")
    add_target_arguments(parser)
    parser.add_argument(
        "--listen",
        type=float,
        default=1.0,
        metavar="S",
        help="seconds to collect poses (the trail) before drawing (default: 1)",
    )
    parser.add_argument(
        "--timeout", type=float, default=5.0, metavar="S", help="give up after S seconds"
    )


def run(args: argparse.Namespace) -> int:
    connect, prefix = resolve_target(args)
    try:
        scene = collect_scene(connect, prefix, args.listen, max(args.timeout, args.listen))
    except OSError as e:
        log.error("%s", e)
        return 2
    if scene.world is None:
        log.error("no answer from %s/world via %s", prefix, ", ".join(connect))
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
