"""The simulator reports each IR sensor's axis incidence itself (``IrReading.truth_incidence``),
so the bridge publishes ``sensors/ir`` ``truth.incidence`` without re-casting rays."""

from __future__ import annotations

import numpy as np
import pytest
from koala_bridge.core.raycast import cast_fan_arrays
from koala_bridge.core.resources import default_config_path
from koala_bridge.runtime.settings import apply_override, load_config
from koala_bridge.sim.simulator import Simulator
from koala_bridge.sim.types import WheelCommand


@pytest.mark.parametrize("ideal", [False, True])
def test_truth_incidence_is_the_axis_ray_incidence(ideal: bool) -> None:
    config = apply_override(load_config(default_config_path()), ["sensors", "ir", "ideal"], ideal)
    sim = Simulator(config)
    r = sim.reset(3)
    fan = sim.ir.fan
    axis_body = np.ascontiguousarray(fan.body[:, fan.k // 2 :: fan.k])
    max_range = np.full(fan.n, sim.ir.max_range_m)
    checked = hits = 0
    for _ in range(400):
        if r.ir is not None:
            assert r.ir.truth_incidence is not None
            p = r.pose
            rays, _ = cast_fan_arrays(sim.walls, axis_body, max_range, p.x, p.y, p.theta)
            finite = np.isfinite(np.asarray(r.ir.truth_ranges, dtype=float))
            expected = np.where(finite, rays[5], np.nan)
            np.testing.assert_array_equal(r.ir.truth_incidence, expected)
            checked += 1
            hits += int(finite.sum())
        r = sim.step(WheelCommand(0.2, 0.15))
    assert checked > 50 and hits > 0
