"""Zenoh: the bridge's session, the JSON messages it publishes, and the ``world`` queryable.

Key expressions under ``<prefix>`` (default ``koala/<robot name>``; no trailing ``/``: a key is
``<prefix>/<suffix>``), JSON (encoding ``application/json``), SI units, ``t`` in
simulation seconds, world frame x east / y north / theta CCW from +x, body frame FLU:

=====================  ==========================================================================
``truth/pose``          ``{t, x, y, theta}``
``sensors/ir``          ``{t, counts[16], ambient[16], truth: {counts, ranges, incidence}}``
``sensors/sonar``       ``{t, ranges[n] (m, null = no echo), truth: {ranges, incidence}}``
``sensors/odometry``    ``{t, left_ticks, right_ticks, truth: {left_ticks, right_ticks}}``
``sensors/gyro``        ``{t, yaw_rate (rad/s, CCW+), truth: {yaw_rate}}``
``sensors/compass``     ``{t, mx, my, mz (uT, body FLU), truth: {mx, my, mz}}``
``sensors/camera``      ``{t, observations: [{id, range, bearing}], truth: {observations}}``
``status``              ``{t, real_time_factor, buses: {name: {sent, received, rejected,
                        dropped}}, motor_command_source, leds, localisation}`` (the service adds
                        the last three; docs/protocols.md, "Zenoh")
``estimate/pose``       ``{t, x, y, theta, cov}`` (the localisation node, runtime/localisation.py)
``estimate/cell``       ``{t, cell: [col, row], p}``
``estimate/grid``       ``{t, cols, rows, cell_m, encoding, data, cell, p}`` (belief, base64)
``map/occupancy``       ``{t, cols, rows, resolution_m, origin, encoding, scale, data}`` (int8)
``world`` (queryable)   the world (``koala_bridge.sim.world.World.to_dict``) plus ``robot``
=====================  ==========================================================================

The ``estimate/*`` and ``map/occupancy`` payloads are built by :mod:`estimation.messages`
(docs/localisation.md, "Zenoh payloads") and published by the service through the same session.

The message builders are pure functions of a :class:`sim.types.Readings`; :class:`ZenohLink`
owns the session. Non-finite numbers (no echo, nothing in range) are sent as ``null``.

Range truth: ``ranges`` (m) along each sensor's axis (IR) or to the nearest surface of the beam
(sonar), ``null`` where nothing is within the sensor's maximum range; ``incidence`` (rad) the
angle between that ray and the surface normal, ``null`` where there is no surface (or, for IR,
where the caller did not supply it).
"""

from __future__ import annotations

import json
import logging
import math
import re
import threading
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any

import numpy as np
import zenoh
from koala_bridge.drivers.messages import TransportError
from koala_bridge.runtime.counters import BusCounters
from koala_bridge.runtime.settings import ZenohSettings
from koala_bridge.sim.types import LandmarkObservation, Readings

log = logging.getLogger(__name__)

ZENOH_BUS = "zenoh"


# -- message builders (pure) -------------------------------------------------------------------

def _num(v: Any) -> float | None:
    f = float(v)
    return f if math.isfinite(f) else None


def _nums(values: Iterable[Any]) -> list[float | None]:
    return [_num(v) for v in values]


def _ints(values: Iterable[Any]) -> list[int]:
    return [int(v) for v in values]


def _observations(obs: Iterable[LandmarkObservation]) -> list[dict[str, Any]]:
    return [{"id": int(o.id), "range": _num(o.range), "bearing": _num(o.bearing)} for o in obs]


def pose_message(r: Readings) -> dict[str, Any]:
    return {"t": r.t, "x": r.pose.x, "y": r.pose.y, "theta": r.pose.theta}


def sensor_messages(
    r: Readings, ir_incidence: Sequence[float] | np.ndarray | None = None
) -> dict[str, dict[str, Any]]:
    """``{key suffix: message}`` for every sensor reading due in ``r`` (see module table).

    ``ir_incidence`` (n,) rad: incidence of each IR sensor's axis ray (nan: none), which the
    simulator's :class:`koala_bridge.sim.types.IrReading` does not carry; None publishes ``null``s.
    """
    out: dict[str, dict[str, Any]] = {}
    t = r.t
    if r.ir is not None:
        n = len(r.ir.counts)
        out["sensors/ir"] = {
            "t": t,
            "counts": _ints(r.ir.counts),
            "ambient": _ints(r.ir.ambient),
            "truth": {
                "counts": _ints(r.ir.truth_counts),
                "ranges": _nums(r.ir.truth_ranges),
                "incidence": [None] * n if ir_incidence is None else _nums(ir_incidence),
            },
        }
    if r.sonar is not None:
        out["sensors/sonar"] = {
            "t": t,
            "ranges": _nums(r.sonar.ranges),
            "truth": {"ranges": _nums(r.sonar.truth_ranges), "incidence": _nums(r.sonar.incidence)},
        }
    if r.odometry is not None:
        o = r.odometry
        out["sensors/odometry"] = {
            "t": t,
            "left_ticks": int(o.left_ticks),
            "right_ticks": int(o.right_ticks),
            "truth": {
                "left_ticks": int(getattr(o, "truth_left_ticks", o.left_ticks)),
                "right_ticks": int(getattr(o, "truth_right_ticks", o.right_ticks)),
            },
        }
    if r.gyro is not None:
        out["sensors/gyro"] = {
            "t": t,
            "yaw_rate": float(r.gyro.yaw_rate),
            "truth": {"yaw_rate": float(r.gyro.truth_yaw_rate)},
        }
    if r.compass is not None:
        m, mt = r.compass.field_uT, r.compass.truth_field_uT
        out["sensors/compass"] = {
            "t": t,
            "mx": float(m[0]),
            "my": float(m[1]),
            "mz": float(m[2]),
            "truth": {"mx": float(mt[0]), "my": float(mt[1]), "mz": float(mt[2])},
        }
    if r.camera is not None:
        out["sensors/camera"] = {
            "t": t,
            "observations": _observations(r.camera.observations),
            "truth": {"observations": _observations(r.camera.truth)},
        }
    return out


def status_message(
    t: float, real_time_factor: float, buses: Mapping[str, Mapping[str, int]]
) -> dict[str, Any]:
    return {
        "t": t,
        "real_time_factor": _num(real_time_factor),
        "buses": {name: dict(c) for name, c in buses.items()},
    }


def encode(message: Mapping[str, Any]) -> bytes:
    """Strict JSON (no NaN/Infinity literals) as UTF-8."""
    return json.dumps(message, allow_nan=False, separators=(",", ":")).encode()


# -- session -----------------------------------------------------------------------------------

def session_config(settings: ZenohSettings) -> zenoh.Config:
    """A :class:`zenoh.Config` for ``settings``: mode, listen/connect endpoints, scouting."""
    config = zenoh.Config()
    config.insert_json5("mode", json.dumps(settings.mode))
    config.insert_json5("listen/endpoints", json.dumps(list(settings.listen)))
    config.insert_json5("connect/endpoints", json.dumps(list(settings.connect)))
    config.insert_json5(
        "scouting/multicast/enabled", json.dumps(settings.multicast_scouting)
    )
    return config


def zenoh_error_text(e: Exception) -> str:
    """A Zenoh error's message without the Rust source locations it carries."""
    return re.sub(r"\s+at \S+\.rs:\d+\.?", "", str(e)).strip()


def _session_error(settings: ZenohSettings, e: Exception) -> str:
    """One line saying why the session did not open."""
    listen = ", ".join(settings.listen) or "nothing"
    text = zenoh_error_text(e)
    if "address already in use" in text.lower():
        return (
            f"cannot open the Zenoh session: {listen} is already in use (another koala-bridge "
            "running?); listen elsewhere with --set 'zenoh.listen=[\"tcp/127.0.0.1:7448\"]'"
        )
    return f"cannot open the Zenoh session (listen {listen}): {text}"


class ZenohLink:
    """The bridge's Zenoh session: publishers under the prefix and the ``world`` queryable.

    ``world_answer`` is called for each query and returns the JSON-ready answer. Publishing is
    thread-safe (Zenoh sessions are). Use as a context manager or call :meth:`close`.
    """

    def __init__(
        self,
        settings: ZenohSettings,
        world_answer: Callable[[], Mapping[str, Any]],
        counters: BusCounters | None = None,
    ) -> None:
        self.settings = settings
        self.prefix = settings.prefix
        self._world_answer = world_answer
        self._counters = counters or BusCounters()
        self._lock = threading.Lock()
        self._publishers: dict[str, zenoh.Publisher] = {}
        try:
            self._session = zenoh.open(session_config(settings))
        except zenoh.ZError as e:
            raise OSError(_session_error(settings, e)) from e
        self._queryable = self._session.declare_queryable(
            f"{self.prefix}/world", self._on_world_query
        )

    def _on_world_query(self, query: zenoh.Query) -> None:
        try:
            payload = encode(self._world_answer())
        except Exception:  # a bad answer must not kill Zenoh's callback thread
            log.exception("world query failed")
            query.reply_err(b"internal error building the world answer")
            self._counters.rejected(ZENOH_BUS)
            return
        query.reply(f"{self.prefix}/world", payload, encoding=zenoh.Encoding.APPLICATION_JSON)
        self._counters.received(ZENOH_BUS)
        self._counters.sent(ZENOH_BUS)

    def publish(self, suffix: str, message: Mapping[str, Any]) -> None:
        """Put ``message`` as JSON on ``<prefix>/<suffix>``."""
        self.publish_json(suffix, encode(message))

    def publish_json(self, suffix: str, payload: bytes) -> None:
        """Put ``payload``, already JSON, on ``<prefix>/<suffix>`` as it is (a replay puts the
        recorded bytes back)."""
        with self._lock:
            pub = self._publishers.get(suffix)
            if pub is None:
                pub = self._session.declare_publisher(
                    f"{self.prefix}/{suffix}", encoding=zenoh.Encoding.APPLICATION_JSON
                )
                self._publishers[suffix] = pub
        try:
            pub.put(payload)
        except zenoh.ZError as e:
            raise TransportError(f"zenoh: cannot publish {self.prefix}/{suffix}: {e}") from e
        self._counters.sent(ZENOH_BUS)

    def publish_readings(self, r: Readings, with_pose: bool) -> None:
        """Publish every sensor reading due in ``r``, and the truth pose if ``with_pose``."""
        if with_pose:
            self.publish("truth/pose", pose_message(r))
        for suffix, message in sensor_messages(r).items():
            self.publish(suffix, message)

    def close(self) -> None:
        with self._lock:
            for pub in self._publishers.values():
                pub.undeclare()
            self._publishers.clear()
        self._queryable.undeclare()
        self._session.close()

    def __enter__(self) -> ZenohLink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
