"""Drive-control error (seeds/000 eq. 1–4, per-wheel reading; sim/models/drive.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from _stats import assert_mean, assert_normal_variance
from koala_bridge.core.schema import ConfigError
from koala_bridge.sim.models.drive import (
    DriveErrorParams,
    heading_error_variance,
    integrate_wheel_steps,
    perturb_wheel_steps,
)

# The error terms these tests do not study, off (config/default.toml switches them on; the
# params' keyword defaults are its values, tests/unit/test_config_schema.py).
QUIET = {"drive_error": 0.0, "reference_rate_hz": 200.0, "wall_traction_min": 1.0,
         "wall_traction_max": 1.0}


def make_params(**kw: object) -> DriveErrorParams:
    """DriveErrorParams with :data:`QUIET` under ``kw``."""
    return DriveErrorParams(**{**QUIET, **kw})  # type: ignore[arg-type]

B = 0.30  # wheel base used by these tests, m


def test_ideal_returns_commanded_steps_and_draws_nothing() -> None:
    p = make_params(ideal=True, drive_error=0.5)
    rng = np.random.default_rng(1)
    state = rng.bit_generator.state
    assert perturb_wheel_steps(0.001, -0.002, 200.0, p, rng) == (0.001, -0.002)
    assert rng.bit_generator.state == state


def test_single_step_relative_error_is_gaussian_with_drive_sigma() -> None:
    p = make_params(drive_error=0.1, reference_rate_hz=200.0)
    rng = np.random.default_rng(2)
    steps = np.array([perturb_wheel_steps(0.001, 0.002, 200.0, p, rng) for _ in range(20000)])
    assert_normal_variance(steps[:, 0] / 0.001 - 1.0, 0.01, mean=0.0, wrong=0.0125)
    assert_normal_variance(steps[:, 1] / 0.002 - 1.0, 0.01, mean=0.0, wrong=0.0125)


@pytest.mark.parametrize("step_hz", [200.0, 400.0])
def test_heading_error_of_a_straight_run_matches_eq2_and_is_rate_invariant(step_hz: float) -> None:
    """Drive 0.3 m straight at 0.2 m/s; heading error variance = sigma^2 sum(l^2+r^2)/b^2 with the
    per-step sigma rescaled to the step rate, i.e. the same at 200 and 400 Hz."""
    p = make_params(drive_error=0.2, reference_rate_hz=200.0)
    rng = np.random.default_rng(3)
    n_steps = int(1.5 * step_hz)
    step = 0.2 / step_hz
    runs = 300
    finals = np.empty(runs)
    for k in range(runs):
        x = y = th = 0.0
        for _ in range(n_steps):
            dl, dr = perturb_wheel_steps(step, step, step_hz, p, rng)
            x, y, th = integrate_wheel_steps(x, y, th, dl, dr, B)
        finals[k] = th
    sigma_step = 0.2 * math.sqrt(step_hz / 200.0)
    var = heading_error_variance(np.full(n_steps, step), np.full(n_steps, step), B, sigma_step)
    # At the reference rate this is 0.2^2 * 2 * 300 * 0.001^2 / 0.09 = 2.67e-4 rad^2.
    var_ref = 0.2**2 * 2 * 300 * 0.001**2 / B**2
    assert var == pytest.approx(var_ref)
    # Without the rate rescaling, 400 Hz would give half the variance: must be rejected.
    assert_normal_variance(finals, var, mean=0.0, wrong=var / 2)


def test_wall_contact_realises_a_uniform_fraction_of_each_step() -> None:
    p = make_params(drive_error=0.0, wall_traction_min=0.2, wall_traction_max=0.6)
    rng = np.random.default_rng(4)
    f = np.array([perturb_wheel_steps(1.0, 1.0, 200.0, p, rng, in_contact=True)
                  for _ in range(20000)])
    assert f.min() >= 0.2 and f.max() <= 0.6
    # U(0.2, 0.6): mean 0.4, std 0.4/sqrt(12)
    assert_mean(f[:, 0], 0.4, 0.4 / math.sqrt(12), wrong=0.41)
    assert_mean(f[:, 1] - f[:, 0], 0.0, 0.4 / math.sqrt(6))
    free = perturb_wheel_steps(1.0, 1.0, 200.0, p, rng, in_contact=False)
    assert free == (1.0, 1.0)


def test_integrate_wheel_steps_arc_and_turn() -> None:
    x, y, th = integrate_wheel_steps(0.0, 0.0, 0.0, 0.1, 0.1, B)
    assert (x, y, th) == pytest.approx((0.1, 0.0, 0.0))
    # Quarter circle of radius 1 m about (0, 1): right wheel on the outside.
    arc = math.pi / 2
    x, y, th = integrate_wheel_steps(0.0, 0.0, 0.0, arc * (1 - B / 2), arc * (1 + B / 2), B)
    assert (x, y, th) == pytest.approx((1.0, 1.0, math.pi / 2))


def test_same_seed_same_stream() -> None:
    p = make_params(drive_error=0.1, wall_traction_min=0.5)
    a = [perturb_wheel_steps(0.001, 0.001, 200.0, p, np.random.default_rng(7), True)
         for _ in range(3)]
    b = [perturb_wheel_steps(0.001, 0.001, 200.0, p, np.random.default_rng(7), True)
         for _ in range(3)]
    assert a == b


def test_from_dict_rejects_unknown_key_with_suggestion() -> None:
    with pytest.raises(ConfigError, match="drive_error"):
        DriveErrorParams.from_dict({"drive_eror": 0.1})
    with pytest.raises(ConfigError):
        DriveErrorParams.from_dict({"wall_traction_min": 0.9, "wall_traction_max": 0.5})
    assert DriveErrorParams.from_dict({"drive_error": 0.05}).drive_error == 0.05
