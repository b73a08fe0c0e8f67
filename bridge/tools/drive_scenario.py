"""Scripted drives of the bridge's own simulated robot, with the localisation node fed as in a
real run, and the issue-15 figures of its estimate (bench, tests and the figure share this).

:func:`run_scenario` opens one :class:`koala_bridge.runtime.sim_source.SimulatedRobotSource` on a
configuration (``config/default.toml`` by default) on the **fast** clock, every bus open on free
loopback ports (the node reads exactly the bytes the service puts on its buses, plus the camera's
observations, as in ``koala-bridge run``), and drives a scripted sequence of wheel speeds. The
script is applied by :class:`ScriptedArbiter` -- the service's own motor arbiter asked for the
command of each step in the simulation loop's thread -- so a run is one ``service.run`` and the
same for a seed. (Calling ``service.run`` once per segment would not do: every call after the
first starts again from ``Simulator.reset``.) A recorder in memory keeps ``truth/pose``
(50 Hz), every ``estimate/*`` channel (``estimate/pose`` at 20 Hz with its covariance, and
whatever else the node publishes there, e.g. ``estimate/health``) and ``events/fault``.

The **hostile** scenario (:data:`HOSTILE`, 60 s on the default world; start (1.75, 1.75) facing
east; wheel speeds left/right in m/s):

====  ======  ==============  ============  ==================================================
  #   start   segment         left, right   what happens (seed 1)
====  ======  ==============  ============  ==================================================
  1    0.0    settle           0,     0      standing still
  2    1.0    spin left       -0.15, +0.15   ~180° on the spot (1.05 rad/s)
  3    4.0    spin right      +0.15, -0.15   back to east
  4    7.0    straight east   +0.20, +0.20   0.7 m to (2.45, 1.75)
  5   10.5    back up         -0.20, -0.20   back to the start
  6   14.0    arc right       +0.25, +0.10   quarter turn (r 0.33 m) to (2.09, 1.41), facing S
  7   17.0    straight south  +0.20, +0.20   0.4 m
  8   19.0    back north      -0.20, -0.20   0.4 m backwards
  9   21.0    arc back        -0.25, -0.10   the arc backwards, to the start facing east
 10   24.0    wall push       +0.25, +0.25   east; the body (r = 0.19 m) meets the east wall
                                             x = 3.0 at ~28.3 s and the wheels push (and slip)
                                             for ~4.2 s while the encoders keep counting
 11   32.5    back off        -0.20, -0.20   0.6 m off the wall
 12   35.5    spin left       -0.15, +0.15   ~180°, to face west
 13   38.5    straight west   +0.20, +0.20   0.4 m (kidnap variant: at 40 s the robot is put at
                                             (0.75, 0.75) facing north, ~1.5 m away)
 14   40.5    spin 360        +0.20, -0.20   a full turn on the spot (1.4 rad/s)
 15   45.0    arc left        +0.10, +0.25   quarter turn left
 16   48.0    arc back        -0.10, -0.25   and back along it
 17   51.0    straight        +0.10, +0.10   0.3 m
 18   54.0    back up         -0.10, -0.10   0.3 m
 19   57.0    spin left       -0.15, +0.15   ~180°
====  ======  ==============  ============  ==================================================

Every segment after the kidnap has >= 0.1 m of clearance from both places the robot can be in
(with and without the kidnap); the only wall contact is segment 10.
"""

from __future__ import annotations

import math
import socket
import threading
import time
from bisect import bisect_right
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from koala_bridge.core.geometry import wall_clearance
from koala_bridge.core.resources import default_config_path
from koala_bridge.core.topics import EstimatePose, FaultEventMessage, TruthPose
from koala_bridge.estimation.metrics import (
    AlignedPoses,
    KidnapRecovery,
    TrackingMetrics,
    align,
    kidnap_recovery,
    tracking_metrics,
)
from koala_bridge.runtime.localisation import LocalisationSettings
from koala_bridge.runtime.robot_io import MotorArbiter
from koala_bridge.runtime.settings import BridgeSettings, apply_override, load_config
from koala_bridge.runtime.sim_source import SimulatedRobotSource
from koala_bridge.sim.config import load_sim_config
from koala_bridge.sim.types import WheelCommand
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

ESTIMATE_PREFIX = "estimate/"
SCRIPT_SOURCE = "scenario"
CONTACT_CLEARANCE_M = 0.005     # truth body closer than this to a wall: in contact


@dataclass(frozen=True)
class Segment:
    """Constant wheel speeds (m/s) for ``duration_s`` simulated seconds."""

    name: str
    duration_s: float
    left_mps: float
    right_mps: float


@dataclass(frozen=True)
class Kidnap:
    """The robot picked up at ``t_s`` and put at ``(x, y)`` m, heading ``theta_deg`` (None: its
    heading kept): the harness's ``kidnap`` fault (bridge/runtime/faults.py)."""

    t_s: float = 40.0
    x: float = 0.75
    y: float = 0.75
    theta_deg: float | None = 90.0

    def fault(self) -> dict[str, Any]:
        """The ``[[faults]]`` table."""
        table: dict[str, Any] = {"kind": "kidnap", "target": "robot", "start_s": self.t_s,
                                 "x": self.x, "y": self.y}
        if self.theta_deg is not None:
            table["theta_deg"] = self.theta_deg
        return table


HOSTILE: tuple[Segment, ...] = (
    Segment("settle", 1.0, 0.0, 0.0),
    Segment("spin left", 3.0, -0.15, 0.15),
    Segment("spin right", 3.0, 0.15, -0.15),
    Segment("straight east", 3.5, 0.20, 0.20),
    Segment("back up", 3.5, -0.20, -0.20),
    Segment("arc right", 3.0, 0.25, 0.10),
    Segment("straight south", 2.0, 0.20, 0.20),
    Segment("back north", 2.0, -0.20, -0.20),
    Segment("arc back", 3.0, -0.25, -0.10),
    Segment("wall push", 8.5, 0.25, 0.25),
    Segment("back off", 3.0, -0.20, -0.20),
    Segment("spin left", 3.0, -0.15, 0.15),
    Segment("straight west", 2.0, 0.20, 0.20),
    Segment("spin 360", 4.5, 0.20, -0.20),
    Segment("arc left", 3.0, 0.10, 0.25),
    Segment("arc back", 3.0, -0.10, -0.25),
    Segment("straight", 3.0, 0.10, 0.10),
    Segment("back up", 3.0, -0.10, -0.10),
    Segment("spin left", 3.0, -0.15, 0.15),
)
#: the kidnap of the hostile scenario's kidnap variant (>= 1 m from where the robot is at 40 s)
HOSTILE_KIDNAP = Kidnap()

SCENARIOS: dict[str, tuple[Segment, ...]] = {"hostile": HOSTILE}


def segment_times(segments: Sequence[Segment]) -> list[tuple[Segment, float, float]]:
    """Each segment with its start and end time, s."""
    out, t = [], 0.0
    for s in segments:
        out.append((s, t, t + s.duration_s))
        t += s.duration_s
    return out


class ScriptedArbiter(MotorArbiter):
    """The service's motor arbiter, driven by a script: at each step the simulation loop asks
    :meth:`command` for simulated time ``t``, and the segment in force at ``t`` is set (as a
    command from :data:`SCRIPT_SOURCE`). After the last segment the wheels stop."""

    def __init__(self, segments: Sequence[Segment], watchdog_s: float = 0.0) -> None:
        super().__init__(watchdog_s)
        timed = segment_times(segments)
        self._starts = [t0 for _, t0, _ in timed]
        self._end = timed[-1][2] if timed else 0.0
        self._speeds = [(s.left_mps, s.right_mps) for s, _, _ in timed]
        self._current = -1

    def command(self, t: float) -> WheelCommand:
        # 1e-9: segment boundaries are multiples of dt, the loop's t a sum of them
        k = bisect_right(self._starts, t + 1e-9) - 1 if t < self._end - 1e-9 else len(
            self._speeds)
        if k != self._current:
            self._current = k
            left, right = self._speeds[k] if 0 <= k < len(self._speeds) else (0.0, 0.0)
            self.set(left, right, SCRIPT_SOURCE)
        return super().command(t)


class _TimedNode:
    """The localisation node behind a stopwatch: every method call the service makes on it is
    timed in thread CPU time (``time.thread_time``: the loop thread's own work, not the bus
    reader threads' or Zenoh's)."""

    def __init__(self, node: Any) -> None:
        self._node = node
        self.cpu_s = 0.0
        self.calls = 0

    def __getattr__(self, name: str) -> Any:
        attr = getattr(self._node, name)
        if not callable(attr):
            return attr

        def timed(*args: Any, **kwargs: Any) -> Any:
            t0 = time.thread_time()
            try:
                return attr(*args, **kwargs)
            finally:
                self.cpu_s += time.thread_time() - t0
                self.calls += 1

        return timed


class _Recorder:
    """A :class:`koala_bridge.runtime.source.Tap` in memory: truth, every ``estimate/*``
    channel and fault events; bus frames are not kept."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.channels: dict[str, list[tuple[float, Mapping[str, Any]]]] = {}

    def declare(self, keys: Iterable[str] = (), buses: Iterable[str] = ()) -> None:
        pass

    def record(self, channel: str, t: float, payload: Mapping[str, Any]) -> None:
        if (channel in (TruthPose.TOPIC, FaultEventMessage.TOPIC)
                or channel.startswith(ESTIMATE_PREFIX)):
            with self.lock:
                self.channels.setdefault(channel, []).append((t, payload))

    def record_frame(self, bus: str, direction: str, t: float, data: bytes,
                     **fields: object) -> None:
        pass


@dataclass
class ScenarioResult:
    """What one scripted run recorded, and its figures.

    Attributes:
        segments: each segment with its start and end, s.
        truth_t, truth: ``truth/pose`` times ``(T,)`` and poses ``(T, 3)``.
        est_t, estimate, cov: ``estimate/pose`` times, poses ``(N, 3)``, covariances ``(N, 3, 3)``.
        estimates: every ``estimate/*`` channel as recorded, ``[(t, payload), ...]``.
        fault_events: the ``events/fault`` payloads.
        contact: wall-contact intervals of the truth ``[(t0, t1), ...]``.
        walls: ``(M, 4)`` wall segments ``[x0, y0, x1, y1]`` of the world (for plots).
        landmarks: ``(K, 3)`` the world's camera landmarks ``[id, x, y]``.
        kidnap: the kidnap scripted, or None; ``kidnap_from``: where the robot was taken from.
        estimator_cpu_s: loop-thread CPU time spent in the localisation node.
        sim_s, wall_s: simulated and wall seconds of the run.
    """

    seed: int
    segments: list[tuple[Segment, float, float]]
    truth_t: FloatArray
    truth: FloatArray
    est_t: FloatArray
    estimate: FloatArray
    cov: FloatArray
    estimates: dict[str, list[tuple[float, Mapping[str, Any]]]]
    fault_events: list[Mapping[str, Any]]
    contact: list[tuple[float, float]]
    walls: FloatArray
    body_radius_m: float
    kidnap: Kidnap | None
    kidnap_from: tuple[float, float] | None
    estimator_cpu_s: float
    sim_s: float
    wall_s: float
    landmarks: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))

    @property
    def kidnap_distance_m(self) -> float | None:
        """How far the kidnap moved the robot, m (None: no kidnap happened)."""
        if self.kidnap is None or self.kidnap_from is None:
            return None
        return math.hypot(self.kidnap.x - self.kidnap_from[0], self.kidnap.y - self.kidnap_from[1])

    def aligned(self) -> AlignedPoses:
        """Estimate and truth at the estimate's times (no interpolation across the kidnap)."""
        breaks = [] if self.kidnap is None else [self.kidnap.t_s]
        return align(self.truth_t, self.truth, self.est_t, self.estimate, self.cov, breaks)

    def metrics(self, start: float = -math.inf, end: float = math.inf) -> TrackingMetrics:
        """RMSE, heading RMSE and NEES over ``start <= t < end``."""
        return tracking_metrics(self.aligned().window(start, end))

    def recovery(self, threshold_m: float = 0.2, hold_s: float = 1.0) -> KidnapRecovery | None:
        """When the estimate came back after the kidnap (None: no kidnap in this run)."""
        if self.kidnap is None:
            return None
        a = self.aligned()
        return kidnap_recovery(a.t, a.position_error, self.kidnap.t_s, threshold_m, hold_s)

    def cpu_per_sim_s_ms(self) -> float:
        """The estimator's CPU cost per simulated second, ms."""
        return 1000.0 * self.estimator_cpu_s / self.sim_s if self.sim_s > 0 else math.nan


def _free_port(kind: int) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def scenario_config(config_path: str | Path | None = None, seed: int = 1,
                    kidnap: Kidnap | None = None,
                    overrides: Sequence[tuple[list[str], Any]] = (),
                    start_from_prior: bool = False) -> dict[str, Any]:
    """The configuration of a scenario run: ``config_path`` on the fast clock with ``seed``,
    the localisation node on, every bus on free loopback ports, plus the kidnap fault (added
    to the file's ``[[faults]]``) and ``overrides`` (``(["section", "key"], value)``).

    ``start_from_prior``: the estimator's initial pose is the world's start plus one draw from
    its own prior, ``N(0, diag(sxy^2, sxy^2, sth^2))`` (``[localisation] initial_sigma_*``),
    seeded by ``seed``. A NEES test is a test of consistency only when the initial error is
    distributed as the initial covariance says (Bar-Shalom, Li & Kirubarajan, "Estimation with
    Applications to Tracking and Navigation", 2001, sec. 5.4: the filter is initialised from a
    draw of the prior); an exact start against a 2 cm / 3 deg prior makes the first seconds'
    NEES near 0, below the band, whatever the filter does.
    """
    config = load_config(default_config_path() if config_path is None else config_path)
    if start_from_prior:
        config = apply_override(config, ["localisation", "initial_pose"],
                                _drawn_start(config, seed))
    for key, value in (
        (["run", "clock"], "fast"),
        (["run", "duration_s"], 0.0),
        (["sim", "seed"], seed),
        (["zenoh", "listen"], [f"tcp/127.0.0.1:{_free_port(socket.SOCK_STREAM)}"]),
        (["zenoh", "connect"], []),
        (["buses", "mavlink", "port"], _free_port(socket.SOCK_DGRAM)),
        (["buses", "can", "socketcand_port"], 0),
        (["localisation", "enabled"], True),
        *overrides,
    ):
        config = apply_override(config, key, value)
    if kidnap is not None:
        config["faults"] = [*config.get("faults", []), kidnap.fault()]
    return config


def _drawn_start(config: dict[str, Any], seed: int) -> list[float]:
    """The world's start plus one draw of the localisation prior (:func:`scenario_config`):
    ``[x, y, theta_deg]`` for ``[localisation] initial_pose``."""
    loc = LocalisationSettings.from_config(config)
    start = load_sim_config(config).world.start
    if loc is None or start is None:
        raise ValueError("start_from_prior needs [localisation] and a world with a start pose")
    # its own stream: the run's noise streams (seeded by the same seed) stay as they were
    rng = np.random.default_rng([seed, 0x5EED_0F_12])
    dx, dy = rng.normal(0.0, loc.initial_sigma_xy_m, 2)
    dth = rng.normal(0.0, loc.initial_sigma_theta_deg)
    return [start.x + float(dx), start.y + float(dy), math.degrees(start.theta) + float(dth)]


def run_scenario(segments: Sequence[Segment] = HOSTILE, *, seed: int = 1,
                 kidnap: Kidnap | None = None, config_path: str | Path | None = None,
                 overrides: Sequence[tuple[list[str], Any]] = (),
                 on_service: Callable[[SimulatedRobotSource], None] | None = None,
                 start_from_prior: bool = False,
                 ) -> ScenarioResult:
    """Drive ``segments`` on the bridge's simulated robot (module docstring) and record.

    Args:
        segments: the script; the run lasts their total duration.
        seed: the run's seed (``[sim] seed``: every noise stream and the faults' draws).
        kidnap: optional kidnap fault; it must fall inside the run.
        config_path: the configuration file (None: the shipped ``default.toml``).
        overrides: more ``(key parts, value)`` settings.
        on_service: called with the opened service before it runs (e.g. to inspect it).
        start_from_prior: start the estimator from a draw of its prior (:func:`scenario_config`).
    """
    duration = sum(s.duration_s for s in segments)
    if kidnap is not None and not 0.0 < kidnap.t_s < duration:
        raise ValueError(f"kidnap t_s {kidnap.t_s:g} is outside the run (0, {duration:g}) s")
    config = scenario_config(config_path, seed, kidnap, overrides, start_from_prior)
    recorder = _Recorder()
    settings = BridgeSettings.from_config(config)
    service = SimulatedRobotSource(config, settings, tap=recorder)
    service.arbiter = ScriptedArbiter(segments, settings.buses.motor_watchdog_s)
    if service.localisation is None:
        raise ValueError("the scenario needs the localisation node ([localisation] enabled)")
    timer = _TimedNode(service.localisation)
    service.localisation = timer  # type: ignore[assignment]
    walls = np.asarray(service.sim.walls.segments, dtype=float).copy()
    radius = float(service.sim.config.robot.body_radius_m)
    landmarks = np.array([[m.id, m.x, m.y] for m in service.sim.world.landmarks],
                         dtype=float).reshape(-1, 3)
    service.open()
    try:
        if on_service is not None:
            on_service(service)
        w0 = time.perf_counter()
        last = service.run(threading.Event(), duration_s=duration)
        wall_s = time.perf_counter() - w0
    finally:
        service.close()
    channels = recorder.channels
    truth_t, truth = _poses(channels.get(TruthPose.TOPIC, []))
    est = channels.get(EstimatePose.TOPIC, [])
    est_t, estimate = _poses(est)
    cov = np.array([m["cov"] for _, m in est], dtype=float).reshape(-1, 3, 3)
    events = [m for _, m in channels.get(FaultEventMessage.TOPIC, [])]
    kidnap_from = None
    for e in events:
        if e.get("kind") == "kidnap":
            frm = e.get("detail", {}).get("from")
            if frm is not None:
                kidnap_from = (float(frm[0]), float(frm[1]))
    return ScenarioResult(
        seed=seed,
        segments=segment_times(segments),
        truth_t=truth_t, truth=truth, est_t=est_t, estimate=estimate, cov=cov,
        estimates={k: v for k, v in channels.items() if k.startswith(ESTIMATE_PREFIX)},
        fault_events=events,
        contact=contact_intervals(truth_t, truth, walls, radius),
        walls=walls, body_radius_m=radius,
        kidnap=kidnap if kidnap_from is not None else None, kidnap_from=kidnap_from,
        estimator_cpu_s=timer.cpu_s, sim_s=float(last.t), wall_s=wall_s, landmarks=landmarks,
    )


def _poses(samples: Sequence[tuple[float, Mapping[str, Any]]]) -> tuple[FloatArray, FloatArray]:
    t = np.array([m["t"] for _, m in samples], dtype=float)
    p = np.array([[m["x"], m["y"], m["theta"]] for _, m in samples], dtype=float).reshape(-1, 3)
    return t, p


def contact_intervals(t: FloatArray, truth: FloatArray, walls: FloatArray, radius: float,
                      clearance_m: float = CONTACT_CLEARANCE_M) -> list[tuple[float, float]]:
    """The intervals in which the true body circle is within ``clearance_m`` of a wall."""
    if t.size == 0:
        return []
    touching = wall_clearance(truth, walls) - radius < clearance_m
    out: list[tuple[float, float]] = []
    start: float | None = None
    for k in range(t.size):
        if touching[k] and start is None:
            start = float(t[k])
        elif not touching[k] and start is not None:
            out.append((start, float(t[k - 1])))
            start = None
    if start is not None:
        out.append((start, float(t[-1])))
    return out
