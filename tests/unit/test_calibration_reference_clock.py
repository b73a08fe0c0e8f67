"""A dense reference heading whose stamps jitter around a regular clock (a host stamping a
tracker's samples on receipt) is read on that clock (streams.regular_clock, on_regular_clock).

Differenced over jittered stamps, the reference rate is wrong by ``w (e_(i+1) - e_i) / dt``:
with 2 ms at 100 Hz, rate space fitted a -7 % gain (errors in the variables) and a 5 ms time
offset (half a sample: a shift that smooths the jitter), and missed a 0.01 rad/s bias.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from _bundles import gyro_bundle
from koala_bridge.calibration.bundle import load_bundle
from koala_bridge.calibration.model import declared_model
from koala_bridge.calibration.pipeline import StreamResult, calibrate
from koala_bridge.calibration.streams import regular_clock
from koala_bridge.calibration.synthetic import DECLARED

DT = 0.01
MAX_JITTER_S = 0.0045  # inside half a sample: the stamps stay in order


def _numbers(rng: np.random.Generator, n: int, drop: float) -> np.ndarray:
    """Sample numbers of a clock's ``n`` samples with a share ``drop`` of them lost."""
    keep = rng.random(n) >= drop
    keep[0] = True
    return np.flatnonzero(keep).astype(float)


@pytest.mark.parametrize(("n", "sigma", "drop"), [(10_000, 0.002, 0.0), (30_000, 0.002, 0.01),
                                                  (5_000, 0.0005, 0.02)])
def test_the_regular_clock_is_recovered(n: int, sigma: float, drop: float) -> None:
    rng = np.random.default_rng(2)
    period = DT * (1 + 2e-4)  # the tracker's clock 200 ppm off the gyro's
    k = _numbers(rng, n, drop)
    true = 3.0 + k * period
    stamps = true + np.clip(rng.normal(0.0, sigma, k.size), -MAX_JITTER_S, MAX_JITTER_S)
    clock = regular_clock(stamps)
    assert clock is not None
    # the least-squares clock through n samples: its error at the ends is a few sigma / sqrt(n)
    assert np.max(np.abs(clock - true)) < 10 * sigma / np.sqrt(k.size)


def test_regular_or_irregular_but_right_stamps_are_left_alone() -> None:
    rng = np.random.default_rng(3)
    assert regular_clock(np.arange(0.0, 50.0, DT)) is None  # regular already
    # an event-driven tracker: intervals anywhere from 5 to 15 ms, no clock behind them
    assert regular_clock(np.cumsum(rng.uniform(0.005, 0.015, 5000))) is None


def _motion() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    t = np.arange(0.0, 100.0 + DT / 2, DT)
    w = 0.8 * np.sin(2 * np.pi * t / 7) + 0.3 * np.sin(2 * np.pi * t / 2.3)
    theta = np.r_[0.0, np.cumsum(0.5 * (w[1:] + w[:-1]) * np.diff(t))]
    return t, w, theta


def _gyro(path: Path) -> StreamResult:
    bundle = load_bundle(path)
    (res,) = (r for r in calibrate(bundle, declared_model(DECLARED, bundle.meta))
              if r.problem.name == "gyro")
    return res


@pytest.mark.parametrize("seed", [0, 1])
def test_a_bias_against_jittered_stamps_is_found_in_rate_space(tmp_path: Path,
                                                               seed: int) -> None:
    t, w, theta = _motion()
    rng = np.random.default_rng(seed)
    stamps = t + np.clip(rng.normal(0.0, 0.002, t.size), -MAX_JITTER_S, MAX_JITTER_S)
    res = _gyro(gyro_bundle(tmp_path / "b", stamps, theta,
                            w + 0.01 + rng.normal(0.0, 0.002, t.size), gyro_t=t))
    assert res.problem.metric == "rms_rate_error"
    assert any(n.startswith("the reference's stamps jitter around a regular 100 Hz clock")
               for n in res.problem.notes)
    # not a gain pulled towards 0, not a half-sample time offset: the bias
    assert [i.name for i in res.effects] == ["bias"]
    ((p, se),) = res._params_and_se()
    assert se is not None and abs(float(p[0]) - 0.01) < 4 * float(se[0])


def test_right_stamps_of_an_irregular_tracker_are_kept(tmp_path: Path) -> None:
    # the heading sampled at irregular instants and stamped right: its differenced rate is
    # right, and on a regular clock it would not be; a clean gyro gets nothing
    t, w, _ = _motion()
    rng = np.random.default_rng(4)
    t_ref = np.r_[0.0, np.cumsum(rng.uniform(0.005, 0.015, 10_000))]
    t_ref = t_ref[t_ref <= t[-1]]
    res = _gyro(_irregular_bundle(tmp_path / "b", t_ref, t, w, rng))
    assert not any("stamps jitter" in n for n in res.problem.notes)
    assert res.effects == []


def _irregular_bundle(out: Path, t_ref: np.ndarray, t: np.ndarray, w: np.ndarray,
                      rng: np.random.Generator) -> Path:
    theta = np.r_[0.0, np.cumsum(0.5 * (w[1:] + w[:-1]) * np.diff(t))]
    # the heading at the tracker's instants (the motion is smooth: linear between 10 ms
    # samples is right to 1e-5 rad)
    return gyro_bundle(out, t_ref, np.interp(t_ref, t, theta),
                       w + rng.normal(0.0, 0.002, t.size), gyro_t=t)


def test_a_heading_that_flips_by_pi_is_said(tmp_path: Path) -> None:
    # the heading of a sensor tilted past 90 deg, derived from an orientation, flips by pi
    # where the gyro does not turn; a motion without flips gets no such note
    t, w, theta = _motion()
    flipped = theta + np.pi * ((t > 30) & (t < 31))
    res = _gyro(gyro_bundle(tmp_path / "b", t, flipped, w))
    (note,) = (n for n in res.problem.notes if n.startswith("the reference heading jumps"))
    assert "2 time(s)" in note and "t = 30" in note
    clean = _gyro(gyro_bundle(tmp_path / "c", t, theta, w))
    assert not any(n.startswith("the reference heading jumps") for n in clean.problem.notes)
