"""Recordings: what the bridge published and every raw bus frame, in one MCAP file.

File layout (docs/recording.md has the full description):

* profile ``koala-bridge``; a metadata record ``koala-bridge`` with ``format_version`` (this
  module's :data:`FORMAT_VERSION`), ``source`` (``sim`` | ``real``), ``seed``, ``config_path``,
  ``config`` (the TOML text), and a metadata record ``world`` with the world and robot parameters
  as JSON (the answer of the ``<prefix>/world`` queryable).
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
import io
import json
import logging
import os
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from koala_bridge.core.topics import JSON_SCHEMA_DIALECT
from koala_bridge.core.topics import json_schema as topic_json_schema
from mcap.exceptions import EndOfFile
from mcap.records import Channel, Footer, Header, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

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


def _topic_schema(topic: str) -> dict[str, Any]:
    """The schema of the MCAP topic (``/sensors/ir``) of a Zenoh key."""
    return topic_json_schema(topic[1:])


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
        )
        self._writer.start(profile=PROFILE, library=f"koala-bridge recording/{FORMAT_VERSION}")
        meta = {"format_version": str(FORMAT_VERSION), "created_unix_s": f"{time.time():.3f}"}
        meta.update({k: _as_text(v) for k, v in (metadata or {}).items()})
        self._writer.add_metadata(META_NAME, meta)
        if world is not None:
            self._writer.add_metadata(WORLD_META_NAME, {"json": json.dumps(world)})
        self._channels: dict[str, int] = {}
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

    def _channel(self, topic: str, schema: Callable[[str], dict[str, Any]]) -> int:
        """The id of ``topic``'s channel, registered (with its schema) on first use."""
        channel_id = self._channels.get(topic)
        if channel_id is None:
            s = schema(topic)
            schema_id = self._writer.register_schema(
                name=s["title"], encoding="jsonschema", data=json.dumps(s).encode()
            )
            channel_id = self._writer.register_channel(topic, "json", schema_id)
            self._channels[topic] = channel_id
            self._msg_seq[channel_id] = 0
        return channel_id

    def _write(
        self, topic: str, t: float, data: bytes, schema: Callable[[str], dict[str, Any]]
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
    source: str, config: Mapping[str, Any], config_path: str | os.PathLike[str] | None
) -> dict[str, str]:
    """The ``koala-bridge`` metadata of a run: source, seed, config path and the resolved
    configuration (file + command-line overrides) as JSON."""
    seed = (config.get("sim") or {}).get("seed")
    return {
        "source": source,
        "seed": "" if seed is None else str(seed),
        "config_path": "" if config_path is None else str(Path(config_path).resolve()),
        "config": json.dumps(config, default=str),
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
    ``messages`` then holds everything up to the last complete chunk.
    """

    path: Path
    profile: str
    metadata: dict[str, dict[str, str]]
    messages: list[RecordedMessage]
    complete: bool
    schemas: dict[str, str] = field(default_factory=dict)  # topic -> JSON schema text

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
        return sorted({m.topic for m in self.messages} | set(self.schemas))

    def topic(self, topic: str) -> list[RecordedMessage]:
        """Messages of one topic (``/sensors/gyro`` or ``sensors/gyro``) in file order."""
        name = topic_name(topic)
        return [m for m in self.messages if m.topic == name]

    def counts(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for m in self.messages:
            out[m.topic] = out.get(m.topic, 0) + 1
        return out


def open_recording(path: str | os.PathLike[str]) -> Recording:
    """Read a recording, complete or cut short, with the MCAP library's streaming reader.

    Raises :class:`RecordingError` if the file is not MCAP at all.
    """
    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as e:
        raise RecordingError(f"cannot read {p}: {e}") from e
    if not raw.startswith(MCAP_MAGIC):
        # Checked here: the reader's own complaint about a short or foreign file is a struct
        # error ("unpack requires a buffer of 8 bytes") that says nothing to a user.
        what = "it is empty" if not raw else "it does not begin with the MCAP magic bytes"
        raise RecordingError(f"{p} is not an MCAP file: {what}")
    reader = StreamReader(io.BytesIO(raw))
    profile = ""
    metadata: dict[str, dict[str, str]] = {}
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    messages: list[RecordedMessage] = []
    complete = False
    records = reader.records
    while True:
        try:
            record = next(records)
        except StopIteration:
            break
        except Exception as e:  # noqa: BLE001 - any decode error of the tail means "cut short"
            # The tail of a file cut short: a partial record (EndOfFile, a short struct, a zstd
            # frame cut in two). Everything before it is good.
            if not messages and not metadata and not profile:
                raise RecordingError(
                    f"{p} is not a readable MCAP file: nothing readable after its magic bytes "
                    f"({_read_error(e)})"
                ) from e
            log.info(
                "%s ends in a partial record (%s): read up to the last complete chunk",
                p,
                _read_error(e),
            )
            break
        if isinstance(record, Metadata):
            metadata[record.name] = dict(record.metadata)
        elif isinstance(record, Schema):
            schemas[record.id] = record
        elif isinstance(record, Channel):
            channels[record.id] = record
        elif isinstance(record, Message):
            ch = channels.get(record.channel_id)
            if ch is None:
                continue
            messages.append(
                RecordedMessage(ch.topic, record.log_time, record.sequence, record.data)
            )
        elif isinstance(record, Footer):
            complete = True
        elif isinstance(record, Header):
            profile = record.profile
    topic_schemas = {
        ch.topic: schemas[ch.schema_id].data.decode()
        for ch in channels.values()
        if ch.schema_id in schemas
    }
    return Recording(p, profile, metadata, messages, complete, topic_schemas)


def _read_error(e: Exception) -> str:
    """What went wrong reading a record, never empty (the MCAP library's ``EndOfFile`` has no
    message)."""
    if isinstance(e, EndOfFile):
        return "the file ends inside a record"
    return str(e) or type(e).__name__
