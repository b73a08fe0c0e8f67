"""Overhead of the localisation node on the bridge's simulation loop.

    python -m bench.bench_localisation [--seconds S] [--window W]     (also run by `make bench`)

What is timed: one :class:`koala_bridge.runtime.sim_source.SimulatedRobotSource` on
``config/default.toml`` (every error model on, every bus open on free loopback ports, Zenoh
publishing), fast clock, the robot driving an arc -- alternately *with* its
:class:`koala_bridge.runtime.localisation.LocalisationNode` and *without*
(the node detached), in windows of ``W`` simulated seconds, in the same process and the same run.
Each figure is the best window (the least disturbed on a shared machine, the ``timeit``
convention) with the median beside it. The algorithms alone are in bench/bench_estimation.py.

Prints simulation steps per wall second with and without the node, the real-time factor of each
(fast mode), the slowdown, and the node's cost per simulated second. In realtime mode the loop has
``1 - 1/RTF`` of each step free, so the node cannot push the real-time factor below 1 unless the
fast-mode factor with the node falls to 1.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from pathlib import Path

import numpy as np

from bench._common import fast_bridge_config

REPO = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=8.0, help="wall seconds in all (default 8)")
    ap.add_argument("--window", type=float, default=4.0,
                    help="simulated seconds per window (default 4)")
    args = ap.parse_args(argv)

    sys.path.insert(0, str(REPO))
    from koala_bridge.runtime.settings import BridgeSettings
    from koala_bridge.runtime.sim_source import SimulatedRobotSource

    config = fast_bridge_config()
    service = SimulatedRobotSource(config, BridgeSettings.from_config(config))
    node = service.localisation
    assert node is not None
    service.open()
    rates: dict[str, list[float]] = {"off": [], "on": []}
    stop = threading.Event()
    try:
        service.arbiter.set(0.10, 0.14, "bench")  # an arc through the arena
        service.run(stop, duration_s=1.0)          # warm-up: compiled casts, first frames
        end = time.perf_counter() + args.seconds
        steps = round(args.window / service.dt)
        while time.perf_counter() < end or min(len(v) for v in rates.values()) < 2:
            for label in ("off", "on"):
                service.localisation = node if label == "on" else None
                t0 = time.perf_counter()
                service.run(stop, duration_s=args.window)
                rates[label].append(steps / (time.perf_counter() - t0))
    finally:
        service.localisation = node
        service.close()
    best = {k: max(v) for k, v in rates.items()}
    median = {k: float(np.median(v)) for k, v in rates.items()}
    per_sim_s = (1.0 / best["on"] - 1.0 / best["off"]) / service.dt * 1000.0
    print(f"bridge loop, config/default.toml, fast clock, {len(rates['on'])} windows of "
          f"{args.window:g} sim-s each (best / median)")
    for k in ("off", "on"):
        print(f"  localisation {k:3s}  {best[k]:8.0f} steps/s  (median {median[k]:8.0f})  "
              f"= {best[k] * service.dt:6.1f} x real time")
    print(f"  slowdown          {best['off'] / best['on']:8.2f} x   node cost "
          f"{per_sim_s:5.1f} ms per simulated second")
    snap = node.snapshot()
    print(f"  node inputs (one run): {snap['frames']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
