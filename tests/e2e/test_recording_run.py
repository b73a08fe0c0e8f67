"""`run --record`: a 60 s run (fast clock) opens with the mcap library, every channel present,
counts match the configured rates within 2 %, no gap in any bus sequence; its bundle agrees."""

from __future__ import annotations

import csv
import json
import signal
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import can
import pytest
from _recorded_run import DURATION_S, KTEAM_COMMANDS, RecordedRun, record_run
from conftest import BridgeProcess
from koala_bridge.drivers.can_codec import KoalaCanCodec
from koala_bridge.drivers.messages import RangeFrame, RangeKind, Reject
from koala_bridge.drivers.rangeframes import decode_range_frame
from koala_bridge.recording.export import export_bundle
from koala_bridge.recording.mcap_file import FROM_ROBOT, TO_ROBOT, Recording, open_recording
from mcap.reader import make_reader


@pytest.fixture(scope="module")
def run60(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RecordedRun]:
    yield record_run(tmp_path_factory.mktemp("run60"))


@pytest.fixture(scope="module")
def rec(run60: RecordedRun) -> Recording:
    return open_recording(run60.path)


def expected_rates(rec: Recording) -> dict[str, float]:
    """Messages per simulation second per channel, from the recorded configuration."""
    config = json.loads(rec.metadata["koala-bridge"]["config"])
    s = {name: float(section["rate_hz"]) for name, section in config["sensors"].items()}
    z, mav = config["zenoh"], config["buses"]["mavlink"]
    return {
        "/truth/pose": float(z["pose_rate_hz"]),
        "/status": float(z["status_rate_hz"]),
        "/sensors/ir": s["ir"],
        "/sensors/sonar": s["sonar"],
        "/sensors/odometry": s["encoders"],
        "/sensors/gyro": s["gyro"],
        "/sensors/compass": s["compass"],
        "/sensors/camera": s["camera"],
        "/bus/serial/rangefinders": s["ir"] + s["sonar"],
        "/bus/can": s["encoders"] + s["gyro"],
        "/bus/mavlink": float(mav["heartbeat_hz"]) + s["compass"],
        **localisation_rates(config),
    }


def localisation_rates(config: dict) -> dict[str, float]:
    """The estimator node's channels (bridge/runtime/localisation.py), when it is on."""
    loc = config.get("localisation") or {}
    if not loc.get("enabled"):
        return {}
    # estimate/health also goes out at every change of state: none on this still run
    return {"/estimate/pose": float(loc["pose_rate_hz"]),
            "/estimate/health": float(loc["robust"]["health_rate_hz"]),
            "/estimate/cell": float(loc["cell_rate_hz"]),
            "/estimate/grid": float(loc["grid_rate_hz"]),
            "/map/occupancy": float(loc["occupancy_rate_hz"])}


def test_opens_with_mcap_library_every_channel_counts_match_rates(
    run60: RecordedRun, rec: Recording
) -> None:
    with run60.path.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        topics = {c.id: c.topic for c in summary.channels.values()}
        counts = {topics[i]: n for i, n in summary.statistics.channel_message_counts.items()}
        scene = set()
        for ch in summary.channels.values():
            schema = summary.schemas[ch.schema_id]
            if schema.name.startswith("foxglove."):  # the scene (runtime/foxglove_scene.py)
                assert (schema.encoding, ch.message_encoding) == ("protobuf", "protobuf")
                scene.add(ch.topic)
            else:
                assert (schema.encoding, ch.message_encoding) == ("jsonschema", "json")
        assert sum(1 for _ in reader.iter_messages()) == sum(counts.values())
    assert rec.complete
    rates = expected_rates(rec)
    assert scene and all(topic.startswith(("/world/", "/koala/")) for topic in scene)
    assert set(counts) - scene == set(rates) | {"/bus/serial/kteam"}
    for topic, rate in rates.items():
        from_robot = (
            sum(1 for m in rec.topic(topic) if m.json()["dir"] == FROM_ROBOT)
            if topic.startswith("/bus/")
            else counts[topic]
        )
        expected = rate * DURATION_S
        assert abs(from_robot - expected) <= 0.02 * expected, (topic, from_robot, expected)
    # sample times cover the run
    t = [m.t for m in rec.topic("/sensors/gyro")]
    assert t[0] == 0.0 and t[-1] == pytest.approx(DURATION_S)
    # status: one per period from the first period on, the last at the stop time, none twice
    period = 1.0 / rates["/status"]
    n_status = round(DURATION_S / period)
    assert [m.t for m in rec.topic("/status")] == pytest.approx(
        [k * period for k in range(1, n_status + 1)])


def test_a_bus_no_client_used_still_has_its_channel(
    bridge: Callable[..., BridgeProcess], tmp_path: Path
) -> None:
    path = tmp_path / "quiet.mcap"
    b = bridge(clock="fast", extra=["--duration", "2.5", "--record", str(path)])
    assert b.proc.wait(timeout=120) == 0, b.log()
    with path.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and summary.statistics is not None
    topics = {c.topic: c.id for c in summary.channels.values()}
    counts = summary.statistics.channel_message_counts
    # No K-Team client: its bus channel is there, empty; every other channel too.
    assert "/bus/serial/kteam" in topics
    assert counts.get(topics["/bus/serial/kteam"], 0) == 0
    rec = open_recording(path)
    scene = {c.topic for c in summary.channels.values()  # the Foxglove scene beside them
             if summary.schemas[c.schema_id].name.startswith("foxglove.")}
    assert set(topics) - scene == set(expected_rates(rec)) | {"/bus/serial/kteam"}
    assert "/bus/serial/kteam" in rec.topics and not rec.topic("/bus/serial/kteam")
    # Stopped between two statuses (2.5 s, 1 Hz): one more, the final counters at the stop time.
    period = 1.0 / expected_rates(rec)["/status"]
    every = [k * period for k in range(1, int(2.5 / period + 1e-9) + 1)]
    assert [m.t for m in rec.topic("/status")] == pytest.approx(
        every + ([] if every[-1] == pytest.approx(2.5) else [2.5]))


def test_no_gap_in_any_sequence(rec: Recording) -> None:
    for topic in rec.topics:
        seqs = [m.sequence for m in rec.topic(topic)]
        assert seqs == list(range(len(seqs))), topic  # MCAP per-channel sequence
        if topic.startswith("/bus/"):
            for d in (FROM_ROBOT, TO_ROBOT):
                s = [m.json()["seq"] for m in rec.topic(topic) if m.json()["dir"] == d]
                assert s == list(range(len(s))), (topic, d)

    # The buses' own sequence numbers: range frames per kind (u16), MAVLink (u8).
    per_kind: dict[RangeKind, list[int]] = {RangeKind.IR: [], RangeKind.SONAR: []}
    for m in rec.topic("/bus/serial/rangefinders"):
        frame = decode_range_frame(m.frame_bytes())
        assert isinstance(frame, RangeFrame), frame
        per_kind[frame.kind].append(frame.seq)
        assert frame.t_us == round(m.t * 1e6) & 0xFFFFFFFF
    for kind, seqs in per_kind.items():
        assert len(seqs) > 100
        assert seqs == [(seqs[0] + i) & 0xFFFF for i in range(len(seqs))], kind
    mav = [m.frame_bytes() for m in rec.topic("/bus/mavlink") if m.json()["dir"] == FROM_ROBOT]
    assert all(f[0] == 0xFD for f in mav)  # MAVLink 2, one message per frame
    assert [f[4] for f in mav] == [(mav[0][4] + i) & 0xFF for i in range(len(mav))]
    codec = KoalaCanCodec()
    for m in rec.topic("/bus/can"):
        d = m.json()
        msg = can.Message(arbitration_id=d["can_id"], is_extended_id=d["extended"],
                          data=m.frame_bytes())
        assert not isinstance(codec.decode(msg), Reject)


def test_both_directions_of_kteam_recorded(run60: RecordedRun, rec: Recording) -> None:
    frames = rec.topic("/bus/serial/kteam")
    to_robot = b"".join(m.frame_bytes() for m in frames if m.json()["dir"] == TO_ROBOT)
    from_robot = b"".join(m.frame_bytes() for m in frames if m.json()["dir"] == FROM_ROBOT)
    assert to_robot == b"".join(KTEAM_COMMANDS)
    assert from_robot == b"".join(reply for _, reply in run60.kteam_exchanges)


def test_bundle_agrees_one_for_one_with_the_recording(rec: Recording, tmp_path: Path) -> None:
    out = export_bundle(rec.path, tmp_path / "bundle")

    def rows(name: str) -> list[dict[str, str]]:
        with (out / name).open(newline="") as f:
            return list(csv.DictReader(f))

    for name, topic, cols in (
        ("odometry.csv", "sensors/odometry", ("t", "left_ticks", "right_ticks")),
        ("gyro.csv", "sensors/gyro", ("t", "yaw_rate")),
        ("compass.csv", "sensors/compass", ("t", "mx", "my", "mz")),
        ("truth_pose.csv", "truth/pose", ("t", "x", "y", "theta")),
    ):
        got = [[float(r[c]) for c in cols] for r in rows(name)]
        want = [[float(m.json()[c]) for c in cols] for m in rec.topic(topic)]
        assert got == want, name
    ranges = rows("range.csv")
    sonar = [m.json() for m in rec.topic("sensors/sonar")]
    ir = [m.json() for m in rec.topic("sensors/ir")]
    assert len(ranges) == sum(len(m["ranges"]) for m in sonar) + sum(len(m["counts"]) for m in ir)
    got_sonar = [(float(r["t"]), int(r["sensor"]), r["measured"], r["true_range"])
                 for r in ranges if r["kind"] == "sonar"]
    want_sonar = [(m["t"], i, "" if v is None else repr(v),
                   "" if m["truth"]["ranges"][i] is None else repr(m["truth"]["ranges"][i]))
                  for m in sonar for i, v in enumerate(m["ranges"])]
    assert got_sonar == want_sonar
    assert [int(r["measured"]) for r in ranges if r["kind"] == "ir"] == [
        c for m in ir for c in m["counts"]
    ]
    # IR rows carry the axis range and incidence of the message's truth companion.
    def cell(v: float | None) -> str:
        return "" if v is None else repr(v)

    assert [(r["true_range"], r["incidence_angle"]) for r in ranges if r["kind"] == "ir"] == [
        (cell(rng), cell(inc)) for m in ir
        for rng, inc in zip(m["truth"]["ranges"], m["truth"]["incidence"], strict=True)
    ]
    meta = json.loads((out / "meta.json").read_text())
    assert meta["seed"] == json.loads(rec.metadata["koala-bridge"]["config"])["sim"]["seed"]
    assert meta["config_path"].endswith("default.toml")
    assert (out / "landmark_map.csv").exists() and (out / "landmarks.csv").exists()


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGTERM], ids=["SIGKILL", "SIGTERM"])
def test_run_killed_while_recording_leaves_a_readable_file(
    sig: int, bridge: Callable[..., BridgeProcess], tmp_path: Path
) -> None:
    path = tmp_path / "killed.mcap"
    b = bridge(clock="realtime", extra=["--record", str(path)])
    deadline = time.monotonic() + 20
    # a few chunks (the Foxglove scene channels fill them too)
    while path.stat().st_size < 80_000 and time.monotonic() < deadline:
        time.sleep(0.1)
    b.stop(sig)
    rec = open_recording(path)
    assert rec.complete == (sig == signal.SIGTERM)
    gyro = rec.topic("sensors/gyro")
    assert len(gyro) > 50
    assert [m.sequence for m in gyro] == list(range(len(gyro)))
    if sig == signal.SIGTERM:
        with path.open("rb") as f:
            summary = make_reader(f).get_summary()
        assert summary is not None and summary.statistics is not None
        assert summary.statistics.message_count == len(rec.messages)
