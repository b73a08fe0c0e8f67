"""Export a recording (.mcap) as a measurement bundle of CSV files.

The bundle (docs/bundle-format.md; docs/recording.md lists the columns) holds one row
per recorded reading: truth_pose.csv, odometry.csv, gyro.csv, compass.csv, range.csv (sonar and IR
with their noise-free ranges, kind, sensor id, incidence angle), landmarks.csv, landmark_map.csv
and meta.json (recording, seed, config). `koala-bridge calibrate` reads the bundle.

A recording of several robots (`[[robots]]`, docs/multirobot.md) is exported one robot at a
time: --robot NAME picks it, and its bundle is that of a one-robot recording.

examples:
  koala-bridge run --clock fast --duration 60 --record /tmp/run.mcap
  koala-bridge export /tmp/run.mcap --bundle /tmp/run-bundle
  koala-bridge run --config examples/two_robots.toml --duration 60 --record /tmp/two.mcap
  koala-bridge export /tmp/two.mcap --robot beta --bundle /tmp/beta-bundle
"""

from __future__ import annotations

import argparse
import logging
import sys

from koala_bridge.recording.export import export_bundle

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("recording", metavar="FILE.mcap", help="a recording of `run --record`")
    parser.add_argument(
        "--bundle", metavar="DIR", required=True, help="directory to write (created if needed)"
    )
    parser.add_argument(
        "--robot", metavar="NAME",
        help="the robot to export of a recording of [[robots]] (required for one; the names are "
        "in the error without it)",
    )


def run(args: argparse.Namespace) -> int:
    try:  # a RecordingError is reported by cli/main.py
        out = export_bundle(args.recording, args.bundle, args.robot)
    except OSError as e:
        print(f"koala-bridge export: cannot write the bundle {args.bundle}: {e.strerror or e}",
              file=sys.stderr)
        return 1
    files = sorted(p.name for p in out.iterdir())
    log.info("bundle written to %s: %s", out, ", ".join(files))
    return 0
