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


# -- export and replay of one robot of a fleet's recording (--robot) ----------------------------

@pytest.fixture(scope="module")
def fleet_recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("fleet") / "two.mcap"
    done = subprocess.run(
        [sys.executable, "-m", "koala_bridge", "run",
         "--config", str(REPO / "examples" / "two_robots.toml"), "--clock", "fast",
         "--duration", "2", "--record", str(out),
         "--set", f'zenoh.listen=["tcp/127.0.0.1:{free_port()}"]',
         "--set", "localisation.enabled=false", "--set", "buses.mavlink.port=0"],
        capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stderr
    return out


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "koala_bridge", *args],
                          capture_output=True, text=True, timeout=120, check=False)


def test_export_of_a_fleet_recording_names_its_robots(fleet_recording: Path,
                                                      tmp_path: Path) -> None:
    for command in (["export", str(fleet_recording), "--bundle", str(tmp_path / "b")],
                    ["replay", str(fleet_recording), "--no-zenoh"]):
        done = _cli(*command)
        assert done.returncode == 2
        assert done.stderr.strip().splitlines() == [
            f"koala-bridge {command[0]}: two.mcap is a recording of 2 robots (alpha, beta): "
            "choose one with --robot NAME"]
    done = _cli("export", str(fleet_recording), "--bundle", str(tmp_path / "b"), "--robot", "bet")
    assert done.returncode == 2
    assert "no robot 'bet' (its robots: alpha, beta); did you mean 'beta'?" in done.stderr
    assert not (tmp_path / "b").exists()


def test_export_one_robot_of_a_fleet_recording(fleet_recording: Path, tmp_path: Path) -> None:
    rec = open_recording(fleet_recording)
    for name, x0, theta0 in (("alpha", 1.3, 0.0), ("beta", 2.2, 3.141592653589793)):
        bundle = tmp_path / name
        done = _cli("export", str(fleet_recording), "--bundle", str(bundle), "--robot", name)
        assert done.returncode == 0, done.stderr
        rows = (bundle / "truth_pose.csv").read_text().splitlines()
        assert rows[0] == "t,x,y,theta"
        assert len(rows) - 1 == rec.counts()[f"/{name}/truth/pose"]
        xs = [float(r.split(",")[1]) for r in rows[1:]]
        assert xs == [m.json()["x"] for m in rec.topic(f"/{name}/truth/pose")]
        assert xs[0] == x0
        meta = json.loads((bundle / "meta.json").read_text())
        assert meta["robot"]["start_pose"] == {"x": x0, "y": 1.75, "theta": theta0}
        assert meta["source"].endswith(f", robot {name}")
        assert {"range.csv", "odometry.csv", "gyro.csv", "landmark_map.csv"} <= {
            p.name for p in bundle.iterdir()}


def test_one_robot_view_of_a_fleet_recording(fleet_recording: Path) -> None:
    from koala_bridge.runtime.replay import plan_replay

    rec = open_recording(fleet_recording)
    beta = rec.robot("beta")
    assert "/truth/pose" in beta.topics and "/bus/can" in beta.topics
    assert "/world/map" in beta.topics                     # the world's channels are shared
    assert "/beta/truth/tf" in beta.topics                 # the scene as one robot's, named beta
    assert not [t for t in beta.topics if "alpha" in t or "scene" in t]
    assert {t for t in beta.topics if "beta" in t} == {
        t.replace("/beta/scene/", "/beta/") for t in rec.topics if t.startswith("/beta/scene/")}
    assert beta.robot(None) is beta                        # a one-robot recording now
    assert beta.world is not None and beta.world["start"]["x"] == 2.2
    plan = plan_replay(beta, zenoh=False)
    assert plan.dialect.name == "koala25"                  # beta's firmware, not alpha's
    assert plan_replay(rec.robot("alpha"), zenoh=False).dialect.name == "koala1"
    sent = sum(1 for m in rec.topic("/bus/beta/can") if m.json()["dir"] == "from_robot")
    assert plan.counts["can"] == sent > 0


def test_replay_one_robot_of_a_fleet_recording(fleet_recording: Path) -> None:
    done = _cli("replay", str(fleet_recording), "--robot", "beta", "--no-zenoh", "--speed", "20",
                "--linger", "0", "--set", "buses.mavlink.port=0")
    assert done.returncode == 0, done.stderr
    assert "Replaying two.mcap: can " in done.stdout
    assert "virtual             channel 'koala-beta'" in done.stdout  # beta's own buses
    assert "Replay done: sent can " in done.stdout


def test_robot_option_on_a_one_robot_recording_is_refused(tmp_path: Path) -> None:
    one = REPO / "tests" / "data" / "recordings" / "before-foxglove.mcap"
    done = _cli("export", str(one), "--bundle", str(tmp_path / "b"), "--robot", "alpha")
    assert done.returncode == 2
    assert "is a recording of one robot: --robot alpha applies only" in done.stderr
