"""End to end: a `koala-bridge run` subprocess and the real client libraries on every bus.

pyserial on the K-Team and range-frame ptys, python-can (socketcand, slcan) with cantools and the
shipped DBC, pymavlink on UDP, and Zenoh: after a motor command the truth pose moves, encoder
ticks match the distance driven, the integrated gyro matches the heading change, the compass
heading matches the truth, and IR counts rise as the robot nears a wall.
"""

from __future__ import annotations

import math
import time
import tomllib
from pathlib import Path

import can
import cantools
import pytest
import serial
from koala_bridge.core.geometry import wrap_angle as wrap
from koala_bridge.drivers.messages import RangeKind
from koala_bridge.drivers.rangeframes import RangeFrameDecoder

REPO = Path(__file__).resolve().parents[2]


def config_ticks_per_metre() -> float:
    """``[robot] ticks_per_metre`` of the config the bridge runs on."""
    with open(REPO / "config" / "default.toml", "rb") as f:
        return float(tomllib.load(f)["robot"]["ticks_per_metre"])


def kteam(port: serial.Serial, command: str) -> str:
    """Send one K-Team command, return its reply line without CR LF."""
    port.reset_input_buffer()
    port.write(command.encode() + b"\r")
    reply = port.read_until(b"\r\n")
    assert reply.endswith(b"\r\n"), f"no reply to {command!r}: {reply!r}"
    return reply[:-2].decode()


def open_serial(path: str) -> serial.Serial:
    return serial.Serial(path, 115200, timeout=5)


def wait_still(watch, timeout: float = 60.0) -> dict:
    """Wait until two truth poses 0.2 simulation seconds apart are equal; return the later."""
    deadline = time.monotonic() + timeout
    a = watch.wait_for("truth/pose")
    while time.monotonic() < deadline:
        b = watch.after("truth/pose", a["t"] + 0.2)
        if (b["x"], b["y"], b["theta"]) == (a["x"], a["y"], a["theta"]):
            return b
        a = b
    raise AssertionError("robot did not come to rest")


# On the fast clock the robot drives on while the test reacts (a few ms idle, seconds on a busy
# machine): the watchdog stops it this many simulation seconds after the last drive command,
# so the distance is bounded whatever the machine's load (here 0.27 m, well short of the wall).
DRIVE_WATCHDOG = "buses.motor_watchdog_s=2.0"


def test_kteam_drive_moves_the_robot_and_ticks_match_distance(bridge, zenoh_watch) -> None:
    b = bridge(sets=[DRIVE_WATCHDOG])
    watch = zenoh_watch(b)
    with open_serial(b.endpoints["serial"]["kteam"]) as port:
        assert kteam(port, "B").startswith("b,")
        assert kteam(port, "G,0,0") == "g"
        start = wait_still(watch)
        assert kteam(port, "D,30,30") == "d"
        moved = watch.wait_for("truth/pose", lambda m: m["x"] > start["x"] + 0.15)
        assert abs(moved["y"] - start["y"]) < 1e-6  # straight line east
        assert kteam(port, "D,0,0") == "d"
        end = wait_still(watch)
        left, right = (int(v) for v in kteam(port, "H").split(",")[1:])
        assert kteam(port, "E") == "e,0,0"
    distance = math.hypot(end["x"] - start["x"], end["y"] - start["y"])
    assert 0.15 < distance < 1.0
    ticks_per_metre = watch.query("world")["robot"]["ticks_per_metre"]
    # Ideal encoders: ticks / ticks_per_metre is the distance each wheel rolled.
    assert left / ticks_per_metre == pytest.approx(distance, abs=2e-3)
    assert right / ticks_per_metre == pytest.approx(distance, abs=2e-3)
    # Zenoh odometry agrees with the serial counters (G,0,0 was sent at rest at `start`).
    odo = watch.after("sensors/odometry", end["t"])
    assert odo["left_ticks"] - left == odo["right_ticks"] - right


def test_ir_counts_rise_as_the_robot_nears_a_wall(bridge, zenoh_watch) -> None:
    b = bridge()
    watch = zenoh_watch(b)
    robot = watch.query("world")["robot"]
    poses = robot["sensors"]["ir"]["poses"]
    front = [i for i, p in enumerate(poses) if abs(wrap(p["theta"])) < 0.3]
    assert front, poses
    decoder = RangeFrameDecoder()
    with open_serial(b.endpoints["serial"]["kteam"]) as port, \
            open_serial(b.endpoints["serial"]["rangefinders"]) as frames:
        far_serial = [int(v) for v in kteam(port, "N").split(",")[1:]]
        assert len(far_serial) == 16
        far_zenoh = watch.wait_for("sensors/ir")["counts"]
        assert kteam(port, "D,100,100") == "d"  # east, towards the wall at x = 3 m
        # Front sensors sit 0.175 m ahead of the centre and see up to 0.25 m.
        watch.wait_for("truth/pose", lambda m: m["x"] > 2.72, timeout=30)
        assert kteam(port, "D,0,0") == "d"
        near_pose = wait_still(watch)
        near_serial = [int(v) for v in kteam(port, "N").split(",")[1:]]
        near_zenoh = watch.after("sensors/ir", near_pose["t"])["counts"]
        frames.reset_input_buffer()
        ir_frames = []
        while len(ir_frames) < 2:
            ir_frames += [f for f in decoder.feed(frames.read(64)) if f.kind == RangeKind.IR]
    assert max(near_serial[i] for i in front) > max(far_serial[i] for i in front) + 50
    assert max(near_zenoh[i] for i in front) > max(far_zenoh[i] for i in front) + 50
    assert list(ir_frames[-1].readings) == near_serial  # robot at rest: same counts everywhere
    assert near_pose["x"] < 3.0  # collisions stop the robot at the wall


def test_world_queryable_answers_world_and_robot(bridge, zenoh_watch) -> None:
    b = bridge()
    answer = zenoh_watch(b).query("world")
    assert answer["cols"] == 6 and answer["rows"] == 6 and answer["cell_m"] == 0.5
    assert answer["walls"] and answer["landmarks"]
    robot = answer["robot"]
    assert robot["ticks_per_metre"] == config_ticks_per_metre()
    assert robot["wheel_base_m"] > 0
    assert len(robot["sensors"]["ir"]["poses"]) == 16


def socketcand_bus(b) -> can.BusABC:
    sc = b.endpoints["can"]["socketcand"]
    return can.Bus(interface="socketcand", host=sc["host"], port=sc["port"], channel=sc["channel"])


def recv_named(bus: can.BusABC, db, name: str, timeout: float = 60.0,
               after_t: float | None = None) -> dict:
    """The next ``name`` frame (with ``after_t``: the first stamped at that simulation time or
    later; the bridge stamps socketcand frames with it)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        msg = bus.recv(0.5)
        if msg is None or msg.arbitration_id != db.get_message_by_name(name).frame_id:
            continue
        if after_t is None or msg.timestamp >= after_t - 1e-6:
            return db.decode_message(msg.arbitration_id, msg.data)
    raise AssertionError(f"no {name} frame" + (f" at t >= {after_t}" if after_t else ""))


def motor_command(db, left: float, right: float) -> can.Message:
    m = db.get_message_by_name("MotorCommand")
    return can.Message(arbitration_id=m.frame_id, is_extended_id=False,
                       data=m.encode({"left_speed": left, "right_speed": right}))


def test_can_socketcand_motor_command_moves_robot_and_odometry_follows(bridge, zenoh_watch) -> None:
    b = bridge(sets=["buses.motor_watchdog_s=3.0"])  # at most 0.3 m (see DRIVE_WATCHDOG)
    watch = zenoh_watch(b)
    db = cantools.database.load_file(b.endpoints["can"]["dbc"])
    with socketcand_bus(b) as bus:
        first = recv_named(bus, db, "WheelOdometry")
        start = wait_still(watch)
        bus.send(motor_command(db, 0.1, 0.1))
        watch.wait_for("truth/pose", lambda m: m["x"] > start["x"] + 0.2)
        bus.send(motor_command(db, 0.0, 0.0))
        end = wait_still(watch)
        # Frames carry their simulation time: skip what was queued while driving.
        last = recv_named(bus, db, "WheelOdometry", after_t=end["t"])
        gyro = recv_named(bus, db, "Gyro", after_t=end["t"])
    ticks_per_metre = watch.query("world")["robot"]["ticks_per_metre"]
    distance = end["x"] - start["x"]
    for side in ("left_ticks", "right_ticks"):
        assert (last[side] - first[side]) / ticks_per_metre == pytest.approx(distance, abs=2e-3)
    assert gyro["yaw_rate"] == pytest.approx(0.0, abs=1e-4)


def test_can_slcan_spin_integrated_gyro_matches_heading_change(bridge, zenoh_watch) -> None:
    # Real-time clock: 100 Gyro frames per second, every one read, so the sum is complete.
    b = bridge(clock="realtime")
    watch = zenoh_watch(b)
    db = cantools.database.load_file(b.endpoints["can"]["dbc"])
    gyro_id = db.get_message_by_name("Gyro").frame_id
    rate_hz = watch.query("world")["robot"]["sensors"]["gyro"]["rate_hz"]
    with can.Bus(interface="slcan", channel=b.endpoints["can"]["slcan"]) as bus:
        recv_named(bus, db, "Gyro")
        start = wait_still(watch)
        bus.send(motor_command(db, -0.06, 0.06))  # spin counter-clockwise in place
        integrated = 0.0
        frames = 0
        t_end = time.monotonic() + 2.0
        stopped = False
        quiet = 0
        while quiet < 30:  # until 30 zero-rate frames in a row after the stop
            msg = bus.recv(30.0)  # 100 frames/s: only a stopped stream waits that long
            assert msg is not None, "Gyro stream stopped"
            if msg.arbitration_id != gyro_id:
                continue
            rate = db.decode_message(msg.arbitration_id, msg.data)["yaw_rate"]
            integrated += rate / rate_hz
            frames += 1
            if not stopped and time.monotonic() > t_end:
                bus.send(motor_command(db, 0.0, 0.0))
                stopped = True
            quiet = quiet + 1 if stopped and rate == 0 else 0
        end = wait_still(watch)
    change = wrap(end["theta"] - start["theta"])
    assert change > 0.3  # it did turn, counter-clockwise
    assert integrated == pytest.approx(change, rel=0.02, abs=0.01)
    assert abs(end["x"] - start["x"]) < 1e-6 and abs(end["y"] - start["y"]) < 1e-6


def compass_heading(conn, timeout: float = 10.0) -> tuple[float, int]:
    msg = conn.recv_match(type="SCALED_IMU", blocking=True, timeout=timeout)
    assert msg is not None, "no SCALED_IMU"
    return math.atan2(-msg.ymag, msg.xmag) % (2 * math.pi), msg.time_boot_ms


def test_mavlink_compass_heading_matches_truth(bridge, zenoh_watch) -> None:
    from pymavlink import mavutil

    b = bridge()
    watch = zenoh_watch(b)
    world = watch.query("world")
    north = math.radians(world["earth_field"]["north_deg"])  # CCW from +x
    conn = mavutil.mavlink_connection(b.endpoints["mavlink"]["url"], source_system=255)
    try:
        hb = conn.wait_heartbeat(timeout=10)
        assert hb is not None
        with open_serial(b.endpoints["serial"]["kteam"]) as port:
            for command in ("D,0,0", "D,-30,30", "D,0,0"):
                kteam(port, command)
                if command != "D,0,0":
                    watch.wait_for("truth/pose", lambda m: m["theta"] > 1.0)
                    continue
                pose = wait_still(watch)
                # Skip samples queued before the robot came to rest.
                while True:
                    heading, t_ms = compass_heading(conn)
                    if t_ms / 1000 >= pose["t"]:
                        break
                # Heading: clockwise from magnetic north; theta: counter-clockwise from east.
                expected = (north - pose["theta"]) % (2 * math.pi)
                assert abs(wrap(heading - expected)) < math.radians(3), (heading, expected)
    finally:
        conn.close()


def test_status_counts_and_real_time_factor(bridge, zenoh_watch) -> None:
    b = bridge()
    watch = zenoh_watch(b)
    # Fast clock: the factor (simulation s per wall s since the start) exceeds 1 once the start
    # (imports, first steps) is behind it; on a busy machine the first status may not be there yet.
    status = watch.wait_for("status", lambda m: m["buses"].get("can.socketcand") is not None
                            and m["real_time_factor"] > 1.0, timeout=120)
    for bus in ("kteam", "rangefinders", "can.socketcand", "can.slcan", "mavlink", "zenoh"):
        assert set(status["buses"][bus]) >= {"sent", "received", "rejected"}
    assert status["buses"]["mavlink"]["sent"] > 0  # UDP sends whether or not anyone listens
    assert status["buses"]["zenoh"]["sent"] > 0


def test_duration_ends_the_run_with_exit_zero(bridge) -> None:
    b = bridge(extra=["--duration", "2"])
    assert b.proc.wait(30) == 0
    assert "Stopped at t = 2.000 s" in b.log()


@pytest.mark.parametrize("signame", ["SIGINT", "SIGTERM"])
def test_signals_stop_cleanly(bridge, signame: str) -> None:
    import os
    import signal

    b = bridge(clock="realtime")
    kteam_path = b.endpoints["serial"]["kteam"]
    assert os.path.exists(kteam_path)
    assert b.stop(getattr(signal, signame)) == 0
    assert "Traceback" not in b.log()


def test_every_endpoint_accepts_clients_as_soon_as_the_file_exists(bridge) -> None:
    import json
    import os
    import socket

    b = bridge()
    ep = b.endpoints
    assert json.loads(b.endpoints_file.read_text()) == ep
    assert set(ep) == {"serial", "can", "mavlink", "zenoh"}
    assert os.path.isabs(ep["can"]["dbc"]) and cantools.database.load_file(ep["can"]["dbc"])
    for path in (ep["serial"]["kteam"], ep["serial"]["rangefinders"], ep["can"]["slcan"]):
        with open_serial(path):
            pass
    sc = ep["can"]["socketcand"]
    with socket.create_connection((sc["host"], sc["port"]), timeout=2) as s:
        assert s.recv(16).startswith(b"< hi >")
    host, port = ep["zenoh"]["endpoints"][0].removeprefix("tcp/").rsplit(":", 1)
    socket.create_connection((host, int(port)), timeout=2).close()
    assert ep["mavlink"]["url"] == f"udpin:127.0.0.1:{b.mavlink_port}"
    assert ep["zenoh"]["prefix"] == "koala/koala"
