"""bridge.export: a recording's bundle agrees one for one with its messages."""

from __future__ import annotations

import argparse
import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest
from koala_bridge.cli import export as export_cli
from koala_bridge.recording.export import RANGE_COLUMNS, export_bundle
from koala_bridge.recording.mcap_file import Recorder, RecordingError, open_recording

WORLD = {
    "name": "test",
    "cell_m": 0.5,
    "landmarks": [
        {"id": 1, "colour": "red", "x": 0.05, "y": 2.95, "facing_deg": -45.0, "a_max_deg": 120.0},
        {"id": 3, "colour": "blue", "x": 2.95, "y": 0.05, "facing_deg": 0.0, "a_max_deg": 1e4},
    ],
    "start": {"x": 1.75, "y": 1.75, "theta_deg": 90.0},
    "robot": {"ticks_per_metre": 90284.0, "wheel_base_m": 0.3, "sonar_poses": [[0, 0, 0]]},
}


def _none_if_nan(v: float) -> float | None:
    return None if math.isnan(v) else v


def write_synthetic_recording(path: Path, seconds: float = 2.0, seed: int = 5) -> None:
    """Messages shaped as bridge/runtime/zenoh_io.py publishes them, at distinct rates."""
    rng = np.random.default_rng(seed)
    dt = 0.01
    with Recorder(path, metadata={"source": "sim", "seed": seed, "config_path": "x.toml"},
                  world=WORLD) as rec:
        for k in range(round(seconds / dt)):
            t = k * dt
            rec.record("truth/pose", t, {"t": t, "x": 1 + 0.1 * t, "y": 1.0, "theta": 0.3})
            rec.record("sensors/odometry", t, {"t": t, "left_ticks": 9 * k, "right_ticks": -k,
                                               "truth": {"left_ticks": 9 * k, "right_ticks": -k}})
            if k % 2 == 0:
                w = float(rng.normal())
                rec.record("sensors/gyro", t, {"t": t, "yaw_rate": w, "truth": {"yaw_rate": 0.0}})
            if k % 5 == 0:
                m = rng.normal(size=3).tolist()
                rec.record("sensors/compass", t, {"t": t, "mx": m[0], "my": m[1], "mz": m[2],
                                                  "truth": {"mx": 1.0, "my": 0.0, "mz": -4.0}})
                true = rng.uniform(0.1, 3, size=4)
                true[3] = np.nan
                meas = true + rng.normal(0, 0.01, size=4)
                meas[2] = np.nan
                rec.record("sensors/sonar", t, {
                    "t": t,
                    "ranges": [_none_if_nan(v) for v in meas.tolist()],
                    "truth": {"ranges": [_none_if_nan(v) for v in true.tolist()],
                              "incidence": [0.1, 0.2, 0.3, None]},
                })
                ir_ranges = [None] * 16
                ir_ranges[4:6] = rng.uniform(0.02, 0.25, size=2).tolist()
                ir_incidence = [None] * 16
                ir_incidence[4:6] = [0.0, 0.7]
                rec.record("sensors/ir", t, {
                    "t": t, "counts": rng.integers(0, 1024, 16).tolist(), "ambient": [0] * 16,
                    "truth": {"counts": [0] * 16, "ranges": ir_ranges,
                              "incidence": ir_incidence},
                })
            if k % 10 == 0:
                obs = [{"id": 1, "range": 1.5 + t, "bearing": -0.2}, {"id": 3, "range": 2.0,
                                                                     "bearing": 0.4}][: k % 3]
                rec.record("sensors/camera", t, {"t": t, "observations": obs,
                                                 "truth": {"observations": obs}})
            rec.record_frame("can", "from_robot", t, b"\x00" * 8, can_id=0x101)


def _rows(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def _num(cell: str) -> float | None:
    return None if cell == "" else float(cell)


@pytest.fixture()
def recording(tmp_path: Path) -> Path:
    path = tmp_path / "run.mcap"
    write_synthetic_recording(path)
    return path


def test_bundle_agrees_one_for_one(recording: Path, tmp_path: Path) -> None:
    out = export_bundle(recording, tmp_path / "bundle")
    rec = open_recording(recording)

    for name, topic, cols in (
        ("truth_pose.csv", "truth/pose", ("t", "x", "y", "theta")),
        ("odometry.csv", "sensors/odometry", ("t", "left_ticks", "right_ticks")),
        ("gyro.csv", "sensors/gyro", ("t", "yaw_rate")),
        ("compass.csv", "sensors/compass", ("t", "mx", "my", "mz")),
    ):
        rows = _rows(out / name)
        msgs = [m.json() for m in rec.topic(topic)]
        assert len(rows) == len(msgs) > 0, name
        assert list(rows[0]) == list(cols)
        for row, msg in zip(rows, msgs, strict=True):
            assert [float(row[c]) for c in cols] == [float(msg[c]) for c in cols], name

    rows = _rows(out / "range.csv")
    assert tuple(rows[0]) == RANGE_COLUMNS
    expected = []
    for m in sorted(rec.topic("sensors/sonar") + rec.topic("sensors/ir"),
                    key=lambda m: m.log_time_ns):
        msg = m.json()
        truth = msg["truth"]
        kind, measured = (("sonar", msg["ranges"]) if m.topic == "/sensors/sonar"
                          else ("ir", msg["counts"]))
        for i, value in enumerate(measured):
            expected.append((msg["t"], kind, i, value, truth["ranges"][i],
                             truth["incidence"][i]))
    got = [(float(r["t"]), r["kind"], int(r["sensor"]), _num(r["measured"]),
            _num(r["true_range"]), _num(r["incidence_angle"])) for r in rows]
    assert got == expected
    assert any(g[3] is None for g in got) and any(g[4] is None for g in got)  # no echo kept
    ir_true = [g[4] for g in got if g[1] == "ir" and g[4] is not None]
    assert ir_true and all(0.02 <= r <= 0.25 for r in ir_true)  # IR rows get true_range

    cam = [m.json() for m in rec.topic("sensors/camera")]
    obs = [(msg["t"], o) for msg in cam for o in msg["observations"]]
    rows = _rows(out / "landmarks.csv")
    assert [(float(r["t"]), int(r["landmark_id"]), float(r["range"]), float(r["bearing"]))
            for r in rows] == [(t, o["id"], o["range"], o["bearing"]) for t, o in obs]

    assert _rows(out / "landmark_map.csv") == [
        {"id": "1", "x": "0.05", "y": "2.95", "colour": "red"},
        {"id": "3", "x": "2.95", "y": "0.05", "colour": "blue"},
    ]
    meta = json.loads((out / "meta.json").read_text())
    assert meta["seed"] == 5 and meta["recording"] == str(recording.resolve())
    assert meta["config_path"] == "x.toml"
    assert meta["robot"]["ticks_per_metre"] == 90284.0
    assert meta["robot"]["start_pose"] == {"x": 1.75, "y": 1.75, "theta": math.pi / 2}
    assert meta["sensor"] == {"sonar_poses": [[0, 0, 0]]}
    assert meta["units"]["range.measured"] == {"sonar": "m", "ir": "counts"}


def test_cli_export(recording: Path, tmp_path: Path) -> None:
    parser = argparse.ArgumentParser()
    export_cli.add_arguments(parser)
    args = parser.parse_args([str(recording), "--bundle", str(tmp_path / "b")])
    assert export_cli.run(args) == 0
    assert {p.name for p in (tmp_path / "b").iterdir()} == {
        "truth_pose.csv", "odometry.csv", "gyro.csv", "compass.csv", "range.csv",
        "landmarks.csv", "landmark_map.csv", "meta.json",
    }


def test_export_refuses_a_recording_without_readings(tmp_path: Path) -> None:
    path = tmp_path / "empty.mcap"
    with Recorder(path) as rec:
        rec.record_frame("can", "from_robot", 0.0, b"")
    with pytest.raises(RecordingError, match="no reading"):
        export_bundle(path, tmp_path / "b")


def test_a_camera_that_saw_no_landmark_leaves_no_landmarks_file(tmp_path: Path) -> None:
    """Camera messages with no observation all run (a short run facing away): no
    landmarks.csv rather than a header alone, which calibrate refuses as no table; the bundle
    still calibrates."""
    from koala_bridge.calibration.bundle import load_bundle

    path = tmp_path / "blind.mcap"
    with Recorder(path, world=WORLD) as rec:
        for k in range(50):
            t = 0.02 * k
            rec.record("truth/pose", t, {"t": t, "x": 1.0, "y": 1.0, "theta": 0.3})
            rec.record("sensors/gyro", t, {"t": t, "yaw_rate": 0.0, "truth": {"yaw_rate": 0.0}})
            rec.record("sensors/camera", t, {"t": t, "observations": [],
                                             "truth": {"observations": []}})
    out = export_bundle(path, tmp_path / "b")
    assert not (out / "landmarks.csv").exists()
    assert "landmarks.csv" not in json.loads((out / "meta.json").read_text()).get("rows", {})
    assert load_bundle(out).get("gyro") is not None
