"""Bad input files end in one clear line on stderr (exit 2), never a traceback.

Measurement bundles (docs/bundle-format.md): one row, header only, NaN/inf/1e308 cells, ragged
rows, binary and UTF-16 bytes, missing, reversed or repeated time, a ``meta.json`` that is not
an object or declares meaningless numbers (``ticks_per_metre: 0``) -> ``koala-bridge calibrate``
names the file, and the line and column where there is one.

MCAP recordings (docs/recording.md): bits flipped anywhere -> ``export``, ``calibrate`` and
``replay`` name the damaged record (the CRCs are checked) and ``export`` leaves no bundle; a
file cut short at any offset -> a WARNING saying what was kept and lost, and the rest exported
(or one line when nothing is left to export).

The loaders also take arbitrary bytes and text from hypothesis: they raise nothing but the
project's errors.
"""

from __future__ import annotations

import json
import logging
import os
import random
import re
import shutil
import struct
import subprocess
import tempfile
from collections.abc import Callable
from pathlib import Path

import pytest
from conftest import REPO, bridge_command
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from koala_bridge.calibration.bundle import load_bundle, read_meta
from koala_bridge.calibration.errors import BundleError
from koala_bridge.cli.main import main
from koala_bridge.core.errors import KoalaBridgeError
from koala_bridge.recording.mcap_file import (
    FROM_ROBOT,
    MCAP_MAGIC,
    RECOVER_HINT,
    Recorder,
    RecordingError,
    open_recording,
)

REAL = REPO / "tests" / "data" / "real"
FUZZ = settings(max_examples=200, deadline=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


def one_line(err: str, command: str, *needles: str) -> str:
    """The single stderr line of a failed subcommand; checks it names what it should."""
    assert "Traceback" not in err, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(f"koala-bridge {command}: "), lines[0]
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


# -- bundles -----------------------------------------------------------------------------------

def gyro(n: int = 50, t: Callable[[int], float] = lambda i: i * 0.01) -> str:
    return "t,yaw_rate\n" + "".join(f"{t(i):.2f},{0.001 * i}\n" for i in range(n))


def truth(n: int = 50, t: Callable[[int], float] = lambda i: i * 0.01) -> str:
    return "t,x,y,theta\n" + "".join(f"{t(i):.2f},{0.01 * i},0,0\n" for i in range(n))


#: A small valid bundle (calibrated with exit 0 below); each case replaces some of its files.
BASE: dict[str, str | bytes] = {"gyro.csv": gyro(), "truth_pose.csv": truth(), "meta.json": "{}"}

#: name -> (files replacing the base's, what the one line must say)
BUNDLES: dict[str, tuple[dict[str, str | bytes], tuple[str, ...]]] = {
    "one_row": ({"truth_pose.csv": "t,x,y,theta\n0,0,0,0\n"},
                ("truth_pose.csv", "1 data row")),
    "header_only": ({"gyro.csv": "t,yaw_rate\n"}, ("gyro.csv", "no data row")),
    "empty_file": ({"gyro.csv": ""}, ("gyro.csv", "no header row")),
    "blank_lines_only": ({"gyro.csv": "\n\n\n"}, ("gyro.csv", "no header row")),
    "nan_time": ({"gyro.csv": gyro().replace("0.10,", "nan,")},
                 ("gyro.csv line 12", "column 't'", "every row needs its time")),
    "no_compass_value": ({"compass.csv": "t,mx,my\n0,nan,nan\n0.1,,\n0.2,1,2\n"},
                         ("compass.csv", "1 row(s) with a number in every one of t, mx, my")),
    "empty_time": ({"gyro.csv": gyro().replace("0.10,", ",")}, ("gyro.csv line 12", "'t'")),
    "1e308_value": ({"gyro.csv": gyro().replace(",0.01\n", ",1e308\n")},
                    ("gyro.csv line 12", "column 'yaw_rate'", "1e308")),
    "1e308_time": ({"gyro.csv": gyro().replace("0.10,", "1e308,")},
                   ("gyro.csv line 12", "column 't'")),
    "inf_value": ({"truth_pose.csv": truth().replace("0.1,0,0", "inf,0,0")},
                  ("truth_pose.csv line 12", "column 'x'", "inf")),
    "minus_inf_value": ({"truth_pose.csv": truth().replace("0.1,0,0", "0.1,-inf,0")},
                        ("truth_pose.csv line 12", "column 'y'")),
    "ragged_short": ({"gyro.csv": gyro().replace("0.10,0.01\n", "0.10\n")},
                     ("gyro.csv line 12", "1 cell(s)", "header has 2")),
    "ragged_long": ({"gyro.csv": gyro().replace("0.10,0.01\n", "0.10,0.01,7,8\n")},
                    ("gyro.csv line 12", "4 cell(s)")),
    "binary": ({"gyro.csv": b"t,yaw_rate\n0,1\n\xff\xfe\x00\x01garbage\n"},
               ("gyro.csv line 3", "not UTF-8")),
    "utf16": ({"gyro.csv": gyro().encode("utf-16")}, ("gyro.csv line 1", "not UTF-8")),
    "nul_byte": ({"gyro.csv": gyro().replace("0.10,", "0.1\x00,")},
                 ("gyro.csv line 12", "NUL")),
    "text_in_required": ({"gyro.csv": gyro().replace(",0.01\n", ",fast\n")},
                         ("gyro.csv line 12", "column 'yaw_rate'", "'fast'")),
    "duplicate_header": ({"gyro.csv": "t,t\n0,1\n1,2\n"}, ("gyro.csv line 1", "twice")),
    "missing_column": ({"gyro.csv": "t,rate\n0,1\n1,2\n"}, ("gyro.csv", "yaw_rate")),
    "reversed_time": ({"truth_pose.csv": truth(t=lambda i: 0.5 - i * 0.01)},
                      ("truth_pose.csv line 3", "before the previous row")),
    "duplicate_time": ({"gyro.csv": gyro(t=lambda i: (i // 2) * 0.01)},
                       ("gyro.csv line 3", "repeats the previous row's time")),
    "all_one_time": ({"truth_pose.csv": truth(t=lambda i: 1.0)},
                     ("truth_pose.csv line 3", "repeats")),
    "meta_null": ({"meta.json": "null"}, ("meta.json", "JSON object", "not null")),
    "meta_array": ({"meta.json": "[]"}, ("meta.json", "not an array")),
    "meta_string": ({"meta.json": '"robot"'}, ("meta.json", "not a string")),
    "meta_number": ({"meta.json": "3"}, ("meta.json", "not a number")),
    "meta_not_json": ({"meta.json": "{robot: 1}"}, ("meta.json line 1", "not JSON")),
    "meta_binary": ({"meta.json": b"\xff\xfe{\x00"}, ("meta.json", "not UTF-8")),
    "meta_deep": ({"meta.json": "[" * 100_000 + "]" * 100_000}, ("meta.json", "nested")),
    "meta_nan": ({"meta.json": '{"robot": {"wheel_base_m": NaN}}'}, ("meta.json", "NaN")),
    "meta_1e400": ({"meta.json": '{"reference": {"to_t": 1e400}}'},
                   ("meta.json", "1e400", "out of range")),
    "meta_robot_array": ({"meta.json": '{"robot": []}'}, ("meta.json", "robot", "JSON object")),
    "meta_units_array": ({"meta.json": '{"units": [1]}'}, ("meta.json", "units")),
}

#: lego_brenner (odometry against a tracker) with its meta.json replaced by ...
ODOMETRY_META: dict[str, tuple[str, tuple[str, ...]]] = {
    "ticks_zero": ('{"robot": {"ticks_per_metre": 0, "wheel_base_m": 0.15}}',
                   ("robot.ticks_per_metre", "> 0", "got 0")),
    "ticks_negative": ('{"robot": {"ticks_per_metre": -5, "wheel_base_m": 0.15}}',
                       ("robot.ticks_per_metre", "> 0")),
    "ticks_text": ('{"robot": {"ticks_per_metre": "2865", "wheel_base_m": 0.15}}',
                   ("robot.ticks_per_metre", "must be a number")),
    "ticks_true": ('{"robot": {"ticks_per_metre": true, "wheel_base_m": 0.15}}',
                   ("robot.ticks_per_metre", "must be a number")),
    "ticks_huge": ('{"robot": {"ticks_per_metre": 1e300, "wheel_base_m": 0.15}}',
                   ("robot.ticks_per_metre", "finite")),
    "base_zero": ('{"robot": {"ticks_per_metre": 2865, "wheel_base_m": 0}}',
                  ("robot.wheel_base_m", "> 0")),
    "ratio_zero": ('{"robot": {"ticks_per_metre": 2865, "wheel_diameter_ratio": 0}}',
                   ("robot.wheel_diameter_ratio",)),
    "start_pose_array": ('{"robot": {"ticks_per_metre": 2865, "start_pose": [1, 2]}}',
                         ("robot.start_pose", "JSON object")),
    "start_pose_text": ('{"robot": {"start_pose": {"x": "1", "y": 0}}}',
                        ("robot.start_pose.x", "must be a number")),
    "gyro_bias_text": ('{"sensor": {"gyro": {"bias_rad_s": "0.1"}}}',
                       ("sensor.gyro.bias_rad_s",)),
}


def make_bundle(root: Path, name: str) -> tuple[Path, tuple[str, ...]]:
    d = root / name
    if name in ODOMETRY_META:
        meta, needles = ODOMETRY_META[name]
        shutil.copytree(REAL / "lego_brenner", d)
        (d / "meta.json").write_text(meta)
        return d, ("meta.json", *needles)
    files, needles = BUNDLES[name] if name != "valid" else ({}, ())
    d.mkdir(parents=True)
    for f, content in {**BASE, **files}.items():
        (d / f).write_bytes(content if isinstance(content, bytes) else content.encode())
    return d, needles


def calibrate(bundle: Path, out: Path) -> int:
    return main(["calibrate", str(bundle), "--out", str(out), "--no-plots", "--quiet"])


def test_the_base_bundle_is_valid(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Each bad bundle below differs from this one by its defect only."""
    bundle, _ = make_bundle(tmp_path, "valid")
    assert calibrate(bundle, tmp_path / "out") == 0, capsys.readouterr().err
    lego = tmp_path / "lego"
    shutil.copytree(REAL / "lego_brenner", lego)
    assert calibrate(lego, tmp_path / "out-lego") == 0, capsys.readouterr().err


@pytest.mark.parametrize("name", [*BUNDLES, *ODOMETRY_META])
def test_bad_bundle_is_one_line_exit_2(
    name: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bundle, needles = make_bundle(tmp_path, name)
    assert calibrate(bundle, tmp_path / "out") == 2
    one_line(capsys.readouterr().err, "calibrate", str(bundle), *needles)


@pytest.mark.parametrize("name", ["binary", "ragged_short", "meta_null", "ticks_zero"])
def test_bad_bundle_in_a_subprocess(name: str, tmp_path: Path) -> None:
    bundle, needles = make_bundle(tmp_path, name)
    p = subprocess.run(bridge_command("calibrate", str(bundle), "--out", str(tmp_path / "o"),
                                      "--no-plots", "--quiet"),
                       cwd=tmp_path, capture_output=True, text=True, timeout=300,
                       stdin=subprocess.DEVNULL)
    assert p.returncode == 2, p.stderr
    one_line(p.stderr, "calibrate", *needles)


CSV_CELLS = st.one_of(
    st.sampled_from(["t", "yaw_rate", "x", "y", "0", "1.5", "-2", "nan", "inf", "-inf",
                     "1e308", "1e-320", "", " ", '"', '""', "#", "\x00", "\r", "\ufeff",
                     "1,2", "0x10", "1_0"]),
    st.text(max_size=6),
)
CSV_TEXT = st.one_of(
    st.text(max_size=300),
    st.lists(st.lists(CSV_CELLS, max_size=5), max_size=12).map(
        lambda rows: "\n".join(",".join(r) for r in rows)),
    st.lists(st.tuples(st.floats(allow_nan=True, allow_infinity=True),
                       st.floats(allow_nan=True, allow_infinity=True)), max_size=20).map(
        lambda rows: "t,yaw_rate\n" + "".join(f"{a!r},{b!r}\n" for a, b in rows)),
)


@FUZZ
@given(text=CSV_TEXT, encoding=st.sampled_from(["utf-8", "utf-16", "latin-1"]),
       name=st.sampled_from(["gyro", "truth_pose", "range", "landmark_map"]))
def test_bundle_loader_on_arbitrary_csv(text: str, encoding: str, name: str) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        (Path(tmp) / f"{name}.csv").write_bytes(text.encode(encoding, "replace"))
        try:
            bundle = load_bundle(Path(tmp))
        except BundleError as e:
            assert str(e) and "\n" not in str(e).strip()
        else:
            table = bundle.tables[name]
            if "t" in table.columns:
                assert len(table) >= 1 and all(table["t"][1:] >= table["t"][:-1])


JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(
        st.sampled_from(["robot", "sensor", "units", "reference", "gyro", "start_pose",
                         "ticks_per_metre", "wheel_base_m", "x", "y", "theta", "from_t",
                         "bias_rad_s"]) | st.text(max_size=4), inner, max_size=4),
    max_leaves=12,
)


@FUZZ
@given(meta=st.one_of(JSON_VALUES.map(json.dumps), st.text(max_size=100).map(str.encode),
                      st.binary(max_size=100)))
def test_meta_loader_on_arbitrary_json(meta: str | bytes) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "meta.json"
        path.write_bytes(meta if isinstance(meta, bytes) else meta.encode())
        try:
            assert isinstance(read_meta(path), dict)
        except BundleError as e:
            assert str(e)


# -- recordings --------------------------------------------------------------------------------

WORLD = {"robot": {"ticks_per_metre": 90284.0, "wheel_base_m": 0.285},
         "landmarks": [{"id": 1, "x": 1.0, "y": 2.0, "colour": "red"}]}


def record(path: Path, n: int = 1500, chunk_size: int = 4096) -> Path:
    """A recording of ``n`` steps of 10 ms: poses, gyro, compass, CAN frames, in small chunks."""
    with Recorder(path, metadata={"source": "sim", "seed": 1}, world=WORLD,
                  chunk_size=chunk_size) as rec:
        rec.declare(keys=["truth/pose", "sensors/gyro"], buses=["can", "serial/kteam"])
        for i in range(n):
            t = i * 0.01
            rec.record("truth/pose", t, {"t": t, "x": 0.001 * i, "y": 0.0, "theta": 0.002 * i})
            rec.record("sensors/gyro", t, {"t": t, "yaw_rate": 0.2})
            rec.record_frame("can", FROM_ROBOT, t, bytes([i & 0xFF, 2]), can_id=0x101,
                             extended=False)
    return path


@pytest.fixture(scope="module")
def good(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return record(tmp_path_factory.mktemp("rec") / "good.mcap")


def flipped(good: Path, tmp: Path, pos: int, bit: int = 0) -> Path:
    raw = bytearray(good.read_bytes())
    raw[pos] ^= 1 << bit
    bad = tmp / f"flip-{pos}-{bit}.mcap"
    bad.write_bytes(bytes(raw))
    return bad


def landmarks(good: Path) -> dict[str, int]:
    """Byte offsets of parts of ``good`` worth damaging."""
    raw = good.read_bytes()
    first_chunk = raw.index(b"zstd") + 4 + 8  # the chunk's compressed data
    summary_start = int.from_bytes(raw[-8 - 20:-8 - 12], "little")
    return {
        "header profile": 8 + 9 + 4 + 2,
        "metadata": raw.index(b"format_version"),
        "first chunk data": first_chunk + 20,
        "chunk CRC": raw.index(b"zstd") - 4 - 4 + 1,
        "middle chunk": len(raw) // 2,
        "summary": summary_start + 10,
        "footer CRC": len(raw) - 8 - 2,
        "closing magic": len(raw) - 3,
    }


def test_bit_flips_are_named_and_export_leaves_no_bundle(
    good: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    size = good.stat().st_size
    rng = random.Random(20261124)
    places = list(landmarks(good).values()) + rng.sample(range(8, size), 40)
    for pos in places:
        bad = flipped(good, tmp_path, pos, rng.randrange(8))
        out = tmp_path / f"bundle-{pos}"
        assert main(["export", str(bad), "--bundle", str(out)]) == 2, pos
        line = one_line(capsys.readouterr().err, "export", str(bad), "damaged", RECOVER_HINT)
        # A CRC over a section cannot say where in it the damage is: the line gives the range.
        assert "damaged at byte" in line or re.search(r"section \(bytes \d+-\d+\) fails", line)
        assert not out.exists(), "a damaged recording leaves no bundle"
        assert not [p for p in tmp_path.iterdir() if ".partial-" in p.name]


@pytest.mark.parametrize("part", ["header profile", "metadata", "first chunk data", "chunk CRC",
                                  "summary", "footer CRC"])
def test_damaged_recording_calibrate_and_replay_one_line(
    part: str, good: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = flipped(good, tmp_path, landmarks(good)[part], 3)
    assert main(["calibrate", str(bad), "--out", str(tmp_path / "o"), "--no-plots",
                 "--quiet"]) == 2
    one_line(capsys.readouterr().err, "calibrate", str(bad), "damaged", RECOVER_HINT)
    assert main(["replay", str(bad), "--no-zenoh"]) == 2
    line = one_line(capsys.readouterr().err, "replay", str(bad), "damaged", RECOVER_HINT)
    assert line.endswith(RECOVER_HINT)


def test_damaged_recording_in_a_subprocess(good: Path, tmp_path: Path) -> None:
    bad = flipped(good, tmp_path, landmarks(good)["middle chunk"], 5)
    for args in (["export", str(bad), "--bundle", str(tmp_path / "b")],
                 ["replay", str(bad)]):
        p = subprocess.run(bridge_command(*args), cwd=tmp_path, capture_output=True, text=True,
                           timeout=300, stdin=subprocess.DEVNULL)
        assert p.returncode == 2, p.stderr
        one_line(p.stderr, args[0], "damaged at byte", RECOVER_HINT)


def test_cut_at_any_offset_warns_what_was_lost_and_exports_the_rest(
    good: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str],
    caplog: pytest.LogCaptureFixture,
) -> None:
    raw = good.read_bytes()
    whole = open_recording(good)
    offsets = sorted({9, 16, 40, 200, 1000, *range(2000, len(raw), len(raw) // 37),
                      len(raw) - 100, len(raw) - 37, len(raw) - 9, len(raw) - 3})
    poses = []
    for cut in offsets:
        path = tmp_path / f"cut-{cut}.mcap"
        path.write_bytes(raw[:cut])
        out = tmp_path / f"bundle-{cut}"
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="koala_bridge.recording"):
            code = main(["export", str(path), "--bundle", str(out)])
        err = capsys.readouterr().err
        assert "Traceback" not in err
        if code == 2:  # nothing left to export
            one_line(err, "export", str(path))
            assert not out.exists() and cut < len(raw) // 10, cut
            poses.append(0)
            continue
        assert code == 0 and not err.strip(), (cut, err)
        warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
        rec = open_recording(path)
        if cut > len(raw) - 8:  # only the closing magic is cut: nothing is lost
            assert rec.complete
        else:
            assert not rec.complete and len(warnings) == 1, (cut, warnings)
            assert "kept" in warnings[0] and "lost" in warnings[0] and "t = " in warnings[0]
        meta = json.loads((out / "meta.json").read_text())
        assert meta["recording_complete"] is rec.complete and meta["recording_lost"] == rec.lost
        bundle = load_bundle(out)
        poses.append(len(bundle.tables["truth_pose"]))
    assert poses == sorted(poses), "a longer file never exports fewer rows"
    assert poses[-1] == len(whole.topic("truth/pose"))


def test_export_replaces_a_previous_bundle_but_not_other_files(
    good: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "bundle"
    assert main(["export", str(good), "--bundle", str(out)]) == 0
    (out / "landmarks.csv").write_text("stale\n")  # a file the new export does not write
    assert main(["export", str(good), "--bundle", str(out)]) == 0
    assert not (out / "landmarks.csv").exists()
    (out / "notes.txt").write_text("mine")
    assert main(["export", str(good), "--bundle", str(out)]) == 2
    one_line(capsys.readouterr().err, "export", "notes.txt")
    assert (out / "notes.txt").read_text() == "mine" and (out / "meta.json").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bundle"]


def test_recover_salvages_up_to_the_damage(good: Path, tmp_path: Path) -> None:
    bad = flipped(good, tmp_path, landmarks(good)["middle chunk"], 1)
    fixed = tmp_path / "fixed.mcap"
    assert main(["recover", str(bad), str(fixed)]) == 0
    rec = open_recording(fixed)
    whole = open_recording(good)
    assert rec.complete and 0 < len(rec.messages) < len(whole.messages)
    # Reading goes on after a damaged chunk: what is kept is whole's messages, in order.
    it = iter(whole.messages)
    assert all(m in it for m in rec.messages)


def chunk_offsets(raw: bytes) -> list[tuple[int, int, int, int]]:
    """(record offset, body offset, start, end time in ns) of each chunk record of ``raw``."""
    out, pos = [], len(MCAP_MAGIC)
    while pos + 9 <= len(raw):
        opcode, length = struct.unpack_from("<BQ", raw, pos)
        if opcode == 0x06:
            t0, t1 = struct.unpack_from("<QQ", raw, pos + 9)
            out.append((pos, pos + 9, t0, t1))
        if opcode == 0x02:  # the footer
            break
        pos += 9 + length
    return out


@pytest.mark.parametrize("where", ["compressed data", "length field"])
def test_recover_skips_a_damaged_chunk_and_keeps_the_others(
    where: str, good: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    raw = bytearray(good.read_bytes())
    chunks = chunk_offsets(bytes(raw))
    assert len(chunks) > 10
    pos, body, t0, t1 = chunks[2]  # chunk 3
    if where == "compressed data":
        raw[body + 44 + 30] ^= 0x10  # inside its compressed records (after 44 bytes of fields)
    else:
        raw[pos + 8] ^= 0x40  # the high byte of its length: now past the end of the file
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(raw))
    fixed = tmp_path / "fixed.mcap"
    with caplog.at_level(logging.WARNING, logger="koala_bridge.recording"):
        assert main(["recover", str(bad), str(fixed)]) == 0
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any(f"byte {pos}" in w and "skipped" in w and "lost" in w and "t = " in w
               for w in warnings), warnings
    rec = open_recording(fixed)
    whole = open_recording(good).messages
    k = len(whole) - len(rec.messages)
    a = next(i for i, (m, w) in enumerate(zip(rec.messages, whole, strict=False)) if m != w)
    assert rec.complete and 0 < k
    assert rec.messages == whole[:a] + whole[a + k :], "every message of the other chunks is kept"
    assert all(t0 <= m.log_time_ns <= t1 for m in whole[a : a + k]), "only chunk 3's are lost"


@pytest.fixture(scope="module")
def small() -> bytes:
    with tempfile.TemporaryDirectory() as tmp:
        return record(Path(tmp) / "small.mcap", n=120, chunk_size=1024).read_bytes()


@FUZZ
@given(data=st.one_of(st.binary(max_size=600), st.binary(max_size=600).map(MCAP_MAGIC.__add__)),
       salvage=st.booleans())
def test_open_recording_on_arbitrary_bytes(data: bytes, salvage: bool) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "x.mcap"
        path.write_bytes(data)
        try:
            open_recording(path, salvage=salvage)
        except RecordingError as e:
            assert str(e)


@FUZZ
@given(st.data())
def test_open_recording_on_a_mutated_recording(small: bytes, data: st.DataObject) -> None:
    raw = bytearray(small)
    for _ in range(data.draw(st.integers(0, 4), label="flips")):
        pos = data.draw(st.integers(0, len(raw) - 1), label="pos")
        raw[pos] ^= data.draw(st.integers(1, 255), label="xor")
    cut = data.draw(st.integers(0, len(raw)), label="cut")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "x.mcap"
        path.write_bytes(bytes(raw[:cut]))
        try:
            rec = open_recording(path, salvage=data.draw(st.booleans(), label="salvage"))
        except KoalaBridgeError as e:
            assert str(e)
        else:
            assert rec.complete or rec.lost


def test_a_data_section_crc_failure_names_the_range_not_one_byte(
    good: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    raw = bytearray(good.read_bytes())
    pos, body, _, _ = chunk_offsets(bytes(raw))[1]
    length = struct.unpack_from("<Q", raw, pos + 1)[0]
    index = pos + 9 + length  # the message index record after chunk 2: only the DataEnd CRC sees it
    assert raw[index] == 0x07
    raw[index + 9 + 2 + 4 + 8 + 2] ^= 0x01  # inside its first entry's log time
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(raw))
    assert main(["export", str(bad), "--bundle", str(tmp_path / "b")]) == 2
    line = one_line(capsys.readouterr().err, "export", str(bad), RECOVER_HINT)
    assert re.search(r"the data section \(bytes 8-\d+\) fails its CRC check", line), line
    assert "at byte" not in line, "the check cannot tell where in the section the damage is"


def test_export_removes_the_folders_a_killed_export_left(good: Path, tmp_path: Path) -> None:
    gone = subprocess.Popen(["true"])
    gone.wait()  # its pid names no process now
    stale = [tmp_path / f".bundle.partial-{gone.pid}-x1y2", tmp_path / f".bundle.old-{gone.pid}-z"]
    running = tmp_path / f".bundle.partial-{os.getpid()}-abc"  # a live export's: kept
    others = [tmp_path / f".other.partial-{gone.pid}-q", tmp_path / ".bundle.partial-oldstyle"]
    for d in [*stale, running, *others]:
        d.mkdir()
        (d / "truth_pose.csv").write_text("t\n")
    assert main(["export", str(good), "--bundle", str(tmp_path / "bundle")]) == 0
    assert not any(d.exists() for d in stale)
    assert running.exists() and all(d.exists() for d in others)
    assert (tmp_path / "bundle" / "meta.json").exists()
