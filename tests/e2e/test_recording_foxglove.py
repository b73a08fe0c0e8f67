"""`run --record` writes the scene in Foxglove's standard schemas beside the raw bus frames:
each scene channel has its foxglove.* protobuf schema and every message decodes with it, the
truth pose agrees with the recorded JSON at the same time, the static map comes back every
STATIC_PERIOD_S; export, replay and calibrate read such a recording, and a recording made
before the scene existed (tests/data/recordings/before-foxglove.mcap) still opens, exports and
replays."""

from __future__ import annotations

import math
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest
from _foxglove import protobuf_decoder
from _recorded_run import RecordedRun, record_run
from conftest import REPO, bridge_command
from koala_bridge.recording.export import export_bundle
from koala_bridge.recording.mcap_file import open_recording
from koala_bridge.runtime.foxglove_io import STATIC_PERIOD_S
from koala_bridge.runtime.replay import ZENOH, plan_replay
from mcap.reader import make_reader

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

DATA = Path(__file__).resolve().parents[1] / "data" / "recordings"
DURATION_S = 12.0

SCENE_SCHEMAS = {
    "/world/map": "foxglove.SceneUpdate",
    "/world/grid": "foxglove.Grid",
    "/koala/body": "foxglove.SceneUpdate",
    "/koala/truth/tf": "foxglove.FrameTransform",
    "/koala/truth/pose": "foxglove.PoseInFrame",
    "/koala/estimate/tf": "foxglove.FrameTransform",
    "/koala/estimate/pose": "foxglove.PoseInFrame",
    "/koala/estimate/odometry": "foxglove.Odometry",
    "/koala/estimate/uncertainty": "foxglove.SceneUpdate",
    "/koala/estimate/grid": "foxglove.Grid",
    "/koala/map/occupancy": "foxglove.Grid",
    "/koala/sensors/ir": "foxglove.SceneUpdate",
    "/koala/sensors/sonar": "foxglove.SceneUpdate",
    "/koala/sensors/sonar/scan": "foxglove.PointCloud",
    "/koala/sensors/camera": "foxglove.SceneUpdate",
    "/koala/sensors/compass": "foxglove.SceneUpdate",
    "/koala/log": "foxglove.Log",
}


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RecordedRun]:
    yield record_run(tmp_path_factory.mktemp("fox"), duration_s=DURATION_S)


def test_scene_channels_have_foxglove_schemas_and_decode(run: RecordedRun) -> None:
    decoded: dict[str, list[tuple[int, object]]] = {}
    with run.path.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        scene = {}
        for ch in summary.channels.values():
            schema = summary.schemas[ch.schema_id]
            if ch.topic in SCENE_SCHEMAS:
                assert (schema.encoding, ch.message_encoding) == ("protobuf", "protobuf")
                scene[ch.topic] = schema.name
            else:   # the bridge's own channels are as before
                assert (schema.encoding, ch.message_encoding) == ("jsonschema", "json")
        assert scene == SCENE_SCHEMAS
        decoders = {}
        for schema, channel, message in reader.iter_messages(topics=list(SCENE_SCHEMAS)):
            decode = decoders.setdefault(
                channel.topic, protobuf_decoder(schema.name, schema.data))
            decoded.setdefault(channel.topic, []).append((message.log_time, decode(message.data)))
    assert set(decoded) == set(SCENE_SCHEMAS)

    # the static map: at t = 0 and again every STATIC_PERIOD_S
    times = [t for t, _ in decoded["/world/map"]]
    assert times == [round(k * STATIC_PERIOD_S * 1e9)
                     for k in range(len(times))] and len(times) >= DURATION_S // STATIC_PERIOD_S

    # the truth pose: the recorded JSON's of the same time, once each
    rec = open_recording(run.path)
    truth = {m.log_time_ns: m.json() for m in rec.topic("truth/pose")}
    poses = decoded["/koala/truth/pose"]
    assert [t for t, _ in poses] == sorted(truth)
    for t, msg in poses:
        want = truth[t]
        p = msg.pose  # type: ignore[attr-defined]
        assert (p.position.x, p.position.y) == (want["x"], want["y"])
        assert 2 * math.atan2(p.orientation.z, p.orientation.w) == pytest.approx(want["theta"])
    # the estimate's covariance in the Odometry's 6 x 6 (x, y, yaw)
    estimates = {m.log_time_ns: m.json() for m in rec.topic("estimate/pose")}
    for t, msg in decoded["/koala/estimate/odometry"][:20]:
        cov, six = estimates[t]["cov"], list(msg.pose_covariance)  # type: ignore[attr-defined]
        assert [six[0], six[1], six[5], six[35]] == [cov[0][0], cov[0][1], cov[0][2], cov[2][2]]


def test_export_replay_calibrate_read_it(run: RecordedRun, tmp_path: Path) -> None:
    rec = open_recording(run.path)
    bundle = export_bundle(run.path, tmp_path / "bundle")
    assert (bundle / "meta.json").exists()
    plan = plan_replay(rec)
    replayed = {f.key for f in plan.frames if f.bus == ZENOH}
    assert replayed and not replayed & {t.lstrip("/") for t in SCENE_SCHEMAS}
    done = subprocess.run(
        bridge_command("calibrate", str(run.path), "--out", str(tmp_path / "cal")),
        cwd=REPO, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]


def test_recording_from_before_the_scene_still_opens(tmp_path: Path) -> None:
    old = DATA / "before-foxglove.mcap"
    rec = open_recording(old)
    assert rec.complete and not set(rec.topics) & set(SCENE_SCHEMAS)
    assert (export_bundle(old, tmp_path / "bundle") / "meta.json").exists()
    assert any(f.bus == ZENOH for f in plan_replay(rec).frames)
