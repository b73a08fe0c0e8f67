"""Live view of a bridge over Zenoh: per-stream rates and last values, truth vs estimate, buses.

:class:`MonitorState` is a thread-safe tally fed with ``(key suffix, JSON payload)``; the
``render_*`` functions turn it into rich renderables; :class:`ZenohWatch` is a client session that
subscribes to ``<prefix>/**`` and feeds one. ``koala-bridge monitor`` (bridge/cli/monitor.py) puts
them together in a terminal dashboard; ``koala-bridge snapshot`` reuses the session part.

The monitor opens a Zenoh *client* session (multicast scouting off) connected to the endpoints
given: the bridge's own listen endpoint, or a router's (docs/multihost.md).
"""

from __future__ import annotations

import base64
import json
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh
from koala_bridge.core.errors import TransportError
from koala_bridge.core.geometry import wrap_angle
from koala_bridge.core.topics import (
    EstimateCell,
    EstimatePose,
    OccupancyMap,
    StatusMessage,
    TopicError,
    TruthPose,
    pose_of,
)
from koala_bridge.runtime.zenoh_io import zenoh_error_text
from rich.console import Group
from rich.panel import Panel
from rich.table import Table
from rich.text import Text

log = logging.getLogger(__name__)

DEFAULT_CONNECT = "tcp/127.0.0.1:7447"
DEFAULT_PREFIX = "koala/koala"
RATE_WINDOW_S = 2.0


# -- session -----------------------------------------------------------------------------------


def client_config(connect: Sequence[str], mode: str = "client") -> zenoh.Config:
    """A Zenoh config for a session that connects to ``connect``, multicast scouting off."""
    config = zenoh.Config()
    config.insert_json5("mode", json.dumps(mode))
    config.insert_json5("connect/endpoints", json.dumps(list(connect)))
    config.insert_json5("scouting/multicast/enabled", "false")
    return config


def target_from_endpoints_file(path: str | Path) -> tuple[list[str], str]:
    """``(zenoh endpoints, prefix)`` from a bridge's endpoints file (``run --endpoints-file``)."""
    p = Path(path)
    try:
        d = json.loads(p.read_text(encoding="utf-8"))
    except OSError as e:
        raise TransportError(f"cannot read the endpoints file {p}: {e.strerror or e}") from e
    except ValueError as e:
        raise TransportError(f"{p} is not an endpoints file (not JSON: {e})") from e
    z = d.get("zenoh") if isinstance(d, dict) else None
    if not isinstance(z, dict) or not z.get("endpoints") or not z.get("prefix"):
        raise TransportError(
            f"{p} is not a koala-bridge endpoints file (no zenoh endpoints/prefix)")
    return list(z["endpoints"]), str(z["prefix"])


class ZenohWatch:
    """A client session subscribed to ``<prefix>/**``; calls ``on_message(suffix, payload)``.

    ``suffix`` is the key below the prefix (``sensors/gyro``). The callback runs on Zenoh's
    thread and must be quick. Use as a context manager or call :meth:`close`.
    """

    def __init__(
        self,
        connect: Sequence[str],
        prefix: str,
        on_message: Callable[[str, bytes], None],
        mode: str = "client",
    ) -> None:
        self.prefix = prefix.strip("/")
        self._on_message = on_message
        try:
            self.session = zenoh.open(client_config(connect, mode))
        except zenoh.ZError as e:
            raise TransportError(
                f"cannot reach a Zenoh peer at {', '.join(connect)}: {zenoh_error_text(e)} "
                "(is the bridge running? --connect/--endpoints-file say where)"
            ) from e
        self._sub = self.session.declare_subscriber(f"{self.prefix}/**", self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        suffix = key[len(self.prefix) + 1 :] if key.startswith(self.prefix + "/") else key
        try:
            self._on_message(suffix, sample.payload.to_bytes())
        except Exception:  # a bad message must not kill Zenoh's callback thread
            log.exception("monitor: cannot handle a message on %s", key)

    def query_json(self, suffix: str, timeout_s: float = 3.0) -> Any | None:
        """The first JSON answer of the queryable ``<prefix>/<suffix>``, or None."""
        for reply in self.session.get(f"{self.prefix}/{suffix}", timeout=timeout_s):
            if reply.ok is not None:
                return json.loads(reply.ok.payload.to_bytes())
        return None

    def close(self) -> None:
        self._sub.undeclare()
        self.session.close()

    def __enter__(self) -> ZenohWatch:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# -- state -------------------------------------------------------------------------------------


@dataclass
class StreamStats:
    """What one key has shown: message count, arrival times (wall), sim times, last value."""

    count: int = 0
    wall: deque[float] = field(default_factory=lambda: deque(maxlen=4096))
    sim: deque[float] = field(default_factory=lambda: deque(maxlen=64))
    last: Any = None
    last_wall: float = 0.0
    bad: int = 0

    def wall_rate(self, now: float, window: float = RATE_WINDOW_S) -> float:
        """Messages per wall second over the last ``window`` seconds."""
        n = sum(1 for w in self.wall if now - w <= window)
        return n / window

    def sim_rate(self) -> float | None:
        """Messages per simulation second, from the spacing of the recent ``t`` values."""
        if len(self.sim) < 2:
            return None
        span = self.sim[-1] - self.sim[0]
        return (len(self.sim) - 1) / span if span > 0 else None


class MonitorState:
    """Thread-safe tally of everything seen under a prefix."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self._lock = threading.Lock()
        self._clock = clock
        self.started = clock()
        self.streams: dict[str, StreamStats] = {}

    def on_message(self, suffix: str, payload: bytes) -> None:
        now = self._clock()
        with self._lock:
            s = self.streams.setdefault(suffix, StreamStats())
            s.count += 1
            s.wall.append(now)
            s.last_wall = now
            try:
                value = json.loads(payload)
            except ValueError:
                s.bad += 1
                return
            s.last = value
            t = value.get("t") if isinstance(value, dict) else None
            if isinstance(t, int | float) and (not s.sim or t > s.sim[-1]):
                s.sim.append(float(t))

    def now(self) -> float:
        """The state's clock (monotonic seconds)."""
        return self._clock()

    def last(self, suffix: str) -> Any:
        with self._lock:
            s = self.streams.get(suffix)
            return None if s is None else s.last

    def snapshot(self) -> dict[str, StreamStats]:
        """A copy safe to read while messages keep arriving."""
        with self._lock:
            return {
                k: StreamStats(v.count, deque(v.wall), deque(v.sim), v.last, v.last_wall, v.bad)
                for k, v in self.streams.items()
            }

    def total(self) -> int:
        with self._lock:
            return sum(s.count for s in self.streams.values())


# -- rendering ---------------------------------------------------------------------------------


def _fmt(v: Any, width: int = 60) -> str:
    """Compact one-line JSON of a value, long arrays shortened."""

    def shorten(x: Any) -> Any:
        if isinstance(x, float):
            return round(x, 4)
        if isinstance(x, list):
            head = [shorten(e) for e in x[:6]]
            return head + ["…"] if len(x) > 6 else head
        if isinstance(x, dict):
            return {k: shorten(e) for k, e in x.items() if k not in ("t", "truth")}
        return x

    text = json.dumps(shorten(v), ensure_ascii=False, separators=(",", ":"))
    return text if len(text) <= width else text[: width - 1] + "…"


def render_streams(streams: Mapping[str, StreamStats], now: float) -> Table:
    table = Table(title="streams", expand=True)
    for col, justify in (
        ("key", "left"),
        ("msgs", "right"),
        ("Hz wall", "right"),
        ("Hz sim", "right"),
        ("t", "right"),
        ("age s", "right"),
        ("last value", "left"),
    ):
        table.add_column(col, justify=justify, no_wrap=col != "last value")  # type: ignore[arg-type]
    for key in sorted(streams):
        s = streams[key]
        sim_rate = s.sim_rate()
        table.add_row(
            key,
            str(s.count),
            f"{s.wall_rate(now):.1f}",
            "-" if sim_rate is None else f"{sim_rate:.1f}",
            "-" if not s.sim else f"{s.sim[-1]:.2f}",
            f"{now - s.last_wall:.1f}",
            _fmt(s.last),
        )
    return table


def _pose(v: Any) -> tuple[float, float, float] | None:
    """``(x, y, theta)`` of a ``truth/pose`` or ``estimate/pose`` payload (core.topics)."""
    p = pose_of(v)
    return None if p is None else (float(p.x), float(p.y), float(p.theta))


def render_poses(streams: Mapping[str, StreamStats]) -> Table:
    truth = _pose(streams[TruthPose.TOPIC].last) if TruthPose.TOPIC in streams else None
    est = _pose(streams[EstimatePose.TOPIC].last) if EstimatePose.TOPIC in streams else None
    table = Table(title="truth vs estimate", expand=True)
    for col in ("", "x m", "y m", "theta deg"):
        table.add_column(col, justify="right")
    for name, p in (("truth", truth), ("estimate", est)):
        if p is None:
            table.add_row(name, "-", "-", "-")
        else:
            table.add_row(name, f"{p[0]:.3f}", f"{p[1]:.3f}", f"{math.degrees(p[2]):.1f}")
    if truth and est:
        dist = math.hypot(est[0] - truth[0], est[1] - truth[1])
        dth = math.degrees(wrap_angle(est[2] - truth[2]))
        table.add_row("error", f"|d|={dist:.3f}", "", f"{dth:+.1f}")
    captions = []
    cell = streams.get(EstimateCell.TOPIC)
    if cell is not None and cell.last is not None:
        captions.append(f"estimate/cell: {_fmt(cell.last, 80)}")
    occupancy = streams.get(OccupancyMap.TOPIC)
    summary = _occupancy_summary(occupancy.last) if occupancy is not None else None
    if summary:
        captions.append(summary)
    if captions:
        table.caption = "\n".join(captions)
    return table


def _occupancy_summary(msg: Any) -> str | None:
    """``map/occupancy`` in one line: cells observed and occupied (int8 log-odds, 0 = unknown;
    docs/localisation.md "Zenoh payloads")."""
    try:
        q = base64.b64decode(OccupancyMap.from_json(msg).data)
    except (TopicError, ValueError):
        return None
    known = sum(1 for b in q if b)
    occupied = sum(1 for b in q if 0 < b < 128)  # int8 > 0 as unsigned bytes
    return f"map/occupancy: {known} of {len(q)} cells observed, {occupied} occupied"


def render_status(streams: Mapping[str, StreamStats]) -> Table:
    stream = streams.get(StatusMessage.TOPIC)
    try:
        status = None if stream is None else StatusMessage.from_json(stream.last)
    except TopicError:
        status = None
    title = "buses"
    if status is not None and status.real_time_factor is not None:
        title += f" — real-time factor {status.real_time_factor:.2f}"
    else:
        title += " — no status yet"
    if status is not None:
        title += f", sim t {status.t:.2f} s"
    table = Table(title=title, expand=True)
    for col in ("bus", "sent", "received", "rejected", "detail"):
        table.add_column(col, justify="left" if col in ("bus", "detail") else "right")
    buses = {} if status is None else status.buses
    for name in sorted(buses):
        c = buses[name]
        detail = {k: v for k, v in c.items() if k not in ("sent", "received", "rejected")}
        table.add_row(
            name,
            str(c.get("sent", "-")),
            str(c.get("received", "-")),
            Text(str(c.get("rejected", "-")), style="bold red" if c.get("rejected") else ""),
            _fmt(detail, 50) if detail else "",
        )
    return table


def render(state: MonitorState, header: str = "") -> Group:
    now = state.now()
    streams = state.snapshot()
    parts: list[Any] = []
    if header:
        parts.append(Panel(Text(header), expand=True))
    parts += [render_streams(streams, now), render_poses(streams), render_status(streams)]
    return Group(*parts)


def wait_for(predicate: Callable[[], bool], timeout_s: float, poll_s: float = 0.05) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(poll_s)
    return predicate()
