"""bridge.robot_io: last command wins, watchdog, K-Team units and replies."""

from __future__ import annotations

import numpy as np
import pytest
from koala_bridge.drivers.kteam import format_reply, parse_command
from koala_bridge.drivers.messages import KteamCommand, Reject
from koala_bridge.runtime.robot_io import KteamResponder, MotorArbiter, RobotPort, RobotUnits
from koala_bridge.sim.types import IrReading, OdometryReading, Pose, Readings, WheelCommand

UNITS = RobotUnits(ticks_per_metre=90284.0, speed_unit_s=0.01)


def readings(t: float, left: int, right: int, speed: float = 0.0) -> Readings:
    counts = np.arange(16) * 10
    return Readings(
        t=t, pose=Pose(0, 0, 0), wheel_speeds=WheelCommand(speed, speed),
        odometry=OdometryReading(left, right),
        ir=IrReading(counts, counts + 1, counts, np.full(16, np.inf)),
    )


def test_last_command_received_wins_whatever_the_bus() -> None:
    arb = MotorArbiter()
    assert arb.command(0.0) == WheelCommand(0.0, 0.0)
    arb.set(0.1, 0.1, "kteam")
    arb.set(0.2, -0.2, "can.slcan")
    assert arb.command(0.1) == WheelCommand(0.2, -0.2)
    assert arb.source == "can.slcan"
    arb.set(0.05, 0.05, "kteam")
    assert arb.command(0.2) == WheelCommand(0.05, 0.05)


def test_watchdog_off_holds_and_on_stops() -> None:
    arb = MotorArbiter(watchdog_s=0.0)
    arb.set(0.1, 0.1, "kteam")
    assert arb.command(1000.0) == WheelCommand(0.1, 0.1)
    dog = MotorArbiter(watchdog_s=0.5)
    dog.command(1.0)
    dog.set(0.1, 0.1, "kteam")
    assert dog.command(1.4) == WheelCommand(0.1, 0.1)
    assert dog.command(1.6) == WheelCommand(0.0, 0.0)
    assert dog.source == "watchdog"


def test_kteam_speed_unit_is_pulses_per_10ms() -> None:
    # Koala 2.5 manual: speed in pulses per 10 ms; 90'284 pulses per metre.
    assert UNITS.kteam_speed_to_mps(90) == pytest.approx(90 * 100 / 90284)
    assert UNITS.mps_to_kteam_speed(UNITS.kteam_speed_to_mps(-37)) == -37


def responder() -> tuple[KteamResponder, MotorArbiter, RobotPort]:
    arb, port = MotorArbiter(), RobotPort()
    return KteamResponder(port, arb, UNITS), arb, port


def ask(resp: KteamResponder, line: bytes) -> bytes:
    cmd = parse_command(line, resp.specs)
    return format_reply(resp.reject(cmd) if isinstance(cmd, Reject) else resp.respond(cmd))


def test_kteam_replies() -> None:
    resp, arb, port = responder()
    port.update(readings(0.5, 1000, -200, speed=UNITS.kteam_speed_to_mps(20)))
    assert ask(resp, b"B").startswith(b"b,")
    assert ask(resp, b"D,20,-20") == b"d\r\n"
    assert arb.command(0.5) == WheelCommand(UNITS.kteam_speed_to_mps(20),
                                            UNITS.kteam_speed_to_mps(-20))
    assert ask(resp, b"E") == b"e,20,20\r\n"
    assert ask(resp, b"H") == b"h,1000,-200\r\n"
    assert ask(resp, b"N") == b"n," + b",".join(str(i * 10).encode() for i in range(16)) + b"\r\n"
    assert ask(resp, b"O").startswith(b"o,1,11,")
    assert ask(resp, b"L,1,1") == b"l\r\n" and port.leds == [0, 1]
    assert ask(resp, b"L,1,2") == b"l\r\n" and port.leds == [0, 0]
    assert ask(resp, b"L,0,2") == b"l\r\n" and port.led_states() == [1, 0]  # status "leds"


def test_g_sets_the_counters_that_h_reports() -> None:
    resp, _, port = responder()
    port.update(readings(0.0, 5000, 7000))
    assert ask(resp, b"G,0,100") == b"g\r\n"
    assert ask(resp, b"H") == b"h,0,100\r\n"
    port.update(readings(0.1, 5090, 7090))
    assert ask(resp, b"H") == b"h,90,190\r\n"
    assert port.robot_counters((5090, 7090)) == (90, 190)


def test_counters_wrap_to_int32() -> None:
    resp, _, port = responder()
    port.update(readings(0.0, 0, 0))
    resp.respond(KteamCommand("G", (2**31 - 1, 0)))
    port.update(readings(0.1, 1, 0))
    assert port.counters() == (-(2**31), 0)


@pytest.mark.parametrize(
    ("line", "reply"),
    [
        (b"X", b"z,Unknown command\r\n"),
        (b"D,1", b"z,Protocol error\r\n"),
        (b"D,1000,0", b"z,Out of range\r\n"),
        (b"D,a,b", b"z,Protocol error\r\n"),
        (b"\xff\xfe", b"z,Protocol error\r\n"),
    ],
)
def test_bad_commands_get_error_replies_and_change_nothing(line: bytes, reply: bytes) -> None:
    resp, arb, _ = responder()
    arb.set(0.01, 0.01, "kteam")
    assert ask(resp, line) == reply
    assert arb.command(0.0) == WheelCommand(0.01, 0.01)


def test_kteam_position_move_follows_the_j_trapezoid_and_k_reports_it() -> None:
    """C under J: integrate the arbiter's commands (10 ms steps, no drive error) and the counters
    reach the targets; K says position mode, then on target."""
    resp, arb, port = responder()
    dt, t, ticks = 0.01, 0.0, [0.0, 0.0]
    port.update(readings(t, 0, 0))
    arb.command(t)
    assert ask(resp, b"J,10,128,5,64") == b"j\r\n"
    assert ask(resp, b"C,2000,-500") == b"c\r\n"
    k = parse_command(b"K")
    assert not isinstance(k, Reject)
    first = resp.respond(k).ints
    assert first[1] == 0 and first[4] == 0 and first[0] == 0
    assert first[2] == 2000 and first[5] == -500
    vmax_left = UNITS.kteam_speed_to_mps(10)
    for _ in range(2000):
        cmd = arb.command(t)
        assert abs(cmd.left) <= vmax_left + 1e-12
        ticks[0] += cmd.left * dt * UNITS.ticks_per_metre
        ticks[1] += cmd.right * dt * UNITS.ticks_per_metre
        t += dt
        port.update(readings(t, round(ticks[0]), round(ticks[1])))
        arb.command(t)
        if resp.respond(k).ints[0] and resp.respond(k).ints[3]:
            break
    on_l, mode_l, err_l, on_r, mode_r, err_r = resp.respond(k).ints
    assert (on_l, mode_l, on_r, mode_r) == (1, 0, 1, 0)
    assert abs(err_l) <= 20 and abs(err_r) <= 20   # sampling of the ramps at 10 ms


def test_kteam_d_after_c_is_speed_mode() -> None:
    resp, arb, port = responder()
    port.update(readings(0.0, 0, 0))
    ask(resp, b"C,1000,1000")
    ask(resp, b"D,3,3")
    assert ask(resp, b"K").startswith(b"k,0,1,3,0,1,3")


def test_kteam_b_is_numbers_and_settings_are_acknowledged() -> None:
    resp, _arb, _port = responder()
    assert ask(resp, b"B") == b"b,0.1,1.0\r\n"
    assert ask(resp, b"A,3800,800,100") == b"a\r\n" and resp.speed_pid == (3800, 800, 100)
    assert ask(resp, b"F,100,0,0") == b"f\r\n" and resp.position_pid == (100, 0, 0)
    assert ask(resp, b"Q,1,1") == b"q\r\n" and resp.outputs[1] == 1
    assert ask(resp, b"I,0") == b"i,0\r\n" and ask(resp, b"Y") == b"y,0\r\n"
    assert ask(resp, b"J,0,10,10,10") == b"z,Out of range\r\n"
