"""bridge.recording: MCAP channels and schemas, thread safety, SIGKILL and SIGTERM endings."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import pytest
from koala_bridge.recording.mcap_file import (
    FORMAT_VERSION,
    FROM_ROBOT,
    TO_ROBOT,
    Recorder,
    RecordingError,
    open_recording,
)
from mcap.reader import make_reader
from mcap.records import Message
from mcap.stream_reader import StreamReader

REPO = Path(__file__).resolve().parents[2]


def test_channels_schemas_metadata_and_summary(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    world = {"walls": [[0, 0, 1, 0]], "robot": {"ticks_per_metre": 90284.0}}
    with Recorder(path, metadata={"source": "sim", "seed": 7}, world=world) as rec:
        for i in range(100):
            t = i * 0.01
            rec.record("truth/pose", t, {"t": t, "x": 1.0, "y": 2.0, "theta": 0.1})
            rec.record("sensors/gyro", t, json.dumps({"t": t, "yaw_rate": 0.5}).encode())
            rec.record_frame("can", FROM_ROBOT, t, b"\x01\x02\x03", can_id=0x101, extended=False)
            if i % 10 == 0:
                rec.record_frame("serial/kteam", TO_ROBOT, t, b"H\r")
                rec.record("sensors/ir/truth", t, {"t": t, "counts": [1, 2]})

    # The mcap library's seeking reader sees a complete, indexed file.
    with path.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        topics = {c.id: c.topic for c in summary.channels.values()}
        counts = {topics[k]: v for k, v in summary.statistics.channel_message_counts.items()}
        assert counts == {
            "/truth/pose": 100,
            "/sensors/gyro": 100,
            "/bus/can": 100,
            "/bus/serial/kteam": 10,
            "/sensors/ir/truth": 10,
        }
        for ch in summary.channels.values():
            assert ch.message_encoding == "json"
            schema = summary.schemas[ch.schema_id]
            assert schema.encoding == "jsonschema"
            assert json.loads(schema.data)["type"] == "object"
        assert reader.get_header().profile == "koala-bridge"
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        assert meta["koala-bridge"]["format_version"] == str(FORMAT_VERSION)
        assert meta["koala-bridge"]["seed"] == "7"

    rec2 = open_recording(path)
    assert rec2.complete and rec2.format_version == FORMAT_VERSION
    assert rec2.world == world
    gyro = rec2.topic("sensors/gyro")
    assert [m.sequence for m in gyro] == list(range(100))
    assert gyro[3].log_time_ns == 30_000_000 and gyro[3].json()["yaw_rate"] == 0.5
    can = rec2.topic("/bus/can")[5].json()
    assert can["dir"] == FROM_ROBOT and can["seq"] == 5 and can["can_id"] == 0x101
    assert rec2.topic("/bus/can")[5].frame_bytes() == b"\x01\x02\x03"


def test_concurrent_writers_keep_frame_sequences_gap_free(tmp_path: Path) -> None:
    path = tmp_path / "threads.mcap"
    n = 2000
    with Recorder(path, chunk_size=4096) as rec:

        def writer(bus: str) -> None:
            for i in range(n):
                rec.record_frame(bus, FROM_ROBOT, i * 1e-3, bytes([i & 0xFF]))
                rec.record_frame(bus, TO_ROBOT, i * 1e-3, b"x")

        threads = [threading.Thread(target=writer, args=(b,)) for b in ("can", "mavlink")]
        threads += [threading.Thread(target=writer, args=("can",))]
        for th in threads:
            th.start()
        for th in threads:
            th.join()
    r = open_recording(path)
    for bus, writers in (("can", 2), ("mavlink", 1)):
        for d in (FROM_ROBOT, TO_ROBOT):
            seqs = sorted(m.json()["seq"] for m in r.topic(f"/bus/{bus}") if m.json()["dir"] == d)
            assert seqs == list(range(writers * n))


def test_declared_channels_exist_without_messages(tmp_path: Path) -> None:
    path = tmp_path / "declared.mcap"
    with Recorder(path) as rec:
        rec.declare(keys=["sensors/gyro", "status"], buses=["serial/kteam", "can"])
        rec.record("sensors/gyro", 0.0, {"t": 0.0, "yaw_rate": 0.0})
        rec.declare(keys=["sensors/gyro"], buses=["can"])  # declared twice: one channel
    with path.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and summary.statistics is not None
    topics = sorted(c.topic for c in summary.channels.values())
    assert topics == ["/bus/can", "/bus/serial/kteam", "/sensors/gyro", "/status"]
    counts = {summary.channels[k].topic: v
              for k, v in summary.statistics.channel_message_counts.items()}
    assert counts == {"/sensors/gyro": 1}
    schemas = {c.topic: json.loads(summary.schemas[c.schema_id].data)["title"]
               for c in summary.channels.values()}
    assert schemas["/bus/serial/kteam"] == "koala.bus.Frame"
    assert schemas["/status"] == "koala.Status"
    r = open_recording(path)
    assert r.topics == topics and [m.sequence for m in r.topic("sensors/gyro")] == [0]


def test_records_after_close_are_dropped_not_raised(tmp_path: Path) -> None:
    rec = Recorder(tmp_path / "c.mcap")
    rec.record("status", 0.0, {"t": 0.0})
    rec.close()
    rec.close()
    rec.record("status", 1.0, {"t": 1.0})
    assert rec.dropped == 1 and rec.written == 1
    with pytest.raises(ValueError):
        rec.record_frame("can", "sideways", 0.0, b"")


@pytest.mark.parametrize("content, reason", [
    (b"hello, not an mcap file at all", "not an MCAP file: it does not begin with the MCAP magic"),
    (b"abc", "not an MCAP file: it does not begin with the MCAP magic"),  # shorter than the magic
    (b"", "not an MCAP file: it is empty"),
    (b"\x89MCAP0\r\n", r"nothing readable after its magic bytes \(the file ends inside a record"),
])
def test_not_mcap_is_a_clear_error(tmp_path: Path, content: bytes, reason: str) -> None:
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(content)
    with pytest.raises(RecordingError, match=reason) as e:
        open_recording(bad)
    assert "unpack" not in str(e.value)


def test_a_file_cut_short_says_why_in_the_log(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "whole.mcap"
    with Recorder(path) as rec:
        for i in range(2000):
            rec.record("sensors/gyro", i * 0.01, {"t": i * 0.01, "yaw_rate": 0.25})
            if i % 500 == 499:
                rec.flush()  # whole chunks to read before the cut
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with caplog.at_level("INFO", logger="koala_bridge.recording.mcap_file"):
        r = open_recording(cut)
    assert not r.complete and r.topic("sensors/gyro")
    partial = [m.getMessage() for m in caplog.records if "partial record" in m.getMessage()]
    assert len(partial) == 1 and "()" not in partial[0], partial


_WRITER = textwrap.dedent(
    """
    import signal, sys, threading, time
    from koala_bridge.recording.mcap_file import Recorder, FROM_ROBOT
    rec = Recorder(sys.argv[1], chunk_size=8192, max_chunk_age_s=0.2)
    # The handler only sets an event: the loop closes the recorder (the service's pattern;
    # closing inside the handler could interrupt a record() holding the recorder's lock).
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    i = 0
    while not stop.is_set():
        t = i * 0.001
        rec.record("sensors/gyro", t, {"t": t, "yaw_rate": 0.25})
        rec.record_frame("serial/rangefinders", FROM_ROBOT, t, b"\\xa5\\x5a" + bytes(20))
        i += 1
        if i % 50 == 0:
            time.sleep(0.001)
    rec.close()
    """
)


def _start_writer(path: Path) -> subprocess.Popen[bytes]:
    proc = subprocess.Popen([sys.executable, "-c", _WRITER, str(path)], cwd=REPO)
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:
        if path.exists() and path.stat().st_size > 64 * 1024:
            return proc
        time.sleep(0.05)
    proc.kill()
    raise AssertionError("writer subprocess produced no data")


def test_sigkill_leaves_file_readable_up_to_last_chunk(tmp_path: Path) -> None:
    path = tmp_path / "killed.mcap"
    proc = _start_writer(path)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=10)

    # The mcap library's streaming reader reads every complete chunk, then hits the cut.
    seqs: dict[int, list[int]] = {}
    with path.open("rb") as f:
        try:
            for record in StreamReader(f).records:
                if isinstance(record, Message):
                    seqs.setdefault(record.channel_id, []).append(record.sequence)
        except Exception:  # noqa: BLE001 - the partial tail raises EndOfFile or a decode error
            pass
    assert len(seqs) == 2
    for s in seqs.values():
        assert len(s) > 1000
        assert s == list(range(len(s))), "messages up to the cut are contiguous"

    r = open_recording(path)
    assert not r.complete
    assert len(r.topic("sensors/gyro")) == len(seqs[1])  # channel 1: the first one recorded


def test_sigterm_leaves_complete_indexed_file(tmp_path: Path) -> None:
    path = tmp_path / "terminated.mcap"
    proc = _start_writer(path)
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=10) == 0
    with path.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and summary.statistics is not None
    counts = list(summary.statistics.channel_message_counts.values())
    assert len(counts) == 2 and min(counts) > 1000
    r = open_recording(path)
    assert r.complete
    assert [m.sequence for m in r.topic("sensors/gyro")] == list(range(counts[0]))
