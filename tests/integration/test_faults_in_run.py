"""Faults injected into a running bridge (issue 14 point 3, docs/faults.md), seen by a firmware
on the real transports. Every run is in lockstep, paced by K-Team ``D`` from the test thread, so
what a fault hits is the same every time; CAN is read after each ``d`` (the bridge hands a
period's frames to socketcand before it answers)."""

from __future__ import annotations

import csv
import json
import math
import os
from pathlib import Path

import can
import pytest
import serial
from _inproc import WAIT_S, ListTap, ask, bridge, kteam, socketcand, zenoh_session
from koala_bridge.drivers.can_codec import KoalaCanCodec
from koala_bridge.drivers.messages import GyroFrame, MotorCommandFrame, WheelOdometryFrame
from koala_bridge.runtime.faults import CAN_ERR_BUSOFF, CAN_ERR_PROT

CODEC = KoalaCanCodec()


def cycles(port: serial.Serial, n: int, command: str = "D,0,0") -> None:
    for _ in range(n):
        assert ask(port, command) == "d"


def drain(bus: can.BusABC) -> list[can.Message]:
    out = []
    while (msg := bus.recv(0.05)) is not None:
        out.append(msg)
    return out


def stamps(msgs: list[can.Message], kind: type) -> list[float]:
    """Time stamps of the frames of ``kind``, each sample once (step 0 may come twice)."""
    seen: list[float] = []
    for m in msgs:
        if not m.is_error_frame and isinstance(CODEC.decode(m), kind) and (
                not seen or m.timestamp > seen[-1]):
            seen.append(m.timestamp)
    return seen


def test_a_can_drop_window_removes_exactly_its_frames_and_each_is_an_event() -> None:
    tap = ListTap()
    fault = {"kind": "drop", "target": "can", "start_s": 0.05, "end_s": 0.10, "name": "cut"}
    with bridge(faults=[fault], tap=tap) as source, socketcand(source) as bus, \
            kteam(source) as port:
        cycles(port, 15)
        msgs = drain(bus)
        status = source.status(source.port.t)
    odo = stamps(msgs, WheelOdometryFrame)
    expected = [round(0.01 * k, 2) for k in range(1, 16) if not 5 <= k < 10]
    assert [round(t, 2) for t in odo if t > 0] == expected
    assert [round(t, 2) for t in stamps(msgs, GyroFrame) if t > 0] == expected
    # odometry and gyro at 5 steps each: 10 frames dropped, 10 events, counted in status
    events = tap.on("events/fault")
    assert len(events) == 10 and {e["kind"] for _, e in events} == {"drop"}
    assert sorted({round(e["t"], 2) for _, e in events}) == [0.05, 0.06, 0.07, 0.08, 0.09]
    assert status["faults"] == {"cut": 10}
    # the robot still pushed them: the estimator saw what the firmware saw (nothing)
    recorded = [t for b, d, t, _, f in tap.frames if b == "can" and d == "from_robot"]
    assert not any(0.05 - 1e-9 <= t < 0.10 - 1e-9 for t in recorded)


def test_a_gyro_bias_step_shifts_the_gyro_on_every_bus_from_its_start() -> None:
    tap = ListTap()
    fault = {"kind": "bias", "target": "gyro", "start_s": 0.05, "bias": 0.25}
    with bridge("sensors.gyro.ideal=true", faults=[fault], tap=tap) as source, \
            socketcand(source) as bus, kteam(source) as port:
        cycles(port, 10)                 # at rest: an ideal gyro reads 0
        msgs = drain(bus)
    rates = {round(m.timestamp, 2): CODEC.decode(m).yaw_rate for m in msgs
             if isinstance(CODEC.decode(m), GyroFrame)}
    assert all(rates[t] == 0.0 for t in (0.01, 0.02, 0.03, 0.04))
    assert all(rates[t] == pytest.approx(0.25) for t in (0.05, 0.06, 0.1))
    zenoh_rates = {round(t, 2): m["yaw_rate"] for t, m in tap.on("sensors/gyro")}
    assert zenoh_rates[0.04] == 0.0 and zenoh_rates[0.05] == pytest.approx(0.25)


def test_a_kidnap_moves_the_truth_but_not_the_encoders() -> None:
    tap = ListTap()
    fault = {"kind": "kidnap", "target": "robot", "start_s": 0.05, "x": 1.0, "y": 0.75,
             "theta_deg": 90.0}
    with bridge(faults=[fault], tap=tap) as source, kteam(source) as port:
        cycles(port, 10, "D,10,10")
        odometry = ask(port, "H")
    poses = [(round(t, 2), m) for t, m in tap.on("truth/pose")]
    before = [m for t, m in poses if t < 0.05]
    after = [m for t, m in poses if t > 0.05]
    start = before[0]
    assert math.hypot(before[-1]["x"] - start["x"], before[-1]["y"] - start["y"]) < 0.01
    assert after[0]["x"] == pytest.approx(1.0, abs=0.01)
    assert after[0]["y"] == pytest.approx(0.75, abs=0.01)
    assert after[0]["theta"] == pytest.approx(math.pi / 2, abs=0.05)
    assert odometry == "h,100,100"     # 10 steps of 10 pulses: the jump is not counted
    (event,) = [m for _, m in tap.on("events/fault")]
    assert event["kind"] == "kidnap" and event["detail"]["to"][:2] == [1.0, 0.75]


def test_stuck_ir_repeats_its_last_reading_for_the_window() -> None:
    fault = {"kind": "stuck", "target": "ir", "start_s": 0.1, "end_s": 0.3}
    with bridge(faults=[fault]) as source, kteam(source) as port:
        readings = []
        for _ in range(60):          # N at every 10 ms boundary; IR samples at 20 Hz
            readings.append((source.port.t, ask(port, "N")))
            cycles(port, 1)
    during = {r for t, r in readings if 0.1 <= t < 0.3 - 1e-9}
    before = {r for t, r in readings if t < 0.1 - 1e-9}
    after = {r for t, r in readings if t >= 0.3}
    assert len(during) == 1                         # one reading, held
    assert len(before) > 1 and len(after) > 1       # the noise moves them otherwise


def test_bus_off_silences_can_both_ways_and_signals_it_with_error_frames() -> None:
    fault = {"kind": "bus_off", "target": "can", "start_s": 0.03, "end_s": 0.06}
    with bridge(faults=[fault]) as source, socketcand(source) as bus, kteam(source) as port:
        cycles(port, 3)
        bus.send(CODEC.encode(MotorCommandFrame(0.2, 0.2)))
        cycles(port, 2)          # the command arrived while bus-off: not heard
        moving = ask(port, "H")
        cycles(port, 5)
        msgs = drain(bus)
    errors = [m for m in msgs if m.is_error_frame]
    assert errors and errors[0].arbitration_id & CAN_ERR_BUSOFF
    odo = [round(t, 2) for t in stamps(msgs, WheelOdometryFrame) if t > 0]
    assert odo == [0.01, 0.02, 0.06, 0.07, 0.08, 0.09, 0.1]
    assert moving == "h,0,0"


def test_corrupt_on_can_is_an_error_frame_before_the_intact_frame() -> None:
    fault = {"kind": "corrupt", "target": "can", "start_s": 0.02, "end_s": 0.03}
    with bridge(faults=[fault]) as source, socketcand(source) as bus, kteam(source) as port:
        cycles(port, 4)
        msgs = drain(bus)
    at = [m for m in msgs if round(m.timestamp, 2) == 0.02]
    # a CRC error on the wire, then the frame again (retransmitted), for each of the two
    kinds = ["error" if m.is_error_frame else type(CODEC.decode(m)).__name__ for m in at]
    assert kinds == ["error", "WheelOdometryFrame", "error", "GyroFrame"]
    assert all(m.arbitration_id & CAN_ERR_PROT for m in at if m.is_error_frame)


def test_a_kteam_disconnect_cuts_the_pty_and_lockstep_goes_on_until_it_is_back(
        tmp_path: object) -> None:
    fault = {"kind": "disconnect", "target": "kteam", "start_s": 0.05, "end_s": 0.2}
    endpoints = os.path.join(str(tmp_path), "ep.json")
    with bridge(f'run.endpoints_file="{endpoints}"', faults=[fault]) as source:
        with kteam(source, timeout=1.0) as port:
            cycles(port, 4)
            port.write(b"D,0,0\n")           # this period ends at 0.05: the line is cut
            with pytest.raises(serial.SerialException):
                for _ in range(50):
                    port.readline()
                    port.write(b"H\n")
        # the bridge steps on without the firmware until the line is back, then waits
        assert source.lockstep is not None
        assert source.lockstep.wait_done(20, WAIT_S)
        assert source.endpoints is not None and source.endpoints.kteam
        with open(endpoints) as f:
            path = json.load(f)["serial"]["kteam"]
        assert path == source.endpoints.kteam
        with serial.Serial(path, 115200, timeout=WAIT_S) as port:
            t = source.port.t
            assert t == pytest.approx(0.2)          # and no further: waiting for the firmware
            cycles(port, 3)
            assert source.port.t == pytest.approx(0.23)
        assert source.status(source.port.t)["lockstep"]["unpaced_steps"] == 15


def test_faults_can_be_scheduled_over_zenoh_only_with_remote_commands() -> None:
    tap = ListTap()
    with bridge("zenoh.remote_commands=true", tap=tap) as source, zenoh_session(source) as z, \
            kteam(source) as port:
        prefix = source.settings.zenoh.prefix
        cycles(port, 2)
        fault = {"kind": "drop", "target": "can", "start_s": 0.0, "name": "late"}
        (reply,) = list(z.get(f"{prefix}/faults/schedule", payload=json.dumps(fault),
                              timeout=WAIT_S))
        assert json.loads(reply.ok.payload.to_bytes()) == {"name": "late", "t": 0.02}
        (bad,) = list(z.get(f"{prefix}/faults/schedule",
                            payload=json.dumps({"kind": "drop", "target": "cann"}),
                            timeout=WAIT_S))
        assert "did you mean 'can'" in bad.err.payload.to_bytes().decode()
        cycles(port, 3)
        assert source.status(source.port.t)["faults"] == {"late": 6}
    with bridge() as source, zenoh_session(source) as z:
        replies = list(z.get(f"{source.settings.zenoh.prefix}/faults/schedule",
                             payload=json.dumps(fault), timeout=2.0))
        assert replies == []


def test_fault_events_are_in_the_recording_and_its_export(tmp_path: Path) -> None:
    from koala_bridge.recording.export import export_bundle
    from koala_bridge.recording.mcap_file import Recorder, open_recording, run_metadata

    faults = [{"kind": "kidnap", "target": "robot", "start_s": 0.03, "x": 1.0, "y": 1.0},
              {"kind": "drop", "target": "can", "start_s": 0.05, "end_s": 0.07}]
    path = tmp_path / "run.mcap"
    recorder = Recorder(path, metadata=run_metadata("sim", {"sim": {"seed": 1}}, None))
    with bridge(faults=faults, tap=recorder) as source, kteam(source) as port:
        cycles(port, 10)
    recorder.close()
    events = [m.json() for m in open_recording(path).topic("/events/fault")]
    assert [(e["t"], e["kind"]) for e in events] == [
        (0.03, "kidnap"), (0.05, "drop"), (0.05, "drop"), (0.06, "drop"), (0.06, "drop")]
    bundle = export_bundle(path, tmp_path / "bundle")
    with open(bundle / "faults.csv") as f:
        rows = list(csv.DictReader(f))
    assert [r["kind"] for r in rows] == ["kidnap", "drop", "drop", "drop", "drop"]
    assert json.loads(rows[1]["detail"]) == {"can_id": 0x110}


def test_delay_and_reorder_never_hold_a_kteam_reply_in_lockstep() -> None:
    """A firmware waiting for the reply to D holds simulated time: a held reply would stall
    the run for ever. Replies are only dropped, corrupted or duplicated; nothing is counted
    for the kinds that pass them."""
    faults = [{"kind": "reorder", "target": "kteam", "end_s": 0.1, "name": "swap"},
              {"kind": "delay", "target": "kteam", "end_s": 0.1, "delay_s": 0.05,
               "name": "late"}]
    with bridge(faults=faults) as source, kteam(source, timeout=2.0) as port:
        for k in range(1, 6):
            assert ask(port, "D,10,10") == "d"
            assert ask(port, "H") == f"h,{10 * k},{10 * k}"
        assert source.status(source.port.t)["faults"] == {"swap": 0, "late": 0}
