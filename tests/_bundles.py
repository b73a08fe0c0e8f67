"""A gyro bundle on disk (docs/bundle format): ``truth_pose.csv`` with a heading, ``gyro.csv``
with the yaw rate and any further columns, an empty ``meta.json``."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def gyro_bundle(out: Path, t: np.ndarray, theta: np.ndarray, yaw_rate: np.ndarray,
                gyro_t: np.ndarray | None = None, **columns: np.ndarray) -> Path:
    """Write the bundle to ``out`` (created) and return it; the truth at ``t`` (x = y = 0), the
    gyro at ``gyro_t`` (default ``t``: a late clock is ``t + late``)."""
    out.mkdir(parents=True)
    np.savetxt(out / "truth_pose.csv", np.column_stack([t, 0 * t, 0 * t, theta]),
               delimiter=",", header="t,x,y,theta", comments="", fmt="%.10g")
    np.savetxt(out / "gyro.csv",
               np.column_stack([t if gyro_t is None else gyro_t, yaw_rate, *columns.values()]),
               delimiter=",", header=",".join(["t", "yaw_rate", *columns]), comments="",
               fmt="%.10g")
    (out / "meta.json").write_text("{}", encoding="utf-8")
    return out
