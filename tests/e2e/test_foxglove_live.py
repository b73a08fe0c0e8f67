"""`run --foxglove`: a client speaking the Foxglove WebSocket protocol (tests/_foxglove.py, from
the public specification) subscribes to the map, pose and sonar-scan channels, decodes them
with the protobuf schemas the channels advertise, and finds what Zenoh says (same times, same
values)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
import serial
from _foxglove import FoxgloveClient

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

MAP, POSE, TF, SCAN = ("/world/map", "/koala/truth/pose", "/koala/truth/tf",
                       "/koala/sensors/sonar/scan")
RAW_GYRO = "/sensors/gyro"


def t_ns(stamp: Any) -> int:
    return stamp.seconds * 1_000_000_000 + stamp.nanos


def yaw(q: Any) -> float:
    return 2.0 * math.atan2(q.z, q.w)


@pytest.fixture
def live(bridge, zenoh_watch):  # type: ignore[no-untyped-def]
    b = bridge(clock="realtime", extra=["--foxglove", "127.0.0.1:0"])
    url = b.endpoints["foxglove"]["url"]
    assert url.startswith("ws://127.0.0.1:") and not url.endswith(":0")
    assert f"Foxglove (live view)    {url}" in b.log()
    watch = zenoh_watch(b)
    with serial.Serial(b.endpoints["serial"]["kteam"], 115200, timeout=5) as port:
        port.write(b"D,10,4\r")   # an arc: the pose changes from message to message
        assert port.read_until(b"\r\n").startswith(b"d")
    with FoxgloveClient(url) as client:
        yield b, watch, client


def test_map_pose_and_scan_match_zenoh(live: Any) -> None:
    b, watch, client = live
    client.wait_advertised([MAP, POSE, TF, SCAN, RAW_GYRO])
    assert client.server_info["name"] == "koala-bridge koala"
    schemas = {t: (client.channels[t]["encoding"], client.channels[t]["schemaName"])
               for t in (MAP, POSE, TF, SCAN)}
    assert schemas == {MAP: ("protobuf", "foxglove.SceneUpdate"),
                       POSE: ("protobuf", "foxglove.PoseInFrame"),
                       TF: ("protobuf", "foxglove.FrameTransform"),
                       SCAN: ("protobuf", "foxglove.PointCloud")}
    client.subscribe([MAP, POSE, TF, SCAN, RAW_GYRO])
    got = client.receive(lambda g: len(g.get(MAP, ())) >= 1 and len(g.get(POSE, ())) >= 5
                         and len(g.get(SCAN, ())) >= 3 and len(g.get(RAW_GYRO, ())) >= 5)

    # the map: one wall box per segment of the world queryable, centred on it
    world = watch.query("world")
    scene = got[MAP][0].message
    walls = next(e for e in scene.entities if e.id == "walls")
    assert walls.frame_id == "world"
    centres = sorted((round(c.pose.position.x, 9), round(c.pose.position.y, 9))
                     for c in walls.cubes)
    assert centres == sorted((round((x0 + x1) / 2, 9), round((y0 + y1) / 2, 9))
                             for x0, y0, x1, y1 in world["segments"])
    lengths = sorted(round(c.size.x, 9) for c in walls.cubes)
    assert lengths == sorted(round(math.hypot(x1 - x0, y1 - y0) + 0.02, 9)
                             for x0, y0, x1, y1 in world["segments"])

    # the truth pose (and its transform): Zenoh's truth/pose of the same time, exactly
    watch.after("truth/pose", max(t_ns(r.message.timestamp) for r in got[POSE]) * 1e-9)
    truth = {round(m["t"] * 1e9): m for m in watch.messages["truth/pose"]}
    thetas = set()
    for r in got[POSE]:
        m = truth[t_ns(r.message.timestamp)]
        p = r.message.pose
        assert r.message.frame_id == "world" and r.log_time_ns == t_ns(r.message.timestamp)
        assert (p.position.x, p.position.y) == (m["x"], m["y"])
        assert yaw(p.orientation) == pytest.approx(m["theta"], abs=1e-12)
        thetas.add(m["theta"])
    assert len(thetas) > 1  # the robot turned between them
    for r in got.get(TF, []):
        tf = r.message
        m = truth[t_ns(tf.timestamp)]
        assert (tf.parent_frame_id, tf.child_frame_id) == ("world", "koala/base_link")
        assert (tf.translation.x, tf.translation.y) == (m["x"], m["y"])

    # the sonar scan: each echo of Zenoh's sensors/sonar at its range along its sensor's axis
    watch.after("sensors/sonar", max(t_ns(r.message.timestamp) for r in got[SCAN]) * 1e-9)
    sonar = {round(m["t"] * 1e9): m for m in watch.messages["sensors/sonar"]}
    poses = world["robot"]["sensors"]["sonar"]["poses"]
    for r in got[SCAN]:
        cloud = r.message
        assert cloud.frame_id == "koala/base_link" and cloud.point_stride == 16
        assert [f.name for f in cloud.fields] == ["x", "y", "z", "range"]
        points = np.frombuffer(cloud.data, dtype="<f4").reshape(-1, 4)
        m = sonar[t_ns(cloud.timestamp)]
        echoes = [(p, rng) for p, rng in zip(poses, m["ranges"], strict=True) if rng is not None]
        assert len(points) == len(echoes) > 0
        for (x, y, _z, rng), (pose, want) in zip(points, echoes, strict=True):
            assert rng == pytest.approx(want, rel=1e-6)
            assert x == pytest.approx(pose["x"] + want * math.cos(pose["theta"]), abs=1e-5)
            assert y == pytest.approx(pose["y"] + want * math.sin(pose["theta"]), abs=1e-5)

    # a raw stream for the plots: the bridge's own JSON, as on Zenoh
    gyro = {round(m["t"] * 1e9): m for m in watch.messages.get("sensors/gyro", [])}
    matched = [r for r in got[RAW_GYRO] if round(r.message["t"] * 1e9) in gyro]
    assert matched and all(r.message == gyro[round(r.message["t"] * 1e9)] for r in matched)


def test_time_is_sent_whatever_the_client_subscribes_to(live: Any) -> None:
    """The server's time (op 0x02) is the simulation's, sent to a client subscribed only to the
    pose: the player's clock follows the run without the transform topic open."""
    _, _, client = live
    client.wait_advertised([POSE])
    assert "time" in client.server_info["capabilities"]
    client.subscribe([POSE])
    got = client.receive(lambda g: len(client.times) >= 5 and len(g.get(POSE, ())) >= 2)
    times = client.times
    assert times == sorted(times) and times[-1] > times[0]
    # the simulation's time: the pose's log times are of the same clock
    poses = [r.log_time_ns for r in got[POSE]]
    assert min(poses) <= times[-1] and times[0] <= max(poses) + 1_000_000_000


def test_non_loopback_refused_and_bad_address(bridge: Any, tmp_path: Any) -> None:
    import subprocess

    from conftest import REPO, bridge_command

    for address, words in (("0.0.0.0:0", "not loopback"), ("127.0.0.1:99999", "HOST:PORT"),
                           ("garbage", "--foxglove 'garbage': expected HOST:PORT, e.g. "
                            "127.0.0.1:8765")):
        done = subprocess.run(bridge_command("run", "--foxglove", address), cwd=REPO,
                              capture_output=True, text=True, timeout=120)
        assert done.returncode == 2, done
        lines = done.stderr.strip().splitlines()
        assert len(lines) == 1 and words in lines[0], done.stderr




def test_every_robot_of_a_fleet_on_one_server(bridge: Any) -> None:
    """[[robots]] (examples/two_robots.toml): one server, its URL beside "robots" in the
    endpoints file; one shared map; each robot's scene under /<name>/scene with its own frames,
    each pose what that robot's Zenoh truth says at the same time."""
    from conftest import REPO, ZenohWatch

    b = bridge(clock="realtime", config=REPO / "examples" / "two_robots.toml",
               extra=["--foxglove", "127.0.0.1:0"])
    url = b.endpoints["foxglove"]["url"]
    assert list(b.endpoints["robots"]) == ["alpha", "beta"]
    assert url.startswith("ws://127.0.0.1:") and f"Foxglove (live view)    {url}" in b.log()
    alpha = b.endpoints["robots"]["alpha"]
    assert alpha["zenoh"]["prefix"] == "koala/alpha"
    watch = ZenohWatch(alpha["zenoh"]["endpoints"][0], "koala")  # keys "<name>/truth/pose"
    try:
        with serial.Serial(alpha["serial"]["kteam"], 115200, timeout=5) as port:
            port.write(b"D,10,4\r")   # alpha drives an arc; beta stands
            assert port.read_until(b"\r\n").startswith(b"d")
        names = ("alpha", "beta")
        poses = {n: f"/{n}/scene/truth/pose" for n in names}
        tfs = {n: f"/{n}/scene/truth/tf" for n in names}
        raw = {n: f"/{n}/sensors/gyro" for n in names}
        with FoxgloveClient(url) as client:
            client.wait_advertised([MAP, *poses.values(), *tfs.values(), *raw.values()])
            assert client.server_info["name"] == "koala-bridge alpha, beta"
            for n in names:
                assert client.channels[poses[n]]["schemaName"] == "foxglove.PoseInFrame"
                assert client.channels[tfs[n]]["schemaName"] == "foxglove.FrameTransform"
                assert client.channels[raw[n]]["encoding"] == "json"
            assert not [t for t in client.channels if t.startswith("/koala/")]
            client.subscribe([MAP, *poses.values(), *tfs.values()])
            got = client.receive(lambda g: len(g.get(MAP, ())) >= 1 and all(
                len(g.get(t, ())) >= 5 for t in (*poses.values(), *tfs.values())))
        assert len(got[MAP]) == 1     # one map for both (each robot's body is its own topic)
        for n in names:
            last = max(t_ns(r.message.timestamp) for r in got[poses[n]])
            watch.after(f"{n}/truth/pose", last * 1e-9)
            truth = {round(m["t"] * 1e9): m for m in watch.messages[f"{n}/truth/pose"]}
            for r in got[poses[n]]:
                m = truth[t_ns(r.message.timestamp)]
                p = r.message.pose
                assert r.message.frame_id == "world"
                assert (p.position.x, p.position.y) == (m["x"], m["y"])
                assert yaw(p.orientation) == pytest.approx(m["theta"], abs=1e-12)
            for r in got[tfs[n]]:
                tf, m = r.message, truth[t_ns(r.message.timestamp)]
                assert (tf.parent_frame_id, tf.child_frame_id) == ("world", f"{n}/base_link")
                assert (tf.translation.x, tf.translation.y) == (m["x"], m["y"])
        xs = {n: {r.message.pose.position.x for r in got[poses[n]]} for n in names}
        assert max(xs["alpha"]) < 2.0 < min(xs["beta"])   # two robots, not one drawn twice
        assert len({r.message.pose.orientation.z for r in got[poses["alpha"]]}) > 1  # turning
    finally:
        watch.close()
