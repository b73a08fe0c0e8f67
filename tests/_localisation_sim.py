"""In-process runs of the localisation node on the simulator, through the drivers' encodings.

:class:`BusFeed` does what ``SimulatedRobotSource._emit`` does with a step's readings, minus the
transports: each reading is encoded by the drivers into the bytes the service puts on the buses
(range frames, CAN ``WheelOdometry``/``Gyro`` via the DBC, MAVLink ``SCALED_IMU``) and those bytes
are handed to :meth:`LocalisationNode.on_frame`, which decodes them; the camera (no bus) goes to
``on_camera``. So the node is tested on decoded bus data at simulation speed (the
``--clock fast`` equivalent without ports); tests/e2e/test_localisation_zenoh.py runs the real
service.

The robot is driven by a scripted path in this helper (not in bridge/): one turn on the spot (the
lab's "Find Landmarks" turn, which also lets the node fit the compass's hard iron), then the lab's
full-grid tour of the cell centres (left, up, down, right, else back), back and forth, steered on
the *true* pose so that what is measured is the estimator alone.
"""

from __future__ import annotations

import math
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from koala_bridge.core.geometry import wrap_angle
from koala_bridge.drivers.can_codec import KoalaCanCodec
from koala_bridge.drivers.mavlink_codec import CompassEncoder, MavlinkIdentity
from koala_bridge.drivers.messages import (
    CompassSample,
    GyroFrame,
    RangeFrame,
    RangeKind,
    WheelOdometryFrame,
)
from koala_bridge.drivers.rangeframes import NO_ECHO, encode_range_frame
from koala_bridge.runtime.localisation import LocalisationNode, LocalisationSettings
from koala_bridge.sim.config import load_sim_config
from koala_bridge.sim.simulator import Simulator
from koala_bridge.sim.types import Readings, WheelCommand
from koala_bridge.sim.world import SIDE_STEP, World

ROOT = Path(__file__).resolve().parent.parent
WORLDS = ["lab_walls_1", "lab_walls_2", "lab_walls_3", "lab_trilateration"]


def world_config(world: str, base: str = "default.toml") -> dict[str, Any]:
    """``config/<base>`` with the ``[world]`` of ``config/worlds/<world>.toml``."""
    d = tomllib.loads((ROOT / "config" / base).read_text())
    d["world"] = tomllib.loads((ROOT / "config" / "worlds" / f"{world}.toml").read_text())["world"]
    return d


class BusFeed:
    """A step's readings -> the bytes the bridge puts on its buses -> the node (module doc)."""

    def __init__(self, nodes: list[LocalisationNode]) -> None:
        self.nodes = nodes
        self.can = KoalaCanCodec()
        self.mav = CompassEncoder(MavlinkIdentity(1, 1))
        self.seq = {RangeKind.IR: 0, RangeKind.SONAR: 0}

    def _frame(self, bus: str, t: float, data: bytes, **fields: object) -> None:
        for node in self.nodes:
            node.on_frame(bus, "from_robot", t, data, **fields)

    def _range(self, kind: RangeKind, t: float, readings: tuple[int, ...]) -> None:
        seq = self.seq[kind]
        self.seq[kind] = (seq + 1) & 0xFFFF
        frame = RangeFrame(kind, seq, int(round(t * 1e6)) & 0xFFFFFFFF, readings)
        self._frame("serial/rangefinders", t, encode_range_frame(frame))

    def _can(self, frame: WheelOdometryFrame | GyroFrame, t: float) -> None:
        msg = self.can.encode(frame)
        self._frame("can", t, bytes(msg.data), can_id=msg.arbitration_id,
                    extended=msg.is_extended_id)

    def feed(self, r: Readings) -> None:
        t = r.t
        if r.ir is not None:
            counts = np.clip(np.asarray(r.ir.counts), 0, 1023).astype(int)
            self._range(RangeKind.IR, t, tuple(int(c) for c in counts))
        if r.sonar is not None:
            mm = tuple(NO_ECHO if not math.isfinite(v) else int(min(max(round(v * 1000), 0),
                                                                    0xFFFE))
                       for v in np.asarray(r.sonar.ranges, dtype=float))
            self._range(RangeKind.SONAR, t, mm)
        if r.odometry is not None:
            self._can(WheelOdometryFrame(int(r.odometry.left_ticks), int(r.odometry.right_ticks)),
                      t)
        if r.gyro is not None and math.isfinite(r.gyro.yaw_rate):
            self._can(GyroFrame(max(-20.0, min(20.0, float(r.gyro.yaw_rate)))), t)
        if r.compass is not None:
            m = r.compass.field_uT
            sample = CompassSample(int(round(t * 1000)), float(m[0]), float(m[1]), float(m[2]))
            self._frame("mavlink", t, self.mav.scaled_imu(sample))
        if r.camera is not None:
            for node in self.nodes:
                node.on_camera(t, r.camera.observations)


def coverage_cells(world: World, start: tuple[int, int]) -> list[tuple[int, int]]:
    """The lab's full-grid tour from ``start``: left, up, down, right, else back (seeds/003)."""
    order = ("W", "N", "S", "E")
    back = {"W": "E", "E": "W", "N": "S", "S": "N"}
    cell, visited, moves, path = start, {start}, [], [start]
    while True:
        for s in order:
            n = (cell[0] + SIDE_STEP[s][0], cell[1] + SIDE_STEP[s][1])
            if world.can_move(*cell, s) and n not in visited:
                moves.append(s)
                break
        else:
            if not moves:
                return path
            s = back[moves.pop()]
            n = (cell[0] + SIDE_STEP[s][0], cell[1] + SIDE_STEP[s][1])
        cell = n
        visited.add(cell)
        path.append(cell)


def wheel_command(pose: Any, goal: tuple[float, float], wheel_base: float,
                  vmax: float) -> WheelCommand:
    """Turn on the spot towards ``goal``, then drive at it with a heading correction."""
    dx, dy = goal[0] - pose.x, goal[1] - pose.y
    err = wrap_angle(math.atan2(dy, dx) - pose.theta)
    w = max(-2.0, min(2.0, 3.0 * err))
    v = 0.0 if abs(err) > 0.2 else min(vmax, 0.8 * math.hypot(dx, dy) + 0.02)
    left, right = v - w * wheel_base / 2, v + w * wheel_base / 2
    k = max(1.0, abs(left) / vmax, abs(right) / vmax)
    return WheelCommand(left / k, right / k)


@dataclass
class RunResult:
    world: str
    seconds: float
    wall_s: float
    rmse_m: dict[str, float] = field(default_factory=dict)           # per node label
    heading_rmse_deg: dict[str, float] = field(default_factory=dict)
    max_err_m: dict[str, float] = field(default_factory=dict)
    published: dict[str, dict[str, list[dict[str, Any]]]] = field(default_factory=dict)
    nodes: dict[str, LocalisationNode] = field(default_factory=dict)
    truth: dict[float, tuple[float, float, float]] = field(default_factory=dict)  # t -> pose
    tour_done: bool = False

    def cell_agreement(self, label: str, since: float = 0.0, p_min: float = 0.0) -> float:
        """Share of ``estimate/cell`` messages from ``since`` naming the truth's cell with at
        least ``p_min``."""
        world = self.nodes[label].world
        ok = [m["cell"] == list(world.cell_of(*self.truth[round(m["t"], 6)][:2]))
              and m["p"] >= p_min
              for m in self.published[label]["estimate/cell"] if m["t"] >= since]
        return float(np.mean(ok))

    def occupancy_accuracy(self, label: str) -> tuple[float, int]:
        """Share of the observed occupancy cells classified as the true map has them, and how
        many were observed."""
        occ = self.nodes[label].occupancy
        cls = occ.classify()
        truth = true_occupancy(self.nodes[label].world, occ.rows, occ.cols, occ.resolution_m)
        seen = cls >= 0
        return float(np.mean((cls[seen] == 1) == truth[seen])), int(seen.sum())


def run(world_name: str, seconds: float, seed: int,
        variants: dict[str, dict[str, Any]] | None = None,
        base: str = "default.toml", tours: int | None = None) -> RunResult:
    """Simulate ``seconds`` of the scripted path in ``world_name`` with every error model of
    ``config/<base>``; one node per variant (``{label: {dotted localisation key: value}}``), all
    fed the same frames. ``tours``: stop after that many complete tours (None: run the time)."""
    cfg = world_config(world_name, base)
    variants = variants or {"landmarks": {}, "no_landmarks": {"use_landmarks": False}}
    sim = Simulator(cfg)
    robot = load_sim_config(cfg)
    world = sim.world
    out = RunResult(world_name, seconds, 0.0)
    for label, overrides in variants.items():
        loc = _override(cfg["localisation"], overrides)
        settings = LocalisationSettings.from_dict(loc)
        pub: dict[str, list[dict[str, Any]]] = {}
        out.published[label] = pub
        out.nodes[label] = LocalisationNode(
            settings, robot, lambda k, m, pub=pub: pub.setdefault(k, []).append(m))
    feed = BusFeed(list(out.nodes.values()))
    wb = robot.robot.wheel_base_m
    vmax = robot.robot.max_wheel_speed_mps * 0.25
    assert world.start is not None
    tour = coverage_cells(world, world.cell_of(world.start.x, world.start.y))
    goals = [world.cell_centre(*c) for c in tour]
    gi, done = 0, 0
    spin_until = 2 * math.pi / 1.0 + 1.0  # one turn at 1 rad/s
    truth = out.truth
    t0 = time.perf_counter()
    r = sim.reset(seed=seed)
    for _ in range(int(round(seconds / sim.dt))):
        truth[round(r.t, 6)] = (r.pose.x, r.pose.y, r.pose.theta)
        feed.feed(r)
        if r.t < spin_until:
            cmd = WheelCommand(-0.5 * wb, 0.5 * wb)
        else:
            if math.hypot(goals[gi][0] - r.pose.x, goals[gi][1] - r.pose.y) < 0.03:
                gi += 1
                if gi == len(goals):
                    done += 1
                    if tours is not None and done >= tours:
                        break
                    goals, gi = goals[::-1], 1  # tour back and forth
            cmd = wheel_command(r.pose, goals[gi], wb, vmax)
        r = sim.step(cmd)
    out.wall_s = time.perf_counter() - t0
    out.tour_done = done > 0
    for label, pub in out.published.items():
        e2, h2 = [], []
        for m in pub.get("estimate/pose", []):
            x, y, th = truth[round(m["t"], 6)]
            e2.append((m["x"] - x) ** 2 + (m["y"] - y) ** 2)
            h2.append(wrap_angle(m["theta"] - th) ** 2)
        out.rmse_m[label] = math.sqrt(float(np.mean(e2)))
        out.max_err_m[label] = math.sqrt(float(np.max(e2)))
        out.heading_rmse_deg[label] = math.degrees(math.sqrt(float(np.mean(h2))))
    return out


def _override(loc: dict[str, Any], overrides: dict[str, Any]) -> dict[str, Any]:
    import copy

    out = copy.deepcopy(loc)
    for key, value in overrides.items():
        node = out
        *parents, last = key.split(".")
        for p in parents:
            node = node[p]
        node[last] = value
    return out


def true_occupancy(world: World, rows: int, cols: int, res: float) -> np.ndarray:
    """``(rows, cols)``: True where a wall touches the cell's closed square (the truth the
    occupancy grid is judged against, as in tests/unit/test_estimation_occupancy.py)."""
    truth = np.zeros((rows, cols), dtype=bool)
    tol = 1e-9
    for x0, y0, x1, y1 in world.segments:
        c0 = max(math.floor((min(x0, x1) - tol) / res), 0)
        c1 = min(math.floor((max(x0, x1) + tol) / res), cols - 1)
        r0 = max(math.floor((min(y0, y1) - tol) / res), 0)
        r1 = min(math.floor((max(y0, y1) + tol) / res), rows - 1)
        truth[r0 : r1 + 1, c0 : c1 + 1] = True
    for c, r in world.blocked:
        k = round(world.cell_m / res)
        truth[r * k : (r + 1) * k, c * k : (c + 1) * k] = True
    return truth
