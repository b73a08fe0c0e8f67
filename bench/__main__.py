"""``python -m bench``: run every ``bench/bench_*.py`` present, one process each, in name order.

Arguments after ``--`` are passed to every benchmark (e.g. ``python -m bench -- --seconds 5``).
The exit status is non-zero if any benchmark failed.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path


def main(argv: list[str]) -> int:
    extra = argv[argv.index("--") + 1:] if "--" in argv else []
    here = Path(__file__).resolve().parent
    failed = []
    for path in sorted(here.glob("bench_*.py")):
        print(f"== {path.stem}", flush=True)
        rc = subprocess.call([sys.executable, "-m", f"bench.{path.stem}", *extra],
                             cwd=here.parent)
        if rc != 0:
            failed.append(path.stem)
    if failed:
        print(f"failed: {', '.join(failed)}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
