"""Landmark observations no reference reaches are set aside with a word, not silently.

The MRCLAM run's robots also sighted each other: 407 of 1941 observations named barcodes that
``landmark_map.csv`` does not hold, and dropped out of the stream without a note. The count is
now in the notes of each landmark stream (and so in the report), with how to have them used.
"""

from __future__ import annotations

from pathlib import Path

from koala_bridge.calibration.bundle import load_bundle
from koala_bridge.calibration.model import declared_model
from koala_bridge.calibration.pipeline import calibrate
from koala_bridge.calibration.synthetic import DECLARED, make_bundle


def test_observations_of_unmapped_landmarks_are_counted(tmp_path: Path) -> None:
    d = make_bundle(tmp_path / "b", seed=4, duration_s=60.0)
    obs = (d / "landmarks.csv").read_text().splitlines()
    n = len(obs) - 1
    last = obs[-1].split(",", 1)[0]  # stamped with the last rows: files are in time order
    extra = [f"{last},99,{row.split(',', 2)[2]}" for row in obs[1:6]]
    (d / "landmarks.csv").write_text("\n".join([*obs, *extra]) + "\n")
    bundle = load_bundle(d)
    results = calibrate(bundle, declared_model(DECLARED, bundle.meta))
    landmark = [r for r in results if r.problem.name.startswith("landmark_")]
    assert {r.problem.name for r in landmark} == {"landmark_range", "landmark_bearing"}
    for r in landmark:
        assert any(
            f"5 of {n + 5} observations name a landmark_id not in landmark_map.csv" in note
            for note in r.problem.notes
        ), r.problem.notes
