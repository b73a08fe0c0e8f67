"""``python -m bench.real_data [--mirror DIR]``: write every bundle whose upstream snapshot is
present under the mirror directory; name those that are not (``fetch github:<owner>/<name>``)."""

from __future__ import annotations

import argparse
import importlib
import sys
from pathlib import Path

from bench.real_data._upstream import DATA, DEFAULT_MIRROR, UpstreamMissing

CONVERTERS = (
    "convert_labyrinth_uwb",
    "convert_lias_uwb_trolley",
    "convert_hcsr04_sweeps",
    "convert_mag_ellipsoid_bazhin",
    "convert_roomba_spin",
    "convert_sharp_gp2y0a02_sweep",
)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--mirror", type=Path, default=DEFAULT_MIRROR)
    parser.add_argument("--data", type=Path, default=DATA, help="parent of the bundle dirs")
    args = parser.parse_args(argv)
    missing = 0
    for name in CONVERTERS:
        module = importlib.import_module(f"bench.real_data.{name}")
        try:
            module.main(["--mirror", str(args.mirror), "--out", str(args.data / module.NAME)])
        except UpstreamMissing as e:
            print(f"{module.NAME}: skipped: {e}", file=sys.stderr)
            missing += 1
    return 1 if missing else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
