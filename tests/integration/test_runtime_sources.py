"""Sources and the session: the simulated bridge's buses and the real robot's ports open through
the transport registry; every source is a ``Source``; the session's life cycle."""

from __future__ import annotations

import io
import json
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

import can
import pytest
from _can import wait_for
from koala_bridge.drivers.can_codec import KoalaCanCodec
from koala_bridge.drivers.mavlink_codec import CompassEncoder, MavlinkIdentity
from koala_bridge.drivers.messages import (
    CompassSample,
    GyroFrame,
    RangeFrame,
    RangeKind,
    TransportError,
    WheelOdometryFrame,
)
from koala_bridge.drivers.rangeframes import encode_range_frame
from koala_bridge.drivers.transports import open_byte_transport, open_can_transport
from koala_bridge.drivers.transports.pty import PtyTransport
from koala_bridge.drivers.transports.pythoncan import VirtualCanTransport
from koala_bridge.drivers.transports.serialport import SerialTransport
from koala_bridge.drivers.transports.socketcand import SocketcandServer
from koala_bridge.drivers.transports.tcp import TcpServerTransport
from koala_bridge.runtime import buses as buses_module
from koala_bridge.runtime.buses import bus_urls, open_buses
from koala_bridge.runtime.endpoints import Endpoints
from koala_bridge.runtime.real_source import RealRobotSource
from koala_bridge.runtime.replay import ReplaySource
from koala_bridge.runtime.session import make_source, run_session
from koala_bridge.runtime.settings import (
    BridgeSettings,
    apply_override,
    load_config,
    parse_override,
)
from koala_bridge.runtime.sim_source import SimulatedRobotSource
from koala_bridge.runtime.source import Source

REPO = Path(__file__).resolve().parents[2]


def config_with(*overrides: str, **sections: Mapping[str, Any]) -> dict[str, Any]:
    config = load_config(REPO / "config" / "default.toml")
    for text in overrides:
        config = apply_override(config, *parse_override(text))
    return {**config, **sections}


# ----------------------------------------------------------------------------- the bridge's buses


def test_bus_settings_become_registry_urls() -> None:
    settings = BridgeSettings.from_config(
        config_with(
            "buses.mavlink.transport=tcp", "buses.mavlink.port=0", "buses.can.virtual=true",
            'buses.can.virtual_channel="Koala A"', "buses.can.socketcand_port=0",
        )
    )
    urls = bus_urls(settings.buses)
    assert urls["kteam"] == "pty://" and urls["rangefinders"] == "pty://"
    assert urls["mavlink"] == f"tcp://{settings.buses.mavlink.host}:0"
    channel = settings.buses.can.channel
    assert urls["can.socketcand"] == (
        f"socketcand://{settings.buses.can.socketcand_host}:0/{channel}"
    )
    assert urls["can.virtual"] == "virtual:///Koala%20A"
    off = BridgeSettings.from_config(
        config_with(
            "buses.kteam.enabled=false", "buses.rangefinders.enabled=false",
            "buses.mavlink.enabled=false", "buses.can.socketcand=false", "buses.can.slcan=false",
            "buses.can.virtual=false", "buses.can.socketcan=false",
        )
    )
    assert bus_urls(off.buses) == {}


def test_the_bridge_opens_every_bus_through_the_registry(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    opened: list[str] = []

    def spy(real: Callable[..., Any]) -> Callable[..., Any]:
        def open_(url: str, **options: Any) -> Any:
            opened.append(url)
            return real(url, **options)

        return open_

    monkeypatch.setattr(buses_module, "open_byte_transport", spy(open_byte_transport))
    monkeypatch.setattr(buses_module, "open_can_transport", spy(open_can_transport))
    settings = BridgeSettings.from_config(
        config_with(
            "buses.mavlink.transport=tcp", "buses.mavlink.port=0", "buses.can.socketcand_port=0",
            "buses.can.virtual=true", 'buses.can.virtual_channel="koala-sources-test"',
        )
    )
    buses = open_buses(settings.buses)
    try:
        assert opened == list(bus_urls(settings.buses).values())
        assert buses.kteam is not None and isinstance(buses.kteam.transport, PtyTransport)
        assert buses.mavlink is not None
        assert isinstance(buses.mavlink.transport, TcpServerTransport)
        assert isinstance(buses.can["can.socketcand"], SocketcandServer)
        assert isinstance(buses.can["can.virtual"], VirtualCanTransport)
        assert buses.can["can.virtual"].endpoint.channel == "koala-sources-test"
    finally:
        buses.close()


# ----------------------------------------------------------------------------- the real robot


class ListTap:
    """A recorder stand-in: keeps what a source publishes."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.messages: list[tuple[str, dict[str, Any]]] = []
        self.buses: list[str] = []

    def declare(self, keys: Iterable[str] = (), buses: Iterable[str] = ()) -> None:
        self.buses = list(buses)

    def record(self, channel: str, t: float, payload: Mapping[str, Any]) -> None:
        with self.lock:
            self.messages.append((channel, dict(payload)))

    def record_frame(
        self, bus: str, direction: str, t: float, data: bytes, **fields: object
    ) -> None:
        pass

    def first(self, key: str, timeout: float = 10.0) -> dict[str, Any]:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self.lock:
                for channel, payload in self.messages:
                    if channel == key:
                        return payload
            time.sleep(0.01)
        raise AssertionError(f"no {key} published")


def test_real_source_reads_its_ports_through_the_registry(
    free_tcp_port: int, free_udp_port: int
) -> None:
    """The test plays the robot on the registry's own backends: a pty for range frames, a
    socketcand server for CAN, UDP datagrams for MAVLink; the real source opens them as
    ``serial:``, ``python-can://socketcand/...`` and ``udpin://`` and publishes what came."""
    with (
        open_byte_transport("pty://") as ranges,
        open_can_transport("socketcand://127.0.0.1:0/koala-real") as canbus,
    ):
        sc = canbus.endpoint
        real = {
            "kteam": "loop://",
            "rangefinders": str(ranges.endpoint.path),
            "can_interface": "socketcand",
            "can_channel": "koala-real",
            "can_options": {"host": sc.host, "port": sc.port},
            "mavlink": f"udpin:127.0.0.1:{free_udp_port}",
        }
        config = config_with(f'zenoh.listen=["tcp/127.0.0.1:{free_tcp_port}"]', real=real)
        source = make_source("real", config, BridgeSettings.from_config(config))
        assert isinstance(source, RealRobotSource) and isinstance(source, Source)
        tap = ListTap()
        source.tap = tap
        stop = threading.Event()
        runner = threading.Thread(target=source.run, args=(stop,), kwargs={"duration_s": 0})
        try:
            source.open()
            assert isinstance(source._kteam, SerialTransport)  # loop:// through serial:
            assert set(tap.buses) == {"serial/kteam", "serial/rangefinders", "can", "mavlink"}
            runner.start()
            wait_for(lambda: ranges.stats.clients == 1 and canbus.stats.clients == 1)
            ranges.write(encode_range_frame(RangeFrame(RangeKind.IR, 0, 0, tuple(range(16)))))
            assert tap.first("sensors/ir")["counts"] == list(range(16))
            codec = KoalaCanCodec()
            canbus.send(codec.encode(WheelOdometryFrame(120, -7)))
            canbus.send(codec.encode(GyroFrame(0.25)))
            odometry = tap.first("sensors/odometry")
            assert (odometry["left_ticks"], odometry["right_ticks"]) == (120, -7)
            assert tap.first("sensors/gyro")["yaw_rate"] == pytest.approx(0.25, abs=1e-3)
            with open_byte_transport(f"udp://127.0.0.1:{free_udp_port}") as robot_mavlink:
                encoder = CompassEncoder(MavlinkIdentity(1, 200))
                robot_mavlink.write(encoder.scaled_imu(CompassSample(10, 20.0, -5.0, 40.0)))
                compass = tap.first("sensors/compass")
            assert compass["mx"] == pytest.approx(20.0, abs=0.1)
            assert compass["mz"] == pytest.approx(40.0, abs=0.1)
        finally:
            stop.set()
            if runner.is_alive():
                runner.join(10)
            source.close()
        assert "real robot" in source.describe()
        assert source.summary().startswith("Stopped at t = ")


def test_real_source_names_the_port_it_cannot_open(tmp_path: Path, free_tcp_port: int) -> None:
    missing = tmp_path / "ttyNONE"
    config = config_with(
        f'zenoh.listen=["tcp/127.0.0.1:{free_tcp_port}"]', real={"rangefinders": str(missing)}
    )
    source = make_source("real", config, BridgeSettings.from_config(config))
    with source, pytest.raises(OSError, match=f"cannot open rangefinders port '{missing}'") as e:
        source.open()
    assert isinstance(e.value, TransportError)  # the tree's, so the CLI prints one line


# ----------------------------------------------------------------------------- the session


def test_every_source_implements_the_protocol() -> None:
    for cls in (SimulatedRobotSource, RealRobotSource, ReplaySource):
        for method in ("world_answer", "open", "describe", "run", "summary", "close"):
            assert callable(getattr(cls, method, None)), (cls, method)


class FakeSource:
    """Records the session's calls; ``fail_open`` makes ``open()`` fail as a busy port does."""

    def __init__(self, fail_open: bool = False) -> None:
        self.calls: list[str] = []
        self.fail_open = fail_open

    def world_answer(self) -> Mapping[str, Any]:
        return {}

    def open(self) -> Endpoints:
        self.calls.append("open")
        if self.fail_open:
            raise OSError("cannot open bus kteam: busy")
        return Endpoints(kteam="/dev/pts/99")

    def describe(self) -> str:
        self.calls.append("describe")
        return "Faking until stopped."

    def run(self, stop: threading.Event) -> None:
        self.calls.append("run")
        stop.wait(10)

    def summary(self) -> str:
        self.calls.append("summary")
        return "Faked."

    def close(self) -> None:
        self.calls.append("close")


def test_session_order_endpoints_file_and_stop(tmp_path: Path) -> None:
    source = FakeSource()
    out = io.StringIO()
    stop = threading.Event()
    result: list[int] = []
    endpoints_file = tmp_path / "sub" / "endpoints.json"
    runner = threading.Thread(
        target=lambda: result.append(
            run_session(
                source, prog="test", endpoints_file=endpoints_file, stop=stop, out=out,
                after_close=lambda: "Recorder closed.",
            )
        )
    )
    runner.start()
    wait_for(lambda: "run" in source.calls)
    assert json.loads(endpoints_file.read_text())["serial"]["kteam"] == "/dev/pts/99"
    stop.set()
    runner.join(10)
    assert result == [0]
    assert source.calls == ["open", "describe", "run", "summary", "close"]
    lines = out.getvalue().splitlines()
    assert lines[0].startswith("koala-bridge is serving")
    assert f"  Endpoints file          {endpoints_file}" in lines
    assert lines[-3:] == ["Faking until stopped.", "Faked.", "Recorder closed."]
    assert endpoints_file.exists()  # left in place, as before


def test_session_open_failure_is_one_line_and_still_closes(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    source = FakeSource(fail_open=True)
    endpoints_file = tmp_path / "endpoints.json"
    status = run_session(source, prog="koala-bridge run", endpoints_file=endpoints_file)
    assert status == 1
    assert source.calls == ["open", "close"]
    assert capsys.readouterr().err == "koala-bridge run: cannot open bus kteam: busy\n"
    assert not endpoints_file.exists()


def test_session_endpoints_file_failure(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("")
    source = FakeSource()
    status = run_session(source, prog="p", endpoints_file=blocker / "endpoints.json")
    assert status == 1
    assert source.calls == ["open", "close"]
    assert "p: cannot write the endpoints file" in capsys.readouterr().err


def test_make_source_refuses_an_unknown_kind() -> None:
    config = config_with()
    with pytest.raises(ValueError, match="sim, real"):
        make_source("dream", config, BridgeSettings.from_config(config))


def test_can_bus_client_sees_the_same_registry_url_channel() -> None:
    """A channel with characters a URL must quote reaches python-can unchanged."""
    with open_can_transport("python-can://virtual/koala%2Fodd%20name") as bus:
        assert bus.endpoint.channel == "koala/odd name"
        with can.Bus(interface="virtual", channel="koala/odd name") as client:
            client.send(can.Message(arbitration_id=5, data=b"\x01"))
            got = bus.recv(5)
            assert got is not None and got.arbitration_id == 5
