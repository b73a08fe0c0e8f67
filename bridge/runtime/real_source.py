"""The real robot as the source: its ports, read with the same codecs, published and recorded as
in simulation (``koala-bridge run --source real``).

Nothing comes from the simulator: every reading is decoded from the robot's own ports, named in
the ``[real]`` section of the configuration (docs/recording.md, "Real drivers")::

    [real]
    kteam = "/dev/ttyUSB0"              # serial device or pyserial URL (socket://, rfc2217://, loop://)
    kteam_dialect = "koala25"           # koala1 (classic Koala) | koala25 (Koala 2.5)
    kteam_baud = 0                      # 0: the dialect's (koala1 38400 8N2, koala25 115200 8N1)
    kteam_poll = ["P", "G", "N", "&"]   # commands asked at kteam_poll_hz (runtime.real_kteam
    kteam_poll_hz = 10.0                #   POLLABLE: koala25 P -> sensors/odometry, G -> sonar,
                                        #   N -> gyro, & -> compass; koala1 N -> ir, H ->
                                        #   odometry), unless a streaming bus below serves that
                                        #   key (then the poll is only recorded)
    kteam_auto = 0                      # koala25: A,<bits> auto mode (the robot pushes lines)
    rangefinders = "/dev/ttyUSB1"       # range frames: kind 1 -> sensors/ir, 2 -> sensors/sonar
    rangefinders_baud = 115200
    can_interface = "socketcand"        # python-can interface; WheelOdometry -> sensors/odometry,
    can_channel = "koala0"              #   Gyro -> sensors/gyro (config/koala.dbc)
    can_options = { host = "192.168.1.20", port = 29536 }   # extra can.Bus keyword arguments
    mavlink = "udpin:0.0.0.0:14550"     # MAVLink connection string; SCALED_IMU -> sensors/compass

Every key is optional: a port not named is not opened. The K-Team port speaks
``kteam_dialect``: commands are formatted and replies parsed by its
:class:`~koala_bridge.drivers.kteam.Dialect`, and :mod:`runtime.real_kteam` turns the replies
into topic messages in SI. With ``kteam_auto`` (Koala 2.5 only) the source sends ``A,<bits>``
after opening the port, reads every line the robot pushes as it comes (polls, if any, are then
sent without waiting: their replies are read by the same reader) and sends ``A,0`` on close.

``t`` of every message is the host's monotonic time since the start, in seconds (a real robot
has no simulation time; its own sample stamps stay in the raw frames of the recording). The rest
of the configuration (robot, world, zenoh) is read as for a simulated run: the world and robot
description answer the ``world`` queryable, so monitor and snapshot work unchanged.
No ``truth/pose`` is published.

With ``[localisation] enabled``, every frame read from the robot also goes to the estimator node
(:class:`runtime.localisation.LocalisationNode`), which decodes it as it decodes the simulated
buses and publishes ``estimate/*`` and ``map/occupancy`` (no camera: it has no bus).

:class:`RealRobotSource` is a :class:`runtime.source.Source`, as the simulated robot is: ``open()
-> Endpoints``, ``run(stop, duration_s)``, ``close()``, the ``tap`` recorder,
``clock.real_time_factor``. Its ports open through the transport registry
(:mod:`koala_bridge.drivers.transports`): ``kteam`` and ``rangefinders`` as ``serial:PORT``,
CAN as ``python-can://INTERFACE/CHANNEL``, MAVLink as ``udpin://``, ``tcp-client://`` or
``serial:`` (:func:`~koala_bridge.drivers.transports.mavlink_connection_url`).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Annotated, Any

import can
from koala_bridge.core.errors import TransportError
from koala_bridge.core.schema import (
    ConfigError,
    NonNegativeInt,
    Positive,
    PositiveInt,
    Str,
    one_of,
    section,
    tuples,
    validate,
)
from koala_bridge.core.topics import (
    CompassMessage,
    GyroMessage,
    OdometryMessage,
    SonarMessage,
    StatusMessage,
    TopicMessage,
)
from koala_bridge.drivers.dialects import dialect
from koala_bridge.drivers.koala25 import AUTO_BITS
from koala_bridge.drivers.kteam import Dialect
from koala_bridge.drivers.mavlink_codec import CompassDecoder
from koala_bridge.drivers.messages import (
    CompassSample,
    GyroFrame,
    KteamCommand,
    KteamReply,
    RangeKind,
    WheelOdometryFrame,
)
from koala_bridge.drivers.rangeframes import NO_ECHO, RangeFrameDecoder, encode_range_frame
from koala_bridge.drivers.transports import (
    ByteTransport,
    CanTransport,
    mavlink_connection_options,
    mavlink_connection_url,
    open_byte_transport,
    open_can_transport,
)
from koala_bridge.drivers.transports.pythoncan import python_can_url
from koala_bridge.drivers.transports.serialport import serial_url
from koala_bridge.runtime.counters import BusCounters
from koala_bridge.runtime.endpoints import Endpoints
from koala_bridge.runtime.localisation import LocalisationNode
from koala_bridge.runtime.real_kteam import POLLABLE, KteamReplyDecoder, ir_message
from koala_bridge.runtime.settings import KTEAM_DIALECTS, BridgeSettings
from koala_bridge.runtime.source import READ_TIMEOUT_S, Tap, start_reader, until_text
from koala_bridge.runtime.zenoh_io import ZENOH_BUS, ZenohLink
from koala_bridge.sim.config import load_sim_config
from pydantic import AfterValidator, BeforeValidator, Strict

log = logging.getLogger(__name__)

KTEAM_REPLY_TIMEOUT_S = 0.5
KTEAM_BAD_WARN = 5      # replies in a row not understood before a WARNING names the likely cause
KTEAM_MAX_LINE = 1024   # bytes without a terminator before an auto-mode reader drops them
AUTO_ALL = sum(AUTO_BITS.values())


def _auto_bits(value: int) -> int:
    if value > AUTO_ALL:
        raise ValueError(f"must be a bit mask of libkoala's KOALA_AUTOM_* (0..{AUTO_ALL}), "
                         f"got {value}")
    return value


def _port_name(value: Any) -> Any:
    """A port key: "" (the file's way to say "not opened") is None."""
    return None if value == "" else value


#: A port: a device, pyserial URL or connection string; "" or absent = not opened.
_Port = Annotated[Str | None, BeforeValidator(_port_name)]


@section
class RealPorts:
    """``[real]``: where the robot's ports are.

    Every key may be left out; its default is the value ``config/default.toml`` shows (ports
    "" = not opened; the schema's policy, :mod:`koala_bridge.core.schema`).
    """

    kteam: _Port = None
    kteam_dialect: Annotated[Str, one_of(KTEAM_DIALECTS)] = "koala1"
    kteam_baud: NonNegativeInt = 0          # 0: the dialect's line settings
    kteam_poll: Annotated[tuple[Str, ...], BeforeValidator(tuples)] = ()
    kteam_poll_hz: Positive = 10.0
    kteam_auto: Annotated[NonNegativeInt, AfterValidator(_auto_bits)] = 0
    rangefinders: _Port = None
    rangefinders_baud: PositiveInt = 115200
    can_interface: _Port = None
    can_channel: _Port = None
    can_options: Annotated[dict[str, Any], Strict(False)] = field(default_factory=dict)
    mavlink: _Port = None

    def __post_init__(self) -> None:
        s = "real"
        if bool(self.can_interface) != bool(self.can_channel):
            raise ConfigError(f"[{s}] 'can_interface' and 'can_channel' go together")
        if self.kteam_poll and not self.kteam:
            raise ConfigError(f"[{s}] 'kteam_poll' needs 'kteam' (the K-Team serial port)")
        pollable = POLLABLE[self.kteam_dialect]
        for c in self.kteam_poll:
            if c not in pollable:
                raise ConfigError(
                    f"[{s}] 'kteam_poll' has {c!r}, not a command of kteam_dialect = "
                    f"{self.kteam_dialect!r} it can poll (one of {', '.join(pollable)})"
                )
        if self.kteam_auto and self.kteam_dialect != "koala25":
            raise ConfigError(
                f"[{s}] 'kteam_auto' is the Koala 2.5's auto mode: it needs "
                f"kteam_dialect = \"koala25\" (not {self.kteam_dialect!r})"
            )
        if self.kteam_auto and not self.kteam:
            raise ConfigError(f"[{s}] 'kteam_auto' needs 'kteam' (the K-Team serial port)")

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> RealPorts:
        return validate(cls, d, "real")

    @property
    def dialect(self) -> Dialect:
        """The K-Team port's dialect (``kteam_dialect``)."""
        return dialect(self.kteam_dialect)

    def kteam_line(self) -> dict[str, Any]:
        """pyserial options of the K-Team port: the dialect's line settings, with
        ``kteam_baud`` as the bit rate unless it is 0."""
        line = self.dialect.line.pyserial()
        if self.kteam_baud:
            line["baudrate"] = self.kteam_baud
        return line

    @property
    def any_port(self) -> bool:
        """Whether any port is named."""
        return any((self.kteam, self.rangefinders, self.can_interface, self.mavlink))

    @classmethod
    def from_config(cls, config: Mapping[str, Any]) -> RealPorts:
        real = config.get("real")
        ports = cls.from_dict(real) if isinstance(real, Mapping) else None
        if ports is None or not ports.any_port:
            raise ConfigError(
                "--source real needs a [real] section naming the robot's ports "
                "(kteam, rangefinders, can_interface/can_channel, mavlink; docs/recording.md)"
            )
        return ports


class _RealClock:
    """Host time since the start; a real robot runs in real time (factor 1 by definition)."""

    def __init__(self) -> None:
        self._t0 = time.monotonic()

    def start(self) -> None:
        self._t0 = time.monotonic()

    def now(self) -> float:
        return time.monotonic() - self._t0

    def real_time_factor(self, sim_t: float) -> float:
        return 1.0


@dataclass
class _LastReadings:
    t: float = 0.0


class RealRobotSource:
    """Reads the real robot's ports, publishes on Zenoh, records through ``tap``.

    Args:
        config: the whole configuration (with ``[real]``).
        settings: its bridge sections (Zenoh settings, status rate).
        world_answer: the ``world`` queryable's answer (world + robot description).
        tap: optional recorder.
    """

    def __init__(
        self,
        config: Mapping[str, Any],
        settings: BridgeSettings,
        world_answer: Callable[[], Mapping[str, Any]],
        tap: Tap | None = None,
    ) -> None:
        self.ports = RealPorts.from_config(config)
        self.settings = settings
        self.tap = tap
        self.clock = _RealClock()
        self.counters = BusCounters()
        self._world_answer = world_answer
        self.zenoh: ZenohLink | None = None
        self._kteam: ByteTransport | None = None
        self._kteam_lock = threading.Lock()
        self._kteam_bad_run = 0             # K-Team replies in a row not understood
        self._kteam_warned = False
        self._ranges: ByteTransport | None = None
        self._can: CanTransport | None = None
        self._mavlink: ByteTransport | None = None
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        # [buses.can] dbc: the robot's CAN database (needed only with a [real] CAN port)
        self._can_codec = settings.buses.can.codec(needed=bool(self.ports.can_interface))
        self.last = _LastReadings()
        p = self.ports
        self.dialect = p.dialect
        self.kteam_dialect = p.kteam_dialect    # recorded in the metadata (cli/run.py)
        self._kteam_decoder = KteamReplyDecoder(self.dialect)
        # Keys a streaming bus serves: a K-Team reply for them is only recorded.
        self._streamed = (
            ({"sensors/ir", "sensors/sonar"} if p.rangefinders else set())
            | ({"sensors/odometry", "sensors/gyro"} if p.can_interface else set())
            | ({"sensors/compass"} if p.mavlink else set())
        )
        # The estimator node, fed with every frame read from the robot (_frame); None when off.
        self.localisation = LocalisationNode.from_config(
            config, load_sim_config(config), self._publish, can_codec=self._can_codec,
            kteam_dialect=p.kteam_dialect,
        )

    # -- life cycle --------------------------------------------------------------------------

    def world_answer(self) -> Mapping[str, Any]:
        return self._world_answer()

    def open(self) -> Endpoints:
        """Open the robot's ports and the Zenoh session, start the readers."""
        p = self.ports
        try:
            # Every port through the transport registry, as the simulated buses are.
            if p.kteam:
                self._kteam = _open_port("kteam port", p.kteam, serial_url(p.kteam), p.kteam_line)
            if p.rangefinders:
                self._ranges = _open_port(
                    "rangefinders port", p.rangefinders, serial_url(p.rangefinders),
                    lambda: {"baudrate": p.rangefinders_baud},
                )
            if p.can_interface and p.can_channel:
                url = python_can_url(p.can_interface, p.can_channel)
                try:
                    self._can = open_can_transport(url, **dict(p.can_options))
                except (OSError, ValueError) as e:
                    raise TransportError(
                        f"cannot open CAN {p.can_interface}/{p.can_channel}: {e}") from e
            if p.mavlink:
                self._mavlink = _open_port(
                    "MAVLink", p.mavlink, mavlink_connection_url(p.mavlink),
                    lambda: mavlink_connection_options(p.mavlink or ""),
                )
            self.zenoh = ZenohLink(self.settings.zenoh, self._world_answer, self.counters)
        except BaseException:
            self.close()
            raise
        if self.tap is not None:
            # Every port opened gets its channel in the recording, frames or not; the Zenoh
            # keys are what the robot sends, so they appear with their first message.
            opened = (
                ("serial/kteam", self._kteam),
                ("serial/rangefinders", self._ranges),
                ("can", self._can),
                ("mavlink", self._mavlink),
            )
            self.tap.declare(["status"], [bus for bus, port in opened if port is not None])
        self.clock.start()
        if self._kteam is not None:
            # The firmware version, once, as libkoala's and KoreBot's start-up do: the recording
            # holds the robot's B reply (a replay answers B with it), and a port that does not
            # answer it in the configured dialect is said at once.
            self._poll_kteam("B")
        if self._kteam is not None and p.kteam_auto:
            # Auto mode: one reader takes every line, pushed or replied (libkoala's
            # koala_get_from_auto_mode does not tell them apart either).
            self._send_kteam(KteamCommand("A", (p.kteam_auto,)))
            self._spawn("kteam", self._kteam_reader(self._kteam))
        if self._ranges is not None:
            self._spawn("rangefinders", self._range_reader(self._ranges))
        if self._can is not None:
            self._spawn("can", self._can_reader(self._can))
        if self._mavlink is not None:
            self._spawn("mavlink", self._mavlink_reader(self._mavlink))
        return Endpoints(
            zenoh_endpoints=self.zenoh.listening if self.zenoh else self.settings.zenoh.listen,
            zenoh_prefix=self.settings.zenoh.prefix,
        )

    def run(self, stop: threading.Event, duration_s: float | None = None) -> _LastReadings:
        """Poll K-Team and publish ``status`` until ``stop`` or ``duration_s`` host seconds."""
        if self.zenoh is None:
            raise RuntimeError("open() before run()")
        duration = self.settings.run.duration_s if duration_s is None else duration_s
        status_period = 1.0 / self.settings.zenoh.status_rate_hz
        poll_period = 1.0 / self.ports.kteam_poll_hz if self.ports.kteam_poll else None
        next_status = status_period
        next_poll = 0.0
        while not stop.is_set():
            now = self.clock.now()
            if duration and now >= duration:
                break
            if poll_period is not None and now >= next_poll:
                for letter in self.ports.kteam_poll:
                    if self.ports.kteam_auto:
                        self._send_kteam(KteamCommand(letter))   # the reader takes the reply
                    else:
                        self._poll_kteam(letter)
                next_poll += poll_period
            if now >= next_status:
                self._publish_status()
                next_status += status_period
            wake = min(next_status, next_poll if poll_period is not None else next_status)
            stop.wait(max(0.0, min(wake - self.clock.now(), READ_TIMEOUT_S)))
        self.last.t = self.clock.now()
        self._publish_status()
        return self.last

    def describe(self) -> str:
        return f"Reading the real robot's ports {until_text(self.settings.run.duration_s)}."

    def summary(self) -> str:
        rtf = self.clock.real_time_factor(self.last.t)
        return f"Stopped at t = {self.last.t:.3f} s (real-time factor {rtf:.2f})."

    def close(self) -> None:
        if self._kteam is not None and self.ports.kteam_auto:
            self._send_kteam(KteamCommand("A", (0,)))        # the robot stops pushing
        self._stop.set()
        for t in self._threads:
            t.join(timeout=5.0)
        self._threads.clear()
        for port in (self._kteam, self._ranges, self._can, self._mavlink):
            if port is not None:
                port.close()
        self._kteam = self._ranges = self._mavlink = None
        self._can = None
        if self.zenoh is not None:
            self.zenoh.close()
            self.zenoh = None

    def __enter__(self) -> RealRobotSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- helpers -----------------------------------------------------------------------------

    def _spawn(self, name: str, step: Callable[[], None]) -> None:
        thread = start_reader(
            name, step, self._stop, thread_prefix="real",
            transient=(OSError, can.CanError), logger=log,
        )
        self._threads.append(thread)

    def _publish(self, suffix: str, message: dict[str, Any]) -> None:
        if self.zenoh is not None:
            self.zenoh.publish(suffix, message)
        if self.tap is not None:
            self.tap.record(suffix, message["t"], message)

    def _publish_topic(self, message: TopicMessage) -> None:
        """Publish (and record) one message of the robot's readings, on its own key."""
        self._publish(message.TOPIC, message.to_json())

    def _frame(self, bus: str, direction: str, t: float, data: bytes, **fields: object) -> None:
        if self.tap is not None:
            self.tap.record_frame(bus, direction, t, data, **fields)
        if self.localisation is not None:
            self.localisation.on_frame(bus, direction, t, data, **fields)

    def _publish_status(self) -> None:
        counts = self.counters.snapshot()
        buses = {name: {**c, "dropped": 0} for name, c in counts.items() if name != ZENOH_BUS}
        self._publish_topic(StatusMessage(
            self.clock.now(),
            1.0,
            buses,
            source="real",
            localisation=None if self.localisation is None else self.localisation.snapshot(),
        ))

    # -- readers -----------------------------------------------------------------------------

    def _range_reader(self, port: ByteTransport) -> Callable[[], None]:
        decoder = RangeFrameDecoder()

        def step() -> None:
            data = port.read() if port.wait(READ_TIMEOUT_S) else b""
            if not data:
                return
            before = decoder.rejected
            frames = decoder.feed(data)
            t = self.clock.now()
            self.counters.rejected("rangefinders", decoder.rejected - before)
            for f in frames:
                self.counters.received("rangefinders")
                self._frame("serial/rangefinders", "from_robot", t, encode_range_frame(f))
                if f.kind == RangeKind.IR:
                    self._publish_topic(ir_message(t, f.readings))
                else:
                    ranges = tuple(None if r == NO_ECHO else r / 1000.0 for r in f.readings)
                    self._publish_topic(SonarMessage(t, ranges))

        return step

    def _can_reader(self, bus: CanTransport) -> Callable[[], None]:
        codec = self._can_codec

        def step() -> None:
            msg = bus.recv(timeout=READ_TIMEOUT_S)
            if msg is None:
                return
            t = self.clock.now()
            self._frame(
                "can",
                "from_robot",
                t,
                bytes(msg.data),
                can_id=msg.arbitration_id,
                extended=msg.is_extended_id,
            )
            frame = codec.decode(msg)
            if isinstance(frame, WheelOdometryFrame):
                self.counters.received("can")
                self._publish_topic(OdometryMessage(t, frame.left_ticks, frame.right_ticks))
            elif isinstance(frame, GyroFrame):
                self.counters.received("can")
                self._publish_topic(GyroMessage(t, frame.yaw_rate))
            else:  # a Reject, or a frame the robot does not send (MotorCommand)
                self.counters.rejected("can")

        return step

    def _mavlink_reader(self, link: ByteTransport) -> Callable[[], None]:
        decoder = CompassDecoder()

        def step() -> None:
            data = link.read() if link.wait(READ_TIMEOUT_S) else b""
            if not data:
                return
            t = self.clock.now()
            self._frame("mavlink", "from_robot", t, data)
            before = decoder.rejected
            out = decoder.feed_datagram(data) if link.is_datagram else decoder.feed(data)
            self.counters.rejected("mavlink", decoder.rejected - before)
            for m in out:
                self.counters.received("mavlink")
                if isinstance(m, CompassSample):
                    self._publish_topic(CompassMessage(t, m.x_ut, m.y_ut, m.z_ut))

        return step

    def _send_kteam(self, command: KteamCommand) -> None:
        """Write one command to the K-Team port and record it; the reply is not awaited."""
        port = self._kteam
        if port is None:
            return
        data = self.dialect.format_command(command)
        with self._kteam_lock:
            try:
                port.write(data)
            except OSError as e:
                log.warning("kteam: %s", e)
                return
            self._frame("serial/kteam", "to_robot", self.clock.now(), data)
            self.counters.sent("kteam")

    def _poll_kteam(self, letter: str) -> None:
        """Ask ``letter`` and wait (at most :data:`KTEAM_REPLY_TIMEOUT_S`) for its reply line."""
        port = self._kteam
        if port is None:
            return
        command = self.dialect.format_command(KteamCommand(letter))
        end = self.dialect.reply_terminator[-1:]
        t = self.clock.now()
        with self._kteam_lock:
            try:
                _discard_input(port)
                port.write(command)
                self._frame("serial/kteam", "to_robot", t, command)
                self.counters.sent("kteam")
                line = _read_line(port, KTEAM_REPLY_TIMEOUT_S, end)
            except OSError as e:
                log.warning("kteam: %s", e)
                return
        if not line.endswith(end):
            self._kteam_bad(f"no reply to {letter} within {KTEAM_REPLY_TIMEOUT_S} s")
            return
        self._on_kteam_line(self.clock.now(), line, expected=letter)

    def _kteam_bad(self, what: str) -> None:
        """A K-Team reply missing or not understood: counted; the first run of
        :data:`KTEAM_BAD_WARN` in a row (nothing understood in between) is said once, with the
        likeliest cause."""
        self.counters.rejected("kteam")
        log.debug("kteam: %s", what)
        self._kteam_bad_run += 1
        if self._kteam_bad_run == KTEAM_BAD_WARN and not self._kteam_warned:
            self._kteam_warned = True
            d = self.dialect
            log.warning(
                "kteam: %d replies in a row not understood in the %s dialect (last: %s): is "
                "[real] kteam_dialect right for this robot (koala1: classic Koala, 38400 8N2, "
                "replies end CR LF; koala25: Koala 2.5, 115200 8N1, replies end LF), and the "
                "port's speed (now %s)?", KTEAM_BAD_WARN, d.name, what,
                self.ports.kteam_baud or d.line)

    def _kteam_reader(self, port: ByteTransport) -> Callable[[], None]:
        """Auto mode: every line the robot sends, as it comes (recorded with its terminator)."""
        end = self.dialect.reply_terminator[-1:]
        buf = bytearray()

        def step() -> None:
            data = port.read() if port.wait(READ_TIMEOUT_S) else b""
            if not data:
                return
            buf.extend(data)
            t = self.clock.now()
            while (i := buf.find(end)) >= 0:
                line = bytes(buf[: i + 1])
                del buf[: i + 1]
                if line.strip():
                    self._on_kteam_line(t, line)
            if len(buf) > KTEAM_MAX_LINE:
                self.counters.rejected("kteam")
                buf.clear()

        return step

    def _on_kteam_line(self, t: float, line: bytes, expected: str | None = None) -> None:
        """One line from the robot (terminator included): recorded, parsed in the dialect,
        published unless a streaming bus serves its key. ``expected``: the command polled (a
        reply to another one is counted as rejected)."""
        self._frame("serial/kteam", "from_robot", t, line)
        reply = self.dialect.parse_reply(line.strip(b"\r\n"))
        if not isinstance(reply, KteamReply) or reply.is_error or (
            expected is not None and reply.letter != self.dialect.reply_letter(expected)
        ):
            self._kteam_bad(f"{line[:40]!r}" + (f" to {expected}" if expected else ""))
            return
        self.counters.received("kteam")
        self._kteam_bad_run = 0
        # One source per key: a streaming bus wins over K-Team (the line is still recorded).
        if self._kteam_decoder.topic_of(reply) in self._streamed:
            return
        for message in self._kteam_decoder.messages(t, reply):
            self._publish_topic(message)


def _open_port(
    what: str, name: str, url: str, options: Callable[[], dict[str, Any]] = dict
) -> ByteTransport:
    """Open one of the robot's byte ports through the transport registry; ``options()`` gives
    the backend's options (raising ValueError for a bad one, reported as the port's failure)."""
    try:
        return open_byte_transport(url, **options())
    except (OSError, ValueError) as e:
        raise TransportError(f"cannot open {what} {name!r}: {e}") from e


def _discard_input(port: ByteTransport) -> None:
    """Drop what the port holds (a late reply to an earlier poll), as pyserial's
    ``reset_input_buffer`` does; bounded, so a port that streams cannot hold the poll."""
    for _ in range(64):
        if not port.read():
            return


def _read_line(port: ByteTransport, timeout: float, end: bytes = b"\n") -> bytes:
    """The port's input up to and including the first ``end`` byte (the dialect's last
    terminator byte: LF for both), or what came within ``timeout`` seconds (then without it);
    input after the line is dropped."""
    deadline = time.monotonic() + timeout
    buf = bytearray()
    while end not in buf:
        remaining = deadline - time.monotonic()
        if remaining <= 0 or not port.wait(remaining):
            break
        buf += port.read()
    i = buf.find(end)
    return bytes(buf if i < 0 else buf[: i + 1])
