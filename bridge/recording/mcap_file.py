"""Recordings: what the bridge published and every raw bus frame, in one MCAP file.

File layout (docs/recording.md has the full description):

* profile ``koala-bridge``; a metadata record ``koala-bridge`` with ``format_version`` (this
  module's :data:`FORMAT_VERSION`), ``source`` (``sim`` | ``real``), ``seed``, ``config_path``,
  ``config`` (the TOML text), ``kteam_dialect`` (``koala1`` | ``koala25``: what the
  ``/bus/serial/kteam`` frames speak; absent in older recordings, read as ``koala1``), and a
  metadata record ``world`` with the world and robot parameters as JSON
  (the answer of the ``<prefix>/world`` queryable).
* one channel per Zenoh key, named after the key below the prefix: ``/truth/pose``,
  ``/sensors/sonar``, ``/status``, ``/estimate/pose`` …; message encoding ``json``, schema
  encoding ``jsonschema`` (Foxglove opens both), the schema derived from the key's typed message
  in :mod:`koala_bridge.core.topics`.
* one channel per bus: ``/bus/serial/kteam``, ``/bus/serial/rangefinders``, ``/bus/can``,
  ``/bus/mavlink``, carrying JSON ``{t, dir, seq, len, data_b64, …}`` for each frame in either
  direction. ``dir`` is seen from the robot: ``from_robot`` (what the robot, simulated or real,
  put on the bus) or ``to_robot`` (what a client sent it). ``seq`` counts frames per bus and
  direction from 0 without gaps; a gap in a recording means frames were lost.
* :meth:`Recorder.declare` creates channels before their first message (the service declares every
  bus it serves and every key it publishes), so a bus no client used still has its channel.
* ``log_time`` = ``publish_time`` = simulation time in nanoseconds; the MCAP ``sequence`` field
  counts messages per channel.

Crash safety: messages are grouped in small zstd chunks (``chunk_size`` bytes uncompressed, and
at most ``max_chunk_age_s`` of wall time), and every byte the MCAP writer emits goes straight to
the kernel, so a writer killed with SIGKILL leaves a file that :func:`open_recording` (and any
streaming MCAP reader) reads up to its last complete chunk. :meth:`Recorder.close` writes the
summary and footer: a complete, indexed file.
"""

from __future__ import annotations

import base64
import dataclasses
import difflib
import io
import json
import logging
import math
import os
import struct
import threading
import time
import zlib
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from koala_bridge.core.topics import JSON_SCHEMA_DIALECT, TOPICS
from koala_bridge.core.topics import json_schema as topic_json_schema
from mcap.data_stream import ReadDataStream
from mcap.exceptions import EndOfFile
from mcap.opcode import Opcode
from mcap.records import (
    Attachment,
    AttachmentIndex,
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Message,
    MessageIndex,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)
from mcap.stream_reader import breakup_chunk
from mcap.writer import CompressionType, Writer

try:  # the mcap library's zstd chunks need it; without it they fail to decode, as damage would
    import zstandard
except ImportError:  # pragma: no cover
    zstandard = None  # type: ignore[assignment]

log = logging.getLogger(__name__)

PROFILE = "koala-bridge"
FORMAT_VERSION = 1
META_NAME = "koala-bridge"
WORLD_META_NAME = "world"

MCAP_MAGIC = b"\x89MCAP0\r\n"  # the first (and last) 8 bytes of every MCAP file

BUSES = ("serial/kteam", "serial/rangefinders", "can", "mavlink")
FROM_ROBOT = "from_robot"
TO_ROBOT = "to_robot"
DIRECTIONS = (FROM_ROBOT, TO_ROBOT)


from koala_bridge.core.errors import RecordingError  # noqa: E402 - the tree's, re-exported


class UnsupportedRecordingError(RecordingError):
    """A recording is valid MCAP but not one this version can use (format version, channels)."""


# --------------------------------------------------------------------------------------------
# JSON schemas, one per channel (Foxglove shows them; docs/recording.md lists them). A Zenoh
# key's schema is derived from its typed message (koala_bridge.core.topics), the one definition
# the published JSON also comes from; a key without one gets the generic schema (an object with
# a time ``t``). Bus frames are the recording's own records, described here.

BUS_FRAME_SCHEMA: dict[str, Any] = {
    "$schema": JSON_SCHEMA_DIALECT,
    "title": "koala.bus.Frame",
    "type": "object",
    "properties": {
        "t": {"type": "number", "description": "simulation time, s"},
        "dir": {"enum": list(DIRECTIONS), "description": "seen from the robot"},
        "seq": {"type": "integer", "description": "per bus and direction, from 0, no gaps"},
        "len": {"type": "integer"},
        "data_b64": {"type": "string", "contentEncoding": "base64"},
        "transport": {"type": "string", "description": "pty, socketcand, slcan, udp, …"},
        "can_id": {"type": "integer"},
        "extended": {"type": "boolean"},
    },
    "required": ["t", "dir", "seq", "len", "data_b64"],
}


@dataclass(frozen=True)
class ChannelSchema:
    """A channel's schema record (``name``, ``encoding``, ``data``) and its messages' encoding:
    ``jsonschema`` / ``json`` for the bridge's own channels, ``protobuf`` / ``protobuf`` for
    the Foxglove standard-schema channels (docs/recording.md)."""

    name: str
    encoding: str
    data: bytes
    message_encoding: str


def _topic_schema(topic: str) -> dict[str, Any]:
    """The schema of the MCAP topic (``/sensors/ir``) of a Zenoh key; a robot's key of a fleet
    (``/alpha/sensors/ir``, runtime/fleet_source.py) has the schema of its key below the name."""
    key = topic[1:]
    robot, _, below = key.partition("/")
    if below and key not in TOPICS and below in TOPICS:
        return topic_json_schema(below)
    return topic_json_schema(key)


def topic_name(channel: str) -> str:
    """The MCAP topic of a Zenoh key below the prefix: ``sensors/ir`` -> ``/sensors/ir``."""
    return "/" + channel.strip("/")


def bus_topic(bus: str) -> str:
    """The MCAP topic of a bus: ``can`` -> ``/bus/can``."""
    return "/bus/" + bus.strip("/")


def time_ns(t: float) -> int:
    """Simulation seconds -> MCAP log time (ns, never negative)."""
    return max(0, round(t * 1e9))


# --------------------------------------------------------------------------------------------
# Writer


class _KernelFile:
    """A file whose every write goes straight to the kernel (no user-space buffer).

    The MCAP writer buffers a chunk in memory and emits it as a few writes; with this stream a
    SIGKILL loses at most the chunk in progress. Not a ``RawIOBase`` on purpose: the MCAP writer
    would wrap that in a ``BufferedWriter``.
    """

    def __init__(self, path: Path) -> None:
        self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        self._pos = 0

    def write(self, data: bytes) -> int:
        view = memoryview(data)
        while view:
            n = os.write(self._fd, view)
            view = view[n:]
        self._pos += len(data)
        return len(data)

    def tell(self) -> int:
        return self._pos

    def flush(self) -> None:
        """Nothing to do: no user-space buffer."""

    def close(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1


class Recorder:
    """Thread-safe MCAP writer for one run of the bridge.

    ``record(channel, t, payload)`` takes what the bridge publishes on Zenoh (``channel`` is the
    key below the prefix, ``payload`` a JSON object or its encoded bytes);
    ``record_frame(bus, direction, t, data)`` takes one raw bus frame. Both are cheap enough for
    the service loop; errors while writing are logged once and counted in :attr:`dropped`, never
    raised into the caller's loop. Do not call :meth:`close` from a signal handler (it could
    interrupt a ``record`` that holds the lock): let the handler set an event, close in the loop.

    Args:
        path: the ``.mcap`` file to create (truncated if it exists).
        metadata: extra string fields for the ``koala-bridge`` metadata record (``source``,
            ``seed``, ``config_path``, ``config``, …).
        world: the world and robot parameters (JSON-serialisable), stored as metadata ``world``.
        chunk_size: uncompressed bytes per chunk; what a SIGKILL can lose at most.
        max_chunk_age_s: wall time after which a chunk in progress is written anyway.
        clock: monotonic clock for the chunk age (seconds).
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        metadata: Mapping[str, object] | None = None,
        world: Mapping[str, Any] | None = None,
        chunk_size: int = 32 * 1024,
        max_chunk_age_s: float = 0.5,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.path = Path(path)
        self._lock = threading.Lock()
        self._clock = clock
        self._max_chunk_age_s = max_chunk_age_s
        try:
            self._file = _KernelFile(self.path)
        except OSError as e:
            raise RecordingError(f"cannot create recording {self.path}: {e}") from e
        self._writer = Writer(
            self._file,  # type: ignore[arg-type]  # duck-typed stream: write/tell/flush
            chunk_size=chunk_size,
            compression=CompressionType.ZSTD,
            enable_data_crcs=True,  # DataEnd's CRC: a flipped bit outside a chunk is found too
        )
        self._writer.start(profile=PROFILE, library=f"koala-bridge recording/{FORMAT_VERSION}")
        meta = {"format_version": str(FORMAT_VERSION), "created_unix_s": f"{time.time():.3f}"}
        meta.update({k: _as_text(v) for k, v in (metadata or {}).items()})
        self._writer.add_metadata(META_NAME, meta)
        if world is not None:
            self._writer.add_metadata(WORLD_META_NAME, {"json": json.dumps(world)})
        self._channels: dict[str, int] = {}
        self._schema_ids: dict[ChannelSchema, int] = {}  # record_encoded's schema records
        self._msg_seq: dict[int, int] = {}
        self._frame_seq: dict[tuple[str, str], int] = {}
        self._last_flush = clock()
        self._closed = False
        self._failed = False
        self.dropped = 0
        self.written = 0

    # -- public API ---------------------------------------------------------------------------

    def record(self, channel: str, t: float, payload: Mapping[str, Any] | bytes | str) -> None:
        """Record one message of the Zenoh key ``channel`` (below the prefix) at sim time ``t``."""
        if isinstance(payload, Mapping):
            data = json.dumps(payload, separators=(",", ":")).encode()
        elif isinstance(payload, str):
            data = payload.encode()
        else:
            data = bytes(payload)
        with self._lock:
            self._write(topic_name(channel), t, data, _topic_schema)

    def record_frame(
        self, bus: str, direction: str, t: float, data: bytes, **fields: object
    ) -> None:
        """Record one raw frame of ``bus`` (one of :data:`BUSES`) sent in ``direction``.

        ``fields`` adds JSON members (``transport``, and for CAN ``can_id``/``extended``, where
        ``data`` is the frame's payload).
        """
        if direction not in DIRECTIONS:
            raise ValueError(f"direction must be one of {DIRECTIONS}, got {direction!r}")
        topic = bus_topic(bus)
        with self._lock:
            key = (topic, direction)
            seq = self._frame_seq.get(key, 0)
            self._frame_seq[key] = seq + 1
            msg = {
                "t": t,
                "dir": direction,
                "seq": seq,
                "len": len(data),
                "data_b64": base64.b64encode(data).decode("ascii"),
                **fields,
            }
            self._write(
                topic,
                t,
                json.dumps(msg, separators=(",", ":")).encode(),
                lambda _topic: BUS_FRAME_SCHEMA,
            )

    def record_encoded(self, topic: str, t: float, data: bytes, schema: ChannelSchema) -> None:
        """Record one message already encoded by its writer (a Foxglove standard-schema message
        of :mod:`runtime.foxglove_io`) on the MCAP ``topic`` as it is, under ``schema``."""
        with self._lock:
            self._write(topic, t, data, schema)

    def declare_encoded(self, channels: Iterable[tuple[str, ChannelSchema]]) -> None:
        """Create the channels ``(topic, schema)`` of :meth:`record_encoded` now (see
        :meth:`declare`)."""
        with self._lock:
            if self._closed or self._failed:
                return
            for topic, schema in channels:
                self._channel(topic, schema)

    def declare(self, keys: Iterable[str] = (), buses: Iterable[str] = ()) -> None:
        """Create the channels of Zenoh ``keys`` (below the prefix) and of ``buses`` now, before
        their first message: a recording then holds every channel its run served, a bus no
        client used among them (with 0 messages). Channels that exist are left as they are."""
        with self._lock:
            if self._closed or self._failed:
                return
            for key in keys:
                self._channel(topic_name(key), _topic_schema)
            for bus in buses:
                self._channel(bus_topic(bus), lambda _topic: BUS_FRAME_SCHEMA)

    def flush(self) -> None:
        """Write the chunk in progress now (a SIGKILL after this loses nothing recorded so far)."""
        with self._lock:
            if not self._closed and not self._failed:
                self._guard(self._writer.flush)
                self._last_flush = self._clock()

    def close(self) -> None:
        """Write the summary and footer and close the file. Idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            if not self._failed:
                self._guard(self._writer.finish)
            self._file.close()
        log.info(
            "recording %s closed: %d messages, %d dropped", self.path, self.written, self.dropped
        )

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- internals ----------------------------------------------------------------------------

    def _channel(
        self, topic: str, schema: Callable[[str], dict[str, Any]] | ChannelSchema
    ) -> int:
        """The id of ``topic``'s channel, registered (with its schema) on first use: a JSON
        Schema for the topic (JSON messages), or a :class:`ChannelSchema` as it is."""
        channel_id = self._channels.get(topic)
        if channel_id is None:
            if isinstance(schema, ChannelSchema):
                # one schema record for the channels that share it (a SceneUpdate's is 5 kB)
                spec = schema
                schema_id = self._schema_ids.get(spec)
                if schema_id is None:
                    schema_id = self._writer.register_schema(
                        name=spec.name, encoding=spec.encoding, data=spec.data
                    )
                    self._schema_ids[spec] = schema_id
            else:
                s = schema(topic)
                spec = ChannelSchema(s["title"], "jsonschema", json.dumps(s).encode(), "json")
                schema_id = self._writer.register_schema(
                    name=spec.name, encoding=spec.encoding, data=spec.data
                )
            channel_id = self._writer.register_channel(topic, spec.message_encoding, schema_id)
            self._channels[topic] = channel_id
            self._msg_seq[channel_id] = 0
        return channel_id

    def _write(
        self, topic: str, t: float, data: bytes,
        schema: Callable[[str], dict[str, Any]] | ChannelSchema,
    ) -> None:
        if self._closed or self._failed:
            self.dropped += 1
            return
        channel_id = self._channel(topic, schema)
        seq = self._msg_seq[channel_id]
        self._msg_seq[channel_id] = seq + 1
        ns = time_ns(t)
        if not self._guard(lambda: self._writer.add_message(channel_id, ns, data, ns, seq)):
            return
        self.written += 1
        now = self._clock()
        if now - self._last_flush >= self._max_chunk_age_s:
            self._guard(self._writer.flush)
            self._last_flush = now

    def _guard(self, op: Callable[[], object]) -> bool:
        try:
            op()
        except OSError as e:
            self._failed = True
            self.dropped += 1
            log.error("recording %s stopped: %s", self.path, e)
            return False
        return True


def run_metadata(
    source: str,
    config: Mapping[str, Any],
    config_path: str | os.PathLike[str] | None,
    kteam_dialect: str = "koala1",
) -> dict[str, str]:
    """The ``koala-bridge`` metadata of a run: source, seed, config path, the resolved
    configuration (file + command-line overrides) as JSON, and the dialect of the K-Team frames
    (``kteam_dialect``: the simulated pty's ``[buses.kteam] dialect`` or the real robot's
    ``[real] kteam_dialect``; a replay answers in it)."""
    seed = (config.get("sim") or {}).get("seed")
    return {
        "source": source,
        "seed": "" if seed is None else str(seed),
        "config_path": "" if config_path is None else str(Path(config_path).resolve()),
        "config": json.dumps(config, default=str),
        "kteam_dialect": kteam_dialect,
    }


def _as_text(v: object) -> str:
    if isinstance(v, str):
        return v
    return json.dumps(v)


# --------------------------------------------------------------------------------------------
# Reader


@dataclass(frozen=True)
class RecordedMessage:
    """One message of a recording."""

    topic: str
    log_time_ns: int
    sequence: int
    data: bytes
    channel_id: int = 0
    publish_time_ns: int | None = None  # None: the same as log_time_ns

    @property
    def t(self) -> float:
        """Simulation time, s."""
        return self.log_time_ns * 1e-9

    def json(self) -> Any:
        return json.loads(self.data)

    def frame_bytes(self) -> bytes:
        """The raw bytes of a bus frame message."""
        return base64.b64decode(self.json()["data_b64"])


@dataclass
class Recording:
    """A recording read in full: metadata, messages in file order, and whether it was complete.

    ``complete`` is False for a file cut short (a writer killed with SIGKILL, a full disk):
    ``messages`` then holds everything up to the last complete chunk, and ``lost`` says what
    was lost (the same text as the warning :func:`open_recording` logs).
    """

    path: Path
    profile: str
    metadata: dict[str, dict[str, str]]
    messages: list[RecordedMessage]
    complete: bool
    schemas: dict[str, str] = field(default_factory=dict)  # topic -> JSON Schema text (json)
    lost: str = ""
    #: the MCAP records of the channels and their schemas, by id (``koala-bridge recover``
    #: writes them back)
    channel_records: dict[int, Channel] = field(default_factory=dict)
    schema_records: dict[int, Schema] = field(default_factory=dict)
    chunks: int = 0  # complete chunks read

    @property
    def format_version(self) -> int | None:
        v = self.metadata.get(META_NAME, {}).get("format_version")
        return int(v) if v is not None and v.isdigit() else None

    @property
    def world(self) -> dict[str, Any] | None:
        w = self.metadata.get(WORLD_META_NAME)
        return json.loads(w["json"]) if w and "json" in w else None

    @property
    def topics(self) -> list[str]:
        return sorted({m.topic for m in self.messages} | set(self.schemas)
                      | {ch.topic for ch in self.channel_records.values()})

    def topic(self, topic: str) -> list[RecordedMessage]:
        """Messages of one topic (``/sensors/gyro`` or ``sensors/gyro``) in file order."""
        name = topic_name(topic)
        return [m for m in self.messages if m.topic == name]

    def message_encoding(self, m: RecordedMessage) -> str:
        """The encoding of ``m``'s channel: ``json`` for the bridge's messages and bus frames,
        ``protobuf`` for the Foxglove standard-schema channels (docs/recording.md)."""
        ch = self.channel_records.get(m.channel_id)
        return "json" if ch is None else ch.message_encoding

    def counts(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for m in self.messages:
            out[m.topic] = out.get(m.topic, 0) + 1
        return out

    @property
    def robots(self) -> list[dict[str, Any]]:
        """The robots of a recording of ``[[robots]]`` (metadata ``robots``: each robot's
        ``name``, ``prefix``, ``start``, ``seed_offset``, ...), in the file's order; ``[]`` for a
        one-robot recording."""
        text = self.metadata.get(META_NAME, {}).get("robots")
        if not text:
            return []
        try:
            robots = json.loads(text)
        except ValueError as e:
            raise RecordingError(f"{self.path}: its metadata 'robots' is not JSON ({e})") from e
        if not isinstance(robots, list) or not all(
                isinstance(r, dict) and isinstance(r.get("name"), str) for r in robots):
            raise RecordingError(f"{self.path}: its metadata 'robots' is not a list of robots")
        return robots

    def robot(self, name: str | None) -> Recording:
        """The recording as one robot's: for a recording of ``[[robots]]``, the view of robot
        ``name`` as a one-robot recording (:func:`robot_view`); a one-robot recording itself
        when ``name`` is None. Raises :class:`RecordingError` (one line) when ``name`` is
        missing for a fleet's recording, names no robot of it, or is given for a one-robot
        recording."""
        robots = self.robots
        names = [r["name"] for r in robots]
        if not robots:
            if name is None:
                return self
            raise RecordingError(f"{self.path.name} is a recording of one robot: --robot "
                                 f"{name} applies only to a recording of [[robots]]")
        if name is None:
            raise RecordingError(f"{self.path.name} is a recording of {len(names)} robots "
                                 f"({', '.join(names)}): choose one with --robot NAME")
        if name not in names:
            near = difflib.get_close_matches(name, names, n=1)
            hint = f"; did you mean {near[0]!r}?" if near else ""
            raise RecordingError(f"{self.path.name} holds no robot {name!r} (its robots: "
                                 f"{', '.join(names)}){hint}")
        return robot_view(self, robots[names.index(name)], names)


def robot_topic(topic: str, name: str, names: Iterable[str]) -> str | None:
    """The topic of robot ``name``'s channel ``topic`` of a fleet's recording as a one-robot
    recording names it (``/alpha/truth/pose`` -> ``/truth/pose``, ``/bus/alpha/can`` ->
    ``/bus/can``, its Foxglove scene ``/alpha/scene/truth/tf`` -> ``/alpha/truth/tf``, as a
    one-robot run of a robot named ``alpha`` records it: docs/foxglove.md); a channel of the
    world (``/world/map``) as it is; None for another robot's."""
    for robot in names:
        for head in (f"/bus/{robot}/", f"/{robot}/"):
            if topic.startswith(head):
                if robot != name:
                    return None
                rest = topic[len(head):]
                if head.startswith("/bus/"):
                    return "/bus/" + rest
                if rest.startswith("scene/"):
                    return f"/{name}/{rest[len('scene/'):]}"
                return "/" + rest
    return topic


def robot_view(rec: Recording, robot: Mapping[str, Any], names: list[str]) -> Recording:
    """Robot ``robot`` (an entry of :attr:`Recording.robots`) of a fleet's recording ``rec``,
    read as a one-robot recording: its channels under their one-robot names
    (:func:`robot_topic`), the world's channels shared, the others' left out; the metadata's
    ``kteam_dialect`` the robot's and the world's ``start`` (and ``robot``, when recorded) its
    own. The metadata keeps the fleet's ``config`` and names the robot (``robot``)."""
    name = robot["name"]
    topics = {ch.topic: robot_topic(ch.topic, name, names)
              for ch in rec.channel_records.values()}
    topics.update({m.topic: robot_topic(m.topic, name, names) for m in rec.messages
                   if m.topic not in topics})
    channels = {i: dataclasses.replace(ch, topic=t)
                for i, ch in rec.channel_records.items() if (t := topics[ch.topic]) is not None}
    messages = [dataclasses.replace(m, topic=t) for m in rec.messages
                if (t := topics[m.topic]) is not None]
    schemas = {t: text for topic, text in rec.schemas.items()
               if (t := topics.get(topic, topic)) is not None}
    metadata = {k: dict(v) for k, v in rec.metadata.items()}
    run = metadata.setdefault(META_NAME, {})
    run.pop("robots", None)
    run["robot"] = name
    dialect = robot.get("kteam_dialect") or _entry_dialect(run.get("config"), name)
    if dialect:
        run["kteam_dialect"] = dialect
    world = rec.world
    if world is not None:
        start = robot.get("start")
        if isinstance(start, dict) and {"x", "y"} <= start.keys():
            theta = start.get("theta")
            if theta is None:
                theta = math.radians(float(start.get("theta_deg", 0.0)))
            world["start"] = {"x": start["x"], "y": start["y"], "theta": theta}
        if isinstance(robot.get("robot"), dict):
            world["robot"] = robot["robot"]
        metadata[WORLD_META_NAME] = {**metadata.get(WORLD_META_NAME, {}),
                                     "json": json.dumps(world)}
    return dataclasses.replace(rec, metadata=metadata, messages=messages, schemas=schemas,
                               channel_records=channels)


def _entry_dialect(config_text: str | None, name: str) -> str | None:
    """The K-Team dialect of robot ``name`` in a recorded fleet configuration (its entry's
    ``[robots.buses.kteam] dialect``, else the file's), for recordings whose ``robots`` metadata
    does not say it."""
    try:
        config = json.loads(config_text or "{}")
        entry = next(e for e in config.get("robots") or [] if e.get("name") == name)
        for table in (entry, config):
            found = ((table.get("buses") or {}).get("kteam") or {}).get("dialect")
            if found:
                return str(found)
    except (ValueError, AttributeError, StopIteration):
        pass
    return None


class CorruptRecordingError(RecordingError):
    """A recording's bytes are damaged: a CRC does not match, or a complete record cannot be
    decoded. The message names the record and its byte offset (for the data section's CRC, the
    byte range it covers: the check cannot tell where in it the damage is) and ends in
    :data:`RECOVER_HINT`."""


#: The end of every :class:`CorruptRecordingError` message: what the user can do about it.
RECOVER_HINT = "(koala-bridge recover IN OUT salvages what is intact)"


#: MCAP record readers by opcode (the record's body as a stream; a message also needs its
#: length). Opcodes 0x80-0xFF are private records, skipped as the MCAP specification says.
_RECORD_READERS: dict[int, Callable[[ReadDataStream, int], object]] = {
    Opcode.HEADER: lambda s, n: Header.read(s),
    Opcode.FOOTER: lambda s, n: Footer.read(s),
    Opcode.SCHEMA: lambda s, n: Schema.read(s),
    Opcode.CHANNEL: lambda s, n: Channel.read(s),
    Opcode.MESSAGE: lambda s, n: Message.read(s, n),
    Opcode.CHUNK: lambda s, n: Chunk.read(s),
    Opcode.MESSAGE_INDEX: lambda s, n: MessageIndex.read(s),
    Opcode.CHUNK_INDEX: lambda s, n: ChunkIndex.read(s),
    Opcode.ATTACHMENT: lambda s, n: Attachment.read(s),
    Opcode.ATTACHMENT_INDEX: lambda s, n: AttachmentIndex.read(s),
    Opcode.STATISTICS: lambda s, n: Statistics.read(s),
    Opcode.METADATA: lambda s, n: Metadata.read(s),
    Opcode.METADATA_INDEX: lambda s, n: MetadataIndex.read(s),
    Opcode.SUMMARY_OFFSET: lambda s, n: SummaryOffset.read(s),
    Opcode.DATA_END: lambda s, n: DataEnd.read(s),
}
_RECORD_HEADER = struct.Struct("<BQ")  # opcode, length of the body
_FOOTER_SIZE = _RECORD_HEADER.size + 20  # summary_start, summary_offset_start (u64), crc (u32)
#: The largest chunk this reader decompresses (the recorder writes 32 KiB chunks; the mcap
#: library's default is 1 MiB): a larger declared size is a damaged length, not a chunk.
MAX_CHUNK_BYTES = 256 * 1024 * 1024


def _record_name(opcode: int) -> str:
    try:
        return Opcode(opcode).name.lower().replace("_", " ")
    except ValueError:
        return f"unknown (opcode 0x{opcode:02x})"


def _chunk_records(chunk: Chunk) -> list[object]:
    """The records inside a chunk, its CRC checked; raises on any damage."""
    if chunk.uncompressed_size > MAX_CHUNK_BYTES:
        raise ValueError(f"declares {chunk.uncompressed_size} uncompressed bytes")
    if chunk.compression == "zstd" and zstandard is not None:
        declared = zstandard.frame_content_size(chunk.data)
        if declared not in (-1, chunk.uncompressed_size):  # -1: the frame does not say
            raise ValueError(
                f"its zstd frame holds {declared} bytes, the chunk says {chunk.uncompressed_size}"
            )
    if chunk.uncompressed_crc == 0:
        log.debug("a chunk without CRC: its content is not checked")
    return list(breakup_chunk(chunk, validate_crc=True))


def outcome_messages(rec: Recording) -> list[RecordedMessage]:
    """The messages a run's outcome consists of, channel by channel (sorted by topic; per
    channel in the run's order): the truth, every sensor, the estimator, every frame the robot
    put on a bus. Left out: ``/status`` (and a fleet's ``/NAME/status``: a wall-clock real-time
    factor), the Foxglove scene channels (drawn from the others; their Log repeats that
    factor) and the frames the firmware sent (they arrive in scheduling-dependent chunks). Two
    lockstep runs of one config, seed and firmware have the same outcome, bit for bit."""
    out = []
    for m in rec.messages:
        if m.topic.endswith("/status") or rec.message_encoding(m) != "json":
            continue
        if m.topic.startswith("/bus/") and m.json().get("dir") != "from_robot":
            continue
        out.append(m)
    # file order interleaves channels by write time; per channel the order is the run's
    return sorted(out, key=lambda m: m.topic)


def open_recording(path: str | os.PathLike[str], *, salvage: bool = False) -> Recording:
    """Read a recording, complete or cut short, checking every CRC it carries.

    A complete file (it ends in a footer) must be whole: each chunk's CRC, the data section's
    and the summary's are checked, and any damage raises :class:`CorruptRecordingError` naming
    the record and its byte offset. A file cut short (a writer killed with SIGKILL, a full
    disk) is read up to its last complete record, each chunk's CRC checked, and a WARNING says
    what was lost (:attr:`Recording.lost`). With ``salvage`` (``koala-bridge recover``), damage
    skips a damaged chunk (or, when a record length is damaged, goes on at the next chunk whose
    CRC holds), with a warning naming it and the time span lost; damage with no intact chunk after
    it is treated as a cut.

    Raises :class:`RecordingError` if the file cannot be read or is not MCAP at all.
    """
    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as e:
        raise RecordingError(f"cannot read {p}: {e.strerror or e}") from e
    if not raw.startswith(MCAP_MAGIC):
        # Checked here: the reader's own complaint about a short or foreign file is a struct
        # error ("unpack requires a buffer of 8 bytes") that says nothing to a user.
        what = "it is empty" if not raw else "it does not begin with the MCAP magic bytes"
        raise RecordingError(f"{p} is not an MCAP file: {what}")
    return _Walk(p, raw, salvage).run()


class _Walk:
    """One pass over the records of an MCAP file (see :func:`open_recording`)."""

    def __init__(self, path: Path, raw: bytes, salvage: bool) -> None:
        self.path = path
        self.raw = raw
        self.salvage = salvage
        n = len(raw)
        # A file that ends in the magic bytes was closed by its writer (a cut file ends there
        # by a 1 in 2**64 chance): anything wrong inside it is damage, never a cut.
        self.closed = n >= 2 * len(MCAP_MAGIC) + _FOOTER_SIZE and raw.endswith(MCAP_MAGIC)
        self.rec = Recording(path, "", {}, [], False)
        self.last_t_ns: int | None = None
        self.in_summary = False  # past the DataEnd record: every message has been read
        self.skipped: list[str] = []  # salvage: damaged parts skipped, reading went on after them

    def run(self) -> Recording:
        raw, n, pos = self.raw, len(self.raw), len(MCAP_MAGIC)
        while pos < n:
            if n - pos < _RECORD_HEADER.size:
                self._cut(pos, "the file ends inside a record header")
                break
            opcode, length = _RECORD_HEADER.unpack_from(raw, pos)
            body_start = pos + _RECORD_HEADER.size
            if length > n - body_start:
                if self.closed:
                    nxt = self._damaged(
                        pos, f"a {_record_name(opcode)} record claims {length} bytes, more than "
                        "the file holds after it"
                    )
                    if nxt is None:
                        break
                    pos = nxt
                    continue
                self._cut(pos, f"a partial record, a {_record_name(opcode)}", opcode, body_start)
                break
            end = body_start + length
            reader = _RECORD_READERS.get(opcode)
            if reader is None:
                if opcode >= 0x80:  # a private record (MCAP specification): skipped
                    pos = end
                    continue
                nxt = self._damaged(pos, f"a record of unknown type 0x{opcode:02x}")
                if nxt is None:
                    break
                pos = nxt
                continue
            if self.in_summary and opcode != Opcode.FOOTER:
                pos = end  # the summary repeats the data section; its CRC is checked below
                continue
            try:
                record = reader(ReadDataStream(io.BytesIO(raw[body_start:end])), length)
            except Exception as e:  # noqa: BLE001 - any decode error of a whole record: damage
                nxt = self._damaged(pos, f"a {_record_name(opcode)} record cannot be decoded "
                                    f"({_read_error(e)})")
                if nxt is None:
                    break
                pos = nxt
                continue
            if not self._take(pos, record):
                break
            if isinstance(record, DataEnd):
                if (record.data_section_crc and not self.skipped  # skipped: damage already told
                        and record.data_section_crc != zlib.crc32(memoryview(raw)[:pos])):
                    self._damage(pos, f"the data section (bytes {len(MCAP_MAGIC)}-{pos}) fails "
                                 "its CRC check", located=False)
                    break
                self.in_summary = True
            if isinstance(record, Footer):
                closing = raw[end : end + len(MCAP_MAGIC)]
                if len(closing) == len(MCAP_MAGIC) and closing != MCAP_MAGIC:
                    self._damage(end, "the closing magic bytes are damaged")
                elif self._summary_intact(pos, record):
                    self.rec.complete = True
                break
            pos = end
        else:
            if not self.rec.complete:
                self._cut(pos, "the writer never closed it: no summary or footer")
        rec = self.rec
        if self.skipped:
            rec.lost = "; ".join([*self.skipped, *([rec.lost] if rec.lost else [])])
        rec.schemas = {
            ch.topic: rec.schema_records[ch.schema_id].data.decode("utf-8", "replace")
            for ch in rec.channel_records.values()
            if ch.schema_id in rec.schema_records
            and rec.schema_records[ch.schema_id].encoding == "jsonschema"
        }
        return rec

    def _take(self, pos: int, record: object) -> bool:
        """Add one record's content to the recording; False when it is damaged."""
        rec = self.rec
        if isinstance(record, Chunk):
            try:
                inner = _chunk_records(record)
            except Exception as e:  # noqa: BLE001 - zstd, CRC, struct, UTF-8: all damage
                number = rec.chunks + len(self.skipped) + 1
                what = (f"chunk {number} (messages from t = "
                        f"{record.message_start_time * 1e-9:.3f} s) is damaged: {_read_error(e)}")
                if not self.salvage:
                    self._damage(pos, what)
                    return False
                # Its record length is intact: the records after it are read on.
                self._skip(pos, what, record.message_start_time, record.message_end_time)
                return True
            rec.chunks += 1
            for r in inner:
                self._take(pos, r)
        elif isinstance(record, Header):
            rec.profile = record.profile
        elif isinstance(record, Metadata):
            rec.metadata[record.name] = dict(record.metadata)
        elif isinstance(record, Schema):
            rec.schema_records[record.id] = record
        elif isinstance(record, Channel):
            rec.channel_records[record.id] = record
        elif isinstance(record, Message):
            ch = rec.channel_records.get(record.channel_id)
            if ch is not None:
                rec.messages.append(
                    RecordedMessage(
                        ch.topic, record.log_time, record.sequence, record.data,
                        record.channel_id,
                        None if record.publish_time == record.log_time else record.publish_time,
                    )
                )
                self.last_t_ns = max(self.last_t_ns or 0, record.log_time)
        return True

    def _damaged(self, pos: int, what: str) -> int | None:
        """Damage at ``pos`` that leaves no record length to follow: raises unless salvaging;
        then the offset of the next intact chunk (its CRC checked), or None (a cut at ``pos``)."""
        if not self.salvage:
            self._damage(pos, what)
        nxt = self._next_intact_chunk(pos)
        if nxt is None:
            self._cut(pos, what, damaged=True)
            return None
        t1 = struct.unpack_from("<Q", self.raw, nxt + _RECORD_HEADER.size)[0]
        self._skip(pos, f"{what}; bytes {pos}-{nxt} skipped", self.last_t_ns, t1)
        return nxt

    def _next_intact_chunk(self, pos: int) -> int | None:
        """The offset after ``pos`` of the first chunk record that decodes and whose CRC holds."""
        raw, n, q = self.raw, len(self.raw), pos + 1
        while (q := raw.find(bytes([Opcode.CHUNK]), q)) >= 0 and n - q >= _RECORD_HEADER.size:
            _, length = _RECORD_HEADER.unpack_from(raw, q)
            body = q + _RECORD_HEADER.size
            if 40 <= length <= n - body:
                try:
                    chunk = Chunk.read(ReadDataStream(io.BytesIO(raw[body : body + length])))
                    if chunk.uncompressed_crc:  # without a CRC any bytes could pass
                        _chunk_records(chunk)
                        return q
                except Exception:  # noqa: BLE001, S112 - not a chunk: look further
                    pass
            q += 1
        return None

    def _skip(self, pos: int, what: str, t0_ns: int | None, t1_ns: int | None) -> None:
        span = "" if t1_ns is None else (
            f", messages from t = {(t0_ns or 0) * 1e-9:.3f} to {t1_ns * 1e-9:.3f} s lost")
        note = f"damaged at byte {pos} ({what}): skipped{span}"
        self.skipped.append(note)
        log.warning("%s %s; reading on", self.path, note)

    def _summary_intact(self, pos: int, footer: Footer) -> bool:
        if footer.summary_crc:
            start = footer.summary_start or pos
            stop = pos + _RECORD_HEADER.size + 16
            computed = zlib.crc32(self.raw[start:stop])
            if start > pos or computed != footer.summary_crc:
                self._damage(pos, f"the summary section (bytes {start}-{stop}) fails its CRC "
                             "check", located=False)
                return False
        return True

    def _nothing_read(self) -> bool:
        return not self.rec.messages and not self.rec.metadata and not self.rec.profile

    def _damage(self, pos: int, what: str, *, located: bool = True) -> None:
        """``located``: ``pos`` is where the damage is; else only where it was found (``what``
        says which bytes are concerned)."""
        at = f" at byte {pos} of {len(self.raw)}" if located else ""
        where = f"{self.path} is damaged{at}: {what}"
        if not self.salvage:
            raise CorruptRecordingError(f"{where} {RECOVER_HINT}")
        self._cut(pos, what, damaged=True)

    def _cut(
        self, pos: int, what: str, opcode: int | None = None, body_start: int = 0,
        damaged: bool = False,
    ) -> None:
        if self.closed and not damaged:  # a closed file is never cut short: it is damaged
            self._damage(pos, what)
            return
        if self._nothing_read():
            raise RecordingError(
                f"{self.path} is not a readable MCAP file: nothing readable after its magic "
                f"bytes ({'the file ends inside a record' if not damaged else what})"
            )
        rec = self.rec
        kept = (
            f"{len(rec.messages)} messages in {rec.chunks} complete chunk(s)"
            + ("" if self.last_t_ns is None else f", up to t = {self.last_t_ns * 1e-9:.3f} s")
        )
        lost = f"{len(self.raw) - pos} bytes from byte {pos} on"
        if opcode == Opcode.CHUNK and len(self.raw) - body_start >= 16:
            t0, t1 = struct.unpack_from("<QQ", self.raw, body_start)
            lost += f": a chunk of messages from t = {t0 * 1e-9:.3f} to {t1 * 1e-9:.3f} s"
        elif opcode == Opcode.MESSAGE_INDEX:
            lost += ": a message index (no message)"
        else:
            lost += ", with any message they held"
        if self.in_summary:
            rec.lost = (
                f"the summary section ends at byte {pos} ({what}): kept all {kept}; only the "
                "summary and index are lost"
            )
        elif damaged:
            rec.lost = f"damaged at byte {pos} ({what}): kept {kept}; lost {lost}"
        elif pos >= len(self.raw):
            rec.lost = (
                f"cut short at byte {pos} ({what}): kept {kept}; lost the summary and index, "
                "and whatever the writer had not written yet (at most one chunk)"
            )
        else:
            rec.lost = f"cut short at byte {pos} ({what}): kept {kept}; lost {lost}"
        log.warning("%s %s", self.path, rec.lost)


def _read_error(e: Exception) -> str:
    """What went wrong reading a record, never empty (the MCAP library's ``EndOfFile`` has no
    message)."""
    if isinstance(e, EndOfFile):
        return "the record ends before its fields do"
    return str(e) or type(e).__name__
