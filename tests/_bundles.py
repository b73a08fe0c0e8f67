"""A gyro bundle on disk (docs/bundle format): ``truth_pose.csv`` with a heading, ``gyro.csv``
with the yaw rate and any further columns, an empty ``meta.json``."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from koala_bridge.calibration.bundle import load_bundle
from koala_bridge.calibration.model import declared_model
from koala_bridge.calibration.pipeline import StreamResult, calibrate
from koala_bridge.calibration.problem import SkippedStream


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


def calibrate_stream(
    d: Path, name: str, config: Mapping[str, Any] | None = None
) -> tuple[StreamResult | None, list[SkippedStream]]:
    """Calibrate the bundle at ``d`` against ``config`` (default: none, meta.json's model) and
    return the result of stream ``name`` (None when it has none) and the skipped streams."""
    bundle = load_bundle(d)
    skipped: list[SkippedStream] = []
    results = calibrate(bundle, declared_model(config or {}, bundle.meta), skipped=skipped)
    found = [r for r in results if r.problem.name == name]
    return (found[0] if found else None), skipped
