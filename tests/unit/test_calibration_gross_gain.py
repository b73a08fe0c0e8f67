"""A gain far from 1 is a unit or a time base (a new user's car log: its 0.1 s steps read as
seconds made the gyro 9.7 times the reference, its held-out part too still to confirm a scale,
and the report said nothing). A scale the fit part shows beyond 2:1 is said, with the factor it
most likely is (``pipeline._note_gross_gain``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from _bundles import calibrate_stream, gyro_bundle
from koala_bridge.calibration.pipeline import StreamResult
from koala_bridge.calibration.synthetic import DECLARED


def _gyro(tmp_path: Path, factor: float, seconds: float = 60.0, dt: float = 0.01,
          bias: float = 0.0, seed: int = 3) -> StreamResult:
    """``seconds`` every ``dt`` (60 s at 100 Hz) turning back and forth; the gyro's rate (with
    ``bias``) times ``factor``."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, seconds + dt / 2, dt)
    w = 0.6 * np.sin(2 * np.pi * t / 9)
    theta = np.r_[0.0, np.cumsum(0.5 * (w[1:] + w[:-1]) * np.diff(t))]
    d = gyro_bundle(tmp_path / "b", t, theta + rng.normal(0.0, 0.001, t.size),
                    factor * (w + bias + rng.normal(0.0, 0.002, t.size)))
    res, _ = calibrate_stream(d, "gyro", DECLARED)
    assert res is not None
    return res


@pytest.mark.parametrize(("factor", "says"), [
    (180 / np.pi, "57.3 is degrees where radians are meant"),
    (10.0, "10 is a tenfold unit, or a time base"),
    (3.3, "A gain beyond 2:1 is a unit"),
])
def test_a_gross_gain_is_said(tmp_path: Path, factor: float, says: str) -> None:
    res = _gyro(tmp_path, factor)
    (note,) = [n for n in res.problem.notes if "times the reference on the fit part" in n]
    assert says in note
    if factor == 3.3:
        assert ": 3.3" not in note  # no named factor near it


def test_a_gain_near_one_says_nothing(tmp_path: Path) -> None:
    res = _gyro(tmp_path, 1.03)
    assert not any("times the reference on the fit part" in n for n in res.problem.notes)


def test_a_gross_gain_of_the_opposite_sign_is_said_too(tmp_path: Path) -> None:
    """deg/s of the opposite sign: the sign note, and the unit beside it."""
    res = _gyro(tmp_path, -180 / np.pi)
    (note,) = [n for n in res.problem.notes if "times the reference on the fit part" in n]
    assert note.startswith("the readings are -5") and "57.3 is degrees where radians" in note
    assert any("the readings run against the reference" in n for n in res.problem.notes)


def test_a_gain_is_found_where_the_residual_is_no_ar1(tmp_path: Path) -> None:
    """The rate differenced from the noisy heading is white noise's moving difference: its
    first differences are about uncorrelated, and the AR(1) reading of them (``1 + 2 rho_d``)
    was 0.999 where the residual's lag-1 autocorrelation is 0.26. Prewhitened at 0.999, a gain
    of 1.5 did not show, and a time offset was named instead. The plain estimate, far lower,
    is taken (``problem.lag1_autocorrelation``)."""
    res = _gyro(tmp_path, 1.5)
    assert res.selection.rho < 0.5
    assert "scale" in [i.name for i in res.effects]
    found = dict(zip((i.name for i in res.effects), res.effect_params(), strict=True))
    # the reference's noise dilutes the gain by its share, ~1.5 % here (Scale.estimate_bias)
    assert found["scale"][0]["scale_error"] == pytest.approx(0.5, abs=0.03)


@pytest.mark.parametrize("factor", [180 / np.pi, 10.0, 3.3])
def test_a_gross_gain_is_never_written(tmp_path: Path, factor: float) -> None:
    """Two new users' gyros logged in deg/s: the note said "fix it in the bundle" and the same
    report marked ``scale_factor_error = 52.97`` as written. A gain beyond 2:1 describes the
    bundle, not the sensor: it stays in *after* and is not written, with the reason."""
    res = _gyro(tmp_path, factor)
    why = dict(zip([i.name for i in res.effects], res.not_written(), strict=True))
    assert why["scale"] is not None and "A gain beyond 2:1 is a unit" in why["scale"], why
    assert res.after_written() is not None  # the written model leaves the gain out


def test_a_gain_within_2_to_1_is_no_unit(tmp_path: Path) -> None:
    res = _gyro(tmp_path, 1.2)
    why = dict(zip([i.name for i in res.effects], res.not_written(), strict=True))
    assert "scale" in why and "A gain beyond" not in str(why["scale"]), why


def test_a_gyro_in_degrees_is_no_jump_of_the_reference(tmp_path: Path) -> None:
    """The heading-jump note compares the reference's steps with the readings' integral: a gyro
    read in deg/s turned 57 times the reference's smooth path (2 rad more in one 0.1 s step),
    and the note said the reference "jumps 300 time(s) where the gyro does not turn". The
    reference must itself step that far."""
    res = _gyro(tmp_path, 180 / np.pi, dt=0.1, seed=4)
    assert any("57.3 is degrees" in n for n in res.problem.notes)
    assert not any("reference heading jumps" in n for n in res.problem.notes)


def test_effects_fitted_beside_a_gross_gain_are_not_written(tmp_path: Path) -> None:
    """A gyro in deg/s with a 0.01 rad/s bias: the scale was withheld, the bias beside it (0.576,
    in deg/s) written as bias_rad_s. Everything the stream found is in the readings' unit."""
    res = _gyro(tmp_path, 180 / np.pi, bias=0.01)
    why = dict(zip([i.name for i in res.effects], res.not_written(), strict=True))
    assert "scale" in why and "bias" in why, why
    assert all(w is not None for w in why.values()), why
    assert "fitted beside scale" in str(why["bias"])


def test_the_note_quotes_the_table_s_gain(tmp_path: Path) -> None:
    """A new user saw 55.2 in the note and 55.8 in the table for one gain (the note read a
    round's fit on the selection's subset): where the final model holds the scale, the note
    quotes its gain."""
    res = _gyro(tmp_path, 180 / np.pi, seconds=300.0)  # 30 000 rows: selected on a subset
    (note,) = [n for n in res.problem.notes if "times the reference on the fit part" in n]
    quoted = float(note.split("scale fitted ")[1].split(",")[0])
    (scale,) = [p for p, _ in res.effect_params() if "scale_error" in p]
    assert quoted == pytest.approx(scale["scale_error"], rel=1e-3), (note, scale)
