"""Issue 15: the localisation node on the hostile drive, in process (tools/drive_scenario.py).

The bridge's own simulated robot on config/default.toml (fast clock, every bus on free loopback
ports, the node fed from the bytes on its buses as in a real run) drives the 60 s "hostile"
script -- spins, straights, backing up, arcs, a ~4 s push into the east wall while the wheels
slip -- once as it is and once with a kidnap at 40 s (~1.5 m, heading turned). Seed 1; the run is
deterministic for a seed. Two runs, ~4 s of wall time together.

The scenario itself is checked first (it must be hostile in the way the issue describes). The
estimator's figures are then held to the issue's targets loosened as below, and its
``estimate/health`` must say what happened: wall contact during the push, relocalising after the
kidnap, tracking again at the end.
"""

from __future__ import annotations

import numpy as np
import pytest
from koala_bridge.tools.drive_scenario import (
    HOSTILE,
    HOSTILE_KIDNAP,
    ScenarioResult,
    Segment,
    run_scenario,
    wall_clearance,
)

SEED = 1

# ---- bounds -------------------------------------------------------------------------------------
# Issue-15 targets: pose RMSE <= 0.10 m, heading RMSE <= 5 deg, NEES in the 95 % band in >= 90 %
# of the samples, back within 0.2 m <= 10 s after a kidnap of >= 1 m. One seed is one draw of
# each figure, so the test bounds are looser:
# * RMSE: 1.5x the targets. The mean square error of one 60 s run of an estimator that meets the
#   target on average scatters: with ~30 independent stretches in 60 s (an error correlation time
#   of ~2 s) and 2 position axes it is ~chi2(60) / 60 times its mean, whose 1e-3 upper quantile
#   is 1.66, i.e. 1.29x in RMSE; 1.5x leaves room for the drive's seed.
POSE_RMSE_BOUND_M = 0.15
HEADING_RMSE_BOUND_DEG = 7.5
# * NEES: a consistent estimator has 95 % of its samples in the band; the 1201 samples of a run are
#   correlated, ~50 effective ones. Binomial(50, 0.95) / 50 has its lower 1e-3 quantile at 0.84.
NEES_IN_BAND_MIN = 0.84
# * Kidnap: 1.5x the 10 s target (when landmarks come into view after the jump depends on the
#   heading the kidnap leaves and on the script), the 0.2 m threshold held for 1 s.
RECOVERY_BOUND_S = 15.0
RECOVERY_THRESHOLD_M = 0.2
RECOVERY_HOLD_S = 1.0
KIDNAP_MIN_M = 1.0
# The scenario: the wall push lasts ~4.2 s (segment 10 of the script).
CONTACT_MIN_S = 3.0
CONTACT_MAX_S = 6.0



@pytest.fixture(scope="module")
def plain() -> ScenarioResult:
    return run_scenario(HOSTILE, seed=SEED)


@pytest.fixture(scope="module")
def kidnapped() -> ScenarioResult:
    return run_scenario(HOSTILE, seed=SEED, kidnap=HOSTILE_KIDNAP)


def test_the_scenario_is_hostile_as_scripted(plain: ScenarioResult,
                                             kidnapped: ScenarioResult) -> None:
    duration = sum(s.duration_s for s in HOSTILE)
    for run in (plain, kidnapped):
        assert run.sim_s == pytest.approx(duration)
        # truth at 50 Hz, estimate/pose at 20 Hz, both over the whole run
        assert run.truth_t.size == pytest.approx(50 * duration + 1, abs=1)
        assert run.est_t.size == pytest.approx(20 * duration + 1, abs=1)
        assert run.cov.shape == (run.est_t.size, 3, 3)
        # one wall contact, in the wall push, lasting ~4 s
        assert len(run.contact) == 1
        (t0, t1), = run.contact
        push = next((a, b) for s, a, b in run.segments if s.name == "wall push")
        assert push[0] < t0 and t1 <= push[1] + 0.1
        assert CONTACT_MIN_S <= t1 - t0 <= CONTACT_MAX_S
        # not stuck afterwards: the robot backs off the wall and keeps moving
        after = run.truth_t > t1 + 3.0
        assert np.min(wall_clearance(run.truth[after], run.walls)) > run.body_radius_m + 0.05
        assert np.ptp(run.truth[after, 2]) > np.pi   # it still turns
    assert plain.kidnap is None and plain.fault_events == []
    assert kidnapped.kidnap is not None
    d = kidnapped.kidnap_distance_m
    assert d is not None and d >= KIDNAP_MIN_M
    # the truth jumps once, at the kidnap; the encoders and the script go on from there
    jumps = np.hypot(*np.diff(kidnapped.truth[:, :2], axis=0).T)
    assert np.sum(jumps > 0.05) == 1
    assert kidnapped.truth_t[1:][jumps > 0.05][0] == pytest.approx(HOSTILE_KIDNAP.t_s, abs=0.03)


def test_every_estimate_channel_is_recorded(plain: ScenarioResult) -> None:
    assert "estimate/pose" in plain.estimates
    assert all(k.startswith("estimate/") for k in plain.estimates)
    assert plain.estimator_cpu_s > 0


def test_pose_rmse(plain: ScenarioResult) -> None:
    assert plain.metrics().pose_rmse_m <= POSE_RMSE_BOUND_M


def test_heading_rmse(plain: ScenarioResult) -> None:
    assert plain.metrics().heading_rmse_deg <= HEADING_RMSE_BOUND_DEG


def test_nees_in_band(plain: ScenarioResult) -> None:
    nees = plain.metrics().nees
    assert nees is not None
    assert nees.fraction_in_band >= NEES_IN_BAND_MIN


def test_kidnap_recovery(kidnapped: ScenarioResult) -> None:
    rec = kidnapped.recovery(RECOVERY_THRESHOLD_M, RECOVERY_HOLD_S)
    assert rec is not None
    assert rec.duration_s is not None, "never back within 0.2 m after the kidnap"
    assert rec.duration_s <= RECOVERY_BOUND_S


def test_a_run_is_the_same_for_a_seed() -> None:
    script = HOSTILE[:4]        # 7 s: settle, the spins, the straight
    a, b = (run_scenario(script, seed=SEED + 1) for _ in range(2))
    assert np.array_equal(a.truth, b.truth)
    assert np.array_equal(a.estimate, b.estimate) and np.array_equal(a.cov, b.cov)


def _states(run: ScenarioResult) -> list[tuple[float, str, list[str]]]:
    return [(t, m["state"], m["reasons"]) for t, m in run.estimates["estimate/health"]]


def test_health_reports_the_wall_contact(plain: ScenarioResult) -> None:
    (t0, t1), = plain.contact
    during = [(s, r) for t, s, r in _states(plain) if t0 + 0.3 <= t <= t1]
    assert during and all(s == "uncertain" and "wall_contact" in r for s, r in during)
    # nothing made the estimate lost or relocalise without a kidnap
    assert {s for _, s, _ in _states(plain)} <= {"tracking", "uncertain"}
    assert _states(plain)[-1][1] in ("tracking", "uncertain")


def test_health_reports_the_kidnap_and_the_recovery(kidnapped: ScenarioResult) -> None:
    assert kidnapped.kidnap is not None
    states = _states(kidnapped)
    before = {s for t, s, _ in states if t < HOSTILE_KIDNAP.t_s}
    assert before <= {"tracking", "uncertain"}
    after = [(t, s) for t, s, _ in states if t >= HOSTILE_KIDNAP.t_s]
    relocalising = [t for t, s in after if s == "relocalising"]
    assert relocalising, "the kidnap went unnoticed"
    assert relocalising[0] - HOSTILE_KIDNAP.t_s <= RECOVERY_BOUND_S
    assert after[-1][1] in ("tracking", "uncertain")


def test_a_long_push_at_a_walls_end_is_tracked_without_relocalising() -> None:
    """The robot arcs into the end of an inner wall and keeps pushing for ~20 s: the body is
    stopped, the wheels spin, the encoders keep counting. The estimator must hold the stalled
    pose (the range sensors against the map, the encoders' distance realising nothing in
    contact) and never call itself lost: before the stall model it drifted by centimetres a
    second and relocalised ~140 times."""
    run = run_scenario([Segment("arc into a wall's end", 30.0, 0.10, 0.14)], seed=SEED)
    assert run.contact, "the arc did not reach the wall"
    (t0, t1), *_ = run.contact
    assert t1 - t0 >= 15.0          # stalled for the rest of the run
    states = {s for _, s, _ in _states(run)}
    assert states <= {"tracking", "uncertain"}
    aligned = run.aligned()
    during = aligned.t >= t0
    err = np.hypot(aligned.error[during, 0], aligned.error[during, 1])
    # the 0.10 m RMSE target, held as a maximum over the stall
    assert err.max() <= 0.10
