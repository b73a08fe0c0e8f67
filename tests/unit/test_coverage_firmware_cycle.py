"""examples/coverage_firmware.py's RobotClock: how a control cycle cuts the robot's samples.

The firmware's determinism rests on it: which samples belong to cycle k, in which order they are
processed, and that a re-sent sample (the bridge re-sends step 0 while lockstep holds) counts once.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

import pytest
from koala_bridge.drivers.messages import CompassSample, GyroFrame, WheelOdometryFrame

FIRMWARE = Path(__file__).resolve().parents[2] / "examples" / "coverage_firmware.py"


@pytest.fixture(scope="module")
def fw() -> ModuleType:
    spec = importlib.util.spec_from_file_location("coverage_firmware", FIRMWARE)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["coverage_firmware"] = module  # dataclasses look their module up
    try:
        spec.loader.exec_module(module)
    finally:
        del sys.modules["coverage_firmware"]
    return module


def samples(fw: ModuleType, t: float, compass: bool = True) -> list:
    out = [fw.Sample(t, fw.ODOMETRY, WheelOdometryFrame(int(t * 100), 0)),
           fw.Sample(t, fw.GYRO, GyroFrame(0.0))]
    if compass:
        out.append(fw.Sample(t, fw.COMPASS, CompassSample(round(t * 1000), 1.0, 0.0, 0.0)))
    return out


def test_a_cycle_takes_its_samples_in_time_then_stream_order(fw: ModuleType) -> None:
    # period 0.02 s; gyro and odometry at 100 Hz, compass at 50 Hz
    clock = fw.RobotClock(0.02, (100.0, 100.0, 50.0))
    clock.add(samples(fw, 0.0))
    clock.add(samples(fw, 0.0))  # step 0 re-sent while the bridge held: dropped
    clock.start()
    assert clock.end == 0.0
    clock.next_cycle()
    assert clock.behind() == [fw.GYRO, fw.ODOMETRY, fw.COMPASS]
    # arrival order across links: compass first, CAN later, one step at a time
    clock.add([s for s in samples(fw, 0.02) if s.stream == fw.COMPASS])
    clock.add(samples(fw, 0.01, compass=False))
    assert clock.behind() == [fw.GYRO, fw.ODOMETRY]
    clock.add(s for s in samples(fw, 0.02) if s.stream != fw.COMPASS)
    assert clock.behind() == []
    got = [(s.t, s.stream) for s in clock.take()]
    assert got == [(0.0, fw.GYRO), (0.0, fw.ODOMETRY), (0.0, fw.COMPASS),
                   (0.01, fw.GYRO), (0.01, fw.ODOMETRY),
                   (0.02, fw.GYRO), (0.02, fw.ODOMETRY), (0.02, fw.COMPASS)]
    assert clock.take() == []


def test_samples_after_the_cycle_wait_for_the_next(fw: ModuleType) -> None:
    clock = fw.RobotClock(0.02, (100.0, 100.0, 50.0))
    clock.add(samples(fw, 0.0))
    clock.start()
    clock.next_cycle()
    for t in (0.01, 0.02, 0.03):
        clock.add(samples(fw, t, compass=False))
    clock.add(samples(fw, 0.02)[2:])
    assert [s.t for s in clock.take()][-1] == 0.02
    clock.next_cycle()
    assert clock.behind() == [fw.GYRO, fw.ODOMETRY, fw.COMPASS]
    assert [s.t for s in clock.take()] == [0.03, 0.03]  # the rest stays pending


def test_a_robot_that_ran_ahead_ends_the_cycle_at_the_next_boundary(fw: ModuleType) -> None:
    clock = fw.RobotClock(0.02, (100.0, 100.0, 50.0))
    clock.add(samples(fw, 1.0))  # the firmware connected to a robot already running
    clock.start()
    clock.next_cycle()
    clock.add(samples(fw, 1.07, compass=False))
    clock.catch_up()
    assert clock.end == pytest.approx(1.08) and clock.skipped == 3
    assert clock.behind() == [fw.GYRO, fw.ODOMETRY, fw.COMPASS]
    clock.next_cycle()
    clock.add(samples(fw, 1.10))
    clock.catch_up()  # exactly on the boundary: no skip
    assert clock.end == pytest.approx(1.10) and clock.skipped == 3
