"""Replay a recording's raw bus frames on the buses, with their original timing.

What the robot sent (``dir = from_robot`` frames of ``/bus/...`` channels) goes back out on the
same transports ``run`` serves (``[buses]`` of the configuration): range frames on the
rangefinders pty, CAN frames on every CAN interface, MAVLink datagrams/bytes on the MAVLink link.
Frame ``i`` leaves at ``start + (t_i - t_0) / speed`` on the monotonic clock, computed from the
start (no drift); the loop sleeps until shortly before the deadline and spins the rest, so a frame
leaves within a fraction of a millisecond of its time (docs/recording.md has the measurement).

K-Team ASCII is request/response, so its replies are not replayed as a stream: a command from
the client is answered with the latest recorded reply to the same letter at the current replay
time (``h,...`` for ``H``; Koala 2.5 ``@,...`` for ``&``; ``B``, the version, with the first
recorded one even when asked earlier than in the recording), or with the dialect's error reply
``Not recorded`` if the recording has none (Koala 2.5 ``B``: a bare ``#``, shorter than the 7
bytes libkoala reads, so that it stays in step). Commands are parsed, replies ended and errors
lettered in the recording's dialect (metadata ``kteam_dialect``, :func:`recorded_dialect`):
``z,...`` and CR LF for the classic Koala, ``#,...`` and LF for the Koala 2.5. Auto mode of a
Koala 2.5 recording: ``A,bits`` is answered ``a`` and from then on the recorded lines of the
selected streams (``g``, ``e``, ``p``, ``o``, ``m``, ``n``, ``@``: the replies of
``drivers.koala25.AUTO_COMMANDS``) are pushed at their recorded times (within
``AUTO_PUSH_PERIOD_S``), until ``A,0``; they also answer their commands as above.

The recorded Zenoh messages (``truth/pose``, ``sensors/*``, ``status``, ``estimate/*``, ...) go
back out on a Zenoh session at their times too, byte for byte, under ``[zenoh] prefix``, and the
session answers ``<prefix>/world`` with the recording's world: ``monitor`` and ``snapshot`` work
during a replay as during a run.

:func:`plan_replay` refuses, with a message naming the reason, a recording it cannot replay:
another format version, no bus channel, no frame from the robot.
"""

from __future__ import annotations

import bisect
import json
import logging
import os
import sys
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import can
from koala_bridge.drivers.dialects import dialect
from koala_bridge.drivers.koala25 import AUTO_BITS, AUTO_COMMANDS
from koala_bridge.drivers.kteam import KOALA1, Dialect, LineSplitter
from koala_bridge.drivers.messages import KteamReply, Reject, TransportError
from koala_bridge.recording.mcap_file import (
    BUSES,
    FORMAT_VERSION,
    FROM_ROBOT,
    META_NAME,
    PROFILE,
    Recording,
    UnsupportedRecordingError,
)
from koala_bridge.runtime.buses import LockedByteLink, OpenBuses, open_buses
from koala_bridge.runtime.endpoints import Endpoints, endpoints_of
from koala_bridge.runtime.settings import BridgeSettings
from koala_bridge.runtime.zenoh_io import ZenohLink

log = logging.getLogger(__name__)

SPIN_S = 0.002  # sleep until this close to a deadline, then spin: sleep overshoots ~0.1-1 ms
SWITCH_INTERVAL_S = 0.0005  # GIL hand-over while replaying (CPython's default: 5 ms)
STREAM_BUSES = ("serial/rangefinders", "can", "mavlink")
ERROR_NOT_RECORDED = "Not recorded"
"""Text of the error reply to a well-formed command the recording holds no reply to."""
AUTO_PUSH_PERIOD_S = 0.01  # how often recorded Koala 2.5 auto-mode lines are pushed

ZENOH = "zenoh"  # the pseudo-bus of replayed Zenoh messages in plans and statistics


@dataclass(frozen=True)
class ReplayFrame:
    """One frame to put back on a bus at recorded time ``t`` (simulation seconds); for
    ``bus == "zenoh"``, a recorded JSON payload to publish on ``<prefix>/<key>``."""

    t: float
    bus: str
    data: bytes
    can_id: int | None = None
    extended: bool = False
    key: str | None = None


@dataclass
class ReplayPlan:
    """The frames of a recording, sorted by time, and the K-Team replies by letter."""

    frames: list[ReplayFrame]
    kteam_replies: dict[str, tuple[list[float], list[bytes]]]
    counts: dict[str, int]
    t0: float
    t_end: float
    dialect: Dialect = KOALA1
    """The K-Team frames' dialect (:func:`recorded_dialect`)."""


def recorded_dialect(rec: Recording) -> Dialect:
    """The dialect of ``rec``'s K-Team frames: its metadata ``kteam_dialect``; a recording
    without it (older versions) is read as a simulated run's ``[buses.kteam] dialect`` of its
    configuration, else ``koala1``. Raises :class:`UnsupportedRecordingError` for a name this
    version does not know."""
    meta = rec.metadata.get(META_NAME, {})
    name = meta.get("kteam_dialect")
    if not name and meta.get("source") == "sim":
        try:
            config = json.loads(meta.get("config") or "{}")
            name = ((config.get("buses") or {}).get("kteam") or {}).get("dialect")
        except (ValueError, AttributeError):
            name = None
    try:
        return dialect(name or KOALA1.name)
    except ValueError as e:
        raise UnsupportedRecordingError(f"{rec.path.name}: {e}") from e


def plan_replay(
    rec: Recording, buses: tuple[str, ...] | None = None, zenoh: bool = True
) -> ReplayPlan:
    """The frames to replay from ``rec``; raises :class:`UnsupportedRecordingError` with the
    reason if there is nothing this version can replay. ``buses`` limits the buses replayed;
    ``zenoh`` adds the recorded Zenoh messages (bus ``"zenoh"``, counted under that name)."""
    name = rec.path.name
    if rec.profile != PROFILE and rec.format_version is None:
        raise UnsupportedRecordingError(
            f"{name} is an MCAP file but not a koala-bridge recording (profile {rec.profile!r}, "
            "no 'koala-bridge' metadata): nothing to replay"
        )
    if rec.format_version != FORMAT_VERSION:
        raise UnsupportedRecordingError(
            f"{name} is recording format version {rec.format_version}; this koala-bridge "
            f"replays version {FORMAT_VERSION} only"
        )
    bus_topics = sorted(t for t in rec.topics if t.startswith("/bus/"))
    if not bus_topics:
        others = ", ".join(rec.topics) or "nothing"
        raise UnsupportedRecordingError(
            f"{name} has no bus channel (/bus/serial/kteam, /bus/serial/rangefinders, /bus/can, "
            f"/bus/mavlink), only {others}: there are no raw frames to put back on a bus"
        )
    wanted = set(buses or BUSES)
    kteam_dialect = recorded_dialect(rec)
    frames: list[ReplayFrame] = []
    replies: dict[str, tuple[list[float], list[bytes]]] = {}
    counts: dict[str, int] = {}
    unknown: set[str] = set()
    zenoh_frames: list[ReplayFrame] = []
    for m in rec.messages:
        if not m.topic.startswith("/bus/"):
            # the Foxglove standard-schema channels (protobuf) are views of these, not messages
            if zenoh and rec.message_encoding(m) == "json":
                zenoh_frames.append(ReplayFrame(m.t, ZENOH, m.data, key=m.topic.lstrip("/")))
            continue
        bus = m.topic[len("/bus/") :]
        if bus not in BUSES:
            unknown.add(bus)
            continue
        if bus not in wanted:
            continue
        msg = m.json()
        if msg.get("dir") != FROM_ROBOT:
            continue
        data = m.frame_bytes()
        if bus == "serial/kteam":
            for line in data.splitlines():
                if line:
                    times, lines = replies.setdefault(chr(line[0]), ([], []))
                    times.append(m.t)
                    lines.append(line + kteam_dialect.reply_terminator)
        else:
            cid = msg.get("can_id")
            frames.append(
                ReplayFrame(
                    m.t, bus, data, None if cid is None else int(cid), bool(msg.get("extended"))
                )
            )
        counts[bus] = counts.get(bus, 0) + 1
    if unknown:
        log.warning("%s: bus channels this version does not know are skipped: %s", name, unknown)
    if not counts:
        raise UnsupportedRecordingError(
            f"{name} holds no frame sent by the robot (dir = from_robot) on "
            f"{', '.join(sorted(wanted))}: nothing to replay"
        )
    if zenoh_frames:
        frames += zenoh_frames
        counts[ZENOH] = len(zenoh_frames)
    frames.sort(key=lambda f: f.t)  # stable: equal times keep file order
    for letter, (ts, ls) in list(replies.items()):
        order = sorted(range(len(ts)), key=ts.__getitem__)
        replies[letter] = ([ts[i] for i in order], [ls[i] for i in order])
    times = [f.t for f in frames] + [ts[0] for ts, _ in replies.values() if ts]
    t_end = max([f.t for f in frames] + [ts[-1] for ts, _ in replies.values() if ts])
    return ReplayPlan(frames, replies, counts, min(times), t_end, kteam_dialect)


@dataclass
class ReplayStats:
    """What a replay did: frames sent per bus, and how late each frame left (wall seconds)."""

    sent: dict[str, int] = field(default_factory=dict)
    failed: dict[str, int] = field(default_factory=dict)
    lateness: list[float] = field(default_factory=list)
    kteam_answered: int = 0
    stopped_early: bool = False

    def lateness_quantile(self, q: float) -> float:
        if not self.lateness:
            return 0.0
        xs = sorted(self.lateness)
        return xs[min(len(xs) - 1, int(q * len(xs)))]


class Replayer:
    """Puts a :class:`ReplayPlan` on open buses. ``run(stop)`` blocks until done or stopped."""

    def __init__(
        self,
        plan: ReplayPlan,
        buses: OpenBuses,
        speed: float = 1.0,
        linger_s: float = 0.5,
        monotonic: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
        zenoh: ZenohLink | None = None,
        on_sent_all: Callable[[ReplayStats], None] | None = None,
    ) -> None:
        """``on_sent_all`` is called once every frame has been sent, before the linger (the
        command line says so, for the client that waits for the end of the stream)."""
        if not speed > 0:
            raise ValueError(f"speed must be > 0, got {speed!r}")
        self.plan = plan
        self.buses = buses
        self.zenoh = zenoh
        self.speed = speed
        self.linger_s = linger_s
        self._monotonic = monotonic
        self._sleep = sleep
        self._on_sent_all = on_sent_all
        self._start: float | None = None
        self._auto_letters: list[str] = []      # Koala 2.5 auto mode: the streams pushed
        self._pushed_until = 0.0                # replay time of the last push
        self.stats = ReplayStats()
        missing = [b for b in plan.counts if not self._has_bus(b)]
        if missing:
            log.warning("recorded buses not enabled in the configuration, skipped: %s", missing)

    def _has_bus(self, bus: str) -> bool:
        return {
            "serial/kteam": self.buses.kteam is not None,
            "serial/rangefinders": self.buses.rangefinders is not None,
            "mavlink": self.buses.mavlink is not None,
            "can": bool(self.buses.can),
            ZENOH: self.zenoh is not None,
        }[bus]

    def replay_time(self) -> float:
        """The recording's time now (simulation seconds); ``t0`` before the start."""
        if self._start is None:
            return self.plan.t0
        return self.plan.t0 + max(0.0, self._monotonic() - self._start) * self.speed

    def run(self, stop: threading.Event) -> ReplayStats:
        kteam = None
        if self.buses.kteam is not None and self.plan.kteam_replies:
            kteam = threading.Thread(
                target=self._answer_kteam,
                args=(self.buses.kteam, stop),
                name="replay-kteam",
                daemon=True,
            )
        self._start = self._monotonic()
        if kteam is not None:
            kteam.start()
        try:
            for frame in self.plan.frames:
                due = self._start + (frame.t - self.plan.t0) / self.speed
                if not self._wait_until(due, stop):
                    self.stats.stopped_early = True
                    break
                self._send(frame)
                self.stats.lateness.append(self._monotonic() - due)
            else:
                # K-Team answers go on until the recording's last reply time.
                end = self._start + (self.plan.t_end - self.plan.t0) / self.speed
                if not self._wait_until(end, stop):
                    self.stats.stopped_early = True
                else:
                    if self._on_sent_all is not None:
                        self._on_sent_all(self.stats)
                    self._linger(stop)
        finally:
            if kteam is not None:
                stop.set()
                kteam.join(timeout=2.0)
        return self.stats

    def _linger(self, stop: threading.Event) -> None:
        """Keep the buses open ``linger_s`` after the last frame, pushing out what a pty still
        holds: closing a pty's master discards what its client has not read yet."""
        deadline = self._monotonic() + self.linger_s
        while self._monotonic() < deadline and not stop.is_set():
            for link in (self.buses.rangefinders, self.buses.mavlink):
                flush = getattr(link.transport, "flush", None) if link is not None else None
                if flush is not None:
                    try:
                        flush()
                    except TransportError:
                        pass
            stop.wait(0.01)

    def _wait_until(self, due: float, stop: threading.Event) -> bool:
        while True:
            if stop.is_set():
                return False
            remaining = due - self._monotonic()
            if remaining <= 0:
                return True
            if remaining > SPIN_S:
                # Wake up regularly to see ``stop``; finish the last SPIN_S by spinning.
                stop.wait(min(remaining - SPIN_S, 0.1))
            else:
                # Spin without holding the GIL: the transports' I/O threads (socketcand) must
                # run meanwhile, or they wait up to a GIL switch interval (5 ms).
                self._sleep(0)

    def _send(self, frame: ReplayFrame) -> None:
        try:
            if frame.bus == ZENOH:
                if self.zenoh is None:
                    return
                assert frame.key is not None
                self.zenoh.publish_json(frame.key, frame.data)
            elif frame.bus == "can":
                if not self.buses.can:
                    return
                msg = can.Message(
                    arbitration_id=frame.can_id or 0,
                    is_extended_id=frame.extended,
                    data=frame.data,
                    timestamp=frame.t,
                )
                for transport in self.buses.can.values():
                    transport.send(msg)
            else:
                link = (
                    self.buses.rangefinders
                    if frame.bus == "serial/rangefinders"
                    else self.buses.mavlink
                )
                if link is None:
                    return
                link.write(frame.data)
        except TransportError as e:
            n = self.stats.failed.get(frame.bus, 0)
            if n == 0:
                log.warning("replay on %s failed (further failures not logged): %s", frame.bus, e)
            self.stats.failed[frame.bus] = n + 1
            return
        self.stats.sent[frame.bus] = self.stats.sent.get(frame.bus, 0) + 1

    def _answer_kteam(self, link: LockedByteLink, stop: threading.Event) -> None:
        splitter = LineSplitter()
        while not stop.is_set():
            try:
                ready = link.wait(AUTO_PUSH_PERIOD_S if self._auto_letters else 0.1)
                data = link.read() if ready else b""
                for line in splitter.feed(data) if data else []:
                    link.write(self.kteam_reply(line))
                    self.stats.kteam_answered += 1
                for pushed in self._auto_lines():
                    link.write(pushed)
            except TransportError as e:
                if stop.is_set():
                    return
                log.warning("replay kteam: %s", e)
                stop.wait(0.1)

    def kteam_reply(self, line: bytes | Reject) -> bytes:
        """The recorded answer to one command line at the current replay time."""
        d = self.plan.dialect
        cmd = line if isinstance(line, Reject) else d.parse_command(line)
        if isinstance(cmd, Reject):
            return d.format_reply(d.error_reply(cmd))
        if d.name == "koala25" and cmd.letter == "A":
            # auto mode: the recorded lines of the selected streams are pushed from now on
            self._auto_letters = [d.reply_letter(command) for name, command
                                  in AUTO_COMMANDS.items() if cmd.args[0] & AUTO_BITS[name]]
            self._pushed_until = self.replay_time()
            return d.format_reply(d.reply("A"))
        times, lines = self.plan.kteam_replies.get(d.reply_letter(cmd.letter), ([], []))
        i = bisect.bisect_right(times, self.replay_time()) - 1
        if i < 0 and cmd.letter == "B" and lines:
            # the version does not change: asked earlier than in the recording (a client that
            # started faster), it is still the recorded one
            i = 0
        if i < 0:
            if d.name == "koala25" and cmd.letter == "B":
                # libkoala reads B's reply as one 7-byte read(): a longer error reply would leave
                # bytes that it reads as the next command's reply
                return d.format_reply(KteamReply(d.error_letter))
            return d.format_reply(KteamReply(d.error_letter, (ERROR_NOT_RECORDED,)))
        return lines[i]

    def _auto_lines(self) -> list[bytes]:
        """The recorded lines of the auto-mode streams whose times have come since the last call,
        in time order."""
        if not self._auto_letters:
            return []
        now = self.replay_time()
        due: list[tuple[float, bytes]] = []
        for letter in self._auto_letters:
            times, lines = self.plan.kteam_replies.get(letter, ([], []))
            lo = bisect.bisect_right(times, self._pushed_until)
            hi = bisect.bisect_right(times, now)
            due += zip(times[lo:hi], lines[lo:hi], strict=True)
        self._pushed_until = now
        return [line for _, line in sorted(due, key=lambda x: x[0])]


class ReplaySource:
    """A recording put back on the buses: a :class:`runtime.source.Source`, so ``replay`` runs
    in the same session as ``run`` (:func:`runtime.session.run_session`).

    Args:
        rec: the recording (its ``world`` answers the ``world`` queryable).
        plan: what to replay (:func:`plan_replay`).
        settings: the bridge sections whose ``[buses]`` and ``[zenoh]`` are served.
        speed: replay this many times faster than recorded.
        linger_s: keep the buses open this long after the last frame.
        zenoh: open a Zenoh session and publish the recorded messages.
        wait_clients_s: before starting, wait up to this long for a client on each
            connection-oriented bus to be replayed (0: do not wait).
        fifo_priority: run under SCHED_FIFO at this priority (0: normal scheduling).
        say: where a line for people goes (the session's stdout); by default the log.
    """

    def __init__(
        self,
        rec: Recording,
        plan: ReplayPlan,
        settings: BridgeSettings,
        *,
        speed: float = 1.0,
        linger_s: float = 0.5,
        zenoh: bool = True,
        wait_clients_s: float = 0.0,
        fifo_priority: int = 0,
        say: Callable[[str], None] = log.info,
    ) -> None:
        if not speed > 0:
            raise ValueError(f"speed must be > 0, got {speed!r}")
        self.rec = rec
        self.plan = plan
        self.settings = settings
        self.speed = speed
        self.linger_s = max(0.0, linger_s)
        self.wait_clients_s = wait_clients_s
        self.fifo_priority = fifo_priority
        self._use_zenoh = zenoh
        self._say = say
        self._world = rec.world or {}
        self.buses: OpenBuses | None = None
        self.zenoh: ZenohLink | None = None
        self.stats: ReplayStats | None = None

    def world_answer(self) -> Mapping[str, Any]:
        return self._world

    def open(self) -> Endpoints:
        # Before the buses open: the transports' I/O threads inherit the scheduling policy.
        if self.fifo_priority:
            set_fifo_priority(self.fifo_priority)
        try:
            self.buses = open_buses(self.settings.buses)
            if self._use_zenoh:
                self.zenoh = ZenohLink(self.settings.zenoh, self.world_answer)
        except BaseException:
            self.close()
            raise
        return endpoints_of(self.buses, self.settings, zenoh=self.zenoh is not None,
                            zenoh_listening=self.zenoh.listening if self.zenoh else None)

    def describe(self) -> str:
        counts = ", ".join(f"{b} {n}" for b, n in sorted(self.plan.counts.items()))
        span = self.plan.t_end - self.plan.t0
        return (
            f"Replaying {self.rec.path.name}: {counts} frames over {span:.3f} s at speed "
            f"{self.speed:g}."
        )

    def run(self, stop: threading.Event) -> ReplayStats:
        if self.buses is None:
            raise RuntimeError("open() before run()")
        if self.wait_clients_s > 0:
            wait_clients(self.buses, self.plan.counts, self.wait_clients_s, stop)
        # The replay thread and the transports' I/O threads hand the GIL over every 0.5 ms
        # instead of 5 ms: a frame queued for socketcand leaves within a millisecond.
        sys.setswitchinterval(SWITCH_INTERVAL_S)
        linger_s = self.linger_s

        def on_sent_all(stats: ReplayStats) -> None:
            self._say(f"Every frame sent; the buses stay open {linger_s:g} s more (Ctrl-C ends).")

        replayer = Replayer(
            self.plan, self.buses, speed=self.speed, linger_s=linger_s, zenoh=self.zenoh,
            on_sent_all=on_sent_all,
        )
        self.stats = replayer.run(stop)
        return self.stats

    def summary(self) -> str:
        stats = self.stats or ReplayStats(stopped_early=True)
        sent = ", ".join(f"{b} {n}" for b, n in sorted(stats.sent.items()))
        p99 = stats.lateness_quantile(0.99) * 1e3
        return (
            f"Replay {'stopped' if stats.stopped_early else 'done'}: sent {sent}; "
            f"K-Team answers {stats.kteam_answered}; lateness p99 {p99:.3f} ms."
        )

    def close(self) -> None:
        if self.zenoh is not None:
            self.zenoh.close()
            self.zenoh = None
        if self.buses is not None:
            self.buses.close()
            self.buses = None


def wait_clients(
    buses: OpenBuses, counts: Mapping[str, int], timeout: float, stop: threading.Event
) -> None:
    """Wait until every connection-oriented bus to be replayed has a client (or timeout)."""
    links: list[tuple[str, Any]] = []
    if "serial/rangefinders" in counts and buses.rangefinders is not None:
        links.append(("rangefinders", buses.rangefinders))
    if "serial/kteam" in counts and buses.kteam is not None:
        links.append(("kteam", buses.kteam))
    if "mavlink" in counts and buses.mavlink is not None and not buses.mavlink.is_datagram:
        links.append(("mavlink", buses.mavlink))
    if "can" in counts:
        links += [(n, t) for n, t in buses.can.items() if n in ("can.socketcand", "can.slcan")]
    deadline = time.monotonic() + timeout
    waiting = [n for n, link in links if link.stats.clients == 0]
    while waiting and time.monotonic() < deadline and not stop.is_set():
        stop.wait(0.02)
        waiting = [n for n, link in links if link.stats.clients == 0]
    if waiting:
        log.warning("no client on %s after %.1f s: starting anyway", ", ".join(waiting), timeout)


def set_fifo_priority(priority: int) -> None:
    """SCHED_FIFO for this thread and the threads it starts later (the transports' I/O threads)."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (OSError, ValueError) as e:
        log.warning(
            "cannot run under SCHED_FIFO %d (%s): replaying at normal priority", priority, e
        )
