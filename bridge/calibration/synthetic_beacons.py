"""Synthetic range-beacon (UWB) bundles with a known scale and offset, for tests.

The robot drives a Lissajous path inside a square of beacons; each beacon's range is read every
``1 / rate_hz`` s as ``(1 + scale) r + offset + N(0, noise_m^2)`` (``r`` the true distance).
Two bundle forms (docs/bundle-format.md): ``"landmarks"`` writes ``landmarks.csv`` (range only),
``landmark_map.csv`` and ``truth_pose.csv`` (positions only); ``"range"`` writes ``range.csv``
with ``kind = uwb`` and ``true_range``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from koala_bridge.calibration.synthetic import write_columns
from numpy.typing import NDArray


@dataclass(frozen=True)
class UwbCase:
    scale: float = 0.03
    offset_m: float = 0.12
    noise_m: float = 0.03
    duration_s: float = 120.0
    rate_hz: float = 10.0
    #: side of the square of beacons (one at each corner), the robot near its centre
    side_m: float = 8.0


def uwb_truth(
    case: UwbCase,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """``(t, x, y)`` of the robot."""
    t = np.arange(0.0, case.duration_s, 1.0 / case.rate_hz)
    c = case.side_m / 2
    x = c + 0.35 * case.side_m * np.cos(2 * np.pi * t / 40)
    y = c + 0.3 * case.side_m * np.sin(2 * np.pi * t / 27)
    return t, x, y


def beacon_positions(case: UwbCase) -> NDArray[np.float64]:
    s = case.side_m
    return np.array([[0.0, 0.0], [s, 0.0], [s, s], [0.0, s]])


def make_uwb_bundle(out: Path, seed: int, case: UwbCase, form: str = "landmarks") -> Path:
    """Write the bundle (module docstring) to ``out`` and return it."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    t, x, y = uwb_truth(case)
    beacons = beacon_positions(case)
    rows = []
    for i, (bx, by) in enumerate(beacons):
        r = np.hypot(x - bx, y - by)
        measured = (1 + case.scale) * r + case.offset_m + rng.normal(0, case.noise_m, t.size)
        rows.append(np.column_stack([t, np.full(t.size, i), measured, r]))
    table = np.concatenate(rows)
    table = table[np.argsort(table[:, 0], kind="stable")]
    if form == "range":
        lines = ["t,sensor,kind,measured,true_range"]
        lines += [f"{a:.4f},{int(b)},uwb,{c:.6f},{d:.6f}" for a, b, c, d in table]
        (out / "range.csv").write_text("\n".join(lines) + "\n", encoding="utf-8")
        return out
    if form != "landmarks":
        raise ValueError(f"unknown form {form!r}: 'landmarks' or 'range'")
    write_columns(out / "truth_pose.csv", "t,x,y", [t, x, y])
    lines = ["t,landmark_id,range"] + [f"{a:.4f},{int(b)},{c:.6f}" for a, b, c, _ in table]
    (out / "landmarks.csv").write_text("\n".join(lines) + "\n", encoding="utf-8")
    write_columns(out / "landmark_map.csv", "id,x,y", [np.arange(len(beacons)), beacons])
    return out
