"""``--clock lockstep`` (issue 14, docs/protocols.md §6): the bridge in this process, its
firmware a client on the real transports (pyserial on the K-Team pty, python-can's
``socketcand`` interface, zenoh-python for explicit steps).

Each test runs :meth:`SimulatedRobotSource.run` in a thread and plays the firmware from the test
thread; nothing here measures wall time except to give up."""

from __future__ import annotations

import json
import re
import threading
from typing import Any

import pytest
import zenoh
from _inproc import WAIT_S, ask, bridge, kteam, lockstep_config, socketcand, zenoh_session
from koala_bridge.core.errors import ConfigError
from koala_bridge.drivers.can_codec import KoalaCanCodec
from koala_bridge.drivers.messages import MotorCommandFrame, WheelOdometryFrame
from koala_bridge.runtime.settings import BridgeSettings
from koala_bridge.runtime.sim_source import SimulatedRobotSource


def test_held_at_zero_until_the_first_d_then_one_period_per_d() -> None:
    with bridge("lockstep.period_s=0.03") as source, kteam(source) as port:
        assert source.lockstep is not None
        # requests before the first D are answered at t = 0, however long the firmware takes
        for _ in range(5):
            assert ask(port, "H") == "h,0,0"
        assert not source.lockstep.engaged and source.port.t == 0.0
        for k in range(1, 11):
            assert ask(port, "D,10,-10") == "d"          # answered once 30 ms are simulated
            assert source.port.t == pytest.approx(0.03 * k)
            # 3 steps of 10 pulses per D; the reply comes from the boundary's state
            assert ask(port, "H") == f"h,{30 * k},{-30 * k}"
        status = source.status(source.port.t)
        assert status["lockstep"] == {"engaged": True, "cycles": 10, "explicit": 0, "misses": 0,
                                      "unpaced_steps": 0}


def test_the_run_ends_when_the_firmware_closes_the_cycle_bus() -> None:
    config = lockstep_config()
    source = SimulatedRobotSource(config, BridgeSettings.from_config(config))
    source.open()
    try:
        result: list[Any] = []
        loop = threading.Thread(target=lambda: result.append(source.run(threading.Event(), 0)),
                                daemon=True)
        loop.start()
        with kteam(source) as port:
            for _ in range(7):
                ask(port, "D,5,5")
        loop.join(WAIT_S)
        assert not loop.is_alive(), "the run did not end when the firmware left"
        assert result[0].t == pytest.approx(0.07)
    finally:
        source.close()


def test_duration_counts_simulated_seconds() -> None:
    with bridge(duration_s=0.05) as source, kteam(source) as port:
        for _ in range(5):
            assert ask(port, "D,1,1") == "d"
        assert source.port.t == pytest.approx(0.05)
        port.write(b"D,1,1\n")      # the run is over: no period is simulated for it
        assert source.port.t == pytest.approx(0.05)


def test_a_can_cycle_message_paces_the_run_and_every_frame_is_stamped_in_simulated_time() -> None:
    with bridge('lockstep.cycle_bus="can"', 'lockstep.cycle_message="MotorCommand"',
                "lockstep.period_s=0.02") as source, socketcand(source) as bus:
        codec = KoalaCanCodec()
        odometry: list[tuple[float, WheelOdometryFrame]] = []
        for k in range(1, 6):
            bus.send(codec.encode(MotorCommandFrame(0.1, 0.1)))
            # a CAN firmware reads until the sample stamped at the cycle's end
            while not odometry or odometry[-1][0] < 0.02 * k - 1e-9:
                msg = bus.recv(WAIT_S)
                assert msg is not None, f"no odometry for cycle {k}"
                frame = codec.decode(msg)
                if isinstance(frame, WheelOdometryFrame) and (
                        not odometry or msg.timestamp > odometry[-1][0]):
                    odometry.append((msg.timestamp, frame))
        assert source.lockstep is not None and source.lockstep.cycles == 5
        stamps = [t for t, _ in odometry if t > 0]
        assert stamps == pytest.approx([0.01 * i for i in range(1, 11)])    # 100 Hz, no gaps
        # nothing runs ahead of the firmware: the bridge waits at the last boundary
        assert source.port.t == pytest.approx(0.10)


def test_a_quiet_firmware_is_stepped_after_the_timeout_when_asked_and_each_is_a_miss() -> None:
    with bridge('lockstep.on_quiet="step"', "lockstep.quiet_timeout_s=0.05") as source, \
            kteam(source) as port:
        assert source.lockstep is not None
        assert ask(port, "D,0,0") == "d"
        # silence: the bridge steps by itself, one period per quiet timeout
        assert source.lockstep.wait_done(source.lockstep.done + 3, WAIT_S)
        assert source.lockstep.misses >= 3
        assert source.lockstep.cycles == 1


def test_the_default_waits_for_ever_for_a_quiet_firmware() -> None:
    with bridge() as source, kteam(source) as port:
        assert source.lockstep is not None
        assert ask(port, "D,0,0") == "d"
        # nothing comes: however long we wait, no step runs
        assert not source.lockstep.wait_done(2, timeout=0.5)
        assert source.port.t == pytest.approx(0.01) and source.lockstep.misses == 0


def step_query(session: zenoh.Session, prefix: str, payload: str | None) -> list[Any]:
    replies = session.get(f"{prefix}/lockstep/step", payload=payload, timeout=WAIT_S)
    out = []
    for reply in replies:
        if reply.ok is not None:
            out.append(json.loads(reply.ok.payload.to_bytes()))
        else:
            out.append(("error", reply.err.payload.to_bytes().decode()))
    return out


def test_an_explicit_step_over_zenoh_grants_cycles_when_remote_commands_are_on() -> None:
    with bridge("zenoh.remote_commands=true", "lockstep.period_s=0.02") as source, \
            zenoh_session(source) as z:
        prefix = source.settings.zenoh.prefix
        assert step_query(z, prefix, '{"cycles": 3}') == [
            {"t": pytest.approx(0.06), "step": 6, "cycles": 3}]
        assert step_query(z, prefix, None)[0]["t"] == pytest.approx(0.08)
        (bad,) = step_query(z, prefix, '{"cycles": 0}')
        assert bad[0] == "error" and "'cycles' must be an integer" in bad[1]
        assert source.lockstep is not None and source.lockstep.explicit == 4


def test_without_remote_commands_nobody_answers_a_step() -> None:
    with bridge() as source, zenoh_session(source) as z:
        assert step_query(z, source.settings.zenoh.prefix, '{"cycles": 1}') == []
        assert source.port.t == 0.0


@pytest.mark.parametrize("override, message", [
    ("lockstep.period_s=0.015", "'period_s' must be a whole multiple of [sim] dt_s"),
    ('lockstep.cycle_message="DD"', "'cycle_message' must be a K-Team command letter"),
    ('lockstep.on_quiet="sleep"', "on_quiet"),
    ("lockstep.perod_s=0.01", "did you mean"),
])
def test_bad_lockstep_settings_are_one_clear_error(override: str, message: str) -> None:
    config = lockstep_config(override)
    with pytest.raises(ConfigError, match=message.replace("[", r"\[").replace("]", r"\]")):
        SimulatedRobotSource(config, BridgeSettings.from_config(config))


@pytest.mark.parametrize("overrides, message", [
    (['lockstep.cycle_bus="can"', 'lockstep.cycle_message="Motor"'],
     "'Motor' is not a message of the DBC; the firmware's message in the DBC is 'MotorCommand'"),
    (['lockstep.cycle_bus="can"', 'lockstep.cycle_message="Gyro"'],
     "'Gyro' is a message the robot sends, not one the firmware sends"),
    (['lockstep.cycle_message="X"'], "'X' is not a command of the koala1 dialect"),
])
def test_the_cycle_message_must_be_one_the_firmware_sends(overrides: list[str],
                                                          message: str) -> None:
    config = lockstep_config(*overrides)
    with pytest.raises(ConfigError, match=re.escape(message)):
        SimulatedRobotSource(config, BridgeSettings.from_config(config))


def test_a_firmware_that_leaves_before_its_first_command_ends_the_run() -> None:
    config = lockstep_config()
    source = SimulatedRobotSource(config, BridgeSettings.from_config(config))
    source.open()
    try:
        loop = threading.Thread(target=source.run, args=(threading.Event(), 0), daemon=True)
        loop.start()
        with kteam(source) as port:
            assert ask(port, "B").startswith("b,")       # it starts, asks, and crashes
        loop.join(WAIT_S)
        assert not loop.is_alive(), "the run waited for ever for a firmware that had gone"
        assert source.port.t == 0.0
    finally:
        source.close()


def test_explicit_steps_with_no_firmware_on_the_cycle_bus_do_not_end_the_run() -> None:
    with bridge("zenoh.remote_commands=true") as source, zenoh_session(source) as z:
        prefix = source.settings.zenoh.prefix
        for k in range(1, 4):
            assert step_query(z, prefix, None)[0]["t"] == pytest.approx(0.01 * k)
            assert source.lockstep is not None
            # the loop's wait for the next grant has timed out a few times meanwhile
            assert not source.lockstep.wait_done(k + 1, timeout=0.3)


def test_the_step_queryable_says_so_in_another_clock() -> None:
    with bridge('run.clock="fast"', "zenoh.remote_commands=true", duration_s=0.1) as source, \
            zenoh_session(source) as z:
        (error,) = step_query(z, source.settings.zenoh.prefix, None)
        assert error == ("error", "lockstep/step: the bridge runs the fast clock; only "
                                  "--clock lockstep is stepped")


def test_held_step_0_goes_again_to_udp_at_most_every_quarter_second(monkeypatch) -> None:
    # Where clients cannot be seen (MAVLink over UDP) step 0 is re-sent while held, but not at
    # every poll: a firmware that bound its port and is not reading yet would find its socket
    # buffer full of step 0 and the kernel dropping the samples it then asks for. At the first
    # command it goes once more, whenever the last one went.
    from koala_bridge.runtime import sim_source as mod

    now = [100.0]
    monkeypatch.setattr(mod.time, "monotonic", lambda: now[0])
    config = lockstep_config()
    source = SimulatedRobotSource(config, BridgeSettings.from_config(config))
    sent: list[float] = []
    source._initial_frames = [("mavlink", lambda: sent.append(now[0]))]
    monkeypatch.setattr(source, "_client_mark", lambda bus: None)    # UDP: nobody seen
    for _ in range(10):                         # ten polls within one instant: one re-send
        source._resend_initial(held=True)
    assert sent == [100.0]
    now[0] += mod.UNSEEN_RESEND_S / 2
    source._resend_initial(held=True)
    assert sent == [100.0]
    now[0] += mod.UNSEEN_RESEND_S / 2
    source._resend_initial(held=True)
    assert sent == [100.0, 100.0 + mod.UNSEEN_RESEND_S]
    source._resend_initial()                    # the firmware's first command: at once
    assert len(sent) == 3
