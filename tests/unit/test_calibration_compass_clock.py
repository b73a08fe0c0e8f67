"""A compass and its reference heading stamped on clocks apart: 0.5 s off, the held-out heading
error was 0.20 rad against the noise's 0.015, and the report said "unchanged"; 2 s off, 0.74
rad, "unchanged", in silence. ``time_offset`` now applies to a compass against a reference
heading: it reads the reference at the readings' times less ``tau``, started where the
declared model's heading follows the shifted reference best
(``CompassProblem.heading_match``), about the clocks' offset when they look seconds apart
(``CompassProblem.clocks_apart``, said in a note)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from _bundles import calibrate_stream
from koala_bridge.calibration.pipeline import StreamResult
from koala_bridge.calibration.synthetic import DECLARED, Injected, make_bundle

NOTE = "the readings match the reference best"


def _compass(tmp_path: Path, late_s: float, hard_iron: tuple[float, float]) -> StreamResult:
    """300 s at 20 Hz of the synthetic drive (truth and compass only), the compass stamped
    ``late_s`` late, with an undeclared hard iron."""
    d = make_bundle(tmp_path / "b", seed=3, inj=Injected(hard_iron=hard_iron),
                    duration_s=300.0, rate_hz=20.0)
    for f in d.glob("*.csv"):
        if f.name not in ("truth_pose.csv", "compass.csv"):
            f.unlink()
    path = d / "compass.csv"
    header = path.read_text().splitlines()[0]
    a = np.loadtxt(path, delimiter=",", skiprows=1)
    a[:, 0] += late_s
    np.savetxt(path, a, delimiter=",", header=header, comments="", fmt="%.9g")
    res, _ = calibrate_stream(d, "compass", DECLARED)
    shutil.rmtree(d)
    assert res is not None
    return res


@pytest.mark.parametrize(("late_s", "hard_iron"), [
    (2.0, (0.0, 0.0)),
    (-3.0, (5.0, -3.0)),
    (0.5, (0.0, 0.0)),  # at the edge of the +-0.5 s latency window
])
def test_a_compass_on_another_clock_gets_its_time_offset(
    tmp_path: Path, late_s: float, hard_iron: tuple[float, float]
) -> None:
    res = _compass(tmp_path, late_s, hard_iron)
    names = sorted(i.name for i in res.effects)
    assert names == sorted(["time_offset"] + (["hard_iron"] if any(hard_iron) else [])), names
    (found,) = [(p, se) for (p, se) in res.effect_params() if "tau_s" in p]
    tau, se = found[0]["tau_s"], found[1]["tau_s"]
    # the synthetic readings are instants: no half sample; 4 standard errors
    assert abs(tau - late_s) <= 4 * se, (tau, se)
    assert se < 0.01
    # the noise's level again (the synthetic compass's 0.015 rad)
    assert res.after < 0.02 < res.before
    (note,) = [n for n in res.problem.notes if n.startswith(NOTE)]
    # the coarse grid: 10 s in 50 steps of 0.2 s
    assert abs(float(note.split("best ")[1].split(" s")[0]) - late_s) <= 0.2, note


def test_a_compass_on_the_reference_clock_gets_none(tmp_path: Path) -> None:
    res = _compass(tmp_path, 0.0, (5.0, -3.0))
    assert [i.name for i in res.effects] == ["hard_iron"]
    assert not any(n.startswith(NOTE) for n in res.problem.notes)
