"""The classic Koala dialect (``koala1``) as K-Team's KoreBot ``koala.c`` drives it.

The client below is written from docs/protocols.md §1 "Classic Koala (koala1) commands" — the
command strings and reply formats KoreBot's ``koala.c`` sends and ``sscanf``s — not from the
bridge's code: it formats commands by hand and parses replies as C does (``b,%d.%d,%d.%d``,
``h,%d,%d``, ``k,%d,%d,%d,%d,%d,%d``). It talks to a ``koala-bridge run`` subprocess through the
K-Team pty, opened as the ROS koala driver opens the robot's port (38400 baud, 8 data bits,
2 stop bits; a pty ignores the line settings). Waits are on conditions, never on time.
"""

from __future__ import annotations

import re
import time
from collections.abc import Iterator

import pytest
import serial
from koala_bridge.runtime.robot_io import VERSION_TEXT

DEADLINE_S = 60.0       # wall-clock bound on a condition, generous for a busy machine


class KoreBotKoala:
    """The subset of KoreBot ``koala.c`` the tests need: one command, one CR LF reply."""

    def __init__(self, port: serial.Serial) -> None:
        self.port = port

    def _ask(self, command: str, reply_pattern: str) -> tuple[int, ...]:
        self.port.write(command.encode("ascii") + b"\r")
        line = self.port.read_until(b"\r\n")
        assert line.endswith(b"\r\n"), f"no reply to {command!r}: {line!r}"
        text = line[:-2].decode("ascii")
        m = re.fullmatch(reply_pattern, text)
        assert m is not None, f"{command!r} -> {text!r} does not match {reply_pattern!r}"
        return tuple(int(g) for g in m.groups())

    def get_os_version(self) -> tuple[int, int, int, int]:
        """``koa_getOSVersion``: ``b,%d.%d,%d.%d`` -> version, revision, protocol v., r."""
        v = self._ask("B", r"b,(\d+)\.(\d+),(\d+)\.(\d+)")
        return v[0], v[1], v[2], v[3]

    def set_speed(self, left: int, right: int) -> None:
        self._ask(f"D,{left},{right}", "d")

    def read_speed(self) -> tuple[int, ...]:
        return self._ask("E", r"e,(-?\d+),(-?\d+)")

    def set_position_counter(self, left: int, right: int) -> None:
        self._ask(f"G,{left},{right}", "g")

    def read_position(self) -> tuple[int, ...]:
        return self._ask("H", r"h,(-?\d+),(-?\d+)")

    def set_position(self, left: int, right: int) -> None:
        self._ask(f"C,{left},{right}", "c")

    def config_speed_profile(self, vmax_l: int, acc_l: int, vmax_r: int, acc_r: int) -> None:
        self._ask(f"J,{vmax_l},{acc_l},{vmax_r},{acc_r}", "j")

    def read_motion_status(self) -> tuple[int, ...]:
        """``k,T_l,M_l,E_l,T_r,M_r,E_r``: on target, mode (0 position, 1 speed), error."""
        return self._ask("K", r"k,([01]),([01]),(-?\d+),([01]),([01]),(-?\d+)")

    def set_speed_pid(self, kp: int, ki: int, kd: int) -> None:
        self._ask(f"A,{kp},{ki},{kd}", "a")

    def set_position_pid(self, kp: int, ki: int, kd: int) -> None:
        self._ask(f"F,{kp},{ki},{kd}", "f")

    def raw(self, line: str) -> str:
        self.port.write(line.encode("ascii") + b"\r")
        return self.port.read_until(b"\r\n").decode("ascii")


@pytest.fixture
def koala(bridge) -> Iterator[KoreBotKoala]:
    b = bridge(sets=["buses.rangefinders.enabled=false"])
    path = b.endpoints["serial"]["kteam"]
    with serial.Serial(path, 38400, bytesize=8, stopbits=serial.STOPBITS_TWO, timeout=5) as port:
        yield KoreBotKoala(port)
    assert b.stop() == 0


def test_b_parses_as_numbers_like_korebot(koala: KoreBotKoala) -> None:
    version, revision, proto, proto_rev = koala.get_os_version()
    # the regex already admits only digits: the numbers must be the ones the bridge sends
    assert (version, revision, proto, proto_rev) == tuple(
        int(n) for n in re.split(r"[.,]", VERSION_TEXT))


def test_pid_settings_are_acknowledged(koala: KoreBotKoala) -> None:
    koala.set_speed_pid(3800, 800, 100)
    koala.set_position_pid(100, 0, 0)
    assert koala.raw("A,1,2") == "z,Protocol error\r\n"


def test_unknown_letter_gets_unknown_command(koala: KoreBotKoala) -> None:
    assert koala.raw("X") == "z,Unknown command\r\n"
    assert koala.raw("J,0,10,10,10") == "z,Out of range\r\n"     # profile speed >= 1


def test_c_moves_to_the_target_under_the_j_profile_and_k_reports_it(
    koala: KoreBotKoala,
) -> None:
    koala.set_position_counter(0, 0)
    koala.config_speed_profile(20, 64, 10, 64)
    koala.set_position(3000, -1500)
    status = koala.read_motion_status()
    assert status[1] == 0 and status[4] == 0                     # position mode
    deadline = time.monotonic() + DEADLINE_S
    speeds_seen = []
    while True:
        speeds_seen.append(koala.read_speed())
        status = koala.read_motion_status()
        if status[0] == 1 and status[3] == 1:
            break
        assert time.monotonic() < deadline, f"move never ended: {status}"
    # the profile's max speed per wheel is respected (E is rounded to whole units)
    assert all(abs(left) <= 20 and abs(right) <= 10 for left, right in speeds_seen)
    left, right = koala.read_position()
    # open-loop trapezoid sampled every 10 ms: within a few pulses of the target
    assert abs(left - 3000) <= 30 and abs(right + 1500) <= 30, (left, right)
    assert status[2] == 3000 - left and status[5] == -1500 - right


def test_d_after_c_switches_k_to_speed_mode(koala: KoreBotKoala) -> None:
    koala.set_position(100000, 100000)
    koala.set_speed(0, 0)
    status = koala.read_motion_status()
    assert status[1] == 1 and status[4] == 1


# -- management sensors, as the ROS koala driver reads them --------------------------------------
#
# jdawkins/koala-ros, jjdawkins/koala_driver (src/koala.cpp) and jjdawkins/koala_ros2
# (koala_node.py) open the port at 38400 baud, 8 data bits, no parity, 2 stop bits, end every
# command with "\n", read a reply up to "\n" and take the text after the first comma. `M,n`
# reads management sensor n; their conversions: 0 battery voltage 20 mV/unit, 1 consumption
# current 8 mA/unit, 2 ambient temperature 0.1 degC, 3/4 left/right motor current 4 mA/unit,
# 5 battery temperature 0.1 degC. `S` -> `s,<remaining charge, mAh>` is the bridge's reading (no
# driver sends S). Bounds come from [robot.battery] (config/default.toml) through the model in
# sim/battery.py's docstring.

MGMT_UNITS = {0: 0.020, 1: 0.008, 2: 0.1, 3: 0.004, 4: 0.004, 5: 0.1}   # V, A, degC, A, A, degC


class RosKoala:
    """The ROS koala driver's serial I/O: "\\n"-ended commands, replies read up to "\\n"."""

    def __init__(self, port: serial.Serial) -> None:
        self.port = port

    def ask(self, command: str, letter: str) -> str:
        self.port.write(command.encode("ascii") + b"\n")
        line = self.port.read_until(b"\n").decode("ascii")
        assert line.endswith("\n"), f"no reply to {command!r}: {line!r}"
        assert line.startswith(letter), f"{command!r} -> {line!r}"
        return line

    def management(self, n: int) -> float:
        """``M,n`` -> the driver's value in SI-ish units (V, A, degC)."""
        line = self.ask(f"M,{n}", "m")
        return float(line.split(",", 1)[1]) * MGMT_UNITS[n]

    def charge_mAh(self) -> float:
        return float(self.ask("S", "s").split(",", 1)[1])

    def set_speed(self, left: int, right: int) -> None:
        self.ask(f"D,{left},{right}", "d")

    def read_speed(self) -> tuple[int, int]:
        left, right = self.ask("E", "e").split(",", 1)[1].split(",")
        return int(left), int(right)


def _battery() -> dict[str, float]:
    import tomllib

    from conftest import DEFAULT_CONFIG

    with open(DEFAULT_CONFIG, "rb") as f:
        return dict(tomllib.load(f)["robot"]["battery"])


@pytest.fixture
def ros_koala(bridge, zenoh_watch):
    b = bridge(sets=["buses.rangefinders.enabled=false"])
    path = b.endpoints["serial"]["kteam"]
    with serial.Serial(path, 38400, bytesize=serial.EIGHTBITS, parity=serial.PARITY_NONE,
                       stopbits=serial.STOPBITS_TWO, timeout=5) as port:
        yield RosKoala(port), zenoh_watch(b)
    assert b.stop() == 0


def test_management_sensors_at_rest_are_the_configured_battery(ros_koala) -> None:
    koala, watch = ros_koala
    bat = _battery()
    i_max = bat["idle_current_A"] + 2 * bat["motor_stall_current_A"]
    voltage, current, ambient, left, right, bat_temp = (koala.management(n) for n in range(6))
    # V = V_empty + (V_full - V_empty) soc - R I, soc <= initial_charge, I <= I_max
    ocv_max = bat["voltage_empty_V"] + (
        bat["voltage_full_V"] - bat["voltage_empty_V"]) * bat["initial_charge"]
    v_lo = bat["voltage_empty_V"] - bat["internal_resistance_ohm"] * i_max
    assert v_lo - 0.020 <= voltage <= ocv_max + 0.020, voltage
    # at rest I = I_idle (the wheels draw nothing): one unit of rounding either way
    assert abs(current - bat["idle_current_A"]) <= 0.008, current
    assert left == 0.0 and right == 0.0, (left, right)
    assert abs(ambient - bat["ambient_temperature_C"]) <= 0.1, ambient
    # T_bat rises from ambient towards T_amb + R I^2 R_th, never beyond it
    t_max = bat["ambient_temperature_C"] + (
        bat["internal_resistance_ohm"] * i_max**2 * bat["thermal_resistance_K_per_W"])
    assert bat["ambient_temperature_C"] - 0.1 <= bat_temp <= t_max + 0.1, bat_temp
    # Q = capacity x initial charge at reset, drained by at most I_max for the time run so far
    t = watch.wait_for("truth/pose")["t"]
    full = bat["capacity_mAh"] * bat["initial_charge"]
    assert full - i_max * (t + 1.0) / 3.6 - 1.0 <= koala.charge_mAh() <= full, t


def test_driving_draws_motor_current_and_charge(ros_koala) -> None:
    """At a steady wheel speed v a motor draws k_v |v| (sim/battery.py); 1 unit = 4.5 mm/s. The
    charge (whole mAh) falls by at least (I_idle + 2 k_v v) T / 3.6 over T s of steady driving and
    by at most I_max T / 3.6."""
    koala, watch = ros_koala
    bat = _battery()
    at_rest = koala.management(1)
    v_units = 60
    koala.set_speed(-v_units, v_units)                         # spin on the spot: no wall
    deadline = time.monotonic() + DEADLINE_S
    while koala.read_speed() != (-v_units, v_units):
        assert time.monotonic() < deadline
    t0 = watch.wait_for("truth/pose")["t"]
    watch.after("truth/pose", t0 + 0.5, timeout=DEADLINE_S)    # steady: no acceleration term
    v = v_units * 0.0045
    expected = bat["motor_current_per_mps_A"] * v
    left, right = koala.management(3), koala.management(4)
    assert abs(left - expected) <= 0.008 and abs(right - expected) <= 0.008, (left, right)
    driving = koala.management(1)
    i_drive = bat["idle_current_A"] + 2 * expected
    assert abs(driving - i_drive) <= 0.016, driving
    assert driving > at_rest
    t1 = watch.wait_for("truth/pose")["t"]
    charge1 = koala.charge_mAh()
    drive_s = 30.0
    watch.after("truth/pose", t1 + drive_s, timeout=DEADLINE_S)
    charge2 = koala.charge_mAh()
    t2 = watch.wait_for("truth/pose")["t"]
    koala.set_speed(0, 0)
    used = charge1 - charge2
    i_max = bat["idle_current_A"] + 2 * bat["motor_stall_current_A"]
    assert i_drive * drive_s / 3.6 - 1.0 <= used <= i_max * (t2 - t1 + 1.0) / 3.6 + 1.0, used
