"""`replay`: clients on the real transports get the recorded frames, same bytes, same order;
K-Team commands get the recorded replies; unreplayable recordings are refused with the reason.

Timing (inter-frame error vs the recording) is measured by bench/replay_timing.py and reported in
docs/recording.md, not asserted here (it depends on the machine's load).
"""

from __future__ import annotations

import argparse
import signal
import socket
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import can
import pytest
import serial
from _recorded_run import RecordedRun, record_run
from conftest import REPO, BridgeProcess, bridge_command, free_port, wait_endpoints
from koala_bridge.cli import monitor as monitor_cli
from koala_bridge.cli import replay as replay_cli
from koala_bridge.cli.main import main as cli_main
from koala_bridge.drivers.rangeframes import RangeFrameDecoder, encode_range_frame
from koala_bridge.recording.mcap_file import FROM_ROBOT, Recorder, open_recording
from koala_bridge.runtime.replay import plan_replay
from koala_bridge.tools.monitor import ZenohWatch as MonitorWatch
from mcap.writer import Writer


@pytest.fixture(scope="module")
def run3(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RecordedRun]:
    # Real time: on the fast clock a short run could end before the K-Team client is done.
    yield record_run(tmp_path_factory.mktemp("run3"), duration_s=3.0, clock="realtime")


def _args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    replay_cli.add_arguments(parser)
    return parser.parse_args(argv)


def monitor_args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    monitor_cli.add_arguments(parser)
    return parser.parse_args(argv)


def wait_for_log(log_path: Path, text: str, proc: subprocess.Popen[bytes],
                 timeout: float = 120.0) -> None:
    """Wait until the replay has written ``text`` to its log."""
    deadline = time.monotonic() + timeout
    while text not in log_path.read_text():
        assert proc.poll() is None, log_path.read_text()
        assert time.monotonic() < deadline, log_path.read_text()
        time.sleep(0.02)


class Collector:
    """Reads one client connection in a thread, keeping (arrival time, frame bytes)."""

    def __init__(self, name: str, read_frames) -> None:  # type: ignore[no-untyped-def]
        self.frames: list[tuple[float, bytes]] = []
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._read = read_frames
        self._thread = threading.Thread(target=self._loop, name=f"collector-{name}")
        self._thread.start()

    def _loop(self) -> None:
        while not self._stop.is_set():
            try:
                frames = self._read()
            except (OSError, ValueError, can.CanError):  # the replay closed its end
                return
            with self._cond:
                for frame in frames:
                    self.frames.append((time.monotonic(), frame))
                self._cond.notify_all()

    def wait_for(self, n: int, timeout: float) -> int:
        """Wait until ``n`` frames have arrived (or ``timeout`` s); the number that did."""
        with self._cond:
            self._cond.wait_for(lambda: len(self.frames) >= n, timeout)
            return len(self.frames)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()


def test_replay_feeds_clients_the_recorded_frames_in_order(
    run3: RecordedRun, tmp_path: Path
) -> None:
    rec = open_recording(run3.path)
    want = {
        bus: [m.frame_bytes() for m in rec.topic(f"/bus/{bus}") if m.json()["dir"] == FROM_ROBOT]
        for bus in ("serial/rangefinders", "can", "mavlink")
    }
    mav_port = free_port("udp")
    udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    udp.bind(("127.0.0.1", mav_port))
    udp.settimeout(0.1)
    endpoints_file = tmp_path / "replay.json"
    log_path = tmp_path / "replay.log"
    with log_path.open("wb") as log:
        proc = subprocess.Popen(
            bridge_command(
                # Playback starts once every client below is connected (no frame sent before
                # a client can receive it), and the ports stay open until the test is done.
                "replay", str(run3.path), "--speed", "3", "--wait-clients", "120",
                "--linger", "120", "--endpoints-file", str(endpoints_file),
                "--set", f"buses.mavlink.port={mav_port}", "--set", "buses.can.slcan=false",
                "--set", f'zenoh.listen=["tcp/127.0.0.1:{free_port()}"]',
            ),
            cwd=REPO, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
        )
    collectors: list[Collector] = []
    try:
        ep = wait_endpoints(proc, endpoints_file, log_path)
        sc = ep["can"]["socketcand"]
        with (
            serial.Serial(ep["serial"]["rangefinders"], 115200, timeout=0.1) as ranges,
            serial.Serial(ep["serial"]["kteam"], 115200, timeout=30) as kteam,
            can.Bus(interface="socketcand", host=sc["host"], port=sc["port"],
                    channel=sc["channel"]) as bus,
        ):
            decoder = RangeFrameDecoder()

            def read_ranges() -> list[bytes]:
                return [encode_range_frame(f) for f in decoder.feed(ranges.read(4096))]

            def read_can() -> list[bytes]:
                msg = bus.recv(timeout=0.1)
                return [] if msg is None else [bytes(msg.data)]

            def read_udp() -> list[bytes]:
                try:
                    return [udp.recv(4096)]
                except TimeoutError:
                    return []

            collectors = [Collector("ranges", read_ranges), Collector("can", read_can),
                          Collector("mavlink", read_udp)]
            for c, frames in zip(collectors, want.values(), strict=True):
                c.wait_for(len(frames), timeout=120)
            # The replay is past its last frame and lingers: K-Team replies are the last ones.
            wait_for_log(log_path, "Every frame sent", proc)
            # K-Team: answered from the recording (the run's client asked B, D, H, N, X, E).
            kteam.write(b"B\r")
            version = kteam.read_until(b"\r\n")
            kteam.write(b"H\r")
            counters = kteam.read_until(b"\r\n")
            kteam.write(b"O\r")  # never asked while recording: no reply to give
            missing = kteam.read_until(b"\r\n")
            proc.send_signal(signal.SIGINT)  # ends the linger: a clean stop, "Replay done"
            assert proc.wait(timeout=60) == 0, log_path.read_text()
            for c in collectors:  # before the clients close under them
                c.stop()
    finally:
        for c in collectors:
            c.stop()
        udp.close()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    got = dict(zip(("serial/rangefinders", "can", "mavlink"),
                   ([f for _, f in c.frames] for c in collectors), strict=True))
    for bus, frames in want.items():
        assert len(frames) > 50
        assert got[bus] == frames, (bus, len(got[bus]), len(frames))
    replies = dict(run3.kteam_exchanges)
    assert version == replies[b"B\r"]
    assert counters == replies[b"H\r"]
    assert missing.startswith(b"z,")
    assert "Replay done" in log_path.read_text()


def test_replay_republishes_the_recorded_zenoh_messages_for_monitor(
    run3: RecordedRun, tmp_path: Path, zenoh_watch, capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    rec = open_recording(run3.path)
    recorded: dict[str, list[dict]] = {}
    for m in rec.messages:  # the bridge's JSON messages (not the Foxglove scene's protobuf)
        if not m.topic.startswith("/bus/") and rec.message_encoding(m) == "json":
            recorded.setdefault(m.topic[1:], []).append(m.json())
    assert {"truth/pose", "sensors/gyro", "sensors/ir", "status"} <= recorded.keys()
    zenoh_endpoint = f"tcp/127.0.0.1:{free_port()}"
    endpoints_file = tmp_path / "replay.json"
    log_path = tmp_path / "replay.log"
    with log_path.open("wb") as log:
        proc = subprocess.Popen(
            bridge_command(
                # Playback waits for a client on the K-Team pty: the test opens it once both
                # Zenoh subscribers (the watch, the monitor) are in place.
                "replay", str(run3.path), "--endpoints-file", str(endpoints_file),
                "--bus", "can", "--bus", "serial/kteam", "--wait-clients", "120",
                "--set", "buses.can.slcan=false",
                "--set", "buses.can.socketcand=false", "--set", "buses.mavlink.enabled=false",
                "--set", f'zenoh.listen=["{zenoh_endpoint}"]',
            ),
            cwd=REPO, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
        )

    monitor_ready = threading.Event()

    class ReadyMonitorWatch(MonitorWatch):
        """The monitor's own session, flagging when the replay has answered it (so its
        subscriber, declared before, is known to the replay)."""

        def __init__(self, *args, **kwargs) -> None:  # type: ignore[no-untyped-def]
            super().__init__(*args, **kwargs)
            if self.query_json("world", timeout_s=30.0) is not None:
                monitor_ready.set()

    monkeypatch.setattr(monitor_cli, "ZenohWatch", ReadyMonitorWatch)
    monitor_rc: list[int] = []
    monitor = None
    try:
        ep = wait_endpoints(proc, endpoints_file, log_path)
        assert ep["zenoh"]["endpoints"] == [zenoh_endpoint]
        watch = zenoh_watch(BridgeProcess(proc, ep, endpoints_file, log_path, zenoh_endpoint, 0))
        # Answered on the session the watch subscribed on: the replay knows the subscriber.
        assert watch.query("world") == rec.world
        monitor = threading.Thread(target=lambda: monitor_rc.append(monitor_cli.run(
            monitor_args(["--connect", zenoh_endpoint, "--prefix", ep["zenoh"]["prefix"],
                          "--once", "--duration", "1", "--timeout", "120"]))))
        monitor.start()
        assert monitor_ready.wait(60), "the monitor did not reach the replay"
        with serial.Serial(ep["serial"]["kteam"], 115200, timeout=30):  # playback starts
            monitor.join(timeout=180)
            assert proc.wait(timeout=120) == 0, log_path.read_text()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        if monitor is not None:
            monitor.join(timeout=180)
    assert monitor_rc == [0]
    out = capsys.readouterr().out
    assert "sensors/gyro" in out and "truth/pose" in out
    # Subscribed before the first message: every recorded message, in order, unchanged.
    for key, want in recorded.items():
        watch.collect({key: len(want)}, timeout=60)
        assert watch.messages.get(key, []) == want, key


def test_refuses_a_recording_without_bus_channels(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "zenoh-only.mcap"
    with Recorder(path) as rec:
        rec.record("sensors/gyro", 0.0, {"t": 0.0, "yaw_rate": 0.0})
    assert cli_main(["replay", str(path)]) == 2
    err = capsys.readouterr().err
    assert "no bus channel" in err and "/sensors/gyro" in err


def test_refuses_another_format_version(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "future.mcap"
    with Recorder(path, metadata={"format_version": "99"}) as rec:
        rec.record_frame("can", FROM_ROBOT, 0.0, b"\x01", can_id=1)
    assert cli_main(["replay", str(path)]) == 2
    assert "format version 99" in capsys.readouterr().err


def test_refuses_a_foreign_mcap_and_a_recording_of_commands_only(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    foreign = tmp_path / "foreign.mcap"
    with foreign.open("wb") as f:
        w = Writer(f)
        w.start(profile="ros2")
        w.finish()
    assert cli_main(["replay", str(foreign)]) == 2
    assert "not a koala-bridge recording" in capsys.readouterr().err

    inbound = tmp_path / "inbound.mcap"
    with Recorder(inbound) as rec:
        rec.record_frame("can", "to_robot", 0.0, b"\x01", can_id=1)
    assert cli_main(["replay", str(inbound)]) == 2
    assert "no frame sent by the robot" in capsys.readouterr().err


def test_plan_orders_frames_by_time_and_indexes_kteam_replies(tmp_path: Path) -> None:
    path = tmp_path / "p.mcap"
    with Recorder(path) as rec:
        rec.record_frame("mavlink", FROM_ROBOT, 0.2, b"b")
        rec.record_frame("can", FROM_ROBOT, 0.1, b"a", can_id=0x101)
        rec.record_frame("serial/kteam", FROM_ROBOT, 0.3, b"h,1,2\r\n")
        rec.record_frame("serial/kteam", FROM_ROBOT, 0.5, b"h,3,4\r\n")
    plan = plan_replay(open_recording(path))
    assert [(f.bus, f.data) for f in plan.frames] == [("can", b"a"), ("mavlink", b"b")]
    assert plan.frames[0].can_id == 0x101
    times, lines = plan.kteam_replies["h"]
    assert times == pytest.approx([0.3, 0.5]) and lines == [b"h,1,2\r\n", b"h,3,4\r\n"]
    assert plan.t0 == pytest.approx(0.1) and plan.t_end == pytest.approx(0.5)
