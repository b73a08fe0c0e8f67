"""``scenario_config(start_from_prior=True)``: the estimator starts from one draw of its prior.

A NEES test of the hostile drive is a consistency test only when the initial error is
distributed as the initial covariance says. The draw must be that distribution, and the same
for the same seed (the bench's figures are reproducible).
"""

from __future__ import annotations

import math

import numpy as np
from koala_bridge.tools.drive_scenario import scenario_config
from scipy import stats

N = 200


def _initial(seed: int) -> list[float]:
    config = scenario_config(seed=seed, start_from_prior=True)
    return [float(v) for v in config["localisation"]["initial_pose"]]


def test_the_draw_is_reproducible_and_differs_between_seeds() -> None:
    assert _initial(3) == _initial(3)
    assert _initial(3) != _initial(4)
    assert scenario_config(seed=3)["localisation"]["initial_pose"] == []


def test_the_draws_have_the_priors_distribution() -> None:
    config = scenario_config(seed=1)
    loc = config["localisation"]
    sxy, sth = loc["initial_sigma_xy_m"], loc["initial_sigma_theta_deg"]
    start = config["world"]["start"]
    x0, y0, th0 = float(start["x"]), float(start["y"]), float(start["theta_deg"])
    d = np.array([_initial(s) for s in range(N)]) - [x0, y0, th0]
    z = d / [sxy, sxy, sth]
    # each coordinate's mean within 4 standard errors of 0, and N z^2 summed ~ chi2(N): both
    # bounds at a two-sided 1e-4 level
    assert np.all(np.abs(z.mean(axis=0)) < 4 / math.sqrt(N))
    lo, hi = stats.chi2.ppf([5e-5, 1 - 5e-5], N)
    ss = np.sum(z**2, axis=0)
    assert np.all((lo < ss) & (ss < hi)), ss
