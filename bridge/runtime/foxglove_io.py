"""Foxglove: the live WebSocket server of ``run --foxglove`` and the standard-schema channels of
``run --record`` (docs/foxglove.md, docs/recording.md).

Both are fed by one :class:`FoxgloveTap`, a :class:`runtime.source.Tap` that the source hands
every message it publishes (the recorder's own tap goes on behind it, unchanged). The tap turns
each message into Foxglove messages with :class:`runtime.foxglove_scene.SceneTranslator`,
encodes each once (protobuf, with the schema the foxglove-sdk package ships) and hands the bytes
to:

- the live server (:class:`FoxgloveServer`, foxglove-sdk's WebSocket server speaking
  ``foxglove.websocket.v1``): a topic is built only when a client is subscribed to it, and at
  most :data:`SCENE_RATE_HZ` times per wall second (:data:`RAW_RATE_HZ` for the raw streams, the
  bridge's own JSON messages that the plot panels read), so that a fast-clock run does not spend
  its time drawing frames nobody can see;
- the recording (:meth:`recording.mcap_file.Recorder.record_encoded`): every message, at its
  simulation time, through the recorder's own MCAP writer (one writer per file), beside the raw
  bus frames and the JSON channels.

The clients' time (the ``time`` capability) is the simulation's, sent at most
:data:`SCENE_RATE_HZ` times per wall second whatever the clients subscribe to.

The static scene (the map, the world's grid, the robot's body) goes to a client when it
subscribes, and into a recording at t = 0 and every :data:`STATIC_PERIOD_S` simulated seconds
(a player that seeks finds it).

Several robots (``[[robots]]``): one :class:`SceneTranslator` and one :class:`FoxgloveTap` per
robot (its topics under ``/<robot name>/scene``, the world's drawn by the first robot), all on
one server and one recording (:func:`attach_foxglove` with ``robots``).
"""

from __future__ import annotations

import ipaddress
import json
import logging
import re
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import replace
from typing import Any

import foxglove
from foxglove.websocket import Capability, ChannelView, Client, ServerListener
from koala_bridge.core.errors import ConfigError
from koala_bridge.core.topics import json_schema as topic_json_schema
from koala_bridge.drivers.messages import TransportError
from koala_bridge.recording.mcap_file import ChannelSchema, Recorder, time_ns, topic_name
from koala_bridge.runtime.endpoints import Endpoints
from koala_bridge.runtime.foxglove_scene import Output, SceneTranslator
from koala_bridge.runtime.settings import is_loopback_host
from koala_bridge.runtime.source import RobotSource, Tap

__all__ = [
    "DEFAULT_ADDRESS",
    "FoxgloveServer",
    "FoxgloveTap",
    "ServedWithFoxglove",
    "attach_foxglove",
    "foxglove_schema",
    "parse_address",
]

log = logging.getLogger(__name__)

DEFAULT_ADDRESS = "127.0.0.1:8765"
SCENE_RATE_HZ = 20.0    # live: the most messages per wall second on one scene topic
RAW_RATE_HZ = 50.0      # live: ... on one raw stream (the plots)
STATIC_PERIOD_S = 5.0   # recording: the static scene again every this many simulated seconds


def parse_address(text: str, allow_non_loopback: bool = False) -> tuple[str, int]:
    """``HOST:PORT``, ``:PORT``, ``PORT`` or ``HOST`` (``[::1]:PORT`` for IPv6) as
    ``(host, port)``; the host defaults to 127.0.0.1 and the port to 8765 (0: any free port).

    Raises :class:`ConfigError` for a bad address, or a host that is not loopback unless
    ``allow_non_loopback`` (``[run] allow_non_loopback``, docs/security.md).
    """
    default_host, default_port = DEFAULT_ADDRESS.rsplit(":", 1)
    text = text.strip()
    if text.startswith("["):                      # [v6]:port
        host, _, rest = text[1:].partition("]")
        port_text = rest[1:] if rest.startswith(":") else rest
    elif text.count(":") == 1:
        host, port_text = text.split(":")
    elif text.isdigit():
        host, port_text = "", text
    else:
        host, port_text = text, ""
    bare = not port_text and not text.startswith("[")     # HOST alone
    host = host or default_host
    try:
        port = int(port_text or default_port)
    except ValueError:
        port = -1
    if not 0 <= port <= 65535 or not _is_host(host, bare):
        raise ConfigError(f"--foxglove {text!r}: expected HOST:PORT, e.g. {DEFAULT_ADDRESS} "
                          "(port 0 = any free port; a HOST alone is an IP address, localhost "
                          "or a dotted name)")
    if not is_loopback_host(host) and not allow_non_loopback:
        raise ConfigError(
            f"--foxglove {host}: not loopback, so the live view would be reachable from the "
            "network; set [run] allow_non_loopback = true to mean it (docs/security.md), or use "
            "127.0.0.1"
        )
    return host, port


#: A DNS host name (RFC 1123 labels, dot-separated).
_HOST_NAME = re.compile(r"(?!-)[A-Za-z0-9-]{1,63}(?<!-)(\.(?!-)[A-Za-z0-9-]{1,63}(?<!-))*\.?")


def _is_host(host: str, bare: bool) -> bool:
    """Whether ``host`` can be the host of ``--foxglove``: an IP address, or a host name (a
    ``bare`` one, given without a port, only ``localhost`` or a dotted name: a lone word such as
    ``garbage`` is a mistyped address far more often than a machine's name)."""
    try:
        ipaddress.ip_address(host.partition("%")[0])
        return True
    except ValueError:
        pass
    if not _HOST_NAME.fullmatch(host) or host.replace(".", "").isdigit():
        return False
    return not bare or host == "localhost" or "." in host.rstrip(".")


def foxglove_schema(cls: type) -> ChannelSchema:
    """The recording's schema of a :mod:`foxglove.messages` class: its protobuf file
    descriptor set, named ``foxglove.<Name>``, as the SDK ships it."""
    s = cls.get_schema()  # type: ignore[attr-defined]
    return ChannelSchema(s.name, s.encoding, bytes(s.data), "protobuf")


class _Subscriptions(ServerListener):
    """foxglove-sdk's server listener: sets ``event`` when a client subscribes (called on the
    server's thread: it only signals)."""

    def __init__(self, event: threading.Event) -> None:
        self._event = event

    def on_subscribe(self, client: Client, channel: ChannelView) -> None:
        self._event.set()


class FoxgloveServer:
    """foxglove-sdk's WebSocket server in its own context: channels advertised up front, built
    only for subscribed clients and at a bounded rate.

    Raises :class:`TransportError` if the server cannot listen on ``host:port``.
    """

    def __init__(
        self, host: str = "127.0.0.1", port: int = 8765, *, name: str = "koala-bridge",
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._context = foxglove.Context()
        self.clock = clock
        self._lock = threading.Lock()
        self._channels: dict[str, foxglove.Channel] = {}
        self._next: dict[str, float] = {}
        self._period: dict[str, float] = {}
        self._static: dict[str, bytes] = {}
        self._static_t_ns = 0
        self._time_period = 1.0 / SCENE_RATE_HZ
        self._next_time = 0.0           # the clock's time of the next time broadcast
        self._subscribed = threading.Event()
        self._closed = threading.Event()
        if not is_loopback_host(host):
            log.warning("Foxglove live view on %s, reachable from the network "
                        "([run] allow_non_loopback)", host)
        try:
            self._server = foxglove.start_server(
                name=name, host=host, port=port, context=self._context,
                capabilities=[Capability.Time], server_listener=_Subscriptions(self._subscribed),
            )
        except Exception as e:  # the SDK raises its own error types (e.g. address in use)
            raise TransportError(f"cannot start the Foxglove server on {host}:{port}: {e}") from e
        self.host = host
        self.port = int(self._server.port)
        # the static scene for each client that subscribes (the server has no latched topics)
        self._static_thread = threading.Thread(target=self._serve_static,
                                               name="foxglove-static", daemon=True)
        self._static_thread.start()

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"ws://{host}:{self.port}"

    # -- channels ------------------------------------------------------------------------------

    def add_channel(self, topic: str, schema: ChannelSchema | Mapping[str, Any],
                    rate_hz: float = SCENE_RATE_HZ) -> None:
        """Advertise ``topic`` (a Foxglove schema, or a JSON Schema for JSON messages) if it is
        not yet; ``rate_hz`` bounds the messages per wall second it carries."""
        with self._lock:
            if topic in self._channels:
                return
            if isinstance(schema, ChannelSchema):
                channel = foxglove.Channel(
                    topic, schema=foxglove.Schema(name=schema.name, encoding=schema.encoding,
                                                  data=schema.data),
                    message_encoding=schema.message_encoding, context=self._context)
            else:
                channel = foxglove.Channel(topic, schema=dict(schema), message_encoding="json",
                                           context=self._context)
            self._channels[topic] = channel
            self._period[topic] = 1.0 / rate_hz
            self._next[topic] = 0.0

    def __contains__(self, topic: str) -> bool:
        return topic in self._channels

    def due(self, topic: str, now: float | None = None) -> bool:
        """Whether a message on ``topic`` would reach a client now (``now``: the clock's time,
        if the caller has it): the topic's rate allows it and a client is subscribed (then
        the slot is taken). The rate holds on average: a message late by up to one period
        (a real-time run's jitter) does not cost the next one its slot."""
        if now is None:
            now = self.clock()
        next_t = self._next.get(topic)
        if next_t is None or now < next_t or not self._channels[topic].has_sinks():
            return False
        period = self._period[topic]
        self._next[topic] = max(next_t + period, now - period)
        return True

    def next_due(self, topic: str, now: float) -> float:
        """The clock's time before which :meth:`due` of ``topic`` is surely False: its next
        slot, or a period from ``now`` while no client is subscribed to it."""
        if not self._channels[topic].has_sinks():
            return now + self._period[topic]
        return self._next[topic]

    def subscribed(self, topic: str | None = None) -> bool:
        """Whether a client is subscribed to ``topic`` (None: to any topic)."""
        channels = self._channels.values() if topic is None else [self._channels[topic]]
        return any(channel.has_sinks() for channel in channels)

    def log(self, topic: str, data: bytes, t_ns: int) -> None:
        self._channels[topic].log(data, log_time=t_ns)

    def set_time(self, t_ns: int) -> None:
        """The clients' current time (the simulation's)."""
        self._static_t_ns = t_ns
        self._server.broadcast_time(t_ns)

    def tick_time(self, t_ns: int, now: float) -> None:
        """Send the clients the time ``t_ns`` if its slot has come (``now``: the clock's time):
        at most :data:`SCENE_RATE_HZ` times per wall second, whatever the clients subscribe to
        (the player's clock follows the run even with only a plot open), never backwards."""
        if now < self._next_time or t_ns < self._static_t_ns:
            return
        period = self._time_period
        self._next_time = max(self._next_time + period, now - period)
        self.set_time(t_ns)

    def next_time_due(self) -> float:
        """The clock's time before which :meth:`tick_time` sends nothing."""
        return self._next_time

    def add_static(self, messages: Iterable[tuple[str, bytes]]) -> None:
        """Messages each client gets when it subscribes to their topics (their channels must
        exist); a topic's message replaces the one it had. Several taps add theirs."""
        self._static = {**self._static, **dict(messages)}
        self._subscribed.set()

    # -- the static scene ----------------------------------------------------------------------

    def _serve_static(self) -> None:
        while not self._closed.is_set():
            if not self._subscribed.wait(0.2):
                continue
            # the subscription is in force once the listener has returned: a moment later
            self._closed.wait(0.05)
            self._subscribed.clear()
            for topic, data in self._static.items():
                channel = self._channels.get(topic)
                if channel is not None and channel.has_sinks():
                    channel.log(data, log_time=self._static_t_ns)

    def close(self) -> None:
        """Stop the server and close every channel; idempotent."""
        if self._closed.is_set():
            return
        self._closed.set()
        self._static_thread.join(timeout=5.0)
        self._server.stop()
        with self._lock:
            for channel in self._channels.values():
                channel.close()
            self._channels.clear()


class FoxgloveTap:
    """A :class:`runtime.source.Tap` that passes everything on to ``inner`` (the recorder, or
    None) and draws the scene for the live ``server`` and/or the ``recorder``.

    ``raw_namespace``: the live raw streams' topics are the recording's names of the keys below
    it (a robot of ``[[robots]]``: its name, ``/alpha/sensors/gyro``). The robot whose
    translator draws the world's topics also gives the clients the time.

    Thread-safe: a source may call it from several threads (a real robot's readers).
    """

    def __init__(
        self,
        translator: SceneTranslator,
        inner: Tap | None = None,
        *,
        server: FoxgloveServer | None = None,
        recorder: Recorder | None = None,
        raw_namespace: str = "",
    ) -> None:
        self.translator = translator
        self.raw_namespace = raw_namespace
        self.inner = inner
        self.server = server
        self.recorder = recorder
        self._lock = threading.Lock()
        self._schemas = {cls: foxglove_schema(cls) for cls in set(translator.channels().values())}
        self._next_static = 0.0
        self._failed: set[str] = set()
        self._gives_time = translator.world_topics    # one tap per server sends the time
        self._raw_topics: dict[str, str] = {}     # bridge key -> its raw stream's topic
        self._idle_until: dict[str, float] = {}   # bridge key -> when a topic of it may be due
        if server is not None:
            for topic, cls in translator.channels().items():
                server.add_channel(topic, self._schemas[cls])
            server.add_static(self._static_bytes(0.0))

    # -- Tap -----------------------------------------------------------------------------------

    def declare(self, keys: Iterable[str] = (), buses: Iterable[str] = ()) -> None:
        keys = list(keys)
        if self.inner is not None:
            self.inner.declare(keys, buses)
        if self.recorder is not None:
            self.recorder.declare_encoded(
                (topic, self._schemas[cls]) for topic, cls in self.translator.channels().items())
        if self.server is not None:
            for key in keys:
                self._raw_channel(key)

    def record(self, channel: str, t: float, payload: Mapping[str, Any]) -> None:
        if self.inner is not None:
            self.inner.record(channel, t, payload)
        server = self.server
        if (self.recorder is None and server is not None
                and server.clock() < self._idle_until.get(channel, 0.0)):
            return      # live only, and none of the key's topics is due yet: the common case
        with self._lock:
            self._draw(channel, t, payload)

    def record_frame(
        self, bus: str, direction: str, t: float, data: bytes, **fields: object
    ) -> None:
        if self.inner is not None:
            self.inner.record_frame(bus, direction, t, data, **fields)

    # -- internals -----------------------------------------------------------------------------

    def _draw(self, key: str, t: float, payload: Mapping[str, Any]) -> None:
        server, recorder = self.server, self.recorder
        if recorder is not None and t >= self._next_static:
            self._next_static = t + STATIC_PERIOD_S
            for topic, data in self._static_bytes(t):
                recorder.record_encoded(topic, t, data, self._schema_of(topic))
        outputs = self.translator.outputs(key)
        now = None if server is None else server.clock()
        ns = -1
        for out in outputs:
            live = now is not None and server is not None and server.due(out.topic, now)
            if not (live or recorder is not None):
                continue
            encoded = self._encode(out, t, payload)
            if encoded is None:
                continue
            if live:
                assert server is not None
                ns = time_ns(t)
                server.log(out.topic, encoded, ns)
            if recorder is not None:
                recorder.record_encoded(out.topic, t, encoded, self._schemas[out.schema])
        if server is not None:
            assert now is not None
            if self._gives_time:
                # independent of subscriptions: the time is the clients' clock, not a topic
                server.tick_time(time_ns(t) if ns < 0 else ns, now)
            raw = self._raw_topics.get(key)
            if raw is None:
                self._raw_channel(key)      # advertised on first sight: no subscriber yet
            elif server.due(raw, now):
                server.log(raw, json.dumps(payload, separators=(",", ":")).encode(),
                           time_ns(t) if ns < 0 else ns)
            if raw is not None:
                idle = min(server.next_due(topic, now)
                           for topic in (raw, *(o.topic for o in outputs)))
                if self._gives_time:
                    idle = min(idle, server.next_time_due())
                self._idle_until[key] = idle

    def _raw_channel(self, key: str) -> None:
        """Advertise the raw stream of ``key``: the bridge's JSON message, for the plots, on
        the recording's topic name (one layout for the live view and the recordings)."""
        assert self.server is not None
        topic = topic_name(f"{self.raw_namespace}/{key}" if self.raw_namespace else key)
        self.server.add_channel(topic, topic_json_schema(key), RAW_RATE_HZ)
        self._raw_topics[key] = topic

    def _encode(self, out: Output, t: float, payload: Mapping[str, Any]) -> bytes | None:
        """``out``'s message for ``payload``, encoded; None if there is nothing to draw or the
        payload cannot be drawn (logged once per topic: a bad message never stops the loop)."""
        try:
            msg = out.build(t, payload)
            return None if msg is None else bytes(msg.encode())
        except Exception:  # a real robot's odd payload: logged, the loop goes on
            if out.topic not in self._failed:
                self._failed.add(out.topic)
                log.exception("Foxglove: cannot draw %s (further failures not logged)",
                              out.topic)
            return None

    def _static_bytes(self, t: float) -> list[tuple[str, bytes]]:
        return [(topic, bytes(msg.encode())) for topic, msg in self.translator.static(t)]

    def _schema_of(self, topic: str) -> ChannelSchema:
        return self._schemas[self.translator.channels()[topic]]


class ServedWithFoxglove:
    """A source served with a live Foxglove server beside it: the server opens before the
    source (a busy port fails first), its URL is in the endpoints (``foxglove.url`` in the
    endpoints file, a line of the banner), and it closes after the source. Everything else is
    the source's."""

    def __init__(self, source: RobotSource, server_factory: Callable[[], FoxgloveServer],
                 on_open: Callable[[FoxgloveServer], None]) -> None:
        self.source = source
        self._factory = server_factory
        self._on_open = on_open
        self.server: FoxgloveServer | None = None

    def __getattr__(self, name: str) -> Any:
        return getattr(self.source, name)

    def open(self) -> Endpoints:
        self.server = self._factory()
        log.info("Foxglove live view at %s", self.server.url)
        self._on_open(self.server)
        endpoints = self.source.open()
        return replace(endpoints, foxglove_url=self.server.url)

    def close(self) -> None:
        try:
            self.source.close()
        finally:
            if self.server is not None:
                self.server.close()


def attach_foxglove(
    source: RobotSource,
    robot: str,
    *,
    address: tuple[str, int] | None = None,
    recorder: Recorder | None = None,
    robots: Sequence[tuple[str, RobotSource]] = (),
) -> RobotSource:
    """Draw ``source``'s scene for Foxglove: live on ``address`` (``(host, port)``; None: no
    server) and into ``recorder`` (None: no recording). Wraps ``source.tap`` (the recorder's
    tap goes on behind the new one); returns the source to run (``source`` itself, or
    ``source`` with the server, :class:`ServedWithFoxglove`).

    ``robots``: the robots of a ``[[robots]]`` source, ``(name, its source)`` in order; each
    robot's tap is wrapped instead, its scene drawn under ``/<name>/scene`` with frames
    ``<name>/...``, its raw streams under ``/<name>``, the world's topics by the first robot
    only, all on one server (``robot`` then only names the server).
    """
    members = list(robots) or [(robot, source)]
    fleet = bool(robots)
    translators = [
        SceneTranslator(member.world_answer(), name,
                        namespace=f"/{name}/scene" if fleet else "", world_topics=i == 0)
        for i, (name, member) in enumerate(members)]
    inners = [member.tap for _, member in members]

    def wrap(server: FoxgloveServer | None) -> None:
        for (name, member), translator, inner in zip(members, translators, inners, strict=True):
            member.tap = FoxgloveTap(translator, inner, server=server, recorder=recorder,
                                     raw_namespace=name if fleet else "")

    if address is None:
        wrap(None)
        return source
    host, port = address
    return ServedWithFoxglove(  # type: ignore[return-value]
        source, lambda: FoxgloveServer(host, port, name=f"koala-bridge {robot}"), wrap)
