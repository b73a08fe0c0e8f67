"""monitor and snapshot against a Zenoh stand-in for the bridge (the documented keys, loopback)."""

from __future__ import annotations

import argparse
import json
import math
import threading
import time
import tomllib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import zenoh
from _mpl import fonts_loaded  # noqa: F401 - autouse fixture
from conftest import DEFAULT_CONFIG, free_port
from koala_bridge.cli import monitor as monitor_cli
from koala_bridge.cli import snapshot as snapshot_cli
from koala_bridge.core.topics import EstimateGrid, OccupancyMap, TopicError, WorldMessage
from koala_bridge.estimation.messages import grid_message, occupancy_message
from koala_bridge.sim.world import World
from koala_bridge.tools.monitor import MonitorState, render_status, wrap_angle
from koala_bridge.tools.snapshot import (
    Scene,
    SceneCollector,
    draw_scene,
    grid_array,
    render_scene,
)
from matplotlib.image import imread

PREFIX = "koala/standin"


def default_world() -> dict:
    with DEFAULT_CONFIG.open("rb") as f:
        world = World.from_dict(tomllib.load(f)["world"])
    return WorldMessage.of(world, {"ticks_per_metre": 90284.0, "wheel_base_m": 0.3}).to_json()


@dataclass
class StandIn:
    endpoint: str
    world: dict


@pytest.fixture
def standin() -> Iterator[StandIn]:
    """A peer session on tcp/127.0.0.1:<free port> publishing what the bridge publishes."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    world = default_world()
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("listen/endpoints", json.dumps([endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(conf)
    queryable = session.declare_queryable(
        f"{PREFIX}/world", lambda q: q.reply(f"{PREFIX}/world", json.dumps(world))
    )
    stop = threading.Event()
    rows, cols = world["rows"], world["cols"]

    def publish() -> None:
        k = 0
        while not stop.is_set():
            t = k * 0.02
            x, y, th = 1.75 + 0.5 * math.cos(t), 1.75 + 0.5 * math.sin(t), wrap_angle(t + 1.57)

            def put(key: str, msg: dict, t: float = t) -> None:
                session.put(f"{PREFIX}/{key}", json.dumps({"t": t, **msg}))

            put("truth/pose", {"x": x, "y": y, "theta": th})
            put("estimate/pose", {"x": x + 0.1, "y": y - 0.05, "theta": th + 0.1})
            put("sensors/gyro", {"yaw_rate": 1.0, "truth": {"yaw_rate": 1.0}})
            if k % 5 == 0:
                belief = np.full((rows, cols), 0.01)
                belief[int(y / 0.5), int(x / 0.5)] = 0.8
                session.put(f"{PREFIX}/estimate/grid", json.dumps(grid_message(t, belief, 0.5)))
                put("status", {"real_time_factor": 1.0,
                               "buses": {"can": {"sent": k, "received": 3, "rejected": 2}}})
            k += 1
            stop.wait(0.02)

    thread = threading.Thread(target=publish, name="standin-publisher")
    thread.start()
    try:
        yield StandIn(endpoint, world)
    finally:
        stop.set()
        thread.join()
        queryable.undeclare()
        session.close()


def _args(module, argv: list[str]) -> argparse.Namespace:  # type: ignore[no-untyped-def]
    parser = argparse.ArgumentParser()
    module.add_arguments(parser)
    return parser.parse_args(argv)


def test_monitor_once_shows_streams_pose_error_and_buses(
    standin: StandIn, capsys: pytest.CaptureFixture[str]
) -> None:
    args = _args(monitor_cli, ["--connect", standin.endpoint, "--prefix", PREFIX,
                               "--once", "--duration", "1.0"])
    assert monitor_cli.run(args) == 0
    out = capsys.readouterr().out
    for text in ("sensors/gyro", "truth/pose", "estimate/pose", "estimate/grid", "error",
                 "real-time factor 1.00", "can"):
        assert text in out, text


def test_monitor_live_runs_for_its_duration(standin: StandIn) -> None:
    args = _args(monitor_cli, ["--connect", standin.endpoint, "--prefix", PREFIX,
                               "--duration", "0.8", "--refresh-hz", "10"])
    t0 = time.monotonic()
    assert monitor_cli.run(args) == 0
    assert 0.8 <= time.monotonic() - t0 < 5


def test_monitor_state_rates() -> None:
    now = [0.0]
    state = MonitorState(clock=lambda: now[0])
    for k in range(100):  # 50 Hz wall, 10 Hz simulation (a 5x fast clock)
        now[0] = k * 0.02
        state.on_message("sensors/gyro", json.dumps({"t": k * 0.1, "yaw_rate": 0}).encode())
    state.on_message("sensors/gyro", b"not json")
    s = state.snapshot()["sensors/gyro"]
    assert s.count == 101 and s.bad == 1
    assert s.wall_rate(now[0]) == pytest.approx(50, rel=0.02)
    assert s.sim_rate() == pytest.approx(10)
    state.on_message("status", json.dumps({"t": 1, "real_time_factor": 4.9, "buses": {
        "serial/kteam": {"sent": 1, "received": 2, "rejected": 0}}}).encode())
    table = render_status(state.snapshot())
    assert "4.90" in str(table.title) and table.row_count == 1


def test_snapshot_draws_world_truth_estimate_and_belief(standin: StandIn, tmp_path: Path) -> None:
    out = tmp_path / "snap.png"
    args = _args(snapshot_cli, ["--out", str(out), "--connect", standin.endpoint,
                                "--prefix", PREFIX, "--listen", "0.5"])
    assert snapshot_cli.run(args) == 0
    img = imread(out)
    assert img.shape[0] > 500 and img.shape[1] > 500
    rgb = img[..., :3]

    def pixels_near(colour: tuple[float, float, float]) -> int:
        return int((np.abs(rgb - np.array(colour)).max(axis=2) < 0.06).sum())

    assert pixels_near((0.173, 0.627, 0.173)) > 50  # tab:green, truth
    assert pixels_near((0.839, 0.153, 0.157)) > 50  # tab:red, estimate
    assert pixels_near((0.0, 0.0, 0.0)) > 1000  # walls


def test_snapshot_without_a_bridge_fails_clearly(tmp_path: Path) -> None:
    args = _args(snapshot_cli, ["--out", str(tmp_path / "x.png"), "--connect",
                                f"tcp/127.0.0.1:{free_port()}", "--timeout", "0.5",
                                "--listen", "0.1"])
    assert snapshot_cli.run(args) != 0
    assert not (tmp_path / "x.png").exists()


def test_grid_array_reads_the_published_grids() -> None:
    belief = grid_array(EstimateGrid.parse(grid_message(0.0, [[0, 1, 2], [3, 4, 5]], 0.5)))
    assert belief is not None and belief.shape == (2, 3)
    assert belief[1, 0] == 3  # row-major from the south-west corner
    occupancy = grid_array(OccupancyMap.parse(occupancy_message(0.0, [[0.0, 4.0]], 0.1, 4.0)))
    assert occupancy is not None and occupancy.shape == (1, 2)
    assert occupancy[0, 0] == 0.5 and occupancy[0, 1] > 0.95  # P(occupied); 0.5 unknown
    short = {**grid_message(0.0, [[1, 2, 3]], 0.5), "rows": 2}  # data holds 3 of 2x3 cells
    assert grid_array(EstimateGrid.parse(short)) is None
    assert grid_array(None) is None


def test_snapshot_collector_keeps_only_the_grid_messages_shapes() -> None:
    collector = SceneCollector()
    good = grid_message(0.0, [[0.1, 0.9]], 0.5)
    collector.on_message("estimate/grid", json.dumps(good).encode())
    collector.on_message("estimate/grid", json.dumps({"belief": [[1, 2]]}).encode())
    assert collector.scene.belief == EstimateGrid.from_json(good)  # the other shape is left out
    occ = occupancy_message(1.0, [[0.0, 1.0]], 0.1, 4.0)
    collector.on_message("map/occupancy", json.dumps(occ).encode())
    assert collector.scene.occupancy == OccupancyMap.from_json(occ)
    collector.scene.world = default_world()
    fig = draw_scene(collector.scene)
    assert [a.get_ylabel() for a in fig.axes[1:]] == ["P(occupied)", "belief"]  # both drawn


def test_snapshot_refuses_a_world_of_another_shape() -> None:
    with pytest.raises(TopicError, match="world"):
        draw_scene(Scene(world={"cols": 1, "rows": 1, "cell_m": 0.5}))


def _green_red_pixels(scene: Scene, path: Path) -> tuple[int, int]:
    rgb = imread(render_scene(scene, path))[..., :3]

    def near(colour: tuple[float, float, float]) -> int:
        return int((np.abs(rgb - np.array(colour)).max(axis=2) < 0.06).sum())

    return near((0.173, 0.627, 0.173)), near((0.839, 0.153, 0.157))  # tab:green, tab:red


def test_snapshot_truth_stays_visible_under_an_identical_estimate(tmp_path: Path) -> None:
    # A perfect estimate lies exactly on the truth: the truth must not vanish under it.
    world = default_world()
    trail = [(0.1 * k, 1.75 + 0.02 * k, 1.75, 0.3) for k in range(20)]
    green_alone, _ = _green_red_pixels(Scene(world=world, truth=trail), tmp_path / "t.png")
    green, red = _green_red_pixels(
        Scene(world=world, truth=trail, estimate=list(trail)), tmp_path / "te.png")
    assert green_alone > 200
    assert green > 0.6 * green_alone, (green, green_alone)  # most of the truth still shows
    assert red > 50  # and so does the estimate


def test_snapshot_labels_stay_inside_and_clear_of_the_north_arrow() -> None:
    world = default_world()
    fig = draw_scene(Scene(world=world))
    renderer = fig.canvas.get_renderer()  # type: ignore[attr-defined]
    ax = fig.axes[0]
    inside = ax.get_window_extent(renderer)
    texts = [a for a in ax.get_children() if (a.get_gid() or "").startswith("landmark-label-")]
    north = [a.get_window_extent(renderer) for a in ax.get_children() if a.get_gid() == "north"]
    assert len(texts) == len(world["landmarks"]) and len(north) == 2  # arrow and its "N"
    boxes = [t.get_window_extent(renderer) for t in texts]
    for text, box in zip(texts, boxes, strict=True):
        label = text.get_text()  # type: ignore[attr-defined]
        assert inside.contains(box.x0, box.y0) and inside.contains(box.x1, box.y1), label
        assert not any(box.overlaps(n) for n in north), label
    for i, a in enumerate(boxes):
        assert not any(a.overlaps(b) for b in boxes[i + 1 :])
