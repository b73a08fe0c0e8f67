"""`koala-bridge run --record` with [[robots]]: the recording holds every robot's Zenoh keys
and bus frames under its name, with the keys' schemas, and every robot's Foxglove scene under
``/<name>/scene`` beside one shared map; it names the robots in its metadata; the endpoints
file holds one entry per robot."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from _foxglove import protobuf_decoder
from conftest import free_port
from koala_bridge.core.topics import IrMessage, TruthPose
from koala_bridge.recording.mcap_file import open_recording
from mcap.reader import make_reader

REPO = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.slow


def test_run_records_every_robot(tmp_path: Path) -> None:
    out, endpoints = tmp_path / "fleet.mcap", tmp_path / "ep.json"
    done = subprocess.run(
        [sys.executable, "-m", "koala_bridge", "run",
         "--config", str(REPO / "examples" / "two_robots.toml"), "--clock", "fast",
         "--duration", "1", "--record", str(out), "--endpoints-file", str(endpoints),
         "--set", f'zenoh.listen=["tcp/127.0.0.1:{free_port()}"]',
         "--set", "localisation.enabled=false",
         "--set", f"buses.mavlink.port={free_port('udp')}"],
        capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stderr
    assert "Simulating 2 robots (alpha, beta)" in done.stdout
    ep = json.loads(endpoints.read_text())
    assert list(ep["robots"]) == ["alpha", "beta"]
    assert ep["robots"]["beta"]["zenoh"]["prefix"] == "koala/beta"
    assert ep["robots"]["alpha"]["serial"]["kteam"] != ep["robots"]["beta"]["serial"]["kteam"]

    rec = open_recording(out)
    robots = json.loads(rec.metadata["koala-bridge"]["robots"])
    assert [r["name"] for r in robots] == ["alpha", "beta"]
    counts = rec.counts()
    for name in ("alpha", "beta"):
        assert counts[f"/{name}/truth/pose"] == 51          # 50 Hz over 1 s, and t = 0
        assert counts[f"/{name}/sensors/ir"] == 21
        assert counts[f"/bus/{name}/can"] > 0
        assert counts[f"/bus/{name}/serial/rangefinders"] > 0
    alpha = [m.json()["x"] for m in rec.topic("/alpha/truth/pose")]
    beta = [m.json()["x"] for m in rec.topic("/beta/truth/pose")]
    assert alpha[0] == 1.3 and beta[0] == 2.2
    with out.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    titles = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
    assert titles["/beta/sensors/ir"] == IrMessage.TITLE
    assert titles["/alpha/truth/pose"] == TruthPose.TITLE

    # the Foxglove scene of every robot: one map, each robot's channels under /<name>/scene
    encodings = {c.topic: (summary.schemas[c.schema_id].encoding, c.message_encoding)
                 for c in summary.channels.values()}
    scene = {t: titles[t] for t, enc in encodings.items() if enc == ("protobuf", "protobuf")}
    assert {t for t in scene if not t.startswith(("/alpha/scene/", "/beta/scene/"))} == {
        "/world/map", "/world/grid"}
    for name in ("alpha", "beta"):
        assert {t.replace(f"/{name}/", "/r/") for t in scene if t.startswith(f"/{name}/")} == {
            "/r/scene/body", "/r/scene/truth/tf", "/r/scene/truth/pose", "/r/scene/estimate/tf",
            "/r/scene/estimate/pose", "/r/scene/estimate/odometry",
            "/r/scene/estimate/uncertainty", "/r/scene/estimate/grid",
            "/r/scene/map/occupancy", "/r/scene/sensors/ir", "/r/scene/sensors/sonar",
            "/r/scene/sensors/sonar/scan", "/r/scene/sensors/camera",
            "/r/scene/sensors/compass", "/r/scene/log"}
        assert scene[f"/{name}/scene/truth/pose"] == "foxglove.PoseInFrame"
        assert scene[f"/{name}/scene/sensors/ir"] == "foxglove.SceneUpdate"
        assert counts[f"/{name}/scene/truth/pose"] == counts[f"/{name}/truth/pose"]
        assert counts[f"/{name}/scene/body"] == 1
    assert counts["/world/map"] == counts["/world/grid"] == 1    # drawn once, not per robot
    with out.open("rb") as f:
        reader = make_reader(f)
        decoded: dict[str, list[tuple[int, object]]] = {}
        topics = ["/alpha/scene/truth/tf", "/beta/scene/truth/tf",
                  "/alpha/scene/truth/pose", "/beta/scene/truth/pose"]
        for schema, channel, message in reader.iter_messages(topics=topics):
            decode = protobuf_decoder(schema.name, schema.data)
            decoded.setdefault(channel.topic, []).append((message.log_time, decode(message.data)))
    for name, xs in (("alpha", alpha), ("beta", beta)):
        pose = decoded[f"/{name}/scene/truth/pose"]
        assert [p.pose.position.x for _, p in pose] == xs     # the JSON truth, message by message
        assert {p.frame_id for _, p in pose} == {"world"}
        assert {tf.child_frame_id for _, tf in decoded[f"/{name}/scene/truth/tf"]} == {
            f"{name}/base_link"}
