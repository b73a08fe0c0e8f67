"""Record the simulator: a short run of :class:`sim.simulator.Simulator` into an MCAP recording.

The messages are the bridge's own (``runtime.zenoh_io.sensor_messages`` / ``pose_message``) and go
through :class:`recording.mcap_file.Recorder`, so ``recording.export.export_bundle`` turns
the file into the same bundle a ``koala-bridge run --record`` would give, with the resolved config
in its ``meta.json``. The robot is driven in-process by :func:`weave_command` (no buses, no clock):
a slow weave of alternating turns that stays near the start pose, so both wheel base and tick size
are seen and walls are rarely touched. For tests and benches of the calibration loop.

A tool, not part of ``calibration/``: it needs the bridge's live message builders and the
recorder, and calibration itself reads only files (the layer contracts in pyproject.toml).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from koala_bridge.sim.simulator import Simulator
from koala_bridge.sim.types import WheelCommand

#: Wheel command at time t (s) -> (left, right) surface speeds, m/s.
CommandSchedule = Callable[[float], tuple[float, float]]


def weave_command(
    speed_mps: float = 0.12,
    mean_turn_rad_s: float = 0.5,
    turn_amplitude_rad_s: float = 0.5,
    period_s: float = 7.0,
) -> CommandSchedule:
    """Forward at ``speed_mps`` while turning at ``mean_turn_rad_s`` plus a sine of
    ``turn_amplitude_rad_s`` and ``period_s``: the heading covers full circles (compass), both
    wheels change speed independently (odometry), and in the default world the robot loops
    near its start without touching a wall (wall slip would swamp odometry effects) while
    passing close enough to one for the IR sensors."""

    def command(t: float) -> tuple[float, float]:
        w = mean_turn_rad_s + turn_amplitude_rad_s * math.sin(2 * math.pi * t / period_s)
        return speed_mps, w

    return command


def record_simulator(
    config: Mapping[str, Any],
    path: Path,
    duration_s: float,
    seed: int = 1,
    command: CommandSchedule | None = None,
    pose_rate_hz: float | None = None,
) -> Path:
    """Run the simulator for ``duration_s`` and record what the bridge would publish.

    ``config`` is the whole parsed config (``[sim]``, ``[robot]``, ``[sensors.*]``, ``[world]``);
    ``command`` gives the body speed ``(v m/s, omega rad/s)`` at each step (default
    :func:`weave_command`); the truth pose is recorded at ``pose_rate_hz`` (default: the
    config's ``[zenoh] pose_rate_hz``, read with the bridge's typed settings as a run reads it).
    The config's ``[[faults]]`` (docs/faults.md) act as in a run, drawn from ``seed``: on the
    simulator before each step (kidnap, wheel slip), on each step's readings (stuck, glitch,
    bias, ...), and their events are recorded on ``events/fault``; bus faults have no bus here.
    """
    from koala_bridge.core.topics import FaultEventMessage, WorldMessage
    from koala_bridge.recording.mcap_file import Recorder, run_metadata
    from koala_bridge.runtime.faults import FaultInjector, faults_from_config
    from koala_bridge.runtime.settings import BridgeSettings
    from koala_bridge.runtime.zenoh_io import pose_message, sensor_messages

    rate = pose_rate_hz or BridgeSettings.from_config(config).zenoh.pose_rate_hz
    sim = Simulator(config)
    command = command or weave_command()
    pose_period = max(1, round(1.0 / (rate * sim.dt)))
    half_base = 0.5 * sim.config.robot.wheel_base_m
    world = WorldMessage.of(sim.world, sim.robot_description()).to_json()
    steps = round(duration_s / sim.dt)
    with Recorder(path, metadata=run_metadata("sim", config, None), world=world) as rec:
        specs = faults_from_config(config)
        faults = FaultInjector(specs, seed) if specs else None
        r = sim.reset(seed)
        for k in range(steps + 1):
            if faults is not None:
                r = faults.on_readings(r)
            messages = sensor_messages(r)
            if k % pose_period == 0:
                messages = {"truth/pose": pose_message(r), **messages}
            for suffix, message in messages.items():
                rec.record(suffix, r.t, message)
            if faults is not None:
                for event in faults.events():
                    rec.record(FaultEventMessage.TOPIC, event.t, event.to_json())
            if k == steps:
                break
            if faults is not None:
                faults.apply_to_sim(sim, sim.t)
            v, w = command(r.t)
            r = sim.step(WheelCommand(v - w * half_base, v + w * half_base))
    return Path(path)
