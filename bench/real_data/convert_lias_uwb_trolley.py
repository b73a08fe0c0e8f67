"""LIAS-CUHKSZ planar UWB dataset: a trolley with three DW1000-class UWB tags ranging to eight
fixed anchors while pushed around a motion-capture room ("mid" run, 0.23 m/s average, 130 s).

Upstream: github.com/LIAS-CUHKSZ/Efficient-Pose-Estimation-via-UWB-measurements,
``Planar_Dataset/Dynamic/`` (README.md: tag and anchor coordinates, column order; LICENSE: MIT,
copyright 2023 Haodong Jiang).

Cut: the UWB log (~100 Hz, 24 tag-anchor ranges per row) is decimated to every 50th row inside
the motion-capture span (~2 Hz): 259 of 12 908 rows, x 24 links. ``true_range`` is the 3-D
distance from the tag (the rigid body's position plus the tag's surveyed offset turned by the
body's heading) to the anchor, with the motion capture interpolated linearly to the UWB time
stamp (the upstream alignment script does the same, on the same clock).
"""

from __future__ import annotations

import datetime as dt
import sys
from pathlib import Path

import numpy as np
from koala_bridge.recording.export import write_csv

from bench.real_data._upstream import read_upstream, run_converter, write_meta

NAME = "lias_uwb_trolley"
REPO = "LIAS-CUHKSZ/Efficient-Pose-Estimation-via-UWB-measurements"
COMMIT = "cabd39232cb855d3c1160ed16692034f4d41a092"
DIR = "Planar_Dataset/Dynamic/"
UWB = DIR + "UWB_dynamic_exp_mid.csv"
MOCAP = DIR + "motion_capture_dynamic_exp_mid.csv"
STRIDE = 50
# Planar_Dataset/Dynamic/README.md (m): tags in the trolley frame, anchors in the room frame.
TAGS = np.array([[-0.0689, -0.1423, 0.0011], [-0.0750, 0.1402, 0.0016], [0.2034, 0.1451, -0.0008]])
ANCHORS = np.array([
    [-3.4203, 3.0053, 1.0442], [0.0016, 3.0110, 1.0446], [3.6056, 2.9795, 1.0463],
    [3.6011, -0.0008, 1.0422], [3.5674, -3.0087, 1.0443], [-0.0072, -2.9652, 1.0444],
    [-3.4673, -2.9587, 1.0445], [-3.4858, -0.0098, 1.0457],
])


def _stamp(text: str) -> float:
    return dt.datetime.strptime(text, "%Y-%m-%d %H:%M:%S.%f").replace(
        tzinfo=dt.UTC).timestamp()


def _heading(q: np.ndarray) -> np.ndarray:
    """Heading of the body x axis in the room's x-y plane, from (w, x, y, z) quaternions."""
    w, x, y, z = q.T
    return np.arctan2(2 * (x * y + w * z), 1 - 2 * (y * y + z * z))


def convert(mirror: Path, out: Path) -> dict[str, int]:
    uwb_lines = read_upstream(mirror, REPO, COMMIT, UWB).decode().splitlines()
    mocap_lines = read_upstream(mirror, REPO, COMMIT, MOCAP).decode().splitlines()[1:]
    mocap = np.array([[_stamp(c[0]), *map(float, c[1:8])]
                      for c in (line.split(",") for line in mocap_lines)])
    cells = [line.split(",") for line in uwb_lines]
    t_uwb = np.array([_stamp(c[0]) for c in cells])
    inside = np.flatnonzero((t_uwb >= mocap[0, 0]) & (t_uwb <= mocap[-1, 0]))[::STRIDE]
    t0 = t_uwb[inside[0]]
    q = mocap[:, 4:8] / np.linalg.norm(mocap[:, 4:8], axis=1)[:, None]
    heading = np.unwrap(_heading(q))
    rows = []
    for i in inside:
        t = t_uwb[i]
        p = np.array([np.interp(t, mocap[:, 0], mocap[:, k]) for k in (1, 2, 3)])
        th = float(np.interp(t, mocap[:, 0], heading))
        c, s = np.cos(th), np.sin(th)
        for a in range(8):
            for k in range(3):
                cell = cells[i][1 + 3 * a + k]
                if not cell:
                    continue
                lx, ly, lz = TAGS[k]
                tag = p + np.array([c * lx - s * ly, s * lx + c * ly, lz])
                true_range = float(np.linalg.norm(tag - ANCHORS[a]))
                rows.append([f"{t - t0:.3f}", a, k, "uwb", f"{float(cell):.2f}",
                             f"{true_range:.4f}"])
    n = write_csv(out / "range.csv", ["t", "sensor", "tag", "kind", "measured", "true_range"],
                  rows)
    write_meta(out / "meta.json", {
        "name": NAME,
        "description": (
            "Planar UWB dataset of LIAS-CUHKSZ: a trolley carrying three UWB tags, each ranging "
            "to eight fixed anchors (two-way ranging, 1 cm resolution), pushed around a motion-"
            "capture room at 0.23 m/s on average ('mid' run, 130 s). Ranges against the "
            "distance computed from the motion-capture pose and the surveyed tag and anchor "
            "positions."),
        "source": {
            "repository": f"https://github.com/{REPO}",
            "commit": COMMIT,
            "paths": [UWB, MOCAP, DIR + "README.md", "LICENSE"],
            "converter": "bench/real_data/convert_lias_uwb_trolley.py",
        },
        "licence": "MIT (LICENSE of the repository, copyright 2023 Haodong Jiang)",
        "sensor": {
            "uwb": {
                "declared_model": "measured = 3-D distance tag-anchor (no bias, unit scale)",
                "resolution_m": 0.01,
                "tags_body_frame_m": TAGS.tolist(),
                "anchors_room_frame_m": ANCHORS.tolist(),
            },
        },
        "units": {
            "range.measured": "m", "range.true_range": "m",
            "range.sensor": "anchor index 0-7", "range.tag": "tag index 0-2 (covariate)",
            "t": "s (UWB log clock minus the first kept stamp; the motion capture is on the "
                 "same clock)",
        },
        "notes": [
            f"Decimated: every {STRIDE}th UWB row inside the motion-capture span (about 2 Hz of "
            "the 100 Hz log), all 24 tag-anchor links of each kept row; empty cells skipped.",
            "Motion capture: columns 5-8 are the quaternion (w, x, y, z) as the README says; the "
            "rigid body was defined upside down (a 180 deg turn about a horizontal axis), so "
            "the trolley heading is taken as the angle of the body x axis in the room plane "
            "and the tag offsets are turned by that heading only. Of the readings' "
            "conventions tried (w-first or w-last quaternion, heading + k*90 deg, y mirrored), "
            "this one gives the smallest spread of range error per link (median absolute "
            "deviation 0.048 m against 0.10-0.25 m for the others).",
            "A lag between UWB and motion capture was looked for (-0.2..0.2 s): the spread "
            "changes by < 3 %, so none is applied.",
            "Readings of 0.00 m (dropouts) are kept as recorded.",
            "Upstream calibrates a distance-dependent bias per tag-anchor pair from separate "
            "calibration runs (Dynamic_Experiment/1_Calibration) and removes outliers first "
            "(2_Outlier_Rejection_and_Interpolation); neither is applied here.",
        ],
    })
    return {"range": n}


def main(argv: list[str] | None = None) -> int:
    return run_converter(NAME, convert, argv)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
