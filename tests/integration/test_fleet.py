"""Two Koalas in one world in one process ([[robots]], runtime/fleet_source.py), played from the
test thread on their real transports: each robot's buses answer on their own, alpha driving at
beta sees it and stops at contact, lockstep waits for both firmwares, and the same seed gives the
same streams for both robots."""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import can
import numpy as np
import serial
from _inproc import REPO, WAIT_S, ListTap, serving, zenoh_session
from conftest import free_port
from koala_bridge.drivers.messages import MotorCommandFrame, WheelOdometryFrame
from koala_bridge.runtime.fleet_config import robot_entries
from koala_bridge.runtime.fleet_source import FleetSource
from koala_bridge.runtime.settings import (
    BridgeSettings,
    apply_override,
    load_config,
    parse_override,
)
from koala_bridge.sim.simulator import Simulator
from pymavlink import mavutil

RADIUS = 0.19           # [robot] body_radius_m of config/default.toml
ALPHA = {"x": 1.3, "y": 1.75, "theta_deg": 0.0}
BETA = {"x": 2.2, "y": 1.75, "theta_deg": 180.0}
SPEED = 66              # K-Team D units (pulses per 10 ms): 0.29 m/s
PERIOD_S = 0.05         # five 10 ms steps per cycle message


def fleet_config(*overrides: str) -> dict[str, Any]:
    config = load_config(REPO / "config" / "default.toml")
    for text in ('run.clock="lockstep"', f"lockstep.period_s={PERIOD_S}",
                 "localisation.enabled=false", "buses.can.slcan=false",
                 f'zenoh.listen=["tcp/127.0.0.1:{free_port()}"]', *overrides):
        config = apply_override(config, *parse_override(text))
    config["robots"] = [
        {"name": "alpha", "start": ALPHA,
         "buses": {"mavlink": {"port": free_port("udp")}}},
        {"name": "beta", "start": BETA,
         "buses": {"mavlink": {"port": free_port("udp")}}},
    ]
    return config


@contextmanager
def fleet(config: dict[str, Any], tap: ListTap | None = None) -> Iterator[FleetSource]:
    entries = robot_entries(config)
    assert entries is not None
    source = FleetSource(config, BridgeSettings.from_config(config), entries)
    if tap is not None:
        source.tap = tap
    with serving(source):
        yield source


@contextmanager
def ports(source: FleetSource) -> Iterator[dict[str, serial.Serial]]:
    eps = source.endpoints
    assert eps is not None
    opened = {name: serial.Serial(ep.kteam, 115200, timeout=WAIT_S) for name, ep in eps.robots}
    try:
        yield opened
    finally:
        for port in opened.values():
            port.close()


def drive(kteam: dict[str, serial.Serial], cycles: int, alpha: int, beta: int = 0) -> None:
    """``cycles`` lockstep cycles: both firmwares send D, then read their replies."""
    for _ in range(cycles):
        kteam["alpha"].write(f"D,{alpha},{alpha}\n".encode())
        kteam["beta"].write(f"D,{beta},{beta}\n".encode())
        assert kteam["alpha"].readline().strip() == b"d"
        assert kteam["beta"].readline().strip() == b"d"


def _front(poses: list[list[float]]) -> int:
    return int(np.argmin([abs(p[2]) for p in poses]))


def test_alpha_sees_beta_and_stops_at_contact() -> None:
    tap = ListTap()
    config = fleet_config()
    with fleet(config, tap) as source, ports(source) as kteam:
        sim_a = source.robots[0].sim
        # step 0: alpha's forward sonar ends on beta's body, not on the far wall
        deadline = time.monotonic() + WAIT_S
        while not tap.on("alpha/sensors/sonar"):     # the loop's thread emits step 0
            assert time.monotonic() < deadline
            time.sleep(0.01)
        sonar0 = tap.on("alpha/sensors/sonar")[0][1]
        front = _front(sim_a.config.sensors.sonar.poses)
        alone = Simulator(source.entries[0].config).reset(1)
        seen = sonar0["truth"]["ranges"][front]
        assert seen < alone.sonar.truth_ranges[front] - 0.5
        assert abs(seen - (BETA["x"] - RADIUS - ALPHA["x"]
                           - sim_a.config.sensors.sonar.poses[front][0])) < 0.01
        drive(kteam, 50, SPEED)     # 2.5 s at 0.29 m/s: 0.7 m, farther than the 0.52 m gap
        a_poses = tap.on("alpha/truth/pose")
        b_poses = tap.on("beta/truth/pose")
        step_m = sim_a.config.robot.max_wheel_speed_mps * sim_a.dt
        gaps = [math.hypot(a["x"] - b["x"], a["y"] - b["y"])
                for (_, a), (_, b) in zip(a_poses, b_poses, strict=False)]
        assert min(gaps) >= 2 * RADIUS - step_m
        assert gaps[-1] < 2 * RADIUS + 0.03           # pushed on: it stays at contact
        assert a_poses[-1][0] > 2.0                    # t: the run went on meanwhile
        # at contact alpha's forward IR sees beta, a robot alone there sees nothing
        ir = tap.on("alpha/sensors/ir")[-1][1]
        ir_front = _front([[p[0], p[1], (p[2] + 180) % 360 - 180]
                           for p in sim_a.config.sensors.ir.poses])
        assert ir["truth"]["ranges"][ir_front] is not None
        collided = tap.on("alpha/truth/pose")[-1][1]
        alone_cfg = {**source.entries[0].config, "world": {
            **source.entries[0].config["world"],
            "start": {"x": collided["x"], "y": collided["y"],
                      "theta_deg": math.degrees(collided["theta"])}}}
        assert not np.isfinite(Simulator(alone_cfg).reset(1).ir.truth_ranges[ir_front])


def test_each_robots_buses_answer_on_their_own() -> None:
    # alpha's firmware paces on K-Team D, beta's on CAN MotorCommand: each on its own buses
    config = fleet_config()
    config["robots"][1]["lockstep"] = {"cycle_bus": "can", "cycle_message": "MotorCommand"}
    with fleet(config) as source, ports(source) as kteam, zenoh_session(
            source.robots[0]) as z:
        eps = source.endpoints
        assert eps is not None
        poses: dict[str, list[Any]] = {"alpha": [], "beta": []}
        subs = [z.declare_subscriber(f"koala/{name}/truth/pose",
                                     lambda s, name=name: poses[name].append(s))
                for name in poses]
        gcs = {name: mavutil.mavlink_connection(ep.mavlink_url, source_system=255)
               for name, ep in eps.robots}
        sc = {name: can.Bus(interface="socketcand", host=ep.socketcand.host,
                            port=ep.socketcand.port, channel=ep.socketcand.channel)
              for name, ep in eps.robots if ep.socketcand is not None}
        codec = source.robots[1].can_codec
        try:
            for _ in range(20):     # 1 s: beta drives 0.2 m at 0.2 m/s, alpha stands
                kteam["alpha"].write(b"D,0,0\n")
                sc["beta"].send(codec.encode(MotorCommandFrame(0.2, 0.2)))
                assert kteam["alpha"].readline().strip() == b"d"
            assert source.robots[1].sim.pose.x < BETA["x"] - 0.15    # beta faces west
            assert source.robots[0].sim.pose.x == ALPHA["x"]
            # each K-Team pty answers for its own robot: alpha's wheels never turned
            ticks = {}
            for name in ("alpha", "beta"):
                kteam[name].write(b"H\n")
                reply = kteam[name].readline().strip().split(b",")
                assert reply[0] == b"h"
                ticks[name] = (int(reply[1]), int(reply[2]))
            assert ticks["alpha"] == (0, 0)
            assert min(ticks["beta"]) > 1000
            # CAN: each socketcand carries its own robot's odometry (the last frame: time
            # stands still in lockstep until the next cycle message)
            for name, moving in (("alpha", False), ("beta", True)):
                last = None
                while (msg := sc[name].recv(timeout=0.5)) is not None:
                    frame = codec.decode(msg)
                    if isinstance(frame, WheelOdometryFrame):
                        last = frame
                assert last is not None
                assert (last.left_ticks != 0) == moving
            # MAVLink: each robot's compass on its own port, with its own system id
            for name, sysid in (("alpha", 1), ("beta", 2)):
                got = gcs[name].recv_match(type="SCALED_IMU", blocking=True, timeout=WAIT_S)
                assert got is not None and got.get_srcSystem() == sysid
            # Zenoh: each robot's truth under its own prefix
            deadline = time.monotonic() + WAIT_S
            while not (poses["alpha"] and poses["beta"]):
                assert time.monotonic() < deadline, "no truth/pose under a robot's prefix"
                kteam["alpha"].write(b"D,0,0\n")
                sc["beta"].send(codec.encode(MotorCommandFrame(0.0, 0.0)))
                assert kteam["alpha"].readline().strip() == b"d"
        finally:
            for sub in subs:
                sub.undeclare()
            for bus in sc.values():
                bus.shutdown()
            for g in gcs.values():
                g.close()


def test_lockstep_waits_for_every_firmware() -> None:
    config = fleet_config()
    with fleet(config) as source, ports(source) as kteam:
        kteam["alpha"].timeout = 0.5
        kteam["alpha"].write(b"D,10,10\n")          # alpha's firmware cycles; beta's is silent
        assert kteam["alpha"].readline() == b""        # no reply: the period is not simulated
        assert source.fleet.t == 0.0
        assert source.robots[0].lockstep is not None and source.robots[0].lockstep.engaged
        kteam["beta"].write(b"D,0,0\n")              # beta's first cycle message
        kteam["alpha"].timeout = WAIT_S
        assert kteam["alpha"].readline().strip() == b"d"
        assert kteam["beta"].readline().strip() == b"d"
        assert source.fleet.t == PERIOD_S == source.robots[1].sim.t


def _scripted_run(seed: int) -> dict[str, list[Any]]:
    tap = ListTap()
    config = fleet_config(f"sim.seed={seed}")
    with fleet(config, tap) as source, ports(source) as kteam:
        drive(kteam, 12, SPEED, beta=-20)
    keep = ("truth/pose", "sensors/")
    out: dict[str, list[Any]] = {}
    for channel, t, msg in tap.messages:
        name, _, key = channel.partition("/")
        if key.startswith(keep):
            out.setdefault(name, []).append((key, t, msg))
    return out


def test_same_seed_same_streams_for_both_robots() -> None:
    first, second = _scripted_run(3), _scripted_run(3)
    assert set(first) == {"alpha", "beta"}
    for name in first:
        assert len(first[name]) > 50
        assert first[name] == second[name]
    assert first["alpha"] != first["beta"]
