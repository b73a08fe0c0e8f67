"""Campaign throughput (issue 17): runs per minute on the local pool against a Dask cluster on
loopback, how a campaign's wall time grows with its number of cases, and the start-up time of
one run.

1. *Local pool vs Dask*: the first ``--cases`` cases of the example campaign
   (``examples/campaign_coverage.toml``: the coverage firmware, every error model on), each cut
   to ``--sim-s`` simulated seconds (default 30), once on the local pool (one worker per
   core) and once on a Dask scheduler + one worker (``--nthreads`` = cores) started here on
   127.0.0.1. Prints runs per minute of each and the cluster path's overhead (wall time
   ratio - 1; issue: <= 15 %).
   The outcome digests of the two must agree (a cluster run is the same run).
2. *Scaling*: the tiny firmware of the tests (``tests/e2e/_campaign_firmware.py``, 10 simulated
   seconds) on 2, 4, 8 cases on the local pool; a least-squares line wall = a + b * cases, and
   the median start-up time of one run (bridge start to its endpoints file).

    python -m bench.bench_campaign [--cases 4] [--sim-s 30]
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
from koala_bridge.campaign.runner import end_groups

from bench._common import REPO


def campaign(d: dict[str, Any], folder: Path):  # type: ignore[no-untyped-def]
    from koala_bridge.campaign.spec import campaign_from_dict

    return campaign_from_dict(d, folder / "bench.toml")


def timed(c: Any, out: Path, factory: Any, only: list[str]) -> tuple[float, list[dict[str, Any]]]:
    from koala_bridge.campaign.engine import run_campaign

    t0 = time.monotonic()
    outcome = run_campaign(c, out, factory, only=only)
    return time.monotonic() - t0, outcome.selected_records


def start_cluster(tmp: Path, threads: int) -> tuple[str, list[subprocess.Popen[bytes]]]:
    sched = tmp / "scheduler.json"
    common: dict[str, Any] = dict(cwd=tmp, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                  start_new_session=True)
    procs = [subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_scheduler", "--host",
                               "127.0.0.1", "--port", "0", "--no-dashboard", "--scheduler-file",
                               str(sched)], **common)]
    while not sched.exists():
        time.sleep(0.1)
    procs.append(subprocess.Popen(
        [sys.executable, "-m", "distributed.cli.dask_worker", "--scheduler-file", str(sched),
         "--nworkers", "1", "--nthreads", str(threads), "--host", "127.0.0.1", "--no-dashboard",
         "--local-directory", str(tmp / "dask")], **common))
    from distributed import Client

    with Client(scheduler_file=str(sched)) as client:  # wait until the worker is there
        client.wait_for_workers(1, timeout=60)
    return str(sched), procs


def stop_cluster(procs: list[subprocess.Popen[bytes]]) -> None:
    end_groups(procs[::-1])     # the worker before the scheduler


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=4, help="example cases compared (default 4)")
    ap.add_argument("--sim-s", type=float, default=30.0,
                    help="simulated seconds per example run (default 30)")
    args = ap.parse_args(argv)
    from koala_bridge.campaign.executors import dask_executor, default_workers, local_executor

    workers = default_workers()
    example = tomllib.loads((REPO / "examples" / "campaign_coverage.toml").read_text())
    example["campaign"]["sim_duration_s"] = args.sim_s
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        c = campaign(example, REPO / "examples")
        only = [x.case_id for x in c.cases[: args.cases]]

        def local():  # type: ignore[no-untyped-def]
            return local_executor(workers, tmp / "stop")

        wall_local, rec_local = timed(c, tmp / "local", local, only)
        sched, procs = start_cluster(tmp, workers)
        try:
            def cluster():  # type: ignore[no-untyped-def]
                return dask_executor(sched, {}, "bench-stop")

            wall_dask, rec_dask = timed(c, tmp / "dask", cluster, only)
        finally:
            stop_cluster(procs)
        same = [a["figures"].get("digest") for a in rec_local] == [
            b["figures"].get("digest") for b in rec_dask]
        n = len(only)
        print(f"example campaign, {n} cases x {args.sim_s:g} simulated s, {workers} at a time:")
        print(f"  local pool   {wall_local:7.1f} s  {60 * n / wall_local:6.2f} runs/min")
        print(f"  Dask cluster {wall_dask:7.1f} s  {60 * n / wall_dask:6.2f} runs/min")
        print(f"  cluster overhead {100 * (wall_dask / wall_local - 1):+.1f} % (issue: <= 15 %);"
              f" outcome digests identical: {same}")

        tiny = {
            "campaign": {
                "name": "scaling", "sim_duration_s": 10.0,
                "firmware": ["{python}", str(REPO / "tests" / "e2e" / "_campaign_firmware.py"),
                             "{endpoints}", "--seed", "{seed}", "--duration", "{duration_s}",
                             "--period", "0.05"],
                "set": ["lockstep.period_s=0.05", "buses.rangefinders.enabled=false"]},
            "matrix": {"worlds": ["lab_walls_1"], "seeds": list(range(1, 9))},
        }
        t = campaign(tiny, tmp)
        sizes, walls, startups = [2, 4, 8], [], []
        for k in sizes:
            def pool():  # type: ignore[no-untyped-def]
                return local_executor(workers, tmp / "stop")

            wall, records = timed(t, tmp / f"scale{k}", pool,
                                  [x.case_id for x in t.cases[:k]])
            walls.append(wall)
            startups += [r["startup_s"] for r in records if r["startup_s"] is not None]
        b, a = np.polyfit(sizes, walls, 1)
        fit = np.polyval([b, a], sizes)
        worst = max(abs(w - f) / w for w, f in zip(walls, fit, strict=True))
        print(f"scaling, tiny firmware (10 simulated s), {workers} at a time:")
        for k, w in zip(sizes, walls, strict=True):
            print(f"  {k:2d} cases {w:6.1f} s  ({w / k:5.2f} s per case)")
        print(f"  wall = {a:.1f} s + {b:.2f} s x cases (largest deviation from the line "
              f"{100 * worst:.1f} %)")
        print(f"  start-up of one run (bridge start to endpoints file): median "
              f"{statistics.median(startups):.2f} s, max {max(startups):.2f} s "
              f"({len(startups)} runs)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
