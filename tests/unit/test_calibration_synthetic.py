"""Undeclared effects in synthetic bundles: named, parameters recovered, held-out error halved.

Each case of ``calibration.synthetic.CASES`` (every effect of issue 6 and four pairs) runs
on two seeds here; ``bench/bench_calibrate.py --rates N`` runs N seeds for the rates in
docs/calibration.md. On clean bundles no effect may be added.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from koala_bridge.calibration.bundle import load_bundle
from koala_bridge.calibration.model import declared_model
from koala_bridge.calibration.pipeline import calibrate
from koala_bridge.calibration.synthetic import (
    CASES,
    DECLARED,
    Case,
    Injected,
    check_case,
    make_bundle,
)

SEEDS = (1, 2)


def _run(tmp_path: Path, case: Case, seed: int) -> list[str]:
    bundle = load_bundle(make_bundle(tmp_path / "bundle", seed, case.inject))
    return check_case(case, calibrate(bundle, declared_model(DECLARED, bundle.meta)))


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("name", sorted(CASES))
def test_injected_effect_is_found(tmp_path: Path, name: str, seed: int) -> None:
    assert _run(tmp_path, CASES[name], seed) == []


@pytest.mark.parametrize("seed", (11, 12, 13, 14))
def test_clean_bundle_adds_no_effect(tmp_path: Path, seed: int) -> None:
    assert _run(tmp_path, Case(Injected(), {}), seed) == []


def test_generator_is_reproducible(tmp_path: Path) -> None:
    a = make_bundle(tmp_path / "a", 5, Injected(gyro_bias=0.01))
    b = make_bundle(tmp_path / "b", 5, Injected(gyro_bias=0.01))
    for f in ("gyro.csv", "odometry.csv", "range.csv", "compass.csv"):
        assert (a / f).read_bytes() == (b / f).read_bytes()


@pytest.mark.parametrize("seed", range(5000, 5006))
def test_random_study_cases_name_exactly_what_was_injected(tmp_path: Path, seed: int) -> None:
    """Six cases of issue 16's random study (bench/bench_calibrate.py --study: 1-3 families on
    different streams at once, magnitudes and signs drawn; 197/200 right over seeds 5000-5199)."""
    import numpy as np
    from koala_bridge.calibration.synthetic import random_case

    _, inj, expect = random_case(np.random.default_rng(seed))
    bundle = load_bundle(make_bundle(tmp_path / "bundle", seed, inj))
    named = {r.problem.name: {i.name for i in r.effects}
             for r in calibrate(bundle, declared_model(DECLARED, bundle.meta))}
    assert {k: v for k, v in named.items() if v} == expect
