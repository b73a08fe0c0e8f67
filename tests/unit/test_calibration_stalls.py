"""Stall and wheel-slip detection of the odometry stream (``streams/odometry.py``,
:func:`find_stalls`) on hand-made series: a straight drive at a varying speed, sampled at 100 Hz,
with the odometry's pose dead-reckoned in its own frame."""

from __future__ import annotations

import numpy as np
import pytest
from koala_bridge.calibration.streams.odometry import (
    STALL_INTERVAL_S,
    STALL_LAG_STEP_S,
    find_stalls,
    speed_lag,
)

T = np.arange(0.0, 20.0, 0.01)


def _drive(t: np.ndarray, start: float = 2.0) -> np.ndarray:
    """Distance travelled: at rest until ``start``, then 0.1 m/s +- 50 % (3 s period)."""
    u = np.clip(t - start, 0.0, None)
    return 0.1 * (u - 0.5 * 3 / (2 * np.pi) * (np.cos(2 * np.pi * u / 3) - 1))


def _pose(s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return s, np.zeros_like(s), np.zeros_like(s)


def _ref(s: np.ndarray) -> np.ndarray:
    return np.column_stack([1.0 + s, np.full_like(s, 2.0)])


def test_a_wrong_tick_size_is_no_stall() -> None:
    s = _drive(T)
    # The declared tick size three times too large: the odometry says a third of the travel.
    assert find_stalls(T, _pose(s / 3), T, _ref(s), None).spans == ()


def test_a_reference_that_lags_is_no_stall() -> None:
    s = _drive(T)
    lagged = _drive(T - 0.3)  # the tracker shows the motion 0.3 s late
    lag = speed_lag(T[0], T[-1], T, _pose(s), T, _ref(lagged))
    assert lag == pytest.approx(0.3, abs=STALL_LAG_STEP_S)
    assert find_stalls(T, _pose(s), T, _ref(lagged), None).spans == ()


def test_the_encoders_counting_against_a_wall_are_set_aside() -> None:
    s = _drive(T)
    # The body stops from 6 to 9 s (against a wall) and goes on from there; the wheels do not.
    stalled = (T >= 6.0) & (T < 9.0)
    moved = np.cumsum(np.r_[0.0, np.diff(s) * ~stalled[1:]])
    found = find_stalls(T, _pose(s), T, _ref(moved), None)
    assert len(found.spans) == 1
    ((a, b),) = found.spans
    # The stall, an interval of padding on each side, and its ends rounded to the grid.
    assert 6.0 - 2 * STALL_INTERVAL_S <= a <= 6.0 - STALL_INTERVAL_S
    assert 9.0 + STALL_INTERVAL_S <= b <= 9.0 + 2 * STALL_INTERVAL_S
    assert found.reference_m < 0.5 * found.odometry_m


def test_a_turn_the_reference_does_not_make_is_set_aside() -> None:
    # Turning on the spot at 0.5 rad/s except from 10 to 12 s, when something holds the body.
    turn = 0.5 * T
    held = (T >= 10.0) & (T < 12.0)
    theta_ref = np.cumsum(np.r_[0.0, np.diff(turn) * ~held[1:]])
    still = np.zeros_like(T)
    p_ref = np.column_stack([still, still])
    found = find_stalls(T, (still, still, turn), T, p_ref, theta_ref)
    assert len(found.spans) == 1
    ((a, b),) = found.spans
    assert a <= 10.0 - STALL_INTERVAL_S and b >= 12.0 + STALL_INTERVAL_S
    assert b - a <= 2.0 + 4 * STALL_INTERVAL_S
    # Without a reference heading a turn cannot be judged.
    assert find_stalls(T, (still, still, turn), T, p_ref, None).spans == ()


def test_a_moment_of_lag_that_the_reference_makes_up_is_no_stall() -> None:
    """A commanded speed the robot reaches a moment late (a v/omega stream of commands): for
    half a second the reference moves a quarter of what the odometry says, then catches up
    within the next interval. That interval alone fails the ratio test, but over the span
    nothing was lost, so nothing is set aside (the MRCLAM run once lost 8 % of its time so)."""
    s = _drive(T)
    late = (T >= 8.0) & (T < 8.5)
    step = np.diff(s)
    d = np.r_[0.0, step]
    held = d[1:][late[1:]].sum()
    d[1:][late[1:]] *= 0.25
    after = np.flatnonzero((T >= 8.5) & (T < 9.0))
    d[after] += 0.75 * held / after.size  # made up in the next half second
    caught_up = np.cumsum(d)
    assert caught_up[-1] == pytest.approx(s[-1])
    assert find_stalls(T, _pose(s), T, _ref(caught_up), None).spans == ()


@pytest.mark.parametrize(("start", "stop"), [(6.0, 6.5), (6.0, 7.0), (6.2, 7.2)])
def test_a_short_stall_is_set_aside(start: float, stop: float) -> None:
    """Half a second to a second against a wall (5-10 cm the wheels count and the body does
    not make) is a stall, with normal motion around it: the span's padding must not dilute it
    (the totals over the padded span once kept every stall under about a second)."""
    s = _drive(T)
    stalled = (T >= start) & (T < stop)
    moved = np.cumsum(np.r_[0.0, np.diff(s) * ~stalled[1:]])
    assert s[-1] - moved[-1] > 0.04  # what the wheels counted in vain
    found = find_stalls(T, _pose(s), T, _ref(moved), None)
    assert len(found.spans) == 1
    ((a, b),) = found.spans
    assert a <= start and b >= stop
