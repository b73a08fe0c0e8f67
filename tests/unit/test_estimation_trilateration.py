"""Trilateration: the lab's closed form (seeds/003) and the weighted least-squares fix."""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

import numpy as np
import pytest
from koala_bridge.core.geometry import wrap_angle
from koala_bridge.core.grid import Grid
from koala_bridge.estimation import DegenerateGeometryError, EstimationError, trilaterate3, wls_fix
from scipy.stats import chi2

WORLDS = Path(__file__).resolve().parents[2] / "config" / "worlds"


def _ranges(landmarks: np.ndarray, p: np.ndarray) -> np.ndarray:
    return np.hypot(landmarks[:, 0] - p[0], landmarks[:, 1] - p[1])


def _bearings(landmarks: np.ndarray, pose: np.ndarray) -> np.ndarray:
    a = np.arctan2(landmarks[:, 1] - pose[1], landmarks[:, 0] - pose[0]) - pose[2]
    return wrap_angle(a)


def test_closed_form_is_exact_on_noise_free_ranges() -> None:
    rng = np.random.default_rng(3)
    for _ in range(200):
        lm = rng.uniform(-5, 5, size=(3, 2))
        p = rng.uniform(-5, 5, size=2)
        v1, v2 = lm[1] - lm[0], lm[2] - lm[1]
        if abs(v1[0] * v2[1] - v1[1] * v2[0]) < 0.5:  # keep well-conditioned triangles
            continue
        np.testing.assert_allclose(trilaterate3(lm, _ranges(lm, p)), p, atol=1e-9)


def test_closed_form_in_the_lab_trilateration_world() -> None:
    d = tomllib.loads((WORLDS / "lab_trilateration.toml").read_text())
    world = Grid.from_dict(d["world"])
    lm = np.array([[m.x, m.y] for m in world.landmarks])
    for col, row in world.free_cells():
        p = np.array(world.cell_centre(col, row))
        # "the first three are used": every choice of three corner landmarks works
        for pick in ([0, 1, 2], [1, 2, 3], [0, 2, 3], [3, 0, 1]):
            est = trilaterate3(lm[pick], _ranges(lm[pick], p))
            assert world.cell_of(*est) == (col, row)
            np.testing.assert_allclose(est, p, atol=1e-9)


@pytest.mark.parametrize(
    "landmarks",
    [
        [[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]],  # collinear
        [[0.0, 0.0], [0.0, 0.0], [1.0, 3.0]],  # two coincide
        [[0.0, 1.0], [1.0, 1.0], [5.0, 1.0 + 1e-9]],  # collinear to rounding
    ],
)
def test_closed_form_rejects_collinear_landmarks(landmarks: list[list[float]]) -> None:
    with pytest.raises(DegenerateGeometryError, match="collinear"):
        trilaterate3(landmarks, [1.0, 1.0, 1.0])


def test_closed_form_checks_shapes() -> None:
    with pytest.raises(EstimationError):
        trilaterate3([[0, 0], [1, 0]], [1, 1])


def test_wls_is_exact_on_noise_free_data() -> None:
    lm = np.array([[0.0, 0.0], [3.0, 0.0], [3.0, 2.0], [0.0, 2.0], [1.5, 3.0]])
    pose = np.array([1.0, 0.7, 0.4])
    fix = wls_fix(lm, _ranges(lm, pose), 0.01)
    np.testing.assert_allclose(fix.x, pose[:2], atol=1e-9)
    assert fix.dof == 3 and fix.chi2 < 1e-12
    fix = wls_fix(lm, _ranges(lm, pose), 0.01, _bearings(lm, pose), 0.01)
    np.testing.assert_allclose(fix.x, pose, atol=1e-9)
    assert fix.cov.shape == (3, 3)


def test_wls_range_only_on_collinear_landmarks_is_degenerate_but_bearings_resolve_it() -> None:
    lm = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]])
    pose = np.array([0.8, 1.2, -0.3])
    with pytest.raises(DegenerateGeometryError):
        wls_fix(lm, _ranges(lm, pose), 0.01)
    fix = wls_fix(
        lm, _ranges(lm, pose), 0.01, _bearings(lm, pose), 0.01, heading=pose[2], sigma_heading=0.05
    )
    np.testing.assert_allclose(fix.x, pose, atol=1e-9)


def test_wls_needs_three_observations() -> None:
    with pytest.raises(EstimationError, match="N >= 3"):
        wls_fix([[0, 0], [1, 0]], [1.0, 1.0], 0.1)


@pytest.mark.parametrize("with_bearings", [False, True])
def test_wls_covariance_is_consistent(with_bearings: bool) -> None:
    """NEES of the fix against truth, averaged over fixed-seed trials, lies in its chi-square
    interval; so does the residual chi2 (the stated covariance matches the actual error)."""
    rng = np.random.default_rng(11)
    lm = np.array([[0.05, 1.95], [1.95, 1.95], [1.95, 0.05], [0.05, 0.05]])
    trials = 400
    nees, resid, dofs = [], [], []
    for _ in range(trials):
        pose = np.array([*rng.uniform(0.3, 1.7, 2), rng.uniform(-math.pi, math.pi)])
        r_true = _ranges(lm, pose)
        sr = 0.01 + 0.02 * r_true  # camera distance error grows with range (seeds/000 eq. 10-12)
        r = r_true + rng.normal(0, sr)
        if with_bearings:
            sb = math.radians(2.0)
            b = _bearings(lm, pose) + rng.normal(0, sb, 4)
            fix = wls_fix(lm, r, sr, b, sb)
            e = fix.x - pose
            e[2] = wrap_angle(e[2])
        else:
            fix = wls_fix(lm, r, sr)
            e = fix.x - pose[:2]
        nees.append(float(e @ np.linalg.solve(fix.cov, e)))
        resid.append(fix.chi2)
        dofs.append(fix.dof)
    n = 3 if with_bearings else 2
    lo, hi = chi2.ppf([0.0005, 0.9995], trials * n) / trials
    assert lo <= np.mean(nees) <= hi, (np.mean(nees), lo, hi)
    k = dofs[0]
    lo, hi = chi2.ppf([0.0005, 0.9995], trials * k) / trials
    assert lo <= np.mean(resid) <= hi, (np.mean(resid), lo, hi)
