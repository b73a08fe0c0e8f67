"""Columns in another unit than the bundle format's SI (``calibration/units.py``): positions in
mm, a truth heading or bearings in degrees, stamps in ms. Each is a clean synthetic bundle with
one column converted the way a converter forgets to: before, each calibrated into what the unit
made (a landmark range's scale of -0.995, a written gyro bias of -10.4 rad/s, an odometry
"0 -> 0 m" told to record driving); now the streams held against the misread column are not
calibrated, with the reason and the fix, and the others are as on the SI bundle."""

from __future__ import annotations

import math
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from koala_bridge.calibration.bundle import Table, load_bundle
from koala_bridge.calibration.model import declared_model
from koala_bridge.calibration.pipeline import StreamResult, calibrate
from koala_bridge.calibration.problem import SkippedStream
from koala_bridge.calibration.synthetic import DECLARED, Injected, make_bundle
from koala_bridge.calibration.units import (
    bearings_in_degrees,
    heading_in_degrees,
    positions_in_mm,
)


@pytest.fixture(scope="module")
def base(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_bundle(tmp_path_factory.mktemp("units") / "si", seed=3, inj=Injected(),
                       duration_s=120.0)


def _converted(base: Path, out: Path, file: str, column: str,
               convert: Callable[[np.ndarray], np.ndarray]) -> Path:
    shutil.copytree(base, out)
    path = out / f"{file}.csv"
    header = path.read_text().splitlines()[0]
    rows = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    k = header.split(",").index(column)
    rows[:, k] = convert(rows[:, k])
    np.savetxt(path, rows, delimiter=",", header=header, comments="", fmt="%.10g")
    return out


def _calibrate(d: Path) -> tuple[dict[str, StreamResult], dict[str, SkippedStream]]:
    bundle = load_bundle(d)
    skipped: list[SkippedStream] = []
    results = calibrate(bundle, declared_model(DECLARED, bundle.meta), skipped=skipped)
    return {r.problem.name: r for r in results}, {s.stream: s for s in skipped}


def test_the_si_bundle_calibrates_every_stream_with_no_effect(base: Path) -> None:
    results, skipped = _calibrate(base)
    assert set(results) == {"compass", "gyro", "odometry", "range", "landmark_range",
                            "landmark_bearing"}
    assert not skipped
    assert all(not r.effects for r in results.values())


def test_positions_in_mm_set_the_streams_held_against_them_aside(
    base: Path, tmp_path: Path
) -> None:
    d = _converted(base, tmp_path / "mm", "truth_pose", "x", lambda v: 1000 * v)
    d = _converted(d, tmp_path / "mm2", "truth_pose", "y", lambda v: 1000 * v)
    results, skipped = _calibrate(d)
    assert set(skipped) == {"odometry", "landmark_range", "landmark_bearing"}
    for s in skipped.values():
        assert "millimetres read as metres" in s.missing and "m = mm / 1000" in s.fix
    assert set(results) == {"compass", "gyro", "range"}
    assert all(not r.effects for r in results.values())


@pytest.mark.parametrize("wrapped", [True, False])
def test_a_truth_heading_in_degrees_is_set_aside(
    base: Path, tmp_path: Path, wrapped: bool
) -> None:
    # wrapped to [-180, 180): it jumps by 360 where it crosses; unwrapped, it turns 57 times
    # as fast as the robot (the synthetic robot's 0.2-1 rad/s read as 11-57 rad/s)
    def degrees(v: np.ndarray) -> np.ndarray:
        d = np.degrees(v)
        return (d + 180.0) % 360.0 - 180.0 if wrapped else d

    d = _converted(base, tmp_path / "deg", "truth_pose", "theta", degrees)
    results, skipped = _calibrate(d)
    # a bearing needs the robot's heading; the gyro is held against the compass instead, the
    # odometry's windows turned by the best angle, the compass by its field's magnitude
    assert set(skipped) == {"landmark_bearing"}
    assert "degrees?" in skipped["landmark_bearing"].missing
    assert "rad = deg x pi / 180" in skipped["landmark_bearing"].fix
    assert set(results) == {"compass", "gyro", "odometry", "range", "landmark_range"}
    assert all(not r.effects for r in results.values())  # was: gyro bias -10.4 rad/s, written
    assert results["gyro"].problem.notes[0].startswith("reference: calibrated compass heading")
    # said on the streams that would have used the heading, not on the sonar's
    for name, res in results.items():
        said = any("truth_pose.theta" in n and "set aside" in n for n in res.problem.notes)
        assert said == (name in ("compass", "gyro", "odometry")), name


def test_a_heading_set_aside_is_named_where_a_stream_is_left_without_one(
    base: Path, tmp_path: Path
) -> None:
    """With no compass, the gyro has no other reference: its skip said "truth_pose.csv has no
    theta column" of a file that has one."""
    d = _converted(base, tmp_path / "deg", "truth_pose", "theta",
                   lambda v: (np.degrees(v) + 180.0) % 360.0 - 180.0)
    (d / "compass.csv").unlink()
    _, skipped = _calibrate(d)
    gyro = skipped["gyro"]
    assert "it was set aside: truth_pose.theta reaches" in gyro.missing
    assert gyro.fix.startswith("give truth_pose.csv's theta in radians")


def test_a_heading_and_bearings_both_in_degrees_are_both_said(
    base: Path, tmp_path: Path
) -> None:
    d = _converted(base, tmp_path / "deg", "truth_pose", "theta",
                   lambda v: (np.degrees(v) + 180.0) % 360.0 - 180.0)
    d = _converted(d, tmp_path / "deg2", "landmarks", "bearing", np.degrees)
    _, skipped = _calibrate(d)
    bearing = skipped["landmark_bearing"]
    assert "truth_pose.theta reaches" in bearing.missing
    assert "landmarks.bearing reaches" in bearing.missing
    assert "truth_pose.csv's theta" in bearing.fix and "landmarks.csv's bearing" in bearing.fix


def test_bearings_in_degrees_set_the_bearing_stream_aside(base: Path, tmp_path: Path) -> None:
    d = _converted(base, tmp_path / "deg", "landmarks", "bearing", np.degrees)
    results, skipped = _calibrate(d)
    assert set(skipped) == {"landmark_bearing"}
    assert "landmarks.bearing reaches" in skipped["landmark_bearing"].missing
    # the column stays: the camera's range rows are not read as a beacon's
    assert set(results) == {"compass", "gyro", "odometry", "range", "landmark_range"}
    assert all(not r.effects for r in results.values())


def test_stamps_in_ms_leave_the_odometry_no_window_and_say_so(
    base: Path, tmp_path: Path
) -> None:
    d = base
    for i, file in enumerate(("truth_pose", "odometry", "gyro", "compass", "range", "landmarks")):
        d = _converted(d, tmp_path / f"ms{i}", file, "t", lambda v: 1000 * v)
    results, skipped = _calibrate(d)
    odo = skipped["odometry"]
    assert "truth_pose's samples are 50 s apart (median)" in odo.missing
    assert "t in seconds (t_ms / 1000)" in odo.fix
    assert "holds one sample after its anchor at most" in odo.missing
    # the gyro says the same of its gain of 1000 (not written), as before
    (why,) = results["gyro"].not_written()
    assert why is not None and "a time base in ms" in why


def _table(name: str, **columns: np.ndarray) -> Table:
    return Table(name, {k: np.asarray(v, dtype=float) for k, v in columns.items()})


def test_what_the_checks_leave_alone() -> None:
    t = np.arange(0.0, 120.0, 0.01)
    # an unwrapped heading in radians of a rate table turning a gyro at up to 26 rad/s (a
    # reviewer's: the first check called it degrees by its turn rate), its gyro beside it
    rate = 26.0 * np.sin(2 * np.pi * t / 20.0) ** 2
    turned = np.r_[0.0, np.cumsum(0.5 * (rate[1:] + rate[:-1]) * np.diff(t))]
    table = _table("truth_pose", t=t, x=0 * t, y=0 * t, theta=turned)
    gyro = _table("gyro", t=t, yaw_rate=1.01 * rate)
    assert heading_in_degrees(table) is None
    assert heading_in_degrees(table, gyro) is None
    # the same in degrees: 57 times the gyro's turn
    degrees = _table("truth_pose", t=t, theta=np.degrees(turned))
    assert "57" in str(heading_in_degrees(degrees, gyro))
    # a tracker stamped on receipt, three samples within 1 ms at 40 Hz: a heading "fast"
    # between stamps 0.3 ms apart
    bursts = np.sort(np.r_[t[::3], t[::3] + 3e-4, t[::3] + 6e-4])
    spin = _table("truth_pose", t=bursts, theta=np.interp(bursts, t, turned))
    assert heading_in_degrees(spin, gyro) is None
    # a wrapped heading in radians, or in [0, 2 pi)
    assert heading_in_degrees(_table("truth_pose", t=t, theta=np.angle(np.exp(3j * t)))) is None
    assert heading_in_degrees(_table("truth_pose", t=t, theta=(3.0 * t) % (2 * math.pi))) is None
    # a car at 30 m/s with a tracker's jitter
    rng = np.random.default_rng(0)
    car = _table("truth_pose", t=t, x=30.0 * t + rng.normal(0, 0.02, t.size), y=0 * t)
    assert positions_in_mm(car) is None
    # bearings in [0, 2 pi), and ones beyond but for one degree's worth of margin
    assert bearings_in_degrees(_table("landmarks", bearing=[0.1, 3.5, 6.2])) is None
    assert bearings_in_degrees(_table("landmarks", bearing=[0.1, 30.0])) is not None


def test_a_slow_robot_tracked_in_mm_is_beyond_the_checks_reach() -> None:
    """What the numbers cannot show stays the user's: 5 cm/s in mm reads 50 m/s, within a
    ground vehicle's speed."""
    t = np.arange(0.0, 60.0, 0.01)
    slow = _table("truth_pose", t=t, x=50.0 * t, y=0 * t)
    assert positions_in_mm(slow) is None


@pytest.mark.parametrize("spacing_s", [4.5, 5.0])
def test_a_reference_as_sparse_as_the_window_is_not_held_against(
    base: Path, tmp_path: Path, spacing_s: float
) -> None:
    """A reviewer's clean bundles against a truth_pose every 4.5-5 s with 5 s windows: a window
    then holds one sample after its anchor at most, or none, and half of them got wheel_ratio,
    heading_drift or time_offset (one interval allowed); at 5.0 s, '0 -> 0 m'."""
    d = tmp_path / "sparse"
    shutil.copytree(base, d)
    path = d / "truth_pose.csv"
    rows = np.loadtxt(path, delimiter=",", skiprows=1)
    header = path.read_text().splitlines()[0]
    keep = np.r_[True, np.diff(np.floor(rows[:, 0] / spacing_s)) > 0]
    np.savetxt(path, rows[keep], delimiter=",", header=header, comments="", fmt="%.10g")
    results, skipped = _calibrate(d)
    assert "odometry" not in results
    assert "holds one sample after its anchor at most" in skipped["odometry"].missing


def test_a_gyro_converted_twice_does_not_make_a_radian_heading_degrees(
    base: Path, tmp_path: Path
) -> None:
    """A radian heading turning 57 times as far as a gyro converted from deg/s twice: the
    ratio alone cannot tell which is wrong (a reviewer's case, which set the right heading
    aside); the heading turns as a robot does, so it stays."""
    d = _converted(base, tmp_path / "twice", "gyro", "yaw_rate", np.radians)
    results, skipped = _calibrate(d)
    assert "gyro" in results and "landmark_bearing" in results
    assert not skipped
    assert not any("degrees?" in n for r in results.values() for n in r.problem.notes)
