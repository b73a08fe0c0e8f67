"""libRSF "Labyrinth" dataset (TU Chemnitz): a small differential-drive robot with a UWB tag
ranging to four fixed UWB beacons, wheel speeds, and ground-truth positions, 30 s.

Upstream: github.com/densalzmann/libRSF, ``datasets/Indoor_UWB/`` (readme.txt, LICENSE.txt:
CC BY-SA 4.0, copyright 2017-2023 Tim Pfeifer). Every upstream row is kept (233 of each kind).

Bundle: ``range.csv`` (kind ``uwb``, sensor = beacon id, ``true_range`` = planar distance from
the ground-truth position at the same time stamp to the beacon's surveyed position),
``odometry.csv`` (``v, omega`` from the logged wheel speeds and the declared wheel distance),
``truth_pose.csv`` (x, y; no heading upstream).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from koala_bridge.recording.export import write_csv

from bench.real_data._upstream import read_upstream, run_converter, write_meta

NAME = "labyrinth_uwb"
REPO = "densalzmann/libRSF"
COMMIT = "b5241c71970f24c1178bf2d1b320ea6bc0d5cb8a"
INPUT = "datasets/Indoor_UWB/Indoor_UWB_Input.txt"
GT = "datasets/Indoor_UWB/Indoor_UWB_GT.txt"
README = "datasets/Indoor_UWB/readme.txt"


def _rows(text: str, tag: str) -> np.ndarray:
    return np.array(
        [[float(v) for v in line.split()[1:]] for line in text.splitlines()
         if line.split()[:1] == [tag]]
    )


def convert(mirror: Path, out: Path) -> dict[str, int]:
    inp = read_upstream(mirror, REPO, COMMIT, INPUT).decode()
    gt = _rows(read_upstream(mirror, REPO, COMMIT, GT).decode(), "point2")
    rng = _rows(inp, "range2")  # t, range, var, beacon x, beacon y, id, snr
    odo = _rows(inp, "odom2diff")  # t, v_right, v_left, v_y, wheel distance, variances
    t0 = gt[0, 0]
    wheel_distance = float(odo[0, 4])
    beacons = {int(i): (float(x), float(y)) for x, y, i in rng[:, 3:6]}

    gx = np.interp(rng[:, 0], gt[:, 0], gt[:, 1])
    gy = np.interp(rng[:, 0], gt[:, 0], gt[:, 2])
    true_range = np.hypot(gx - rng[:, 3], gy - rng[:, 4])
    n_range = write_csv(
        out / "range.csv", ["t", "sensor", "kind", "measured", "true_range"],
        ([f"{t - t0:.4f}", int(i), "uwb", f"{r:.4f}", f"{tr:.4f}"]
         for t, r, i, tr in zip(rng[:, 0], rng[:, 1], rng[:, 5], true_range, strict=True)),
    )
    v = 0.5 * (odo[:, 1] + odo[:, 2])
    omega = (odo[:, 1] - odo[:, 2]) / wheel_distance
    n_odo = write_csv(
        out / "odometry.csv", ["t", "v", "omega"],
        ([f"{t - t0:.4f}", f"{a:.5f}", f"{b:.5f}"] for t, a, b in zip(odo[:, 0], v, omega,
                                                                      strict=True)),
    )
    n_gt = write_csv(
        out / "truth_pose.csv", ["t", "x", "y"],
        ([f"{t - t0:.4f}", f"{x:.4f}", f"{y:.4f}"] for t, x, y in gt[:, :3]),
    )
    write_meta(out / "meta.json", {
        "name": NAME,
        "description": (
            "libRSF 'Labyrinth' dataset (TU Chemnitz): a small differential-drive robot driving "
            "through a 2.4 m x 2.4 m labyrinth for 30 s with a UWB tag ranging to four fixed UWB "
            "beacons (one range every 0.128 s, beacons in turn), its wheel speeds, and "
            "ground-truth positions at the same time stamps (233 each)."),
        "source": {
            "repository": f"https://github.com/{REPO}",
            "commit": COMMIT,
            "paths": [INPUT, GT, README, "datasets/Indoor_UWB/LICENSE.txt"],
            "converter": "bench/real_data/convert_labyrinth_uwb.py",
        },
        "licence": ("CC BY-SA 4.0 (datasets/Indoor_UWB/readme.txt and LICENSE.txt; "
                    "copyright 2017-2023 Tim Pfeifer, TU Chemnitz)"),
        "robot": {"wheel_base_m": wheel_distance},
        "sensor": {
            "uwb": {
                "declared_model": "measured = planar distance tag-beacon (no bias, unit scale)",
                "range_variance_m2": float(rng[0, 2]),
                "beacons": {str(k): {"x": x, "y": y} for k, (x, y) in sorted(beacons.items())},
            },
            "odometry": {
                "declared_model": ("v = (v_right + v_left)/2, omega = (v_right - v_left)/"
                                   "wheel_base with the logged wheel speeds and wheel distance"),
                "wheel_speed_variance_m2_s2": float(odo[0, 6]),
            },
        },
        "units": {
            "range.measured": "m", "range.true_range": "m", "odometry.v": "m/s",
            "odometry.omega": "rad/s", "truth_pose.x": "m", "truth_pose.y": "m",
            "t": "s (upstream time stamps minus the first, one clock)",
        },
        "notes": [
            "range2 rows: time, range mean, range variance, beacon x, beacon y, beacon id; "
            "odom2diff rows: time, right and left wheel speed, lateral speed (0), distance "
            "between wheels (0.0785 m), variances (upstream readme).",
            "true_range is planar: the ground truth and the beacon positions are 2-D; the height "
            "difference between tag and beacons is not documented, so part of any range-"
            "dependent error may be geometry (sqrt(r^2 + h^2) - r), not the radio.",
            "omega = (v_right - v_left) / 0.0785 is the declared model of the odometry; the "
            "logged wheel speeds are kept only through v and omega.",
            "truth_pose has no heading (upstream ground truth is positions only).",
        ],
    })
    return {"range": n_range, "odometry": n_odo, "truth_pose": n_gt}


def main(argv: list[str] | None = None) -> int:
    return run_converter(NAME, convert, argv)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
