"""The fault log of a recording (``faults.csv``, docs/faults.md) as calibrate reads it
(``calibration.fault_log``): windows paired by name, a glitch's one reading, a kidnap; the rows
it sets aside, of the sensors it names; a log calibrate cannot read is an error naming its
line. The end-to-end case is ``tests/integration/test_calibration_faulted_run.py``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from koala_bridge.calibration.bundle import load_bundle
from koala_bridge.calibration.errors import BundleError
from koala_bridge.calibration.fault_log import read_faults, set_aside_faulted
from koala_bridge.calibration.streams.odometry import reference_jumps


def _log(rows: list[tuple[float, str, str, str, dict[str, object]]]) -> str:
    lines = ["t,name,kind,target,detail"]
    for t, name, kind, target, detail in rows:
        text = json.dumps(detail, separators=(",", ":")).replace('"', '""')
        lines.append(f'{t},{name},{kind},{target},"{text}"')
    return "\n".join(lines) + "\n"


def _bundle(tmp_path: Path, log: str) -> Path:
    d = tmp_path / "b"
    d.mkdir()
    t = np.arange(0.0, 10.0, 0.1)
    np.savetxt(d / "truth_pose.csv", np.column_stack([t, 0 * t, 0 * t, 0 * t]), delimiter=",",
               header="t,x,y,theta", comments="", fmt="%.6g")
    np.savetxt(d / "gyro.csv", np.column_stack([t, 0 * t]), delimiter=",",
               header="t,yaw_rate", comments="", fmt="%.6g")
    rows = ["t,kind,sensor,measured,true_range"]
    for ti in t:
        rows += [f"{ti:.6g},sonar,{s},1.0,1.0" for s in range(3)]
        rows += [f"{ti:.6g},ir,{s},100,0.05" for s in range(2)]
    (d / "range.csv").write_text("\n".join(rows) + "\n", encoding="utf-8")
    (d / "faults.csv").write_text(log, encoding="utf-8")
    (d / "meta.json").write_text("{}", encoding="utf-8")
    return d


LOG = [
    (1.0, "s", "stuck", "sonar", {"phase": "start", "sensors": [1]}),
    (2.0, "g", "glitch", "gyro", {"delta": 0.5}),
    (3.0, "s", "stuck", "sonar", {"phase": "end"}),
    (4.0, "i", "stuck_max", "ir", {"phase": "start", "sensors": []}),
    (5.0, "k", "kidnap", "robot", {"from": [0, 0, 0], "to": [1, 1, 0]}),
    (0.5, "d", "drop", "can", {"can_id": 512}),
]


def test_windows_pair_by_name_and_one_left_open_runs_to_the_end(tmp_path: Path) -> None:
    b = load_bundle(_bundle(tmp_path, _log(LOG)))
    assert b.faults is not None and not b.unknown_files
    faults = {f.name: f for f in read_faults(b.faults, "faults.csv")}
    assert set(faults) == {"s", "g", "i", "k"}  # a bus fault changes no reading
    assert (faults["s"].start, faults["s"].end, faults["s"].sensors) == (1.0, 3.0, (1,))
    assert (faults["g"].start, faults["g"].end) == (2.0, 2.0)
    assert faults["i"].end == np.inf and faults["i"].sensors is None
    assert faults["k"].kind == "kidnap" and faults["k"].start == 5.0


def test_the_rows_set_aside_are_the_named_sensors_in_the_window(tmp_path: Path) -> None:
    b = load_bundle(_bundle(tmp_path, _log(LOG)))
    out, notes = set_aside_faulted(b)
    before, after = b.get("range"), out.get("range")
    assert before is not None and after is not None
    gone = len(before) - len(after)
    # sonar 1 from 1.0 to 3.0 s (21 readings), every IR from 4.0 s to the end (2 x 60)
    assert gone == 21 + 2 * 60
    kind = after.text["kind"].astype(str)
    sonar1 = (kind == "sonar") & (after["sensor"] == 1)
    assert not np.any(sonar1 & (after["t"] >= 1.0) & (after["t"] <= 3.0))
    assert np.sum((kind == "sonar") & (after["t"] >= 1.0) & (after["t"] <= 3.0)) == 2 * 21
    assert not np.any((kind == "ir") & (after["t"] >= 4.0))
    gyro = out.get("gyro")
    assert gyro is not None
    assert not np.any(np.isclose(gyro["t"], 2.0))  # the glitch's reading
    # a kidnap: the readings within two intervals of it (a reference differenced across it)
    assert not np.any(np.abs(gyro["t"] - 5.0) <= 0.2 + 1e-9)
    assert len(gyro) == 100 - 1 - 5
    assert set(notes) == {"gyro", "range:sonar", "range:ir"}
    assert "21 reading(s)" in notes["range:sonar"][0]


def test_a_bundle_without_a_log_is_unchanged(tmp_path: Path) -> None:
    d = _bundle(tmp_path, _log(LOG))
    (d / "faults.csv").unlink()
    b = load_bundle(d)
    assert b.faults is None
    assert set_aside_faulted(b) == (b, {})


def test_a_log_calibrate_cannot_read_is_an_error_naming_its_line(tmp_path: Path) -> None:
    d = _bundle(tmp_path, _log(LOG).replace('""delta"":0.5', '""delta"":'))
    with pytest.raises(BundleError, match=r"faults.csv line 3: detail is not JSON"):
        set_aside_faulted(load_bundle(d))
    (d / "faults.csv").write_text("t,what\n1,x\n", encoding="utf-8")
    with pytest.raises(BundleError, match="lacks required column"):
        load_bundle(d)
    # without names the windows' start and end rows cannot be paired
    (d / "faults.csv").write_text('t,kind,target,detail\n1,stuck,gyro,"{""phase"":""start""}"\n',
                                  encoding="utf-8")
    with pytest.raises(BundleError, match="lacks required column.*name"):
        load_bundle(d)


def test_a_reference_still_but_for_one_jump_is_said_to_jump() -> None:
    t = np.arange(0.0, 60.0, 0.02)
    p = np.zeros((t.size, 2))
    p[t >= 30.0] = (1.0, 0.5)  # a robot that never drove, picked up once
    note = reference_jumps(t, p)
    assert note is not None and note.startswith("the reference jumps: 1 of")
    assert "first at t = 30 s" in note
    assert reference_jumps(t, p, explained=((29.9, 30.1),)) is None
