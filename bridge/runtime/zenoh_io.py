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
``world`` (queryable)   the world and ``robot`` (:class:`koala_bridge.core.topics.WorldMessage`)
=====================  ==========================================================================

Each payload is defined once, as a typed message in :mod:`koala_bridge.core.topics` (which
also gives the recording's JSON Schemas and the export's CSV columns). The ``estimate/*`` and
``map/occupancy`` messages are built by :mod:`estimation.messages` (docs/localisation.md, "Zenoh
payloads") and published by the service through the same session.

The message builders here are pure functions of a :class:`sim.types.Readings`;
:class:`ZenohLink` owns the session. Non-finite numbers (no echo, nothing in range) are sent as
``null``.

Range truth: ``ranges`` (m) along each sensor's axis (IR) or to the nearest surface of the beam
(sonar), ``null`` where nothing is within the sensor's maximum range; ``incidence`` (rad) the
angle between that ray and the surface normal, ``null`` where there is no surface (or, for IR,
where the caller did not supply it).
"""

from __future__ import annotations

import json
import logging
import re
import threading
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import zenoh
from koala_bridge.core.errors import ConfigError
from koala_bridge.core.topics import (
    CameraMessage,
    CameraTruth,
    CompassMessage,
    CompassTruth,
    GyroMessage,
    GyroTruth,
    IrMessage,
    IrTruth,
    Observation,
    OdometryMessage,
    OdometryTruth,
    SonarMessage,
    SonarTruth,
    StatusMessage,
    TopicMessage,
    TruthPose,
    encode,
    finite_or_none,
    ints,
    nums,
)
from koala_bridge.drivers.messages import TransportError
from koala_bridge.runtime.counters import BusCounters
from koala_bridge.runtime.settings import ZERO_PORT, ZenohSettings
from koala_bridge.sim.types import LandmarkObservation, Readings

log = logging.getLogger(__name__)

ZENOH_BUS = "zenoh"


# -- message builders (pure): simulator readings -> topic messages ----------------------------

def _observations(obs: Iterable[LandmarkObservation]) -> tuple[Observation, ...]:
    return tuple(
        Observation(int(o.id), finite_or_none(o.range), finite_or_none(o.bearing)) for o in obs
    )


def truth_pose(r: Readings) -> TruthPose:
    """``truth/pose`` of ``r``."""
    return TruthPose(r.t, r.pose.x, r.pose.y, r.pose.theta)


def sensor_topics(
    r: Readings, ir_incidence: Sequence[float] | np.ndarray | None = None
) -> dict[str, TopicMessage]:
    """``{key suffix: message}`` for every sensor reading due in ``r`` (see module table).

    ``ir_incidence`` (n,) rad: incidence of each IR sensor's axis ray (nan: none), which the
    simulator's :class:`koala_bridge.sim.types.IrReading` does not carry; None publishes ``null``s.
    """
    out: dict[str, TopicMessage] = {}
    t = r.t
    if r.ir is not None:
        n = len(r.ir.counts)
        out[IrMessage.TOPIC] = IrMessage(
            t,
            counts=ints(r.ir.counts),
            ambient=ints(r.ir.ambient),
            truth=IrTruth(
                counts=ints(r.ir.truth_counts),
                ranges=nums(r.ir.truth_ranges),
                incidence=(None,) * n if ir_incidence is None else nums(ir_incidence),
            ),
        )
    if r.sonar is not None:
        out[SonarMessage.TOPIC] = SonarMessage(
            t,
            ranges=nums(r.sonar.ranges),
            truth=SonarTruth(nums(r.sonar.truth_ranges), nums(r.sonar.incidence)),
        )
    if r.odometry is not None:
        o = r.odometry
        out[OdometryMessage.TOPIC] = OdometryMessage(
            t,
            left_ticks=int(o.left_ticks),
            right_ticks=int(o.right_ticks),
            truth=OdometryTruth(
                int(getattr(o, "truth_left_ticks", o.left_ticks)),
                int(getattr(o, "truth_right_ticks", o.right_ticks)),
            ),
        )
    if r.gyro is not None:
        out[GyroMessage.TOPIC] = GyroMessage(
            t, yaw_rate=float(r.gyro.yaw_rate), truth=GyroTruth(float(r.gyro.truth_yaw_rate))
        )
    if r.compass is not None:
        m, mt = r.compass.field_uT, r.compass.truth_field_uT
        out[CompassMessage.TOPIC] = CompassMessage(
            t,
            mx=float(m[0]),
            my=float(m[1]),
            mz=float(m[2]),
            truth=CompassTruth(float(mt[0]), float(mt[1]), float(mt[2])),
        )
    if r.camera is not None:
        out[CameraMessage.TOPIC] = CameraMessage(
            t,
            observations=_observations(r.camera.observations),
            truth=CameraTruth(_observations(r.camera.truth)),
        )
    return out


def pose_message(r: Readings) -> dict[str, Any]:
    """``truth/pose`` of ``r`` as JSON-ready ``dict``."""
    return truth_pose(r).to_json()


def sensor_messages(
    r: Readings, ir_incidence: Sequence[float] | np.ndarray | None = None
) -> dict[str, dict[str, Any]]:
    """:func:`sensor_topics` as JSON-ready ``dict`` s."""
    return {k: m.to_json() for k, m in sensor_topics(r, ir_incidence).items()}


def status_message(
    t: float, real_time_factor: float, buses: Mapping[str, Mapping[str, int]]
) -> dict[str, Any]:
    """The ``status`` message's common part (:class:`core.topics.StatusMessage`) as a dict."""
    return StatusMessage(t, real_time_factor, {n: dict(c) for n, c in buses.items()}).to_json()


# -- session -----------------------------------------------------------------------------------

def session_config(settings: ZenohSettings) -> zenoh.Config:
    """A :class:`zenoh.Config` for ``settings``: mode, listen/connect endpoints, scouting.

    With ``[zenoh] config_file``, Zenoh's own JSON5 configuration is the base (TLS
    certificates under ``transport/link/tls``, ``transport/auth/usrpwd``, ``access_control``,
    ...: Zenoh's format, documented by Zenoh), and our four keys are written on top of it: the
    mode, the listen and connect endpoints and multicast scouting are always koala-bridge's, so
    the banner and the endpoints file stay true. A file that Zenoh cannot read is a
    :class:`ConfigError`.
    """
    if settings.config_file:
        path = Path(settings.config_file).expanduser()
        try:
            config = zenoh.Config.from_file(str(path))
        except (zenoh.ZError, OSError, ValueError) as e:
            raise ConfigError(
                f"[zenoh] 'config_file' {str(path)!r}: {_first_line(zenoh_error_text(e))}"
            ) from None
    else:
        config = zenoh.Config()
    config.insert_json5("mode", json.dumps(settings.mode))
    config.insert_json5("listen/endpoints", json.dumps(list(settings.listen)))
    config.insert_json5("connect/endpoints", json.dumps(list(settings.connect)))
    config.insert_json5(
        "scouting/multicast/enabled", json.dumps(settings.multicast_scouting)
    )
    if any(ZERO_PORT.search(locator) for locator in settings.listen):
        # Zenoh's API does not say which port a listener on port 0 bound; its admin space
        # does (@/<zid>/<mode>: "locators"). Read-only, and only for such a session.
        config.insert_json5("adminspace/enabled", "true")
        config.insert_json5("adminspace/permissions", '{"read": true, "write": false}')
    return config


def bound_locators(session: zenoh.Session, mode: str, timeout_s: float = 5.0) -> tuple[str, ...]:
    """The locators ``session`` listens on, ports resolved (its admin space, which
    :func:`session_config` enables when a listen port is 0)."""
    zid = str(session.zid())
    for reply in session.get(f"@/{zid}/{mode}", timeout=timeout_s):
        if reply.ok is not None:
            info = json.loads(bytes(reply.ok.payload.to_bytes()))
            return tuple(str(x) for x in info.get("locators", ()))
    raise TransportError("zenoh: the session did not report the port it listens on")


def zenoh_error_text(e: Exception) -> str:
    """A Zenoh error's message without the Rust source locations it carries."""
    return re.sub(r"\s+at \S+\.rs:\d+\.?", "", str(e)).strip()


def _first_line(text: str) -> str:
    return text.splitlines()[0] if text else "cannot be read"


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


def open_session(settings: ZenohSettings) -> zenoh.Session:
    """A Zenoh session of ``settings`` (a :class:`TransportError` saying why it cannot open);
    a listener on a non-loopback address is logged as a warning."""
    config = session_config(settings)
    for what in settings.exposure():
        log.warning("%s, reachable from the network ([run] allow_non_loopback)", what)
    try:
        return zenoh.open(config)
    except zenoh.ZError as e:
        raise TransportError(_session_error(settings, e)) from e


class ZenohLink:
    """The bridge's Zenoh session: publishers under the prefix and the ``world`` queryable.

    ``world_answer`` is called for each query and returns the JSON-ready answer. Publishing is
    thread-safe (Zenoh sessions are). Use as a context manager or call :meth:`close`.

    ``session``: an open session to publish through (several robots of one world share one,
    each under its own prefix: runtime/fleet_source.py); it is not closed here. None opens one
    from ``settings``.
    """

    def __init__(
        self,
        settings: ZenohSettings,
        world_answer: Callable[[], Mapping[str, Any]],
        counters: BusCounters | None = None,
        session: zenoh.Session | None = None,
    ) -> None:
        self.settings = settings
        self.prefix = settings.prefix
        self._world_answer = world_answer
        self._counters = counters or BusCounters()
        self._lock = threading.Lock()
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._closed = False
        self._owns_session = session is None
        self._session = session if session is not None else open_session(settings)
        #: The locators the session listens on (a port 0 resolved to the port bound).
        self.listening: tuple[str, ...] = settings.listen
        if any(ZERO_PORT.search(locator) for locator in settings.listen):
            try:
                self.listening = bound_locators(self._session, settings.mode)
            except BaseException:
                if self._owns_session:
                    self._session.close()
                raise
        self._queryable = self._session.declare_queryable(
            f"{self.prefix}/world", self._on_world_query
        )
        self._commands: list[Any] = []

    def command_queryable(
        self, suffix: str, handler: Callable[[bytes], Mapping[str, Any]]
    ) -> None:
        """Answer queries on ``<prefix>/<suffix>`` with ``handler(payload)`` (JSON). A
        ``ValueError`` from the handler is the error reply (bad input, counted as rejected);
        anything else is logged and answered as an internal error. Only for
        ``[zenoh] remote_commands = true``: the caller checks."""

        def on_query(query: zenoh.Query) -> None:
            payload = b"" if query.payload is None else bytes(query.payload.to_bytes())
            try:
                answer = encode(handler(payload))
            except ValueError as e:
                query.reply_err(str(e).encode())
                self._counters.rejected(ZENOH_BUS)
                return
            except Exception:  # must not kill Zenoh's callback thread
                log.exception("%s query failed", suffix)
                query.reply_err(f"internal error answering {suffix}".encode())
                self._counters.rejected(ZENOH_BUS)
                return
            query.reply(f"{self.prefix}/{suffix}", answer,
                        encoding=zenoh.Encoding.APPLICATION_JSON)
            self._counters.received(ZENOH_BUS)
            self._counters.sent(ZENOH_BUS)

        self._commands.append(self._session.declare_queryable(f"{self.prefix}/{suffix}",
                                                              on_query))

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

    def publish(self, suffix: str, message: Mapping[str, Any] | TopicMessage) -> None:
        """Put ``message`` (a typed message or its JSON ``dict``) on ``<prefix>/<suffix>``."""
        payload = message.to_bytes() if isinstance(message, TopicMessage) else encode(message)
        self.publish_json(suffix, payload)

    def publish_json(self, suffix: str, payload: bytes) -> None:
        """Put ``payload``, already JSON, on ``<prefix>/<suffix>`` as it is (a replay puts the
        recorded bytes back)."""
        # The put under the lock too: a publisher undeclared by close() while another thread
        # is in its put() raised "Already borrowed" (a loop not yet stopped, a loaded machine).
        # After close() nothing is put: the link is gone.
        with self._lock:
            if self._closed:
                return
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
            self.publish(TruthPose.TOPIC, truth_pose(r))
        for suffix, message in sensor_topics(r).items():
            self.publish(suffix, message)

    def close(self) -> None:
        """Undeclare everything and close an owned session; a publish after it does nothing.
        Idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            for pub in self._publishers.values():
                pub.undeclare()
            self._publishers.clear()
        self._queryable.undeclare()
        for q in self._commands:
            q.undeclare()
        if self._owns_session:
            self._session.close()

    def __enter__(self) -> ZenohLink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
