"""`run --source real`: a second koala-bridge plays the robot; the real-driver bridge reads its
pty, socketcand and UDP endpoints and publishes on Zenoh exactly what the robot side sent."""

from __future__ import annotations

import argparse
import json
import subprocess
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import can
import pytest
from _mpl import fonts_loaded  # noqa: F401 - autouse fixture
from conftest import DEFAULT_CONFIG, REPO, BridgeProcess, bridge_command, free_port, wait_endpoints
from koala_bridge.cli import monitor as monitor_cli
from koala_bridge.cli import snapshot as snapshot_cli
from koala_bridge.core.schema import ConfigError
from koala_bridge.drivers.can_codec import KoalaCanCodec
from koala_bridge.drivers.mavlink_codec import CompassDecoder
from koala_bridge.drivers.messages import (
    CompassSample,
    GyroFrame,
    MotorCommandFrame,
    RangeFrame,
    RangeKind,
    WheelOdometryFrame,
)
from koala_bridge.drivers.rangeframes import NO_ECHO, decode_range_frame
from koala_bridge.recording.mcap_file import FROM_ROBOT, Recording, open_recording
from koala_bridge.runtime.real_source import RealPorts
from koala_bridge.tools.monitor import ZenohWatch

REAL_SECONDS = 5.0


def contiguous_in(part: Sequence[Any], whole: Sequence[Any]) -> bool:
    """``part`` is ``whole[i : i + len(part)]`` for some ``i``."""
    n = len(part)
    return any(list(whole[i : i + n]) == list(part) for i in range(len(whole) - n + 1))


def robot_sent(rec: Recording) -> dict[str, list[Any]]:
    """What the robot side put on its buses, decoded, as the Zenoh payload values."""
    out: dict[str, list[Any]] = {k: [] for k in ("ir", "sonar", "odometry", "gyro", "compass")}
    codec = KoalaCanCodec()
    mav = CompassDecoder()
    for m in rec.messages:
        if not m.topic.startswith("/bus/") or m.json()["dir"] != FROM_ROBOT:
            continue
        data = m.frame_bytes()
        if m.topic == "/bus/serial/rangefinders":
            f = decode_range_frame(data)
            assert isinstance(f, RangeFrame)
            if f.kind == RangeKind.IR:
                out["ir"].append(list(f.readings))
            else:
                out["sonar"].append([None if r == NO_ECHO else r / 1000.0 for r in f.readings])
        elif m.topic == "/bus/can":
            d = m.json()
            frame = codec.decode(
                can.Message(arbitration_id=d["can_id"], is_extended_id=d["extended"], data=data)
            )
            if isinstance(frame, WheelOdometryFrame):
                out["odometry"].append([frame.left_ticks, frame.right_ticks])
            elif isinstance(frame, GyroFrame):
                out["gyro"].append(frame.yaw_rate)
        elif m.topic == "/bus/mavlink":
            for s in mav.feed_datagram(data):
                if isinstance(s, CompassSample):
                    out["compass"].append([s.x_ut, s.y_ut, s.z_ut])
    return out


def _args(module: Any, argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    module.add_arguments(parser)
    return parser.parse_args(argv)


def zenoh_values(key: str, msg: dict[str, Any]) -> Any:
    return {
        "ir": lambda: msg["counts"],
        "sonar": lambda: msg["ranges"],
        "odometry": lambda: [msg["left_ticks"], msg["right_ticks"]],
        "gyro": lambda: msg["yaw_rate"],
        "compass": lambda: [msg["mx"], msg["my"], msg["mz"]],
    }[key]()


def test_real_driver_mode_publishes_what_the_robot_sent(
    bridge: Callable[..., BridgeProcess], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    robot_rec = tmp_path / "robot.mcap"
    robot = bridge(clock="realtime", extra=["--record", str(robot_rec)])
    ep = robot.endpoints
    sc = ep["can"]["socketcand"]
    # Turn on the spot, so that every stream changes (odometry, gyro, compass, ranges).
    with can.Bus(interface="socketcand", host=sc["host"], port=sc["port"],
                 channel=sc["channel"]) as client:
        client.send(KoalaCanCodec().encode(MotorCommandFrame(0.05, -0.05)))
        time.sleep(0.2)

    zenoh_endpoint = f"tcp/127.0.0.1:{free_port()}"
    config = tmp_path / "real.toml"
    config.write_text(
        DEFAULT_CONFIG.read_text()
        + f"""
[real]
kteam = "{ep["serial"]["kteam"]}"
kteam_poll = ["H"]
kteam_poll_hz = 5.0
rangefinders = "{ep["serial"]["rangefinders"]}"
can_interface = "socketcand"
can_channel = "{sc["channel"]}"
can_options = {{ host = "{sc["host"]}", port = {sc["port"]} }}
mavlink = "udpin:127.0.0.1:{robot.mavlink_port}"
"""
    )
    real_rec = tmp_path / "real.mcap"
    endpoints_file = tmp_path / "real-endpoints.json"
    log_path = tmp_path / "real.log"
    received: dict[str, list[dict[str, Any]]] = {}
    lock = threading.Lock()

    def on_message(suffix: str, payload: bytes) -> None:
        with lock:
            received.setdefault(suffix, []).append(json.loads(payload))

    with log_path.open("wb") as log:
        real = subprocess.Popen(
            bridge_command(
                "run", "--source", "real", "--config", str(config), "--duration",
                str(REAL_SECONDS), "--record", str(real_rec), "--endpoints-file",
                str(endpoints_file), "--set", f'zenoh.listen=["{zenoh_endpoint}"]',
            ),
            cwd=REPO, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
        )
    try:
        wait_endpoints(real, endpoints_file, log_path, timeout=30)
        with ZenohWatch([zenoh_endpoint], "koala/koala", on_message) as watch:
            world = watch.query_json("world")
            # monitor and snapshot work unchanged against the real-driver mode
            assert monitor_cli.run(_args(monitor_cli, [
                "--connect", zenoh_endpoint, "--once", "--duration", "1"])) == 0
            png = tmp_path / "real.png"
            assert snapshot_cli.run(_args(snapshot_cli, [
                "--out", str(png), "--connect", zenoh_endpoint, "--listen", "0.3",
                "--timeout", "1"])) == 0
            assert real.wait(timeout=60) == 0, log_path.read_text()
    finally:
        if real.poll() is None:
            real.kill()
            real.wait()
    monitor_out = capsys.readouterr().out
    assert "sensors/compass" in monitor_out and "sensors/sonar" in monitor_out
    assert png.stat().st_size > 10_000
    assert robot.stop() == 0
    assert world is not None and world["robot"]["ticks_per_metre"] > 0

    sent = robot_sent(open_recording(robot_rec))
    rec = open_recording(real_rec)
    assert rec.complete and rec.metadata["koala-bridge"]["source"] == "real"
    for key in ("ir", "sonar", "odometry", "gyro", "compass"):
        recorded = [zenoh_values(key, m.json()) for m in rec.topic(f"sensors/{key}")]
        live = [zenoh_values(key, m) for m in received.get(f"sensors/{key}", [])]
        assert len(recorded) > 5, key
        assert len(live) > 5, key
        assert contiguous_in(recorded, sent[key]), key      # what the robot sent, no gap
        assert contiguous_in(live, recorded), key           # Zenoh carried the same
    assert len(set(map(tuple, sent["odometry"]))) > 5, "the robot was turning"
    # K-Team: the version once at the start, then H polled (odometry comes from CAN, so H
    # replies are recorded, not published).
    kteam = rec.topic("/bus/serial/kteam")
    asked = [m.frame_bytes() for m in kteam if m.json()["dir"] == "to_robot"]
    replies = [m.frame_bytes() for m in kteam if m.json()["dir"] == FROM_ROBOT]
    assert asked[0] == b"B\r" and len(asked) > 1 and set(asked[1:]) == {b"H\r"}
    assert replies[0].startswith(b"b,") and all(r.startswith(b"h,") for r in replies[1:])
    status = received["status"][-1]
    assert status["source"] == "real"
    assert status["buses"]["rangefinders"]["received"] > 0
    assert status["buses"]["rangefinders"]["rejected"] == 0


def test_real_ports_config_errors() -> None:
    with pytest.raises(ConfigError, match="did you mean 'kteam'"):
        RealPorts.from_dict({"ktema": "/dev/ttyUSB0"})
    with pytest.raises(ConfigError, match="go together"):
        RealPorts.from_dict({"can_interface": "socketcand"})
    with pytest.raises(ConfigError, match="'kteam_poll'"):
        RealPorts.from_dict({"kteam": "loop://", "kteam_poll": ["Q"]})
    with pytest.raises(ConfigError, match=r"\[real\] section"):
        RealPorts.from_config({})


def test_real_recording_declares_the_opened_ports(tmp_path: Path) -> None:
    """A port that carries nothing still has its channel in a real-mode recording (here a
    pyserial loop:// rangefinder port, so no robot is needed), and only opened ports do."""
    config = tmp_path / "real.toml"
    config.write_text(DEFAULT_CONFIG.read_text() + '\n[real]\nrangefinders = "loop://"\n')
    rec_path = tmp_path / "real.mcap"
    subprocess.run(
        bridge_command(
            "run", "--source", "real", "--config", str(config), "--duration", "0.5",
            "--record", str(rec_path), "--set", f'zenoh.listen=["tcp/127.0.0.1:{free_port()}"]',
        ),
        cwd=REPO, check=True, timeout=120, capture_output=True,
    )
    rec = open_recording(rec_path)
    assert rec.complete
    assert "/bus/serial/rangefinders" in rec.topics
    assert not rec.topic("/bus/serial/rangefinders")
    assert not {"/bus/serial/kteam", "/bus/can", "/bus/mavlink"} & set(rec.topics)
