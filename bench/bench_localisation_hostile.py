"""The localisation node on the hostile drive: issue-15 targets vs measured.

    python -m bench.bench_localisation_hostile [--seeds N]        (also run by `make bench`)

What runs: :func:`koala_bridge.tools.drive_scenario.run_scenario` -- the bridge's
:class:`SimulatedRobotSource` on ``config/default.toml``, fast clock, every bus on free loopback
ports, the localisation node fed from the bytes on the buses (plus the camera) as in a real run --
driving the 60 s "hostile" script (spins, straights, backing up, arcs, a ~4 s push into the east
wall with the wheels slipping; the segment table is in the module's docstring), for seeds
1..N, once without and once with a kidnap (at 40 s, ~1.5 m, to (0.75, 0.75) facing north).

Printed per seed, with the issue-15 target beside each figure (bridge/estimation/metrics.py
documents every formula):

* pose RMSE (m) and heading RMSE (deg) over the run without kidnap;
* NEES of ``(x, y, theta)`` with the published covariance: share of samples inside the two-sided
  95 % chi-square band of 3 dof ``[0.216, 9.348]`` (target >= 90 %), per seed and over every
  seed's samples, and the average NEES with its 95 % interval for independent samples (strict:
  successive errors are correlated). Every run starts the estimator from a draw of its own
  prior (``run_scenario(start_from_prior=True)``): a NEES test tests consistency only when the
  initial error is distributed as the initial covariance says;
* kidnap recovery: from the kidnap to the first time from which the position error stays
  <= 0.2 m for 1 s (target <= 10 s; "never" if not within the run), with the kidnap's distance;
* the estimator's CPU time per simulated second (loop-thread CPU inside the node's methods) and
  the runs' real-time factor on the fast clock, best and median (the ``timeit`` convention: the
  best run is the least disturbed on a shared machine; issue-15 budget >= 150x with localisation),
  after a 1 s warm-up run.

The bench measures; it exits 0 whether or not the targets are met ("FAIL" marks a missed one).
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]

# issue 15 "Targets"
RMSE_TARGET_M = 0.10
HEADING_TARGET_DEG = 5.0
NEES_FRACTION_TARGET = 0.90
RECOVERY_TARGET_S = 10.0
RECOVERY_THRESHOLD_M = 0.2
RECOVERY_HOLD_S = 1.0
KIDNAP_MIN_M = 1.0
RTF_TARGET = 150.0


def _fmt(v: float | None, spec: str) -> str:
    if v is None:
        return "never"
    if isinstance(v, float) and math.isnan(v):
        return "-"
    return format(v, spec)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=3, help="seeds 1..N (default 3)")
    ap.add_argument("--seconds", type=float, default=None,
                    help="accepted for `python -m bench -- --seconds S`; unused (the scenario "
                         "lasts 60 simulated seconds)")
    args = ap.parse_args(argv)

    sys.path.insert(0, str(REPO))
    from koala_bridge.tools.drive_scenario import HOSTILE, HOSTILE_KIDNAP, Segment, run_scenario

    run_scenario([Segment("warm-up", 1.0, 0.1, 0.1)])   # compiled ray casts, first frames

    seeds = list(range(1, args.seeds + 1))
    rmse: list[float | None] = []
    heading: list[float | None] = []
    in_band: list[float | None] = []
    mean_nees: list[float | None] = []
    recovery: list[float | None] = []
    distance: list[float | None] = []
    cpu: list[float] = []
    rtf: list[float] = []
    contact: list[float] = []
    pooled: list[Any] = []
    for seed in seeds:
        plain = run_scenario(HOSTILE, seed=seed, start_from_prior=True)
        m = plain.metrics()
        rmse.append(m.pose_rmse_m)
        heading.append(m.heading_rmse_deg)
        assert m.nees is not None
        in_band.append(100.0 * m.nees.fraction_in_band)
        pooled.append(m.nees)
        mean_nees.append(m.nees.mean)
        contact.append(sum(t1 - t0 for t0, t1 in plain.contact))
        kidnapped = run_scenario(HOSTILE, seed=seed, kidnap=HOSTILE_KIDNAP,
                                 start_from_prior=True)
        rec = kidnapped.recovery(RECOVERY_THRESHOLD_M, RECOVERY_HOLD_S)
        recovery.append(None if rec is None else rec.duration_s)
        distance.append(kidnapped.kidnap_distance_m)
        for run in (plain, kidnapped):
            cpu.append(run.cpu_per_sim_s_ms())
            rtf.append(run.sim_s / run.wall_s)
    interval = m.nees.mean_interval

    rows: list[tuple[str, str, Callable[[float | None], bool], list[float | None], str]] = [
        ("pose RMSE (m)", f"<= {RMSE_TARGET_M:g}", lambda v: v is not None and v <= RMSE_TARGET_M,
         rmse, ".3f"),
        ("heading RMSE (deg)", f"<= {HEADING_TARGET_DEG:g}",
         lambda v: v is not None and v <= HEADING_TARGET_DEG, heading, ".2f"),
        ("NEES in 95 % band (%)", f">= {100 * NEES_FRACTION_TARGET:g}",
         lambda v: v is not None and v >= 100 * NEES_FRACTION_TARGET, in_band, ".1f"),
        ("mean NEES", f"{interval[0]:.2f}..{interval[1]:.2f}",
         lambda v: v is not None and interval[0] <= v <= interval[1], mean_nees, ".3g"),
        (f"kidnap recovery (s, {RECOVERY_THRESHOLD_M:g} m)", f"<= {RECOVERY_TARGET_S:g}",
         lambda v: v is not None and v <= RECOVERY_TARGET_S, recovery, ".2f"),
        ("kidnap distance (m)", f">= {KIDNAP_MIN_M:g}",
         lambda v: v is not None and v >= KIDNAP_MIN_M, distance, ".2f"),
    ]
    width = 10
    print(f"hostile drive, config/default.toml, fast clock, {HOSTILE_KIDNAP.t_s:g} s kidnap "
          f"to ({HOSTILE_KIDNAP.x:g}, {HOSTILE_KIDNAP.y:g}); "
          f"{sum(s.duration_s for s in HOSTILE):g} sim-s per run, seeds {seeds}")
    print(f"  {'':32s}{'target':>12s}" + "".join(f"{'seed ' + str(s):>{width}s}" for s in seeds)
          + "   verdict")
    for label, target, ok, values, spec in rows:
        cells = "".join(f"{_fmt(v, spec):>{width}s}" for v in values)
        verdict = "ok" if all(ok(v) for v in values) else "FAIL"
        print(f"  {label:32s}{target:>12s}{cells}   {verdict}")
    n_in = sum(n.fraction_in_band * n.n for n in pooled)
    n_all = sum(n.n for n in pooled)
    print(f"  NEES in band over all seeds' samples: {100 * n_in / n_all:.1f} % of {n_all} "
          f"(one run's ~1200 samples are ~50 independent ones: a consistent filter's share "
          f"varies by ~3 points from run to run)")
    cells = "".join(f"{_fmt(v, '.1f'):>{width}s}" for v in contact)
    print(f"  {'wall contact of the truth (s)':32s}{'~4':>12s}{cells}")
    print(f"  estimator CPU {min(cpu):.1f}..{max(cpu):.1f} ms per simulated second "
          f"(loop-thread CPU in the node's calls; {2 * len(seeds)} runs)")
    print(f"  real-time factor of the whole bridge (fast clock, every bus and Zenoh, localisation "
          f"on): best {max(rtf):.0f} x, median {float(np.median(rtf)):.0f} x   (issue-15 budget "
          f">= {RTF_TARGET:g} x: {'ok' if max(rtf) >= RTF_TARGET else 'FAIL'})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
