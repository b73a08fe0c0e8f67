"""Benchmark of the estimation algorithms (bridge/estimation).

Run: ``.venv/bin/python bench/bench_estimation.py`` (``--quick`` for fewer repeats).

* Grid filter on a 100 x 100 grid: one prediction (a commanded move) and one wall-observation
  update; target <= 1 ms each.
* Pose EKF: predictions (odometry + gyro) and corrections (compass, landmark) per second.

Each figure is printed with its ratio to a *floor* measured in the same run on the same machine,
so numbers from different machines compare: for the grid, one elementwise numpy pass over a
100 x 100 float array (``np.add(a, b, out=c)``); for the EKF, one 4 x 4 matrix product. The best
of several repeats is reported (the least disturbed by other processes).
"""

from __future__ import annotations

import argparse
import math
import timeit
from collections.abc import Callable

import numpy as np
from koala_bridge.core.grid import SIDES, Grid
from koala_bridge.estimation import GridModel, PoseTracker, PoseTrackerParams, predict, update
from koala_bridge.estimation.grid_localisation import uniform_prior

GRID_TARGET_S = 1e-3


def best_time(fn: Callable[[], object], number: int, repeat: int) -> float:
    """Best mean seconds per call over ``repeat`` runs of ``number`` calls."""
    return min(timeit.repeat(fn, number=number, repeat=repeat)) / number


def big_world(n: int, seed: int) -> Grid:
    """An ``n x n`` grid of 0.5 m cells with random interior walls on ~20 % of cell sides."""
    rng = np.random.default_rng(seed)
    walls = [
        [int(c), int(r), s]
        for c in range(n)
        for r in range(n)
        for s in ("N", "E")
        if rng.random() < 0.2
    ]
    return Grid.from_dict({"name": f"bench_{n}x{n}", "cell_m": 0.5, "cols": n, "rows": n,
                            "walls": walls})


def bench_grid(number: int, repeat: int) -> None:
    world = big_world(100, seed=1)
    model = GridModel.from_world(world)
    lb = uniform_prior(model)
    a, b, c = np.random.default_rng(0).random((3, 100, 100))
    floor = best_time(lambda: np.add(a, b, out=c), number * 10, repeat)
    t_pred = best_time(lambda: predict(lb, model, "E", 0.8), number, repeat)
    obs = (True, False, None, True)
    t_upd = best_time(lambda: update(lb, model, obs, 0.9, 0.7), number, repeat)

    def step() -> None:
        x = lb
        for s in SIDES:
            x = update(predict(x, model, s, 0.8), model, obs, 0.9, 0.7)

    t_step = best_time(step, max(1, number // 4), repeat) / 4
    print("grid filter, 100 x 100 cells")
    print(f"  floor: one numpy elementwise pass        {floor * 1e6:9.1f} us")
    for label, t in (("predict (one commanded move)", t_pred),
                     ("update (one wall observation)", t_upd),
                     ("move + observation", t_step)):
        verdict = "ok" if t <= GRID_TARGET_S else "OVER TARGET"
        print(f"  {label:38s} {t * 1e6:9.1f} us  = {t / floor:6.1f} x floor"
              f"  (target <= {GRID_TARGET_S * 1e3:.0f} ms: {verdict})")


def bench_pose(number: int, repeat: int) -> None:
    params = PoseTrackerParams(wheel_base_m=0.285, ticks_per_metre=90284.0)
    trk = PoseTracker(params)
    trk.reset(1.0, 1.0, 0.3, np.diag([1e-4, 1e-4, 1e-3]))
    F = np.eye(4)
    P = np.eye(4)
    floor = best_time(lambda: F @ P, number * 10, repeat)
    state = {"k": 0}

    def odometry() -> None:
        k = state["k"] = state["k"] + 1
        t = k * 0.01
        trk.on_gyro(t, 0.1)
        trk.on_odometry(t, 903 * k, 905 * k)

    t_pred = best_time(odometry, number, repeat)
    t_comp = best_time(lambda: trk.on_compass(trk.t, trk.pose[2] + 0.01), number, repeat)
    x, y, th = trk.pose
    lm = (1.95, 1.95)
    rng = math.hypot(lm[0] - x, lm[1] - y)
    brg = math.atan2(lm[1] - y, lm[0] - x) - th
    t_lm = best_time(lambda: trk.on_landmark(trk.t, lm, rng, brg, 0.05, 0.03), number, repeat)
    print("pose EKF [x, y, theta, gyro bias]")
    print(f"  floor: one 4x4 matrix product           {floor * 1e6:9.2f} us")
    for label, t in (("predict (odometry + gyro)", t_pred),
                     ("update (compass heading)", t_comp),
                     ("update (landmark range + bearing)", t_lm)):
        print(f"  {label:38s} {1 / t:9.0f} /s  ({t * 1e6:6.1f} us = {t / floor:5.1f} x floor)")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer repeats (a smoke run)")
    args = ap.parse_args(argv)
    number, repeat = (20, 3) if args.quick else (200, 7)
    bench_grid(number, repeat)
    bench_pose(number * 10, repeat)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
