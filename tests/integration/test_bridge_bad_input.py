"""Bad input on every port of a running bridge is rejected, counted in `status`, and changes
nothing else: the robot stays where it is, no other counter moves, and the port keeps serving.

Inputs: random bytes, over-long and truncated lines, unknown commands and CAN ids, wrong DLC,
frames that only the robot sends, corrupted and truncated MAVLink packets, garbage datagrams.
"""

from __future__ import annotations

import random
import socket
import time

import can
import cantools
import serial
from koala_bridge.drivers.rangeframes import RangeFrameDecoder

SEED = 20261122


def noise(n: int, rng: random.Random) -> bytes:
    return bytes(rng.randrange(256) for _ in range(n))


def status_after(watch, t: float, bus: str, rejected: int) -> dict:
    """The first status at or after simulation time ``t`` with ``rejected`` rejects on ``bus``."""
    return watch.wait_for(
        "status", lambda m: m["t"] >= t and m["buses"].get(bus, {}).get("rejected", 0) >= rejected
    )


def assert_nothing_else_changed(watch, start: dict, status: dict, bus: str) -> None:
    pose = watch.after("truth/pose", status["t"])
    assert (pose["x"], pose["y"], pose["theta"]) == (start["x"], start["y"], start["theta"])
    for name, counts in status["buses"].items():
        if name not in (bus, "zenoh"):
            assert counts["received"] == 0 and counts["rejected"] == 0, (name, counts)
    assert status["motor_command_source"] == ""


def test_kteam_garbage_gets_error_replies_and_the_port_keeps_working(bridge, zenoh_watch) -> None:
    rng = random.Random(SEED)
    b = bridge()
    watch = zenoh_watch(b)
    start = watch.wait_for("truth/pose")
    bad_lines = [b"X", b"D,1", b"D,10,10,10", b"D,1000,0", b"D,a,b", b"G,1.5,2", b"L,7,1",
                 b"d,10,10", b"\x00\xff\xfe", b"A" * 300]
    with serial.Serial(b.endpoints["serial"]["kteam"], 115200, timeout=5) as port:
        for line in bad_lines:
            port.write(line + b"\r")
            reply = port.read_until(b"\r\n")
            assert reply.startswith(b"z,") and reply.endswith(b"\r\n"), (line, reply)
        # Random bytes without any terminator, then a terminator: at most one bad line.
        port.write(bytes(c for c in noise(200, rng) if c not in b"\r\n") + b"\r")
        assert port.read_until(b"\r\n").startswith(b"z,")
        port.write(b"B\r")
        assert port.read_until(b"\r\n").startswith(b"b,")
        port.write(b"H\r")
        assert port.read_until(b"\r\n") == b"h,0,0\r\n"
    t = watch.wait_for("truth/pose")["t"]
    status = status_after(watch, t, "kteam", len(bad_lines) + 1)
    assert status["buses"]["kteam"]["received"] == 2  # B and H
    assert_nothing_else_changed(watch, start, status, "kteam")


def test_rangefinder_port_rejects_input_and_keeps_streaming(bridge, zenoh_watch) -> None:
    rng = random.Random(SEED)
    b = bridge()
    watch = zenoh_watch(b)
    start = watch.wait_for("truth/pose")
    with serial.Serial(b.endpoints["serial"]["rangefinders"], 115200, timeout=5) as port:
        port.write(noise(500, rng))
        port.flush()
        t = watch.wait_for("truth/pose")["t"]
        status = status_after(watch, t, "rangefinders", 1)
        port.reset_input_buffer()
        decoder = RangeFrameDecoder()
        frames = []
        while len(frames) < 3:
            frames += decoder.feed(port.read(64))
    assert_nothing_else_changed(watch, start, status, "rangefinders")


def test_socketcand_bad_frames_and_protocol_garbage(bridge, zenoh_watch) -> None:
    rng = random.Random(SEED)
    b = bridge()
    watch = zenoh_watch(b)
    start = watch.wait_for("truth/pose")
    sc = b.endpoints["can"]["socketcand"]
    db = cantools.database.load_file(b.endpoints["can"]["dbc"])
    motor = db.get_message_by_name("MotorCommand").frame_id
    odometry = db.get_message_by_name("WheelOdometry").frame_id
    bad = [
        can.Message(arbitration_id=0x123, data=b"\x01\x02", is_extended_id=False),  # unknown id
        can.Message(arbitration_id=motor, data=b"\x10\x00\x10", is_extended_id=False),  # DLC 3
        can.Message(arbitration_id=motor, data=bytes(8), is_extended_id=False),  # DLC 8
        can.Message(arbitration_id=motor, data=bytes(4), is_extended_id=True),  # extended id
        can.Message(arbitration_id=odometry, data=bytes(8), is_extended_id=False),  # robot's own
        can.Message(arbitration_id=motor, data=b"\xff\x7f\x00\x00", is_extended_id=False),  # 32 m/s
    ]
    with can.Bus(interface="socketcand", host=sc["host"], port=sc["port"],
                 channel=sc["channel"]) as bus:
        for msg in bad:
            bus.send(msg)
        # A raw client speaking garbage to the server.
        with socket.create_connection((sc["host"], sc["port"]), timeout=5) as raw:
            assert raw.recv(64).startswith(b"< hi >")
            raw.sendall(b"< open " + sc["channel"].encode() + b" >")
            raw.recv(64)
            raw.sendall(b"< rawmode >< bogus command >< send 1 2 >< send XYZ 1 00 >")
            raw.sendall(noise(300, rng).replace(b">", b"").replace(b"<", b"") + b">")
            time.sleep(0.5)
        t = watch.wait_for("truth/pose")["t"]
        status = status_after(watch, t, "can.socketcand", len(bad) + 3)
        assert status["buses"]["can.socketcand"]["received"] == 0
        assert_nothing_else_changed(watch, start, status, "can.socketcand")
        # The bus still serves: a valid MotorCommand moves the robot.
        bus.send(can.Message(arbitration_id=motor, is_extended_id=False,
                             data=db.encode_message("MotorCommand",
                                                    {"left_speed": 0.1, "right_speed": 0.1})))
        watch.wait_for("truth/pose", lambda m: m["x"] > start["x"] + 0.05)


def test_slcan_bad_frames_and_garbage_commands(bridge, zenoh_watch) -> None:
    rng = random.Random(SEED)
    b = bridge()
    watch = zenoh_watch(b)
    start = watch.wait_for("truth/pose")
    with serial.Serial(b.endpoints["can"]["slcan"], 115200, timeout=2) as port:
        port.write(b"O\r")  # open the channel, as an slcan driver does
        bad_frames = [b"t1003102030\r",          # MotorCommand, DLC 3
                      b"t7FF0\r",                # unknown id
                      b"T000001004000000000\r",  # MotorCommand id as an extended frame
                      b"t1108" + b"00" * 8 + b"\r"]  # WheelOdometry: the robot's own frame
        for frame in bad_frames:
            port.write(frame)
        port.write(b"tZZZ1FF\r" + b"Q\r" + b"t10\r")  # not frames at all
        port.write(bytes(c for c in noise(200, rng) if c != 0x0D) + b"\r")
        time.sleep(0.3)
        t = watch.wait_for("truth/pose")["t"]
        status = status_after(watch, t, "can.slcan", len(bad_frames) + 3)
        assert status["buses"]["can.slcan"]["received"] == 0
        assert_nothing_else_changed(watch, start, status, "can.slcan")
        # Still serving: frames keep coming.
        port.reset_input_buffer()
        port.read_until(b"\r")  # the rest of a frame cut by the reset
        assert port.read_until(b"\r").startswith((b"t1108", b"t1204"))


def test_mavlink_garbage_datagrams(bridge, zenoh_watch) -> None:
    from pymavlink.dialects.v20 import common as mavlink2

    rng = random.Random(SEED)
    b = bridge()
    watch = zenoh_watch(b)
    start = watch.wait_for("truth/pose")
    gcs = mavlink2.MAVLink(None, 255, 190)
    heartbeat = bytes(gcs.heartbeat_encode(6, 8, 0, 0, 4).pack(gcs))
    corrupted = bytearray(heartbeat)
    corrupted[-1] ^= 0xFF
    datagrams = [noise(40, rng), heartbeat[:7], bytes(corrupted), b"\xfd" + noise(30, rng)]
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", b.mavlink_port))
        sock.settimeout(5)
        _, bridge_addr = sock.recvfrom(2048)
        for d in datagrams:
            sock.sendto(d, bridge_addr)
        sock.sendto(heartbeat, bridge_addr)  # a ground station's valid heartbeat is accepted
        t = watch.wait_for("truth/pose")["t"]
        status = status_after(watch, t, "mavlink", len(datagrams))
        status = watch.wait_for("status", lambda m: m["buses"]["mavlink"]["received"] >= 1)
        # Still serving: SCALED_IMU keeps arriving.
        parser = mavlink2.MAVLink(None)
        deadline = time.monotonic() + 5
        kinds = set()
        while "SCALED_IMU" not in kinds and time.monotonic() < deadline:
            data, _ = sock.recvfrom(2048)
            kinds |= {m.get_type() for m in parser.parse_buffer(data) or []}
    assert "SCALED_IMU" in kinds
    assert_nothing_else_changed(watch, start, status, "mavlink")
