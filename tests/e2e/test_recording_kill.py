"""After kill -9, a recording is readable by the standard MCAP tooling up to its last complete
chunk: `koala-bridge recover` rewrites what a killed `run --record` left into a complete,
indexed file that `mcap.reader.make_reader` (a seeking reader, as Foxglove and the `mcap` CLI
are) reads, with every message our own tolerant reader recovers."""

from __future__ import annotations

import signal
import subprocess
import time
from collections import Counter
from pathlib import Path

from conftest import REPO, bridge_command
from koala_bridge.recording.mcap_file import open_recording
from mcap.reader import make_reader
from mcap.records import Message
from mcap.stream_reader import StreamReader


def _grown(path: Path, size: int, timeout: float = 120.0) -> None:
    deadline = time.monotonic() + timeout
    while not (path.exists() and path.stat().st_size > size):
        assert time.monotonic() < deadline, f"{path} never grew past {size} bytes"
        time.sleep(0.05)


def test_killed_run_is_recovered_into_a_file_every_mcap_reader_opens(bridge, tmp_path: Path):
    killed = tmp_path / "killed.mcap"
    b = bridge(clock="fast", extra=["--duration", "3600", "--record", str(killed)])
    _grown(killed, 400_000)
    assert b.stop(signal.SIGKILL) == -signal.SIGKILL

    ours = open_recording(killed)
    assert not ours.complete and ours.lost and len(ours.messages) > 1000
    # The streaming reader of the mcap library reads the same messages up to the cut.
    streamed: list[Message] = []
    with killed.open("rb") as f:
        try:
            for record in StreamReader(f).records:
                if isinstance(record, Message):
                    streamed.append(record)
        except Exception:  # noqa: BLE001 - the cut tail: EndOfFile or a decode error
            pass
    assert len(streamed) == len(ours.messages)

    out = tmp_path / "recovered.mcap"
    p = subprocess.run(bridge_command("recover", str(killed), str(out)), cwd=REPO,
                       capture_output=True, text=True, timeout=120, stdin=subprocess.DEVNULL)
    assert p.returncode == 0, p.stderr
    assert "Traceback" not in p.stderr
    warnings = [line for line in p.stderr.splitlines() if " WARNING " in line]
    assert len(warnings) == 1 and "cut short" in warnings[0] and "lost" in warnings[0], p.stderr

    with out.open("rb") as f:
        reader = make_reader(f, validate_crcs=True)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        assert reader.get_header().profile == "koala-bridge"
        read = [(ch.topic, m.sequence, m.log_time, m.data) for _, ch, m in
                reader.iter_messages(log_time_order=False)]
        meta = {m.name for m in reader.iter_metadata()}
    assert len(read) == len(ours.messages) == summary.statistics.message_count
    assert read == [(m.topic, m.sequence, m.log_time_ns, m.data) for m in ours.messages]
    assert Counter(t for t, *_ in read) == Counter(ours.counts())
    assert meta == {"koala-bridge", "world"}
    # Every channel the run declared is there, those without a message too.
    assert {c.topic for c in summary.channels.values()} == set(ours.topics)
    again = open_recording(out)
    assert again.complete and not again.lost and again.world == ours.world


def test_recover_refuses_to_overwrite_and_reports_one_line(tmp_path: Path) -> None:
    src = tmp_path / "a.mcap"
    src.write_bytes(b"not mcap")
    dst = tmp_path / "b.mcap"
    dst.write_bytes(b"")
    for args, needle in (([src, tmp_path / "c.mcap"], "not an MCAP file"),
                         ([src, dst], "exists")):
        p = subprocess.run(bridge_command("recover", *map(str, args)), cwd=REPO,
                           capture_output=True, text=True, timeout=120,
                           stdin=subprocess.DEVNULL)
        assert p.returncode == 2 and "Traceback" not in p.stderr
        lines = p.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("koala-bridge recover:"), p.stderr
        assert needle in lines[0]
    assert not (tmp_path / "c.mcap").exists() and dst.read_bytes() == b""
