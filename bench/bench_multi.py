"""Ten robots in one world ([[robots]]) on the fast clock: the real-time factor, against the
single robot measured in the same run.

    python -m bench.bench_multi [--robots N] [--window S] [--windows K]

What is timed, each as the best of K windows of S simulated seconds (the least disturbed on a
shared machine, the ``timeit`` convention), with the median beside it:

1. **fleet simulator**: :meth:`koala_bridge.sim.fleet.Fleet.step` of N robots of
   ``config/default.toml`` (every sensor and error model on), each seeing the others with IR,
   sonar and camera and colliding with them, every robot driving an arc;
2. **fleet bridge**: :class:`koala_bridge.runtime.fleet_source.FleetSource` with the same N
   robots, every bus on (K-Team and range-frame ptys, CAN on socketcand, slcan and virtual,
   MAVLink over UDP, Zenoh publishing; no client connected), the estimator node off (it is
   firmware-side work, not a sensor: ``--localisation`` turns it on);
3. the floors, in the same process: one robot's :meth:`Simulator.step` alone, and one robot's
   whole bridge loop (:class:`SimulatedRobotSource`, same buses).

The issue-18 target is N = 10 at >= 20x real time. Prints each figure and the ratios to the
floors (N robots cost about N single robots when the ratio is ~N).

Measured on the 2-core build machine (load average ~3.6 from other jobs), 2026-11-27,
``python -m bench.bench_multi``::

    1 robot: Simulator.step alone (floor)              189.9x  (188.5x)
    10 robots: Fleet.step                               12.8x  (12.4x)
    1 robot: whole bridge loop (floor)                  71.9x  (61.3x)
    10 robots: whole bridge loop (FleetSource)           4.5x  (4.4x)
    cost of 10 robots / 1 robot: simulator 14.8, bridge 15.9

The target is not met: the buses' and Zenoh's work per robot on the one loop thread bounds ten
robots near 8x (docs/multirobot.md "Speed").
"""

from __future__ import annotations

import argparse
import copy
import socket
import statistics
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

from bench._common import fast_bridge_config, free_port

TARGET_RTF = 20.0


def _starts(config: dict[str, Any], n: int) -> list[dict[str, float]]:
    """``n`` start poses at the centres of free cells of the world (bodies never overlap: cells
    are 0.5 m, bodies 0.38 m across)."""
    from koala_bridge.sim.world import World

    world = World.from_dict(config["world"])
    cells = world.free_cells()
    if len(cells) < n:
        raise SystemExit(f"the world has {len(cells)} free cells, fewer than {n} robots")
    step = max(1, len(cells) // n)
    out = []
    for i in range(n):
        x, y = world.cell_centre(*cells[i * step])
        out.append({"x": x, "y": y, "theta_deg": float(37 * i % 360)})
    return out


def _fleet_config(n: int, localisation: bool) -> dict[str, Any]:
    config = fast_bridge_config()
    config["localisation"]["enabled"] = localisation
    config["robots"] = [{"name": f"k{i}", "start": start}
                        for i, start in enumerate(_starts(config, n))]
    return config


def _windows(run_window: Callable[[], float], window_s: float, k: int) -> tuple[float, float]:
    """(best, median) real-time factor over ``k`` windows; ``run_window`` returns wall s."""
    rtfs = [window_s / run_window() for _ in range(k)]
    return max(rtfs), statistics.median(rtfs)


def bench_sim(n: int, window_s: float, k: int) -> tuple[float, float]:
    from koala_bridge.sim.fleet import Fleet
    from koala_bridge.sim.simulator import Simulator
    from koala_bridge.sim.types import WheelCommand

    config = _fleet_config(n, False)
    sims = []
    for robot in config["robots"]:
        c = {k: copy.deepcopy(v) for k, v in config.items() if k != "robots"}
        c["world"]["start"] = robot["start"]
        sims.append(Simulator(c))
    fleet = Fleet(sims)
    fleet.reset(1)
    commands = [WheelCommand(0.25, 0.2 + 0.01 * i) for i in range(n)]
    steps = round(window_s / fleet.dt)

    def window() -> float:
        t0 = time.perf_counter()
        for _ in range(steps):
            fleet.step(commands)
        return time.perf_counter() - t0

    window()    # warm-up: compiled kernels
    return _windows(window, window_s, k)


def bench_bridge(n: int | None, window_s: float, k: int, localisation: bool
                 ) -> tuple[float, float]:
    """The whole loop: ``n`` robots of a fleet, or None: one robot's SimulatedRobotSource."""
    from koala_bridge.runtime.settings import BridgeSettings

    if n is None:
        from koala_bridge.runtime.sim_source import SimulatedRobotSource

        config = fast_bridge_config()
        config["localisation"]["enabled"] = localisation
        source: Any = SimulatedRobotSource(config, BridgeSettings.from_config(config))
        robots = [source]
    else:
        from koala_bridge.runtime.fleet_config import robot_entries
        from koala_bridge.runtime.fleet_source import FleetSource

        config = _fleet_config(n, localisation)
        config["buses"]["mavlink"]["port"] = free_port(socket.SOCK_DGRAM)
        entries = robot_entries(config)
        assert entries is not None
        source = FleetSource(config, BridgeSettings.from_config(config), entries)
        robots = source.robots
    stop = threading.Event()
    source.open()
    try:
        for i, robot in enumerate(robots):
            robot.arbiter.set(0.25, 0.2 + 0.01 * i, "bench")

        def window() -> float:
            t0 = time.perf_counter()
            source.run(stop, duration_s=window_s)
            return time.perf_counter() - t0

        window()
        return _windows(window, window_s, k)
    finally:
        source.close()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--robots", type=int, default=10, help="robots in the world (default 10)")
    ap.add_argument("--window", type=float, default=2.0,
                    help="simulated seconds per window (default 2)")
    ap.add_argument("--windows", type=int, default=3, help="windows per figure (default 3)")
    ap.add_argument("--localisation", action="store_true",
                    help="run the estimator node of every robot too")
    args = ap.parse_args(argv)
    n, w, k = args.robots, args.window, args.windows
    rows = [
        ("1 robot: Simulator.step alone (floor)", bench_sim(1, w, k)),
        (f"{n} robots: Fleet.step", bench_sim(n, w, k)),
        ("1 robot: whole bridge loop (floor)", bench_bridge(None, w, k, args.localisation)),
        (f"{n} robots: whole bridge loop (FleetSource)",
         bench_bridge(n, w, k, args.localisation)),
    ]
    print(f"real-time factor, best (median) of {k} windows of {w:g} simulated s; "
          f"estimator node {'on' if args.localisation else 'off'}")
    for label, (best, med) in rows:
        print(f"  {label:<46} {best:8.1f}x  ({med:.1f}x)")
    sim1, simn, br1, brn = (r[1][0] for r in rows)
    print(f"  cost of {n} robots / 1 robot: simulator {sim1 / simn:.1f}, "
          f"bridge {br1 / brn:.1f}")
    ok = brn >= TARGET_RTF
    print(f"  target: {n} robots, whole bridge >= {TARGET_RTF:g}x real time: "
          f"{'met' if ok else 'NOT met'} ({brn:.1f}x); simulator alone "
          f"{'meets' if simn >= TARGET_RTF else 'misses'} it ({simn:.1f}x)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
