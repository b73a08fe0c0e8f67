"""bridge.zenoh_io: JSON messages (truth companions, null for no echo) and a real Zenoh session:
a peer on loopback with multicast scouting off, as zenoh-python's own tests do."""

from __future__ import annotations

import json
import math
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import zenoh
from koala_bridge.runtime.counters import BusCounters
from koala_bridge.runtime.settings import (
    BridgeSettings,
    apply_override,
    load_config,
    parse_override,
)
from koala_bridge.runtime.zenoh_io import (
    ZenohLink,
    encode,
    sensor_messages,
    session_config,
    status_message,
)
from koala_bridge.sim.types import (
    CameraReading,
    CompassReading,
    GyroReading,
    IrReading,
    LandmarkObservation,
    OdometryReading,
    Pose,
    Readings,
    SonarReading,
    WheelCommand,
)

REPO = Path(__file__).resolve().parents[2]


def readings(t: float = 1.25) -> Readings:
    """A stand-in for one simulator step with every sensor due."""
    obs = (LandmarkObservation(2, 1.5, -0.25),)
    return Readings(
        t=t,
        pose=Pose(1.0, 2.0, 0.5),
        wheel_speeds=WheelCommand(0.1, 0.1),
        ir=IrReading(np.full(16, 7), np.full(16, 3), np.full(16, 6), np.full(16, np.inf)),
        sonar=SonarReading(np.array([0.5, np.nan]), np.array([0.49, np.nan]),
                           np.array([0.1, np.nan])),
        odometry=OdometryReading(100, -20),
        gyro=GyroReading(0.25, 0.2),
        compass=CompassReading(np.array([20.0, -1.0, -43.0]), np.array([19.0, 0.0, -43.0])),
        camera=CameraReading(obs, obs),
    )


def test_sensor_messages_carry_truth_with_the_same_field_names() -> None:
    m = sensor_messages(readings())
    assert set(m) == {"sensors/ir", "sensors/sonar", "sensors/odometry", "sensors/gyro",
                      "sensors/compass", "sensors/camera"}
    for msg in m.values():
        assert msg["t"] == 1.25
        assert "truth" in msg
        for key in msg["truth"]:
            assert key in msg or key in ("ranges", "incidence")  # IR: counts measured, ranges true
    assert m["sensors/sonar"]["ranges"] == [0.5, None]      # null = no echo
    assert m["sensors/sonar"]["truth"]["incidence"] == [0.1, None]
    ir = m["sensors/ir"]["truth"]
    assert ir["counts"] == [6] * 16
    assert ir["ranges"] == [None] * 16 and ir["incidence"] == [None] * 16  # nothing in range
    assert m["sensors/compass"]["truth"] == {"mx": 19.0, "my": 0.0, "mz": -43.0}
    assert m["sensors/camera"]["observations"] == [{"id": 2, "range": 1.5, "bearing": -0.25}]
    json.loads(encode(m["sensors/sonar"]))  # strict JSON: no NaN literal


def test_ir_truth_carries_axis_ranges_and_the_given_incidence() -> None:
    r = readings()
    ranges = np.full(16, np.inf)
    ranges[:2] = [0.05, 0.2]
    ir = IrReading(r.ir.counts, r.ir.ambient, r.ir.truth_counts, ranges)
    incidence = np.full(16, np.nan)
    incidence[:2] = [0.0, 0.3]
    m = sensor_messages(Readings(r.t, r.pose, r.wheel_speeds, ir=ir), ir_incidence=incidence)
    truth = m["sensors/ir"]["truth"]
    assert truth["ranges"] == [0.05, 0.2] + [None] * 14
    assert truth["incidence"] == [0.0, 0.3] + [None] * 14
    json.loads(encode(m["sensors/ir"]))


def test_only_due_readings_are_published() -> None:
    r = Readings(t=0.0, pose=Pose(0, 0, 0), wheel_speeds=WheelCommand())
    assert sensor_messages(r) == {}


def test_status_message_and_nan_rtf() -> None:
    msg = status_message(2.0, math.nan, {"kteam": {"sent": 1, "received": 2, "rejected": 3}})
    assert msg == {"t": 2.0, "real_time_factor": None,
                   "buses": {"kteam": {"sent": 1, "received": 2, "rejected": 3}}}


def settings(port: int):
    cfg = load_config(REPO / "config" / "default.toml")
    cfg = apply_override(cfg, *parse_override(f'zenoh.listen=["tcp/127.0.0.1:{port}"]'))
    return BridgeSettings.from_config(cfg).zenoh


def test_session_config_sets_loopback_peer_without_multicast() -> None:
    c = session_config(settings(7447))
    assert json.loads(c.get_json("mode")) == "peer"
    assert json.loads(c.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7447"]
    assert json.loads(c.get_json("scouting/multicast/enabled")) is False


def client_session(endpoint: str) -> zenoh.Session:
    c = zenoh.Config()
    c.insert_json5("mode", '"peer"')
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("connect/endpoints", json.dumps([endpoint]))
    return zenoh.open(c)


@pytest.fixture
def link_and_client(
    free_tcp_port: int,
) -> Iterator[tuple[ZenohLink, zenoh.Session, BusCounters]]:
    port = free_tcp_port
    counters = BusCounters()
    link = ZenohLink(settings(port), lambda: {"cols": 6, "robot": {"wheel_base_m": 0.3}},
                     counters)
    client = client_session(f"tcp/127.0.0.1:{port}")
    try:
        yield link, client, counters
    finally:
        client.close()
        link.close()


def test_publish_and_subscribe_over_loopback(link_and_client) -> None:
    link, client, counters = link_and_client
    got: dict[str, dict] = {}
    done = threading.Event()

    def on_sample(sample: zenoh.Sample) -> None:
        got[str(sample.key_expr)] = json.loads(sample.payload.to_bytes())
        if len(got) >= 7:
            done.set()

    sub = client.declare_subscriber(f"{link.prefix}/**", on_sample)
    try:
        deadline = time.monotonic() + 10
        while not done.is_set() and time.monotonic() < deadline:
            link.publish_readings(readings(), with_pose=True)
            done.wait(0.1)
    finally:
        sub.undeclare()
    assert got[f"{link.prefix}/truth/pose"] == {"t": 1.25, "x": 1.0, "y": 2.0, "theta": 0.5}
    assert got[f"{link.prefix}/sensors/gyro"]["truth"] == {"yaw_rate": 0.2}
    assert counters.snapshot()["zenoh"]["sent"] >= 7


def test_a_publisher_thread_racing_close_neither_raises_nor_puts_after_it(
    free_tcp_port: int,
) -> None:
    # A loop not yet stopped when its link closes (a loaded machine): its put() and close()'s
    # undeclare() once met in one publisher ("Already borrowed"). Now a put after close is
    # nothing, and none overlaps the undeclare.
    counters = BusCounters()
    link = ZenohLink(settings(free_tcp_port), dict, counters)
    errors: list[BaseException] = []
    started = threading.Event()

    def publisher() -> None:
        try:
            for k in range(100_000):
                link.publish("sensors/gyro", {"k": k})
                started.set()
        except BaseException as e:      # noqa: BLE001 - the test's subject
            errors.append(e)

    t = threading.Thread(target=publisher)
    t.start()
    assert started.wait(10)
    link.close()
    sent = counters.snapshot()["zenoh"]["sent"]
    t.join(60)
    assert not t.is_alive() and errors == []
    assert counters.snapshot()["zenoh"]["sent"] == sent     # nothing put after close
    link.close()                                             # idempotent


def test_world_queryable_answers_json(link_and_client) -> None:
    link, client, counters = link_and_client
    deadline = time.monotonic() + 10
    answer = None
    while answer is None and time.monotonic() < deadline:
        for reply in client.get(f"{link.prefix}/world", timeout=2.0):
            if reply.ok is not None:
                answer = json.loads(reply.ok.payload.to_bytes())
        if answer is None:
            time.sleep(0.1)
    assert answer == {"cols": 6, "robot": {"wheel_base_m": 0.3}}
    assert counters.snapshot()["zenoh"]["received"] >= 1


def test_port_in_use_is_a_clear_error(free_tcp_port: int) -> None:
    port = free_tcp_port
    with ZenohLink(settings(port), dict):
        with pytest.raises(OSError, match="cannot open the Zenoh session"):
            ZenohLink(settings(port), dict)
