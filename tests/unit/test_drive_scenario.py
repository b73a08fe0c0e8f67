"""The pure parts of bridge/tools/drive_scenario.py: the scripted arbiter, wall clearance and
contact intervals, the kidnap fault table (the runs themselves:
tests/integration/test_localisation_hostile.py)."""

from __future__ import annotations

import numpy as np
import pytest
from koala_bridge.runtime.faults import fault_spec
from koala_bridge.tools.drive_scenario import (
    HOSTILE,
    HOSTILE_KIDNAP,
    Kidnap,
    ScriptedArbiter,
    Segment,
    contact_intervals,
    segment_times,
    wall_clearance,
)


def test_the_hostile_script_lasts_60_s() -> None:
    assert sum(s.duration_s for s in HOSTILE) == pytest.approx(60.0)
    timed = segment_times(HOSTILE)
    push = [(t0, t1) for s, t0, t1 in timed if s.name == "wall push"]
    assert push == [(pytest.approx(24.0), pytest.approx(32.5))]
    assert 0 < HOSTILE_KIDNAP.t_s < 60.0


def test_the_scripted_arbiter_follows_the_segments_in_simulated_time() -> None:
    arb = ScriptedArbiter([Segment("a", 0.5, 0.1, 0.2), Segment("b", 0.25, -0.3, 0.3)])
    dt = 0.01
    seen = [arb.command(k * dt) for k in range(80)]     # t = 0 .. 0.79
    assert {(c.left, c.right) for c in seen[:50]} == {(0.1, 0.2)}
    assert {(c.left, c.right) for c in seen[50:75]} == {(-0.3, 0.3)}
    assert {(c.left, c.right) for c in seen[75:]} == {(0.0, 0.0)}   # the script has ended
    assert arb.source == "scenario"
    # t built by summing dt (as the loop does) still switches at 0.5
    t = 0.0
    for _ in range(50):
        t += dt
    assert (arb.command(t - dt).left, arb.command(t).left) == (0.1, -0.3)


def test_wall_clearance_and_contact() -> None:
    walls = np.array([[0.0, 0.0, 0.0, 3.0], [0.0, 3.0, 3.0, 3.0]])
    pts = np.array([[1.0, 1.0], [0.5, 4.0], [-1.0, -1.0]])
    assert wall_clearance(pts, walls) == pytest.approx([1.0, 1.0, np.hypot(1.0, 1.0)])
    t = np.arange(10) * 0.1
    x = np.array([1.0, 0.5, 0.2, 0.19, 0.191, 0.19, 0.4, 0.19, 0.19, 0.19])
    truth = np.column_stack([x, np.full(10, 1.5), np.zeros(10)])
    assert contact_intervals(t, truth, walls, 0.19) == [
        (pytest.approx(0.3), pytest.approx(0.5)), (pytest.approx(0.7), pytest.approx(0.9))]


def test_the_kidnap_is_a_valid_fault_table() -> None:
    spec = fault_spec(HOSTILE_KIDNAP.fault(), "faults", 1)
    assert (spec.kind, spec.target, spec.start_s, spec.x, spec.y, spec.theta_deg) == (
        "kidnap", "robot", 40.0, 0.75, 0.75, 90.0)
    assert "theta_deg" not in Kidnap(theta_deg=None).fault()
