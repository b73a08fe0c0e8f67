"""sim.battery: the charge drains with the current the wheels draw (sim/battery.py docstring)."""

from __future__ import annotations

import pytest
from koala_bridge.core.schema import ConfigError
from koala_bridge.runtime.settings import load_config
from koala_bridge.sim.battery import Battery, BatteryConfig, motor_current
from koala_bridge.sim.simulator import Simulator
from koala_bridge.sim.types import WheelCommand

from tests.conftest import REPO

CFG = BatteryConfig.from_dict({
    "chemistry": "NiMH", "capacity_mAh": 1000.0, "initial_charge": 1.0, "voltage_full_V": 12.0,
    "voltage_empty_V": 10.0, "internal_resistance_ohm": 0.5, "idle_current_A": 0.2,
    "motor_current_per_mps_A": 1.0, "motor_current_per_mps2_A": 0.5,
    "motor_stall_current_A": 2.0, "ambient_temperature_C": 20.0,
    "thermal_resistance_K_per_W": 4.0, "thermal_time_constant_s": 100.0,
})
V_MAX = 0.5


def test_at_rest_only_the_electronics_draw() -> None:
    bat = Battery(CFG, V_MAX)
    r = bat.step((0.0, 0.0), (0.0, 0.0), 3600.0)
    # one hour at 0.2 A: 200 mAh; V = V_empty + (V_full - V_empty) soc - R I
    assert r.charge_mAh == pytest.approx(800.0)
    assert r.voltage_V == pytest.approx(10.0 + 2.0 * 0.8 - 0.5 * 0.2)
    assert r.motor_currents_A == (0.0, 0.0)


def test_running_current_is_proportional_to_speed() -> None:
    bat = Battery(CFG, V_MAX)
    bat.step((0.3, -0.3), (0.3, -0.3), 0.01)            # accelerating step
    r = bat.step((0.3, -0.3), (0.3, -0.3), 0.01)        # steady
    assert r.motor_currents_A == pytest.approx((0.3, 0.3))
    assert r.current_A == pytest.approx(0.2 + 0.6)


def test_a_stalled_wheel_draws_up_to_the_stall_current() -> None:
    # pushing against a wall: the set-point is full speed, the wheel does not turn
    assert motor_current(0.0, 0.0, V_MAX, 0.01, V_MAX, CFG) == pytest.approx(2.0)
    # half the set-point unreached: half the stall current
    assert motor_current(0.0, 0.0, V_MAX / 2, 0.01, V_MAX, CFG) == pytest.approx(1.0)
    # never more than the stall current, whatever the acceleration
    assert motor_current(V_MAX, -V_MAX, V_MAX, 0.01, V_MAX, CFG) == pytest.approx(2.0)


def test_a_wheel_slipping_against_a_wall_draws_the_stall_current() -> None:
    # wall contact with the drive-error model: the wheel turns at its set-point, the ground under
    # it does not move; without contact the same speeds are free running
    assert motor_current(V_MAX, V_MAX, V_MAX, 0.01, V_MAX, CFG, v_ground=0.0) == pytest.approx(2.0)
    assert motor_current(0.2, 0.2, 0.2, 0.01, V_MAX, CFG, v_ground=0.1) == pytest.approx(
        1.0 * 0.2 + 2.0 * 0.1 / V_MAX)
    assert motor_current(0.2, 0.2, 0.2, 0.01, V_MAX, CFG) == pytest.approx(0.2)


def test_pushing_into_a_wall_draws_the_stall_current_with_or_without_slip() -> None:
    for name in ("default.toml", "ideal.toml"):    # drive-error model on (slip) and off (stall)
        cfg = load_config(REPO / "config" / name)
        sim = Simulator(cfg)
        sim.reset(1)
        v = cfg["robot"]["max_wheel_speed_mps"]
        for _ in range(3000):                        # 30 s at full speed: into the first wall
            r = sim.step(WheelCommand(v, v))
        assert r.collided and r.battery is not None, name
        stall = cfg["robot"]["battery"]["motor_stall_current_A"]
        assert r.battery.motor_currents_A == pytest.approx((stall, stall)), name


def test_charge_never_goes_below_zero_and_temperature_relaxes_to_its_target() -> None:
    bat = Battery(CFG, V_MAX)
    for _ in range(100):
        r = bat.step((0.0, 0.0), (V_MAX, V_MAX), 600.0)   # stalled, 4.2 A
    assert r.charge_mAh == 0.0
    assert r.voltage_V == pytest.approx(10.0 - 0.5 * 4.2)
    # steady state: T_amb + R I^2 R_th
    assert r.temperature_C == pytest.approx(20.0 + 0.5 * 4.2**2 * 4.0)


def test_empty_voltage_must_be_below_full() -> None:
    with pytest.raises(ConfigError, match="'voltage_empty_V'"):
        BatteryConfig.from_dict({**CFG.__dict__, "voltage_empty_V": 12.0})


def test_the_simulator_drains_the_battery_faster_when_driving() -> None:
    cfg = load_config(REPO / "config" / "ideal.toml")
    still, moving = Simulator(cfg), Simulator(cfg)
    still.reset(1)
    moving.reset(1)
    for _ in range(500):
        a = still.step(WheelCommand(0.0, 0.0))
        b = moving.step(WheelCommand(0.2, 0.2))
    assert a.battery is not None and b.battery is not None
    bat = cfg["robot"]["battery"]
    used_still = bat["capacity_mAh"] - a.battery.charge_mAh
    assert used_still == pytest.approx(bat["idle_current_A"] * 5.0 / 3.6)
    assert b.battery.charge_mAh < a.battery.charge_mAh
    assert b.battery.voltage_V < a.battery.voltage_V
    assert not b.collided                          # 1 m of open floor: free running
    assert b.battery.motor_currents_A == pytest.approx(
        (bat["motor_current_per_mps_A"] * 0.2,) * 2, rel=1e-9)
