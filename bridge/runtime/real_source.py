"""The real robot as the source: its ports, read with the same codecs, published and recorded as
in simulation (``koala-bridge run --source real``).

Nothing comes from the simulator: every reading is decoded from the robot's own ports, named in
the ``[real]`` section of the configuration (docs/recording.md, "Real drivers")::

    [real]
    kteam = "/dev/ttyUSB0"              # serial device or pyserial URL (socket://, rfc2217://, loop://)
    kteam_baud = 115200
    kteam_poll = ["N", "H"]             # commands asked at kteam_poll_hz: N -> sensors/ir,
    kteam_poll_hz = 10.0                #   H -> sensors/odometry, unless a streaming bus below
                                        #   serves that key (then the poll is only recorded)
    rangefinders = "/dev/ttyUSB1"       # range frames: kind 1 -> sensors/ir, 2 -> sensors/sonar
    rangefinders_baud = 115200
    can_interface = "socketcand"        # python-can interface; WheelOdometry -> sensors/odometry,
    can_channel = "koala0"              #   Gyro -> sensors/gyro (config/koala.dbc)
    can_options = { host = "192.168.1.20", port = 29536 }   # extra can.Bus keyword arguments
    mavlink = "udpin:0.0.0.0:14550"     # MAVLink connection string; SCALED_IMU -> sensors/compass

Every key is optional: a port not named is not opened. ``t`` of every message is the host's
monotonic time since the start, in seconds (a real robot has no simulation time; its own sample
stamps stay in the raw frames of the recording). The rest of the configuration (robot, world,
zenoh) is read as for a simulated run: the world and robot description answer the ``world``
queryable, so monitor and snapshot work unchanged. No ``truth/pose`` is published.

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
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Annotated, Any

import can
from koala_bridge.core.errors import TransportError
from koala_bridge.core.schema import (
    ConfigError,
    Positive,
    PositiveInt,
    Str,
    section,
    tuples,
    validate,
)
from koala_bridge.core.topics import (
    CompassMessage,
    GyroMessage,
    IrMessage,
    OdometryMessage,
    SonarMessage,
    StatusMessage,
    TopicMessage,
    ints,
)
from koala_bridge.drivers.kteam import LineSplitter, format_command, parse_reply
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
from koala_bridge.runtime.settings import BridgeSettings
from koala_bridge.runtime.source import READ_TIMEOUT_S, Tap, start_reader, until_text
from koala_bridge.runtime.zenoh_io import ZENOH_BUS, ZenohLink
from koala_bridge.sim.config import load_sim_config
from pydantic import AfterValidator, BeforeValidator, Strict

log = logging.getLogger(__name__)

KTEAM_REPLY_TIMEOUT_S = 0.5
POLLABLE = {"N": "sensors/ir", "H": "sensors/odometry"}


def _port_name(value: Any) -> Any:
    """A port key: "" (the file's way to say "not opened") is None."""
    return None if value == "" else value


def _pollable(value: tuple[str, ...]) -> tuple[str, ...]:
    for c in value:
        if c not in POLLABLE:
            raise ValueError(f"has {c!r}, not one of {sorted(POLLABLE)}")
    return value


#: A port: a device, pyserial URL or connection string; "" or absent = not opened.
_Port = Annotated[Str | None, BeforeValidator(_port_name)]


@section
class RealPorts:
    """``[real]``: where the robot's ports are.

    Every key may be left out; its default is the value ``config/default.toml`` shows (ports
    "" = not opened; the schema's policy, :mod:`koala_bridge.core.schema`).
    """

    kteam: _Port = None
    kteam_baud: PositiveInt = 115200
    kteam_poll: Annotated[tuple[Str, ...], BeforeValidator(tuples),
                          AfterValidator(_pollable)] = ()
    kteam_poll_hz: Positive = 10.0
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

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> RealPorts:
        return validate(cls, d, "real")

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
        self._ranges: ByteTransport | None = None
        self._can: CanTransport | None = None
        self._mavlink: ByteTransport | None = None
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        # [buses.can] dbc: the robot's CAN database (needed only with a [real] CAN port)
        self._can_codec = settings.buses.can.codec(needed=bool(self.ports.can_interface))
        self.last = _LastReadings()
        p = self.ports
        self._streamed = ({"sensors/ir"} if p.rangefinders else set()) | (
            {"sensors/odometry"} if p.can_interface else set()
        )
        # The estimator node, fed with every frame read from the robot (_frame); None when off.
        self.localisation = LocalisationNode.from_config(
            config, load_sim_config(config), self._publish, can_codec=self._can_codec
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
                self._kteam = _open_port(
                    "kteam port", p.kteam, serial_url(p.kteam), lambda: {"baudrate": p.kteam_baud}
                )
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
        if self._ranges is not None:
            self._spawn("rangefinders", self._range_reader(self._ranges))
        if self._can is not None:
            self._spawn("can", self._can_reader(self._can))
        if self._mavlink is not None:
            self._spawn("mavlink", self._mavlink_reader(self._mavlink))
        return Endpoints(
            zenoh_endpoints=self.settings.zenoh.listen, zenoh_prefix=self.settings.zenoh.prefix
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
                    self._publish_topic(_ir_message(t, f.readings))
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

    def _poll_kteam(self, letter: str) -> None:
        port = self._kteam
        if port is None:
            return
        command = format_command(KteamCommand(letter))
        t = self.clock.now()
        with self._kteam_lock:
            try:
                _discard_input(port)
                port.write(command)
                self._frame("serial/kteam", "to_robot", t, command)
                self.counters.sent("kteam")
                line = _read_line(port, KTEAM_REPLY_TIMEOUT_S)
            except OSError as e:
                log.warning("kteam: %s", e)
                return
        t = self.clock.now()
        if not line.endswith(b"\n"):
            self.counters.rejected("kteam")
            log.debug("kteam: no reply to %s", letter)
            return
        self._frame("serial/kteam", "from_robot", t, line)
        splitter = LineSplitter()
        lines = [x for x in splitter.feed(line) if isinstance(x, bytes)]
        reply = parse_reply(lines[0]) if lines else None
        if not isinstance(reply, KteamReply) or reply.letter != letter.lower():
            self.counters.rejected("kteam")
            return
        self.counters.received("kteam")
        values = list(reply.ints)
        # One source per key: a streaming bus wins over polling (the poll is still recorded).
        if POLLABLE[letter] in self._streamed:
            return
        if letter == "N":
            self._publish_topic(_ir_message(t, values))
        elif letter == "H" and len(values) == 2:
            self._publish_topic(OdometryMessage(t, values[0], values[1]))


def _ir_message(t: float, counts: Sequence[int]) -> IrMessage:
    """``sensors/ir`` of a real robot: proximity counts only. Neither the range frames nor the
    K-Team ``N`` reply carry ambient light, so ``ambient`` is null for every sensor (not
    measured) and there is no ``truth``."""
    return IrMessage(t, ints(counts), (None,) * len(counts))


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


def _read_line(port: ByteTransport, timeout: float) -> bytes:
    """The port's input up to and including the first ``\\n``, or what came within ``timeout``
    seconds (then without ``\\n``); input after the line is dropped."""
    deadline = time.monotonic() + timeout
    buf = bytearray()
    while b"\n" not in buf:
        remaining = deadline - time.monotonic()
        if remaining <= 0 or not port.wait(remaining):
            break
        buf += port.read()
    end = buf.find(b"\n")
    return bytes(buf if end < 0 else buf[: end + 1])
