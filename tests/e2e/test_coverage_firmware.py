"""examples/coverage_firmware.py against a real bridge subprocess (``--clock lockstep``).

The bridge runs a lab world with every seed error model on and records what happened; the
firmware, another process, sees only the K-Team serial pty, the socketcand CAN server and the
MAVLink UDP stream. Success is judged on the *truth* recorded by the bridge (``/truth/pose``):
the robot must have stopped near the centre of every reachable cell -- not on the firmware's word.

Lockstep: simulated time advances one ``[lockstep] period_s`` per K-Team ``D`` of the firmware,
so the run is the same however loaded the machine is. ``PERIOD_S`` = 0.02 s: the wall time is
set by the bridge's cost per 10 ms simulation step (every error model, the recorder, Zenoh), not
by the number of cycles -- 0.01 s runs at ~600 control cycles per wall second (~6x real time),
0.02 s at ~400-550 (~8-11x), 0.05 s at ~130-170 (no faster) on a 2-core machine.

``python tests/e2e/test_coverage_firmware.py --seeds 20 --random-start`` runs every lab wall world
with seeds 0..19 (random start cell and heading per seed) and prints a table
(docs/localisation.md, "Coverage firmware"); ``--clock fast`` / ``realtime`` and ``--period-s``
run the same firmware against the other clocks or another period.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import random
import signal
import socket
import subprocess
import sys
import time
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import tomli_w
from koala_bridge.estimation import decode_occupancy
from koala_bridge.recording.mcap_file import open_recording
from koala_bridge.sim.world import World

ROOT = Path(__file__).resolve().parents[2]
FIRMWARE = ROOT / "examples" / "coverage_firmware.py"
CENTRE_TOLERANCE_M = 0.1  # the truth passed this close to a cell's centre: the cell was visited
PERIOD_S = 0.02  # [lockstep] period_s: the firmware's control period


def free_port(kind: int = socket.SOCK_STREAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def write_config(
    tmp: Path, world: str, zenoh_port: int, mav_port: int,
    start: tuple[float, float, float] | None = None, period_s: float = PERIOD_S,
) -> Path:
    d = tomllib.loads((ROOT / "config" / "default.toml").read_text())
    d["world"] = tomllib.loads((ROOT / "config" / "worlds" / f"{world}.toml").read_text())["world"]
    if start is not None:
        d["world"]["start"] = {"x": start[0], "y": start[1], "theta_deg": start[2]}
    for name, sec in d["sensors"].items():
        if name != "encoders":  # encoders count the commanded rotation; drive error is below
            sec["ideal"] = False
    d["robot"]["drive_error"]["ideal"] = False
    d["buses"]["motor_watchdog_s"] = 0.5  # a stalled firmware stops the robot, not a wall
    d["buses"]["rangefinders"]["enabled"] = False
    d["buses"]["can"].update(socketcand_port=0, slcan=False, virtual=False)
    d["buses"]["mavlink"]["port"] = mav_port
    d["zenoh"]["listen"] = [f"tcp/127.0.0.1:{zenoh_port}"]
    d["lockstep"]["period_s"] = period_s   # the bridge's and the firmware's control period
    path = tmp / f"{world}.toml"
    path.write_bytes(tomli_w.dumps(d).encode())
    return path


def visited_cells(mcap: Path, world: World) -> set[tuple[int, int]]:
    cells = set()
    for m in open_recording(mcap).topic("/truth/pose"):
        p = m.json()
        c = world.cell_of(p["x"], p["y"])
        cx, cy = world.cell_centre(*c)
        if math.hypot(p["x"] - cx, p["y"] - cy) < CENTRE_TOLERANCE_M:
            cells.add(c)
    return cells


def occupancy_accuracy(msg: dict[str, Any], world: World) -> tuple[float, int]:
    """Share of observed cells of a ``map/occupancy`` payload classified as the true map has them
    (a cell is occupied when a wall touches its closed square), and the number observed."""
    lo = decode_occupancy(msg)
    res = float(msg["resolution_m"])
    truth = np.zeros(lo.shape, dtype=bool)
    tol = 1e-9
    for x0, y0, x1, y1 in world.segments:
        c0 = max(math.floor((min(x0, x1) - tol) / res), 0)
        c1 = min(math.floor((max(x0, x1) + tol) / res), lo.shape[1] - 1)
        r0 = max(math.floor((min(y0, y1) - tol) / res), 0)
        r1 = min(math.floor((max(y0, y1) + tol) / res), lo.shape[0] - 1)
        truth[r0 : r1 + 1, c0 : c1 + 1] = True
    seen = lo != 0
    return float(np.mean((lo[seen] > 0) == truth[seen])), int(seen.sum())


def run_once(
    tmp: Path, world_name: str, seed: int, timeout_s: float = 240.0, random_start: bool = False,
    clock: str = "lockstep", period_s: float = PERIOD_S,
) -> dict[str, Any]:
    """One bridge + firmware run; returns the firmware's report plus truth-based results. With
    ``random_start`` the robot starts at a seeded random free cell's centre, facing a random
    cardinal direction. In lockstep the bridge ends the run itself when the firmware closes the
    K-Team port; with another ``clock`` it is stopped with SIGTERM."""
    start = None
    if random_start:
        rng = random.Random(seed)
        w = World.from_dict(
            tomllib.loads((ROOT / "config" / "worlds" / f"{world_name}.toml").read_text())["world"]
        )
        x, y = w.cell_centre(*rng.choice(w.free_cells()))
        start = (x, y, float(rng.choice([0, 90, 180, 270])))
    cfg = write_config(tmp, world_name, free_port(), free_port(socket.SOCK_DGRAM), start,
                       period_s)
    endpoints = tmp / f"endpoints_{world_name}_{seed}.json"
    mcap = tmp / f"run_{world_name}_{seed}.mcap"
    report = tmp / f"report_{world_name}_{seed}.json"
    bridge = subprocess.Popen(
        [sys.executable, "-m", "koala_bridge", "run", "--config", str(cfg), "--clock", clock,
         "--seed", str(seed), "--endpoints-file", str(endpoints), "--record", str(mcap),
         "--log-level", "WARNING"],
        cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
    )
    try:
        deadline = time.monotonic() + 60
        while not endpoints.exists():
            if bridge.poll() is not None or time.monotonic() > deadline:
                err = bridge.stderr.read().decode() if bridge.stderr else ""
                raise RuntimeError(f"bridge did not start: {err[-2000:]}")
            time.sleep(0.05)
        fw = subprocess.run(
            [sys.executable, str(FIRMWARE), "--endpoints-file", str(endpoints), "--config",
             str(cfg), "--world", str(ROOT / "config" / "worlds" / f"{world_name}.toml"),
             "--seed", str(seed), "--report", str(report), "--timeout-s", str(timeout_s),
             "--log-level", "WARNING"],
            cwd=ROOT, capture_output=True, text=True, timeout=timeout_s + 30,
        )
    finally:
        try:
            if clock == "lockstep":  # the firmware has closed its port: the bridge stops itself
                bridge.wait(timeout=30)
        except subprocess.TimeoutExpired:
            pass
        if bridge.poll() is None:
            bridge.send_signal(signal.SIGTERM)
        try:
            bridge.wait(timeout=30)
        except subprocess.TimeoutExpired:
            bridge.kill()
            bridge.wait()
        if bridge.stderr:
            bridge.stderr.close()
    (tmp / f"firmware_{world_name}_{seed}.log").write_text(fw.stderr)
    assert fw.returncode in (0, 1), fw.stderr[-3000:]
    result = json.loads(report.read_text())
    result["firmware_log"] = fw.stderr[-4000:]
    world = World.from_dict(
        tomllib.loads((ROOT / "config" / "worlds" / f"{world_name}.toml").read_text())["world"]
    )
    result["truth_visited"] = sorted(visited_cells(mcap, world))
    result["free_cells"] = sorted(world.free_cells())
    result["map_accuracy"], result["map_observed"] = occupancy_accuracy(
        result["occupancy"], world)
    return result


@pytest.mark.timeout(400)
def test_firmware_covers_every_cell_through_the_buses(tmp_path: Path) -> None:
    res = run_once(tmp_path, "lab_walls_1", seed=1)
    assert res["complete"], res
    assert set(map(tuple, res["truth_visited"])) == set(res["free_cells"]), res
    # the firmware's own belief of where it went matches where it went
    assert {tuple(c) for c in res["visited"]} == set(map(tuple, res["truth_visited"]))
    # its IR occupancy grid (seeds/004) agrees with the true map
    assert res["map_observed"] > 200 and res["map_accuracy"] >= 0.95, res["map_accuracy"]


def main() -> None:
    import tempfile

    ap = argparse.ArgumentParser(description="coverage firmware over seeds and lab worlds")
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--worlds", nargs="*", default=["lab_walls_1", "lab_walls_2", "lab_walls_3"])
    ap.add_argument("--random-start", action="store_true",
                    help="start each run in a seeded random cell and cardinal heading")
    ap.add_argument("--clock", default="lockstep", choices=["lockstep", "fast", "realtime"])
    ap.add_argument("--period-s", type=float, default=PERIOD_S,
                    help=f"[lockstep] period_s, the firmware's control period (default {PERIOD_S})")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        for world in args.worlds:
            for seed in range(args.seeds):
                t0 = time.monotonic()
                try:
                    r = run_once(Path(tmp), world, seed, random_start=args.random_start,
                                 clock=args.clock, period_s=args.period_s)
                    ok = r["complete"] and set(map(tuple, r["truth_visited"])) == set(
                        r["free_cells"])
                    print(f"{world} seed {seed}: {'ok' if ok else 'INCOMPLETE'} "
                          f"localised {r['localised_cell']} after {r['localisation_moves']} "
                          f"moves, {len(r['truth_visited'])}/{len(r['free_cells'])} cells, "
                          f"robot time {r['robot_time_s']} s, resyncs {r['resyncs']}, "
                          f"wall fixes {r['wall_fixes']}, map {r['map_accuracy']:.3f} of "
                          f"{r['map_observed']}, {r['cycles']} cycles, "
                          f"{r['cycles_per_wall_s']} cycles/s, skipped {r['skipped_periods']}, "
                          f"wall {time.monotonic() - t0:.0f} s",
                          flush=True)
                    if not ok:
                        print(r["firmware_log"], flush=True)
                except Exception as e:  # report and go on with the next run
                    print(f"{world} seed {seed}: FAILED {e!r}", flush=True)


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    main()
