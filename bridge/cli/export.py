"""Export a recording (.mcap) as a measurement bundle of CSV files.

The bundle (docs/bundle-format.md; docs/recording.md lists the columns) holds one row
per recorded reading: truth_pose.csv, odometry.csv, gyro.csv, compass.csv, range.csv (sonar and IR
with their noise-free ranges, kind, sensor id, incidence angle), landmarks.csv, landmark_map.csv
and meta.json (recording, seed, config). `koala-bridge calibrate` reads the bundle.

example:
  koala-bridge run --clock fast --duration 60 --record /tmp/run.mcap
  koala-bridge export /tmp/run.mcap --bundle /tmp/run-bundle
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


def run(args: argparse.Namespace) -> int:
    try:  # a RecordingError is reported by cli/main.py
        out = export_bundle(args.recording, args.bundle)
    except OSError as e:
        print(f"koala-bridge export: cannot write the bundle {args.bundle}: {e.strerror or e}",
              file=sys.stderr)
        return 1
    files = sorted(p.name for p in out.iterdir())
    log.info("bundle written to %s: %s", out, ", ".join(files))
    return 0
