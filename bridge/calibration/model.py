"""The declared sensor model: what MODEL.toml (the bridge's config) and ``meta.json`` state.

The simulator owns the config schema; this module reads the keys calibration needs tolerantly
(a missing key means ideal/nominal) and applies the precedence of the bundle format: for data from
another robot, ``meta.json`` ``robot``/``sensor`` values override the config file.

Keys read (units in the key name where not SI)::

    [robot]            wheel_base_m, ticks_per_metre
    [sensors.gyro]     ideal, bias_rad_s, scale_error
    [sensors.compass]  ideal, hard_iron_uT = [x, y, z], soft_iron = [[3x3]]
    [sensors.ir]       ideal, curve = {range_m = [...], counts = [...]}, per_sensor_offset_counts
    [sensors.sonar]    ideal, glitch_probability
"""

from __future__ import annotations

import logging
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from bridge.calibration.errors import ModelConfigError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class StartPose:
    x: float
    y: float
    theta: float


@dataclass(frozen=True)
class DeclaredModel:
    """Declared values after precedence (meta.json > MODEL.toml > ideal).

    ``config`` is the TOML document as read (written back, with found effects, by
    ``--write-config``); ``sources`` says where each declared value came from.
    """

    config: Mapping[str, Any]
    ticks_per_metre: float | None = None
    wheel_base_m: float | None = None
    start_pose: StartPose | None = None
    gyro_bias_rad_s: float = 0.0
    gyro_scale_error: float = 0.0
    compass_hard_iron: tuple[float, float, float] = (0.0, 0.0, 0.0)
    compass_soft_iron: tuple[tuple[float, ...], ...] = (
        (1.0, 0.0, 0.0),
        (0.0, 1.0, 0.0),
        (0.0, 0.0, 1.0),
    )
    ir_curve: tuple[tuple[float, ...], tuple[float, ...]] | None = None
    ir_per_sensor_offset: tuple[float, ...] = ()
    sources: Mapping[str, str] = field(default_factory=dict)


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ModelConfigError(f"{where} must be a number, got {value!r}")
    return float(value)


def _section(doc: Mapping[str, Any], *path: str) -> Mapping[str, Any]:
    node: Any = doc
    for key in path:
        node = node.get(key, {}) if isinstance(node, Mapping) else {}
    return node if isinstance(node, Mapping) else {}


def read_config(path: Path | None) -> dict[str, Any]:
    """Parse MODEL.toml; ``None`` gives an empty (all-ideal) model."""
    if path is None:
        return {}
    try:
        with Path(path).open("rb") as fh:
            return tomllib.load(fh)
    except OSError as e:
        raise ModelConfigError(f"cannot read model config {path}: {e}") from e
    except tomllib.TOMLDecodeError as e:
        raise ModelConfigError(f"{path} is not valid TOML: {e}") from e


def declared_model(config: Mapping[str, Any], meta: Mapping[str, Any]) -> DeclaredModel:
    """Combine the config with a bundle's ``meta.json`` (meta wins) into a DeclaredModel."""
    sources: dict[str, str] = {}
    robot = _section(config, "robot")
    meta_robot = meta.get("robot", {}) if isinstance(meta.get("robot"), Mapping) else {}

    def pick(key: str) -> float | None:
        if isinstance(meta_robot.get(key), int | float):
            sources[key] = "meta.json robot"
            return float(meta_robot[key])
        if key in robot:
            sources[key] = "config [robot]"
            return _number(robot[key], f"[robot] {key}")
        return None

    tpm = pick("ticks_per_metre")
    base = pick("wheel_base_m")
    start = None
    sp = meta_robot.get("start_pose")
    if isinstance(sp, Mapping) and all(isinstance(sp.get(k), int | float) for k in ("x", "y")):
        theta = sp.get("theta")
        if not isinstance(theta, int | float) and isinstance(sp.get("theta_deg"), int | float):
            theta = np.deg2rad(sp["theta_deg"])
        start = StartPose(float(sp["x"]), float(sp["y"]), float(theta or 0.0))
        sources["start_pose"] = "meta.json robot"

    gyro = _section(config, "sensors", "gyro")
    meta_sensor = meta.get("sensor", {}) if isinstance(meta.get("sensor"), Mapping) else {}
    meta_gyro = meta_sensor.get("gyro") if isinstance(meta_sensor.get("gyro"), Mapping) else {}
    ideal_gyro = bool(gyro.get("ideal", False))
    bias = 0.0 if ideal_gyro else _number(gyro.get("bias_rad_s", 0.0), "[sensors.gyro] bias_rad_s")
    scale = (
        0.0 if ideal_gyro else _number(gyro.get("scale_error", 0.0), "[sensors.gyro] scale_error")
    )
    if isinstance(meta_gyro, Mapping):
        if isinstance(meta_gyro.get("bias_rad_s"), int | float):
            bias = float(meta_gyro["bias_rad_s"])
        if isinstance(meta_gyro.get("scale_error"), int | float):
            scale = float(meta_gyro["scale_error"])

    compass = _section(config, "sensors", "compass")
    hard = (0.0, 0.0, 0.0)
    soft = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    if not compass.get("ideal", False):
        if "hard_iron_uT" in compass:
            h = [_number(v, "[sensors.compass] hard_iron_uT") for v in compass["hard_iron_uT"]]
            hard = (h + [0.0, 0.0, 0.0])[:3]  # type: ignore[assignment]
        if "soft_iron" in compass:
            s = np.asarray(compass["soft_iron"], dtype=float)
            if s.shape != (3, 3):
                raise ModelConfigError("[sensors.compass] soft_iron must be a 3x3 array")
            soft = tuple(tuple(float(v) for v in row) for row in s)

    ir = _section(config, "sensors", "ir")
    curve = None
    if not ir.get("ideal", False) and isinstance(ir.get("curve"), Mapping):
        r = tuple(_number(v, "[sensors.ir] curve.range_m") for v in ir["curve"].get("range_m", []))
        c = tuple(_number(v, "[sensors.ir] curve.counts") for v in ir["curve"].get("counts", []))
        if len(r) != len(c) or len(r) < 2:
            raise ModelConfigError(
                "[sensors.ir] curve needs range_m and counts of equal length >= 2"
            )
        curve = (r, c)
    offsets = tuple(
        _number(v, "[sensors.ir] per_sensor_offset_counts")
        for v in ir.get("per_sensor_offset_counts", [])
    )
    return DeclaredModel(
        config=config,
        ticks_per_metre=tpm,
        wheel_base_m=base,
        start_pose=start,
        gyro_bias_rad_s=bias,
        gyro_scale_error=scale,
        compass_hard_iron=hard,
        compass_soft_iron=soft,
        ir_curve=curve,
        ir_per_sensor_offset=offsets,
        sources=sources,
    )
