"""core/motion_profile.py against the closed-form trapezoid, worked by hand."""

from __future__ import annotations

import math

import pytest
from koala_bridge.core.motion_profile import trapezoid


def test_trapezoid_with_cruise() -> None:
    # d = 100, v = 10, a = 5: ramps 2 s each covering 10 each, cruise 80 / 10 = 8 s, T = 12 s
    p = trapezoid(100.0, 10.0, 5.0)
    assert p.t_accel == pytest.approx(2.0)
    assert p.t_cruise == pytest.approx(8.0)
    assert p.duration == pytest.approx(12.0)
    assert p.position(1.0) == pytest.approx(2.5)          # a t^2 / 2
    assert p.position(2.0) == pytest.approx(10.0)
    assert p.position(6.0) == pytest.approx(50.0)         # 10 + 10 * 4
    assert p.position(11.0) == pytest.approx(100.0 - 2.5)
    assert p.position(12.0) == 100.0
    assert p.velocity(1.0) == pytest.approx(5.0)
    assert p.velocity(6.0) == pytest.approx(10.0)
    assert p.velocity(11.5) == pytest.approx(2.5)
    assert p.velocity(12.5) == 0.0 and p.velocity(-1.0) == 0.0


def test_trapezoid_short_move_is_a_triangle() -> None:
    # d = 20 < v^2/a = 100/5: peak sqrt(20 * 5) = 10 ... exactly v_max; take d = 5: peak 5, T = 2 s
    p = trapezoid(5.0, 10.0, 5.0)
    assert p.v_peak == pytest.approx(5.0)
    assert p.t_cruise == pytest.approx(0.0)
    assert p.duration == pytest.approx(2.0)
    assert p.position(1.0) == pytest.approx(2.5)
    assert p.position(2.0) == 5.0


def test_trapezoid_negative_distance_is_mirrored() -> None:
    fwd, back = trapezoid(100.0, 10.0, 5.0), trapezoid(-100.0, 10.0, 5.0)
    for t in (0.5, 2.0, 7.0, 11.9, 13.0):
        assert back.position(t) == pytest.approx(-fwd.position(t))
        assert back.velocity(t) == pytest.approx(-fwd.velocity(t))


def test_trapezoid_position_is_the_integral_of_velocity() -> None:
    p = trapezoid(-37.0, 4.0, 3.0)
    n = 20000
    dt = p.duration / n
    integral = sum(p.velocity((i + 0.5) * dt) for i in range(n)) * dt
    assert integral == pytest.approx(-37.0, rel=1e-6)


def test_trapezoid_zero_distance_and_bad_limits() -> None:
    assert trapezoid(0.0, 1.0, 1.0).duration == 0.0
    with pytest.raises(ValueError):
        trapezoid(1.0, 0.0, 1.0)
    with pytest.raises(ValueError):
        trapezoid(math.inf, 1.0, 1.0)
