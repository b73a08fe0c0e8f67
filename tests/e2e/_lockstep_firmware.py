#!/usr/bin/env python3
"""A small reactive firmware for the lockstep tests, written from the libraries' public docs
(pyserial, python-can's ``socketcand`` interface, cantools, pymavlink), not from the bridge's
code. Its decisions depend on every noisy stream, so any difference in what it is sent, or in
when it sees it, changes the robot's path:

- K-Team ``N`` (IR counts): an obstacle ahead starts a turn; the IR on either side picks the
  turn's direction;
- CAN ``Gyro`` (DBC): the turn ends when the integrated yaw rate reaches 80 deg;
- MAVLink ``SCALED_IMU`` (the compass): the sign of the latest field's x component flips the
  speed of the straight legs between two values.

One control cycle per ``D`` (docs/protocols.md "Lockstep"): send ``N``, read ``n``; decide;
send ``D``, read ``d``; then read the CAN and MAVLink samples the bridge wrote while it
simulated the period, waiting for the ones stamped at the cycle's end (the firmware's only
notion of time is the samples' own time stamps: no wall clock in its logic; a sample whose
time stamp it has seen is not used again). After
``--cycles`` cycles it stops the wheels and closes its ports, which ends a lockstep run.

    python _lockstep_firmware.py ENDPOINTS.json --cycles 600 [--period 0.01]
"""

from __future__ import annotations

import argparse
import json
import math
import sys

import can
import cantools
import serial
from pymavlink import mavutil

# the classic Koala's 16 IR (config/default.toml [sensors.ir] poses): 0-2 and 13-15 look
# forward, 3-5 to the right, 10-12 to the left
FRONT = (0, 1, 2, 13, 14, 15)
RIGHT = (3, 4, 5)
LEFT = (10, 11, 12)
WAIT_S = 10.0              # liveness only: a bridge that stops answering ends the firmware


def last_sample(start: float, end: float, rate_hz: float) -> float | None:
    """The time of the last sample of a ``rate_hz`` stream in the period (start, end], or None
    when the stream has no sample in it."""
    last = math.floor(end * rate_hz + 1e-6) / rate_hz
    return last if last > start + 1e-9 else None


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("endpoints", help="the bridge's --endpoints-file")
    ap.add_argument("--cycles", type=int, default=600)
    ap.add_argument("--period", type=float, default=0.01, help="[lockstep] period_s (s)")
    ap.add_argument("--gyro-hz", type=float, default=100.0)
    ap.add_argument("--compass-hz", type=float, default=50.0)
    args = ap.parse_args(argv)
    ep = json.load(open(args.endpoints))
    port = serial.Serial(ep["serial"]["kteam"], 115200, timeout=WAIT_S)
    sc = ep["can"]["socketcand"]
    bus = can.Bus(interface="socketcand", host=sc["host"], port=sc["port"], channel=sc["channel"])
    db = cantools.database.load_file(ep["can"]["dbc"])
    gyro_id = db.get_message_by_name("Gyro").frame_id
    mav = mavutil.mavlink_connection(ep["mavlink"]["url"])

    def ask(command: str) -> str:
        port.write(command.encode() + b"\n")
        line = port.readline().decode().strip()
        if not line:
            sys.exit(f"no reply to {command!r}")
        return line

    heading = 0.0               # integrated gyro, rad
    turn_left: bool | None = None
    turn_start = 0.0
    field_x = 0.0
    # Time stamps of the last samples used. Until the first D the bridge holds at t = 0 and
    # may send the t = 0 samples again (to a client that connects late): a sample is used once.
    t_gyro = -1.0
    t_mag = -1.0
    path = []
    for k in range(args.cycles):
        ir = [int(v) for v in ask("N").split(",")[1:]]
        if turn_left is None and max(ir[i] for i in FRONT) > 250:
            turn_left = sum(ir[i] for i in RIGHT) >= sum(ir[i] for i in LEFT)
            turn_start = heading
        if turn_left is not None and abs(heading - turn_start) >= math.radians(80):
            turn_left = None
        if turn_left is None:
            speed = 30 if field_x >= 0 else 22
            left, right = speed, speed
        else:
            left, right = (-12, 12) if turn_left else (12, -12)
        if ask(f"D,{left},{right}") != "d":
            sys.exit("D not acknowledged")
        path.append((left, right))
        # the period's samples: the bridge wrote them before 'd'; read up to the cycle's end
        # (samples of t = 0 came before the first D and may have been missed: not waited for)
        start, end = k * args.period, (k + 1) * args.period
        while (due := last_sample(start, end, args.gyro_hz)) is not None and t_gyro < due - 1e-6:
            msg = bus.recv(timeout=WAIT_S)
            if msg is None:
                sys.exit(f"no CAN frame: cycle {k}, waiting for t = {due}, last {t_gyro}")
            if msg.arbitration_id == gyro_id and msg.timestamp > t_gyro:  # each sample once
                rate = db.decode_message(msg.arbitration_id, msg.data)["yaw_rate"]
                heading += rate / args.gyro_hz
                t_gyro = msg.timestamp
        while (due := last_sample(start, end, args.compass_hz)) is not None and t_mag < due - 1e-6:
            m = mav.recv_match(type="SCALED_IMU", blocking=True, timeout=WAIT_S)
            if m is None:
                sys.exit(f"no compass sample: cycle {k}, waiting for t = {due}, last {t_mag}")
            if m.time_boot_ms / 1000.0 > t_mag:
                field_x = m.xmag
                t_mag = m.time_boot_ms / 1000.0
    ask("D,0,0")
    port.close()
    bus.shutdown()
    mav.close()
    print(json.dumps({"cycles": args.cycles, "heading_deg": math.degrees(heading),
                      "t_gyro": t_gyro, "turns": sum(1 for a, b in zip(path, path[1:], strict=False)
                                                      if a[0] != a[1] and b[0] == b[1])}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
