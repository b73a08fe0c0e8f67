"""runtime/foxglove_scene.py and foxglove_io.parse_address: the translation of the bridge's
messages into Foxglove's schemas, checked by decoding the encoded bytes with protobuf from the
schema each message class ships (as a Foxglove client does)."""

from __future__ import annotations

import base64
import math
import time
from typing import Any

import numpy as np
import pytest
from _foxglove import protobuf_decoder
from _sim_support import default_config
from koala_bridge.core.errors import ConfigError
from koala_bridge.core.topics import WorldMessage
from koala_bridge.runtime.endpoints import Endpoints
from koala_bridge.runtime.foxglove_io import FoxgloveTap, foxglove_schema, parse_address
from koala_bridge.runtime.foxglove_scene import SceneTranslator
from koala_bridge.sim.simulator import Simulator

pytestmark = pytest.mark.unit


@pytest.fixture(scope="module")
def world() -> dict[str, Any]:
    sim = Simulator(default_config())
    return WorldMessage.of(sim.world, sim.robot_description()).to_json()


def decoded(msg: Any) -> Any:
    """``msg`` (a foxglove.messages object) encoded, then decoded as a client would."""
    schema = type(msg).get_schema()
    return protobuf_decoder(schema.name, bytes(schema.data))(bytes(msg.encode()))


def build(tr: SceneTranslator, key: str, topic: str, payload: dict[str, Any]) -> Any:
    out = next(o for o in tr.outputs(key) if o.topic == topic)
    return decoded(out.build(payload["t"], payload))


def test_map_has_a_box_per_wall_segment_and_the_landmarks(world: dict[str, Any]) -> None:
    scene = decoded(SceneTranslator(world).world_map())
    entities = {e.id: e for e in scene.entities}
    walls = entities["walls"].cubes
    assert len(walls) == len(world["segments"]) > 0
    x0, y0, x1, y1 = world["segments"][0]
    assert (walls[0].pose.position.x, walls[0].pose.position.y) == ((x0 + x1) / 2, (y0 + y1) / 2)
    assert [t.text for t in entities["landmarks"].texts] == [
        f"landmark {lm['id']}" for lm in world["landmarks"]]


def test_world_grid_marks_blocked_cells_row_zero_south(world: dict[str, Any]) -> None:
    w = {**world, "blocked": [[1, 0], [2, 3]]}
    grid = decoded(SceneTranslator(w).world_grid())
    cells = np.frombuffer(grid.data, dtype=np.uint8).reshape(w["rows"], w["cols"])
    assert grid.column_count == w["cols"] and grid.cell_size.x == w["cell_m"]
    assert sorted(zip(*np.nonzero(cells), strict=True)) == [(0, 1), (3, 2)]  # (row, col)


def test_truth_pose_transform_and_pose(world: dict[str, Any]) -> None:
    tr = SceneTranslator(world, "k2")
    p = {"t": 1.25, "x": 0.5, "y": 2.0, "theta": -2.5}
    tf = build(tr, "truth/pose", "/k2/truth/tf", p)
    assert (tf.parent_frame_id, tf.child_frame_id) == ("world", "k2/base_link")
    assert (tf.timestamp.seconds, tf.timestamp.nanos) == (1, 250_000_000)
    assert (tf.translation.x, tf.translation.y) == (0.5, 2.0)
    assert 2 * math.atan2(tf.rotation.z, tf.rotation.w) == pytest.approx(-2.5)
    pose = build(tr, "truth/pose", "/k2/truth/pose", p)
    assert pose.frame_id == "world" and pose.pose.position.y == 2.0


def test_a_fleet_robot_has_its_scene_under_its_namespace(world: dict[str, Any]) -> None:
    """[[robots]]: robot b's topics under /b/scene, its frames b/...; the world's topics drawn
    by one robot only (the others share them)."""
    first = SceneTranslator(world, "a", namespace="/a/scene")
    other = SceneTranslator(world, "b", namespace="/b/scene", world_topics=False)
    assert {"/world/map", "/world/grid", "/a/scene/body", "/a/scene/truth/pose"} <= set(
        first.channels())
    assert [t for t, _ in first.static()] == ["/world/map", "/world/grid", "/a/scene/body"]
    assert [t for t, _ in other.static()] == ["/b/scene/body"]
    assert all(t.startswith("/b/scene/") for t in other.channels())
    assert len(other.channels()) == len(first.channels()) - 2
    tf = build(other, "truth/pose", "/b/scene/truth/tf", {"t": 0.5, "x": 1, "y": 2, "theta": 0})
    assert (tf.parent_frame_id, tf.child_frame_id) == ("world", "b/base_link")
    scan = other.outputs("sensors/sonar")[1]
    assert scan.topic == "/b/scene/sensors/sonar/scan"


def test_estimate_covariance_and_its_ellipse(world: dict[str, Any]) -> None:
    tr = SceneTranslator(world)
    cov = [[0.04, 0.01, 0.002], [0.01, 0.01, 0.003], [0.002, 0.003, 0.09]]
    p = {"t": 2.0, "x": 1.0, "y": 1.5, "theta": 0.3, "cov": cov}
    odo = build(tr, "estimate/pose", "/koala/estimate/odometry", p)
    six = np.array(odo.pose_covariance).reshape(6, 6)
    idx = [0, 1, 5]
    assert six[np.ix_(idx, idx)].tolist() == cov and six[2:5].sum() == 0
    assert odo.body_frame_id == "koala/estimate"
    ellipse = build(tr, "estimate/pose", "/koala/estimate/uncertainty", p).entities[0].spheres[0]
    values, vectors = np.linalg.eigh(np.array(cov)[:2, :2])
    assert ellipse.size.x == pytest.approx(2 * 2 * math.sqrt(values[1]))   # 2 sigma, major
    assert ellipse.size.y == pytest.approx(2 * 2 * math.sqrt(values[0]))
    q = ellipse.pose.orientation
    major = 2 * math.atan2(q.z, q.w)
    assert abs(math.sin(major - math.atan2(vectors[1, 1], vectors[0, 1]))) < 1e-9


def test_sonar_scan_points_at_each_echo(world: dict[str, Any]) -> None:
    tr = SceneTranslator(world)
    poses = world["robot"]["sensors"]["sonar"]["poses"]
    ranges = [0.5 + 0.1 * i for i in range(len(poses))]
    ranges[2] = None
    cloud = build(tr, "sensors/sonar", "/koala/sensors/sonar/scan", {"t": 0.2, "ranges": ranges})
    pts = np.frombuffer(cloud.data, dtype="<f4").reshape(-1, 4)
    echoes = [(p, r) for p, r in zip(poses, ranges, strict=True) if r is not None]
    assert len(pts) == len(echoes)
    for (x, y, _z, r), (pose, want) in zip(pts, echoes, strict=True):
        assert r == pytest.approx(want)
        assert math.hypot(x - pose["x"], y - pose["y"]) == pytest.approx(want, rel=1e-6)
    cones = build(tr, "sensors/sonar", "/koala/sensors/sonar", {"t": 0.2, "ranges": ranges})
    assert len(cones.entities[0].triangles[0].points) == 3 * len(poses)


def test_grids_from_the_estimators(world: dict[str, Any]) -> None:
    tr = SceneTranslator(world)
    belief = np.arange(12, dtype="<f4").reshape(3, 4) / 66
    g = build(tr, "estimate/grid", "/koala/estimate/grid", {
        "t": 1.0, "cols": 4, "rows": 3, "cell_m": 0.5, "encoding": "float32-le",
        "data": base64.b64encode(belief.tobytes()).decode(), "cell": [3, 2], "p": 0.1})
    assert np.frombuffer(g.data, "<f4").tolist() == belief.ravel().tolist()
    assert (g.row_stride, g.cell_stride, g.fields[0].name) == (16, 4, "p")
    q = np.array([-10, 0, 10, 127], dtype=np.int8)
    occ = build(tr, "map/occupancy", "/koala/map/occupancy", {
        "t": 1.0, "cols": 2, "rows": 2, "resolution_m": 0.05, "origin": [0.0, 0.0],
        "encoding": "int8-logodds", "scale": 0.1, "data": base64.b64encode(q.tobytes()).decode()})
    p = np.frombuffer(occ.data, "<f4")
    assert p == pytest.approx(1 / (1 + np.exp(-q * 0.1)), rel=1e-6) and p[1] == 0.5


def test_logs_of_status_and_faults(world: dict[str, Any]) -> None:
    tr = SceneTranslator(world)
    log = build(tr, "status", "/koala/log", {"t": 3.0, "real_time_factor": 2.0, "buses": {
        "can": {"sent": 5, "received": 1, "rejected": 2, "dropped": 0}}})
    assert "can sent 5 received 1 rejected 2 dropped 0" in log.message
    fault = build(tr, "events/fault", "/koala/log", {
        "t": 3.0, "name": "drop:can#1", "kind": "drop", "target": "can", "detail": {"seq": 4}})
    assert fault.level == 3 and fault.message == "drop on can (drop:can#1): seq=4"  # WARNING


class _Recorder:
    def __init__(self) -> None:
        self.rows: list[tuple[str, float, bytes, str]] = []

    def record_encoded(self, topic: str, t: float, data: bytes, schema: Any) -> None:
        self.rows.append((topic, t, data, schema.name))

    def declare_encoded(self, channels: Any) -> None:
        self.rows += [(topic, -1.0, b"", schema.name) for topic, schema in channels]


def test_tap_records_each_message_once_and_a_bad_payload_is_skipped(
        world: dict[str, Any]) -> None:
    rec = _Recorder()
    tap = FoxgloveTap(SceneTranslator(world), recorder=rec)  # type: ignore[arg-type]
    tap.declare(["truth/pose"], [])
    assert ("/koala/log", -1.0, b"", "foxglove.Log") in rec.rows
    rec.rows.clear()
    tap.record("truth/pose", 0.0, {"t": 0.0, "x": 1.0, "y": 1.0, "theta": 0.0})
    tap.record("estimate/pose", 0.01, {"t": 0.01, "x": 1.0, "y": 1.0, "theta": 0.0,
                                       "cov": "not a matrix"})
    tap.record("sensors/gyro", 0.01, {"t": 0.01, "yaw_rate": 0.0})   # no scene: nothing
    topics = [(topic, t) for topic, t, _, _ in rec.rows]
    assert topics[:3] == [("/world/map", 0.0), ("/world/grid", 0.0), ("/koala/body", 0.0)]
    # a payload that cannot be drawn gives no message, the others still go
    assert ("/koala/truth/tf", 0.0) in topics and ("/koala/estimate/tf", 0.01) in topics
    assert not any(topic == "/koala/estimate/odometry" for topic, _ in topics)
    assert foxglove_schema(type(SceneTranslator(world).world_map())).name == "foxglove.SceneUpdate"


@pytest.mark.parametrize("text, expected", [
    ("", ("127.0.0.1", 8765)), ("127.0.0.1:0", ("127.0.0.1", 0)), ("9000", ("127.0.0.1", 9000)),
    ("localhost", ("localhost", 8765)), ("[::1]:8766", ("::1", 8766)),
    (":8767", ("127.0.0.1", 8767)), ("::1", ("::1", 8765)),
])
def test_parse_address(text: str, expected: tuple[str, int]) -> None:
    assert parse_address(text) == expected


@pytest.mark.parametrize("text", ["127.0.0.1:70000", "127.0.0.1:x", "0.0.0.0:8765", "example.org",
                                  "garbage", "gar bage:8765", "1.2.3", "-x.org", "my-host:8768"])
def test_parse_address_refuses(text: str) -> None:
    with pytest.raises(ConfigError):
        parse_address(text)
    if text in ("0.0.0.0:8765", "example.org", "my-host:8768"):
        assert parse_address(text, allow_non_loopback=True)[0] == text.split(":")[0]
    else:
        # not an address at all: a parse error, never "not loopback" (whatever the setting)
        with pytest.raises(ConfigError, match="expected HOST:PORT, e.g. 127.0.0.1:8765"):
            parse_address(text, allow_non_loopback=True)


def test_endpoints_name_the_live_view_only_when_on() -> None:
    assert "foxglove" not in Endpoints().to_json_dict()
    on = Endpoints(foxglove_url="ws://127.0.0.1:8765")
    assert on.to_json_dict()["foxglove"] == {"url": "ws://127.0.0.1:8765"}
    assert "ws://127.0.0.1:8765" in on.describe()


def test_layout_file_names_topics_that_exist(world: dict[str, Any]) -> None:
    """docs/foxglove-layout.json: every 3D topic is one the translator writes, every plotted
    path a field of a bridge topic (the raw streams)."""
    import json
    from pathlib import Path

    from koala_bridge.core.topics import TOPICS

    layout = json.loads((Path(__file__).resolve().parents[2] / "docs"
                         / "foxglove-layout.json").read_text())
    channels = SceneTranslator(world).channels()
    panels = layout["configById"]
    assert set(panels["3D!koala"]["topics"]) <= set(channels)
    assert panels["Log!koala"]["topicToRender"] in channels
    for name, panel in panels.items():
        for path in panel.get("paths", []):
            topic, field = path["value"].split(".", 1)
            cls = TOPICS[topic.strip("/")]
            assert field.split(".")[0].split("[")[0] in cls.__dataclass_fields__, (name, path)



# foxglove-sdk's server runtime keeps sockets open after stop() (its process-wide runtime):
# nothing this test can close, so the descriptor check is off for it alone.
@pytest.mark.no_leak_check
def test_live_topics_wait_for_a_client_and_their_slot() -> None:
    """The live tap skips a key until one of its topics may be due: with no client, a period
    from now (a client that subscribes waits at most that); with one, the topic's next slot."""
    from _foxglove import FoxgloveClient
    from koala_bridge.runtime.foxglove_io import FoxgloveServer

    now = [10.0]
    server = FoxgloveServer("127.0.0.1", 0, clock=lambda: now[0])
    try:
        server.add_channel("/x", {"type": "object"}, rate_hz=20.0)
        assert not server.due("/x") and server.next_due("/x", 10.0) == pytest.approx(10.05)
        with FoxgloveClient(server.url) as client:
            client.wait_advertised(["/x"])
            client.subscribe(["/x"])
            deadline = time.monotonic() + 30
            while not server.subscribed("/x"):
                assert time.monotonic() < deadline
                time.sleep(0.01)
            slots = 0
            while server.due("/x"):     # the first slots catch up to the clock
                slots += 1
            assert slots >= 1 and server.next_due("/x", now[0]) == pytest.approx(10.05)
            now[0] = 10.04
            assert not server.due("/x")
            now[0] = 10.05
            assert server.due("/x") and server.next_due("/x", now[0]) == pytest.approx(10.10)
    finally:
        server.close()
