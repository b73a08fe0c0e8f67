"""Read pinned upstream files from a fetched repository snapshot, and write bundle files."""

from __future__ import annotations

import argparse
import json
import subprocess
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[2]
DEFAULT_MIRROR = Path("/work/.mirror")
DATA = REPO / "tests" / "data" / "real"


class UpstreamMissing(RuntimeError):
    """The snapshot of the source repository (or the pinned file in it) is not on this machine."""


def git_dir(mirror: Path, repo: str) -> Path:
    """The git directory of the snapshot of ``owner/name`` under ``mirror``
    (``mirror/owner+name/repo`` or ``.../repo/.git``)."""
    base = mirror / repo.replace("/", "+") / "repo"
    for cand in (base / ".git", base):
        if (cand / "HEAD").is_file():
            return cand
    raise UpstreamMissing(f"no snapshot of {repo} under {mirror} (fetch github:{repo} first)")


def read_upstream(mirror: Path, repo: str, commit: str, path: str) -> bytes:
    """The bytes of ``path`` at ``commit`` in the snapshot of ``repo``."""
    proc = subprocess.run(
        ["git", "--git-dir", str(git_dir(mirror, repo)), "show", f"{commit}:{path}"],
        capture_output=True,
        check=False,
    )
    if proc.returncode != 0:
        raise UpstreamMissing(f"{repo}@{commit[:7]}:{path}: {proc.stderr.decode().strip()}")
    return proc.stdout


def write_meta(path: Path, meta: dict[str, Any]) -> None:
    path.write_text(json.dumps(meta, indent=2, ensure_ascii=False) + "\n", encoding="utf-8")


def run_converter(name: str, convert: Callable[[Path, Path], dict[str, int]],
                  argv: Sequence[str] | None = None) -> int:
    """Command line shared by the converters: ``--mirror DIR --out DIR``."""
    parser = argparse.ArgumentParser(description=f"write the {name} measurement bundle")
    parser.add_argument("--mirror", type=Path, default=DEFAULT_MIRROR,
                        help="directory holding fetched snapshots (owner+name/repo)")
    parser.add_argument("--out", type=Path, default=DATA / name, help="bundle directory")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    rows = convert(args.mirror, args.out)
    size = sum(p.stat().st_size for p in args.out.iterdir())
    print(f"{args.out}: " + ", ".join(f"{k} {v} rows" for k, v in rows.items())
          + f"; {size / 1000:.1f} kB")
    return 0
