"""runtime.sim_source in-process: python-can `virtual` (in-process only) commands the robot; opening
fails cleanly; close() leaves no thread, pty or socket behind (the autouse leak check)."""

from __future__ import annotations

import socket
import threading
from pathlib import Path

import can
import cantools
import pytest
from koala_bridge.runtime.buses import BusOpenError
from koala_bridge.runtime.clock import FastClock
from koala_bridge.runtime.settings import (
    BridgeSettings,
    apply_override,
    load_config,
    parse_override,
)
from koala_bridge.runtime.sim_source import SimulatedRobotSource

REPO = Path(__file__).resolve().parents[2]


def make_service(zenoh_port: int, mavlink_port: int, *extra: str) -> SimulatedRobotSource:
    config = load_config(REPO / "config" / "default.toml")
    overrides = [
        "run.clock=fast",
        f'zenoh.listen=["tcp/127.0.0.1:{zenoh_port}"]',
        f"buses.mavlink.port={mavlink_port}",
        "buses.can.socketcand_port=0",
        f'buses.can.virtual_channel="koala-test-{zenoh_port}"',
        *extra,
    ]
    for text in overrides:
        config = apply_override(config, *parse_override(text))
    return SimulatedRobotSource(config, BridgeSettings.from_config(config))


def test_virtual_can_motor_command_drives_the_robot(free_tcp_port: int,
                                                    free_udp_port: int) -> None:
    db = cantools.database.load_file(str(REPO / "config" / "koala.dbc"))
    service = make_service(free_tcp_port, free_udp_port)
    stop = threading.Event()
    with service:
        endpoints = service.open()
        assert endpoints.virtual_can_channel == f"koala-test-{free_tcp_port}"
        runner = threading.Thread(target=service.run, args=(stop,), kwargs={"duration_s": 0})
        runner.start()
        try:
            with can.Bus(interface="virtual", channel=endpoints.virtual_can_channel) as bus:
                odo_id = db.get_message_by_name("WheelOdometry").frame_id
                msg = bus.recv(10)
                while msg is not None and msg.arbitration_id != odo_id:
                    msg = bus.recv(10)
                assert msg is not None
                x0 = service.port.t, service._last_readings.pose.x  # type: ignore[union-attr]
                bus.send(can.Message(
                    arbitration_id=db.get_message_by_name("MotorCommand").frame_id,
                    is_extended_id=False,
                    data=db.encode_message("MotorCommand", {"left_speed": 0.2, "right_speed": 0.2}),
                ))
                for _ in range(2000):
                    r = bus.recv(5)
                    assert r is not None
                    if service._last_readings.pose.x > x0[1] + 0.1:  # type: ignore[union-attr]
                        break
                else:
                    pytest.fail("robot did not move")
                status = service.status(service.port.t)
                assert status["buses"]["can.virtual"]["received"] == 1
                assert status["motor_command_source"] == "can.virtual"
        finally:
            stop.set()
            runner.join(60)
    assert not runner.is_alive()


def test_a_bus_that_cannot_open_closes_everything_opened_before(free_tcp_port: int,
                                                                free_udp_port: int) -> None:
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        service = make_service(free_tcp_port, free_udp_port, f"buses.can.socketcand_port={port}")
        with pytest.raises(BusOpenError, match="can.socketcand"):
            service.open()
        service.close()  # idempotent


def test_run_for_a_duration_returns_the_last_readings(free_tcp_port: int,
                                                      free_udp_port: int) -> None:
    service = make_service(free_tcp_port, free_udp_port, "buses.kteam.enabled=false",
                           "buses.can.slcan=false")
    with service:
        endpoints = service.open()
        assert endpoints.kteam is None and endpoints.slcan is None
        last = service.run(threading.Event(), duration_s=1.5)
    assert last.t == pytest.approx(1.5)
    # run.clock=fast: the loop is never paced (FastClock never waits, test_bridge_clock.py). How
    # much faster than real time 1.5 s ran is the machine's speed and load, not asserted here;
    # test_status_counts_and_real_time_factor sees a bridge's status report it above 1.
    assert isinstance(service.clock, FastClock)
