"""Compass disturbances (hard/soft iron, motor currents, noise; sim/models/compass.py).

The noise-free part (seeds/000 eq. 16–18) is the core's sim/sensors/compass.py, tested there.
"""

from __future__ import annotations

import numpy as np
import pytest
from _stats import assert_mean, assert_normal_variance
from koala_bridge.core.schema import ConfigError
from koala_bridge.sim.models.compass import CompassErrorParams, measure
from koala_bridge.sim.sensors.compass import field_body as world_to_body

# The error terms these tests do not study, off (config/default.toml switches them on; the
# params' keyword defaults are its values, tests/unit/test_config_schema.py).
QUIET = {"hard_iron_uT": (0.0, 0.0, 0.0),
         "soft_iron": ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)),
         "motor_uT_per_A": ((0.0, 0.0), (0.0, 0.0), (0.0, 0.0)), "motor_current_A_per_mps": 0.0,
         "noise_sigma_uT": 0.0}


def make_params(**kw: object) -> CompassErrorParams:
    """CompassErrorParams with :data:`QUIET` under ``kw``."""
    return CompassErrorParams(**{**QUIET, **kw})  # type: ignore[arg-type]

EARTH = np.array([0.0, 20.0, -43.0])   # north along +y


def test_hard_soft_iron_motor_and_noise_statistics() -> None:
    s = ((1.05, 0.02, 0.0), (0.02, 0.97, 0.0), (0.0, 0.0, 1.0))
    p = make_params(hard_iron_uT=(3.0, -2.0, 1.0), soft_iron=s,
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
    out = measure(b, (0.5, 0.5), make_params(ideal=True, noise_sigma_uT=5.0),
                  np.random.default_rng(1))
    assert np.array_equal(out, b)
    with pytest.raises(ConfigError):
        CompassErrorParams.from_dict({"soft_iron": [[1, 0], [0, 1]]})
    p = CompassErrorParams.from_dict({"hard_iron_uT": [1, 2, 3]})
    assert p.hard_iron_uT == (1.0, 2.0, 3.0)
