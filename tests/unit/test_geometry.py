"""core/geometry.py: one wrap_angle (scalar, array and the kernels' compiled copy in
bridge/core/raycast.py agree bit for bit) and one circle fit."""

from __future__ import annotations

import math

import numpy as np
import pytest
from koala_bridge.core.geometry import TAU, circle_centre, wrap_angle
from koala_bridge.core.raycast import wrap_angle_compiled as compiled_wrap

BOUNDARIES = [0.0, -0.0, math.pi, -math.pi, TAU, -TAU, 3 * math.pi, -3 * math.pi,
              math.nextafter(math.pi, 4.0), math.nextafter(-math.pi, -4.0),
              math.nextafter(math.pi, 0.0), math.nextafter(-math.pi, 0.0), 1e-300, -1e-300,
              100 * math.pi, -100 * math.pi + 1e-9, 1e6, -1e6]


def test_pi_stays_pi_and_minus_pi_becomes_pi() -> None:
    assert wrap_angle(math.pi) == math.pi
    assert wrap_angle(-math.pi) == math.pi
    assert wrap_angle(TAU) == 0.0
    assert wrap_angle(0.5) == 0.5 and wrap_angle(-0.5) == -0.5
    assert wrap_angle(math.nextafter(-math.pi, 0.0)) == math.nextafter(-math.pi, 0.0)
    # just past the boundary wraps to just inside the other end
    assert wrap_angle(math.nextafter(math.pi, 4.0)) == pytest.approx(-math.pi, abs=1e-15)
    assert wrap_angle(math.nextafter(math.pi, 4.0)) > -math.pi
    assert math.isnan(wrap_angle(math.nan))


@pytest.mark.parametrize("a", BOUNDARIES)
def test_result_is_in_the_half_open_interval_and_the_same_angle(a: float) -> None:
    w = wrap_angle(a)
    assert -math.pi < w <= math.pi
    assert math.remainder(w - a, TAU) == pytest.approx(0.0, abs=1e-9)


def test_scalar_array_and_compiled_kernel_agree_bit_for_bit() -> None:
    rng = np.random.default_rng(3)
    a = np.concatenate([np.array(BOUNDARIES), rng.uniform(-50, 50, 2000),
                        rng.normal(0, 4, 2000)])
    arr = wrap_angle(a)
    assert isinstance(arr, np.ndarray) and arr.shape == a.shape
    scalar = np.array([wrap_angle(float(x)) for x in a])
    compiled = np.array([compiled_wrap(float(x)) for x in a])
    assert arr.tobytes() == scalar.tobytes() == compiled.tobytes()
    assert np.all((arr > -math.pi) & (arr <= math.pi))


def test_circle_centre_recovers_circle_and_sphere() -> None:
    t = np.linspace(0, 2 * math.pi, 40, endpoint=False)
    pts = np.column_stack([3 + 2 * np.cos(t), -1 + 2 * np.sin(t)])
    np.testing.assert_allclose(circle_centre(pts), [3, -1], atol=1e-12)
    # an arc is enough; noise moves the centre little
    rng = np.random.default_rng(1)
    arc = np.column_stack([20 * np.cos(t[:15]) + 5, 20 * np.sin(t[:15]) - 7])
    arc += rng.normal(0, 0.05, arc.shape)
    np.testing.assert_allclose(circle_centre(arc), [5, -7], atol=0.3)
    u = rng.normal(size=(200, 3))
    sphere = 4 * u / np.linalg.norm(u, axis=1, keepdims=True) + [1, 2, 3]
    np.testing.assert_allclose(circle_centre(sphere), [1, 2, 3], atol=1e-9)


def test_equals_the_exact_ieee_remainder() -> None:
    """fmod is exact and the one shift by 2 pi is exact too (Sterbenz), so the result is the
    exact IEEE remainder moved from -pi to pi: what sim/robot.py computed before (the simulator's
    streams are bit-identical across the change)."""
    rng = np.random.default_rng(7)
    for a in [*BOUNDARIES, *rng.uniform(-1e4, 1e4, 3000), *rng.normal(0, 3, 3000)]:
        r = math.remainder(float(a), TAU)
        assert wrap_angle(float(a)) == (math.pi if r == -math.pi else r), a
