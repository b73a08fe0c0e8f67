"""runtime.koala25_io: the Koala 2.5's replies in its units, its modes, and auto mode's rates
(libkoala / Koala 2.5 manual; docs/protocols.md §1 "Koala 2.5 (koala25) commands")."""

from __future__ import annotations

import math

import numpy as np
import pytest
from koala_bridge.drivers.koala25 import KOALA25
from koala_bridge.drivers.messages import Reject
from koala_bridge.runtime.koala25_io import Koala25Responder
from koala_bridge.runtime.robot_io import MotorArbiter, RobotPort, RobotUnits
from koala_bridge.sim.types import (
    BatteryReading,
    CompassReading,
    GyroReading,
    OdometryReading,
    Pose,
    Readings,
    SonarReading,
    WheelCommand,
)

UNITS = RobotUnits(ticks_per_metre=90284.0, speed_unit_s=0.01)
V_MAX = 0.55
ORIGIN = Pose(0, 0, 0)
DT = 0.01


def make() -> tuple[Koala25Responder, MotorArbiter, RobotPort]:
    arb, port = MotorArbiter(), RobotPort(n_ir=16)
    return Koala25Responder(port, arb, UNITS, V_MAX, "Li-ion"), arb, port


def ask(resp: Koala25Responder, line: bytes) -> bytes:
    cmd = KOALA25.parse_command(line)
    reply = resp.reject(cmd) if isinstance(cmd, Reject) else resp.respond(cmd)
    return KOALA25.format_reply(reply)


def step(port: RobotPort, t: float, speeds: tuple[float, float] = (0.0, 0.0),
         sonar: tuple[float, ...] | None = None, yaw_rate: float = 0.0,
         pose: Pose = ORIGIN) -> None:
    port.update(Readings(
        t=t, pose=pose, wheel_speeds=WheelCommand(*speeds),
        odometry=OdometryReading(0, 0),
        sonar=None if sonar is None else SonarReading(np.array(sonar), np.array(sonar),
                                                      np.zeros(len(sonar))),
        gyro=GyroReading(yaw_rate, yaw_rate),
        compass=CompassReading(np.array([20.0, -5.0, -40.0]), np.zeros(3)),
        battery=BatteryReading(12.34, 1.26, 900.0, 1000.0, 25.0, 20.0, (0.3, 0.45)),
    ))


def test_version_is_the_seven_bytes_libkoala_reads() -> None:
    resp, _, _ = make()
    wire = ask(resp, b"B")
    assert wire == b"b,A-02\n" and len(wire) == 7
    assert chr(wire[2]) == "A" and int(wire[4:6]) == 2      # buffer[2], atoi(buffer+4)


def test_sonar_in_cm_with_the_near_none_and_disabled_codes() -> None:
    resp, _, port = make()
    step(port, 0.0, sonar=(0.10, 0.25, 0.254, 1.0, 2.5, math.nan, 3.0, 0.5, 0.6))
    assert ask(resp, b"G") == b"g,0,25,25,100,250,1000,250,50,60\n"
    assert ask(resp, b"C,3,0") == b"c\n"                     # only sensors 0 and 1
    assert ask(resp, b"G") == b"g,0,25" + b",2000" * 7 + b"\n"


def test_gyro_and_accelerometer_carry_ten_samples_newest_first() -> None:
    resp, _, port = make()
    for k in range(12):
        step(port, k * DT, yaw_rate=0.01 * k)
    n = [int(v) for v in ask(resp, b"N").decode()[2:].split(",")]
    assert len(n) == 30 and n[0::3] == [0] * 10 and n[1::3] == [0] * 10
    deg_per_unit = 0.066
    expected = [round(math.degrees(0.01 * k) / deg_per_unit) for k in range(11, 1, -1)]
    assert n[2::3] == expected
    m = [int(v) for v in ask(resp, b"M").decode()[2:].split(",")]
    assert m[2::3] == [16384] * 10 and m[0::3] == [0] * 10   # at rest: 1 g up, 16384 / g


def test_accelerometer_sees_the_body_move_not_the_wheels_turn() -> None:
    resp, _, port = make()
    step(port, 0.0, pose=Pose(1.0, 2.0, math.pi / 2))
    # heading north, 1 mm north in 10 ms: 0.1 m/s forward from rest, 10 m/s^2 for one step
    step(port, DT, speeds=(0.1, 0.1), pose=Pose(1.0, 2.001, math.pi / 2))
    m = [int(v) for v in ask(resp, b"M").decode()[2:].split(",")]
    assert m[0] == round(10.0 / 9.80665 * 16384) and m[1] == 0
    # pinned against a wall: the wheels spin at 0.3 m/s, the body does not move
    step(port, 2 * DT, speeds=(0.3, 0.3), pose=Pose(1.0, 2.001, math.pi / 2))
    step(port, 3 * DT, speeds=(0.3, 0.3), pose=Pose(1.0, 2.001, math.pi / 2))
    m = [int(v) for v in ask(resp, b"M").decode()[2:].split(",")]
    assert m[:3] == [0, 0, 16384]


def test_magnetometer_battery_and_currents_in_the_manual_units() -> None:
    resp, _, port = make()
    step(port, 0.0, speeds=(0.2, -0.2))
    assert ask(resp, b"&") == b"@,200,-50,-400\n"            # uT x 10 = mGauss
    assert ask(resp, b"V") == b"v,0,123,13,0\n"              # Li-ion, 0.1 V, 0.1 A, no charger
    assert ask(resp, b"O") == b"o,3,-4\n"                    # 0.1 A, sign of the wheel's speed


def test_speed_ramp_and_position_modes_are_reported_by_y() -> None:
    resp, arb, port = make()
    assert ask(resp, b"Y") == b"y,0,0,0,0\n"                 # idle at power-on
    assert ask(resp, b"D,100,100") == b"d\n"
    assert ask(resp, b"Y") == b"y,1,1,0,0\n"
    assert arb.command(0.0) == WheelCommand(UNITS.kteam_speed_to_mps(100),
                                            UNITS.kteam_speed_to_mps(100))
    assert ask(resp, b"J,5,1,10,200,10,0") == b"j\n"         # max_current 0: no limitation
    assert ask(resp, b"K,200,-200") == b"k\n"
    assert ask(resp, b"Y") == b"y,2,2,0,0\n"
    # the ramp: acc_inc / (acc_div + 1) = 2.5 units per 10 ms from the speeds in force (100)
    later = arb.command(0.1)
    assert later.left == pytest.approx(UNITS.kteam_speed_to_mps(100 + 25))
    assert later.right == pytest.approx(UNITS.kteam_speed_to_mps(100 - 25))
    assert ask(resp, b"F,1000,1000") == b"f\n"
    assert ask(resp, b"Y") == b"y,3,3,0,0\n"
    assert ask(resp, b"L,-2940,2940") == b"l\n"
    assert arb.command(0.2) == WheelCommand(-V_MAX, V_MAX)
    assert ask(resp, b"Y") == b"y,4,4,0,0\n"


def test_current_limitation_is_reported_above_j_max_current() -> None:
    resp, _, port = make()
    step(port, 0.0)                                          # motors 0.3 A and 0.45 A
    assert ask(resp, b"J,5,1,10,200,10,4") == b"j\n"         # 0.4 A
    assert ask(resp, b"D,10,10") == b"d\n"
    assert ask(resp, b"Y") == b"y,1,5,0,0\n"


def test_errors_are_not_mistaken_for_replies_by_libkoala() -> None:
    resp, _, _ = make()
    for line in (b"j", b"D,1", b"D,x,1", b"+"):
        wire = ask(resp, line)
        assert wire.startswith(b"#,") and wire.endswith(b"\n") and not wire.endswith(b"\r\n")
    assert ask(resp, b"Z") == b"z\n"


def test_reset_stops_the_wheels_and_restores_power_on_settings() -> None:
    resp, arb, port = make()
    step(port, 0.0)
    ask(resp, b"D,100,100")
    ask(resp, b"A,511")
    ask(resp, b"I,500,-500")
    assert ask(resp, b"Z") == b"z\n"
    assert arb.command(0.01) == WheelCommand(0.0, 0.0)
    assert ask(resp, b"P") == b"p,0,0\n"
    assert resp.auto_bits == 0 and ask(resp, b"Y") == b"y,0,0,0,0\n"


def test_auto_mode_pushes_each_stream_at_its_rate_in_simulated_time() -> None:
    resp, _, port = make()
    assert ask(resp, b"A,289") == b"a\n"                     # sonar + gyro + magnetometer
    lines: dict[str, int] = {}
    for k in range(1, 361):                                  # 3.6 s of 10 ms steps
        step(port, k * DT, sonar=(1.0,) * 9)
        for reply in resp.auto_lines(k * DT):
            lines[reply.letter] = lines.get(reply.letter, 0) + 1
    # 9 sonars x 20 ms = 180 ms: 20 sweeps in 3.6 s; gyro and magnetometer every 100 ms: 36
    assert lines == {"g": 20, "n": 36, "@": 36}
    # one sonar enabled: a sweep is one 20 ms measurement (the manual)
    assert ask(resp, b"C,8,0") == b"c\n" and ask(resp, b"A,1") == b"a\n"
    sweeps = sum(len(resp.auto_lines(k * DT)) for k in range(361, 561))   # 2 s more
    assert sweeps == 100
    assert ask(resp, b"A,0") == b"a\n"
    assert resp.auto_lines(3.7) == []
