"""A ranger's reference that holds one value per sensor cannot show a gain.

A new user's two VL53L1X time-of-flight rangers, each held at its own distance (256 and
265 mm) for 600 s and reading 50 mm short with a few mm apart: a gain fitted through the two
distances is two offsets, and ``scale`` (+1.6) "passed" beside the per-sensor offsets, which
the report then called a unit error. Such a reference determines per-sensor offsets only."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from _bundles import calibrate_stream


def _still_rangers(out: Path, seed: int) -> Path:
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 600.0, 1.0)
    rows = ["t,kind,sensor,measured,true_range"]
    sensors = ((0.256, -0.057), (0.265, -0.043))
    y = [d + o + rng.normal(0.0, 0.003, t.size) for d, o in sensors]
    for k, a in enumerate(t):  # both sensors read each second, rows in time order
        rows += [f"{a:.3f},lidar,{s},{y[s][k]:.5f},{d}" for s, (d, _) in enumerate(sensors)]
    out.mkdir(parents=True)
    (out / "range.csv").write_text("\n".join(rows) + "\n", encoding="utf-8")
    (out / "meta.json").write_text("{}", encoding="utf-8")
    return out


def test_rangers_each_at_one_distance_get_offsets_not_a_scale(tmp_path: Path) -> None:
    for seed in range(3):
        res, _ = calibrate_stream(_still_rangers(tmp_path / f"b{seed}", seed), "range:lidar")
        assert res is not None
        names = [i.name for i in res.effects]
        assert "scale" not in names and "range_dependent" not in names, names
        assert "offset_per:sensor" in names
        assert any(n.startswith("scale not tried: the reference holds one value per sensor")
                   for n in res.problem.notes)
        # the offsets the sensors read: -50 mm in common, -7 mm and +7 mm apart (3 mm of noise
        # over 360 fit readings per sensor: an SE of 0.16 mm, the bound 6 of them)
        params = {k: v for p, _ in res.effect_params() for k, v in p.items()}
        assert abs(params["bias"] + 0.050) < 0.001
        assert abs(params["offset_0"] + 0.007) < 0.001


def test_a_staged_run_says_what_it_could_not_carry(tmp_path: Path) -> None:
    """A ranger's offsets (no simulator key for a lidar) are written as a comment, so a later
    stage's declared model cannot hold them: the new user's staged run dropped them without a
    word, and the second stage was 37 % worse than a hand fit with them."""
    from koala_bridge.calibration.pipeline import Options
    from koala_bridge.calibration.stages import calibrate_stages

    first, second = (_still_rangers(tmp_path / n, k) for k, n in enumerate(("b1", "b2")))
    stages, _ = calibrate_stages([first, second], {}, Options(), tmp_path / "work")
    (later,) = (r for r in stages[1].results if r.problem.name == "range:lidar")
    found = {i.name for i in stages[0].results[0].effects}
    assert {"bias", "offset_per:sensor"} <= found
    (note,) = [n for n in later.problem.notes if n.startswith("not carried from earlier")]
    assert "offset_per:sensor" in note and "(stage 1)" in note
    assert not any(n.startswith("not carried") for n in stages[0].results[0].problem.notes)
