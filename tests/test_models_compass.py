"""Compass (seeds/000 eq. 16–18 + hard/soft iron, motor currents, noise; sim/models/compass.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from _stats import assert_mean, assert_normal_variance

from sim.models.compass import (
    CompassErrorParams,
    field_world,
    heading_from_field,
    measure,
    world_to_body,
)
from sim.schema import ConfigError

EARTH = np.array([0.0, 20.0, -43.0])   # north along +y


def test_sources_fall_with_inverse_square_and_add_as_vectors() -> None:
    src = np.array([[2.0, 0.0, 4.0]])                     # 4 uT at 1 m, east of origin
    f1 = field_world(0.0, 0.0, np.zeros(3), src)
    assert f1 == pytest.approx([1.0, 0.0, 0.0])           # 4 / 2^2, pointing at the source
    f2 = field_world(-2.0, 0.0, np.zeros(3), src)
    assert np.linalg.norm(f1) / np.linalg.norm(f2) == pytest.approx(4.0)
    two = np.array([[2.0, 0.0, 4.0], [0.0, 1.0, 3.0]])
    tot = field_world(0.0, 0.0, EARTH, two)               # eq. 17: F_0 (Earth) + sum F_i
    assert tot == pytest.approx(EARTH + [1.0, 3.0, 0.0])
    # floor at min_distance_m: no infinity on top of a source
    assert np.all(np.isfinite(field_world(2.0, 0.0, EARTH, src)))


def test_body_rotation_and_heading() -> None:
    for th in (0.0, 0.7, -2.5, math.pi):
        b = world_to_body(EARTH, th)
        assert heading_from_field(b, math.pi / 2) == pytest.approx(
            math.atan2(math.sin(th), math.cos(th)))


def test_hard_soft_iron_motor_and_noise_statistics() -> None:
    s = ((1.05, 0.02, 0.0), (0.02, 0.97, 0.0), (0.0, 0.0, 1.0))
    p = CompassErrorParams(hard_iron_uT=(3.0, -2.0, 1.0), soft_iron=s,
                           motor_uT_per_A=((0.5, -0.5), (1.0, 1.0), (0.0, 0.0)),
                           motor_current_A_per_mps=2.0, noise_sigma_uT=0.4)
    rng = np.random.default_rng(30)
    b = world_to_body(EARTH, 0.3)
    v = (0.2, 0.3)
    x = np.array([measure(b, v, p, rng) for _ in range(20000)])
    i = 2.0 * np.array(v)
    expect = np.array(s) @ b + np.array([3.0, -2.0, 1.0]) + np.array(p.motor_uT_per_A) @ i
    for ax in range(3):
        # power: forgetting the motor term shifts x by -0.1 uT, y by 1.0 uT
        assert_mean(x[:, ax], expect[ax], 0.4)
        assert_normal_variance(x[:, ax] - expect[ax], 0.16, mean=0.0, wrong=0.16 * 1.1)
    assert_mean(x[:, 1], expect[1], 0.4, wrong=expect[1] - 1.0)


def test_ideal_and_shape_checks() -> None:
    b = world_to_body(EARTH, 1.0)
    out = measure(b, (0.5, 0.5), CompassErrorParams(ideal=True, noise_sigma_uT=5.0),
                  np.random.default_rng(1))
    assert np.array_equal(out, b)
    with pytest.raises(ConfigError):
        CompassErrorParams.from_dict({"soft_iron": [[1, 0], [0, 1]]})
    p = CompassErrorParams.from_dict({"hard_iron_uT": [1, 2, 3]})
    assert p.hard_iron_uT == (1.0, 2.0, 3.0)
