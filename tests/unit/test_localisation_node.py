"""The localisation node's input handling, without a simulator: config errors, one source per
quantity, encoder counter resets, a clock that goes back, frames that do not decode."""

from __future__ import annotations

import copy
import math
import tomllib
from typing import Any

import pytest
from conftest import REPO
from koala_bridge.core.schema import ConfigError
from koala_bridge.drivers.can_codec import KoalaCanCodec
from koala_bridge.drivers.messages import GyroFrame, WheelOdometryFrame
from koala_bridge.runtime.localisation import LocalisationNode, LocalisationSettings
from koala_bridge.sim.config import load_sim_config


def _config() -> dict[str, Any]:
    return tomllib.loads((REPO / "config" / "default.toml").read_text())


def _node() -> tuple[LocalisationNode, dict[str, list[dict[str, Any]]]]:
    cfg = _config()
    out: dict[str, list[dict[str, Any]]] = {}
    node = LocalisationNode(LocalisationSettings.from_dict(cfg["localisation"]),
                            load_sim_config(cfg), lambda k, m: out.setdefault(k, []).append(m))
    return node, out


def _can(node: LocalisationNode, t: float, frame: WheelOdometryFrame | GyroFrame) -> None:
    msg = KoalaCanCodec().encode(frame)
    node.on_frame("can", "from_robot", t, bytes(msg.data), can_id=msg.arbitration_id,
                  extended=msg.is_extended_id)


def test_config_errors_name_the_key() -> None:
    cfg = _config()
    bad = copy.deepcopy(cfg["localisation"])
    bad["pose"]["compas_sigma_deg"] = 3.0
    with pytest.raises(ConfigError, match="did you mean 'compass_sigma_deg'"):
        LocalisationSettings.from_dict(bad)
    bad = copy.deepcopy(cfg["localisation"])
    bad["grid_prior"] = "somewhere"
    with pytest.raises(ConfigError, match="grid_prior"):
        LocalisationSettings.from_dict(bad)
    off = copy.deepcopy(cfg)
    off["localisation"]["enabled"] = False
    assert LocalisationSettings.from_config(off) is None
    del off["localisation"]
    assert LocalisationSettings.from_config(off) is None


def test_kteam_replies_feed_until_a_stream_is_seen_and_clients_only_are_ignored() -> None:
    node, out = _node()
    x0 = node.tracker.pose[0]
    tpm = node.tracker.params.ticks_per_metre
    node.on_frame("serial/kteam", "from_robot", 0.0, b"h,0,0\r\n")
    node.on_frame("serial/kteam", "from_robot", 0.5, b"h,%d,%d\r\n" % (0.05 * tpm, 0.05 * tpm))
    assert node.tracker.pose[0] == pytest.approx(x0 + 0.05, abs=1e-3)  # start pose faces east
    node.on_frame("serial/kteam", "to_robot", 0.6, b"H\r")      # a client's command: ignored
    _can(node, 0.6, WheelOdometryFrame(1111, 1111))            # a stream: K-Team h now ignored
    node.on_frame("serial/kteam", "from_robot", 1.0, b"h,99999,99999\r\n")
    assert node.tracker.pose[0] == pytest.approx(x0 + 0.05, abs=1e-3)
    assert out["estimate/pose"] and out["estimate/cell"] and out["map/occupancy"]


def test_counter_reset_is_not_motion_and_a_clock_restart_starts_over() -> None:
    node, out = _node()
    x0 = node.tracker.pose[0]
    for k in range(101):  # 1 s at 0.1 m/s
        _can(node, k * 0.01, GyroFrame(0.0))
        _can(node, k * 0.01, WheelOdometryFrame(round(k * 22.222), round(k * 22.222)))
    moved = node.tracker.pose[0] - x0
    assert moved == pytest.approx(0.1, abs=2e-3)
    _can(node, 1.02, WheelOdometryFrame(0, 0))         # K-Team G,0,0 by a client
    assert node.tracker.pose[0] - x0 == pytest.approx(moved, abs=1e-3)   # not a motion
    # simulator reset: time goes back and the robot is at its start again
    _can(node, 0.0, WheelOdometryFrame(0, 0))
    _can(node, 0.02, WheelOdometryFrame(44, 44))
    assert node.tracker.pose[0] - x0 == pytest.approx(0.002, abs=1e-3)
    snap = node.snapshot()
    assert snap["odometry_resets"] >= 1 and snap["clock_restarts"] == 1
    assert out["estimate/pose"][-1]["t"] == 0.0  # publishing restarted with the clock


def test_undecodable_frames_are_counted() -> None:
    node, _ = _node()
    node.on_frame("can", "from_robot", 0.0, b"\x00", can_id=0x7FF, extended=False)
    from koala_bridge.drivers.mavlink_codec import CompassEncoder, MavlinkIdentity
    from koala_bridge.drivers.messages import CompassSample

    packet = bytearray(CompassEncoder(MavlinkIdentity(1, 1)).scaled_imu(CompassSample(0, 1, 2, 3)))
    packet[-1] ^= 0xFF  # bad CRC
    node.on_frame("mavlink", "from_robot", 0.0, bytes(packet))
    node.on_frame("serial/rangefinders", "from_robot", 0.0, b"\xa5\x5a\x01\x01\x00")
    rejected = node.snapshot()["rejected"]
    assert rejected.get("can") == 1 and rejected.get("mavlink", 0) >= 1


def test_a_field_off_the_earths_strength_is_not_a_heading() -> None:
    """A horizontal field 30 % stronger than [world.earth_field] (a magnet near the robot) is
    counted as disturbed and gives no heading; one of the Earth's strength, in any direction, is
    used."""
    from koala_bridge.drivers.mavlink_codec import CompassEncoder, MavlinkIdentity
    from koala_bridge.drivers.messages import CompassSample

    cfg = _config()
    cfg["localisation"]["pose"]["compass_hard_iron_uT"] = [0.0, 0.0]
    node = LocalisationNode(LocalisationSettings.from_dict(cfg["localisation"]),
                            load_sim_config(cfg), lambda k, m: None)
    earth = cfg["world"]["earth_field"]["horizontal_uT"]
    tolerance = cfg["localisation"]["pose"]["compass_field_tolerance"]
    enc = CompassEncoder(MavlinkIdentity(1, 1))
    scales = (1.0, 1.0 - 0.5 * tolerance, 1.0 + 3 * tolerance, 1.0 - 3 * tolerance)
    for k, scale in enumerate(scales):
        a = 0.7 * k
        node.on_frame("mavlink", "from_robot", 0.1 * k, enc.scaled_imu(CompassSample(
            k, earth * scale * math.cos(a), earth * scale * math.sin(a), -40.0)))
    snap = node.snapshot()
    assert snap["compass_disturbed"] == 2
    assert snap["frames"]["compass"] == 4
