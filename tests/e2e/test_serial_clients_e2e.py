"""Firmware test programs run one after another against the K-Team pty of a running bridge
(a subprocess, fast clock): what one program leaves behind -- a half-sent command, replies it never
read -- does not reach the next (issue 12). Each client is its own process, as in a firmware
team's test suite. Before the next program starts, the test waits until the bridge has seen the
last one close the port (its DEBUG log line): a program that reopens the port before the bridge
notices the close is taken for the same client (docs/protocols.md), and on a loaded machine the
bridge's reader may run later than the next program's start-up."""

from __future__ import annotations

import re
import subprocess
import sys
import time
from collections.abc import Callable

from conftest import BridgeProcess
from koala_bridge.drivers.rangeframes import SYNC, RangeFrameDecoder

LEAVE_HALF_SENT = """
import serial, sys
with serial.Serial(sys.argv[1], 115200, timeout=10) as s:
    s.write(b"D,1")
    s.flush()
"""

NEVER_READ = """
import serial, sys
with serial.Serial(sys.argv[1], 115200, timeout=10, write_timeout=60) as s:
    s.write(b"N\\r" * 5000)
    s.flush()
"""

HOLD_UNREAD = """
import serial, sys, time
with serial.Serial(sys.argv[1], 115200, timeout=10):
    time.sleep(float(sys.argv[2]))  # reads nothing: the bridge's queue for it fills
"""

# A plain open(), as a C program or `cat` does: unlike pyserial it flushes nothing at open.
FIRST_BYTES = """
import os, sys
fd = os.open(sys.argv[1], os.O_RDONLY | os.O_NOCTTY)
data = b""
while len(data) < int(sys.argv[2]):
    data += os.read(fd, int(sys.argv[2]) - len(data))
os.close(fd)
sys.stdout.write(data.hex())
"""

ASK = """
import serial, sys
with serial.Serial(sys.argv[1], 115200, timeout=10) as s:
    s.write(sys.argv[2].encode() + b"\\r")
    sys.stdout.write(s.read_until(b"\\r\\n").decode("ascii", "replace"))
"""


def _client(script: str, *args: str) -> str:
    done = subprocess.run(
        [sys.executable, "-c", script, *args], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr
    return done.stdout


CLOSED = "the client closed the port"


def _closes_seen(proc: BridgeProcess) -> int:
    return proc.log_path.read_text(errors="replace").count(CLOSED)


def _run_then_wait_for_close(proc: BridgeProcess, script: str, *args: str) -> str:
    """Run a client program, then wait until the bridge has seen it close the port."""
    before = _closes_seen(proc)
    out = _client(script, *args)
    deadline = time.monotonic() + 60
    while _closes_seen(proc) == before:
        assert time.monotonic() < deadline, "the bridge never saw the client close the port"
        time.sleep(0.02)
    return out


def test_each_program_gets_its_own_replies(bridge: Callable[..., BridgeProcess]) -> None:
    proc = bridge(clock="fast", sets=["buses.rangefinders.enabled=false"],
                  extra=["--log-level", "DEBUG"])
    path = proc.endpoints["serial"]["kteam"]
    for _ in range(3):
        _run_then_wait_for_close(proc, LEAVE_HALF_SENT, path)
        assert _run_then_wait_for_close(proc, ASK, path, "H").startswith("h,")
        _run_then_wait_for_close(proc, NEVER_READ, path)
        reply = _run_then_wait_for_close(proc, ASK, path, "B")
        assert re.fullmatch(r"b,\d+\.\d+,\d+\.\d+\s*", reply)
    assert proc.stop() == 0


def test_range_frames_start_whole_after_a_client_that_never_read(
    bridge: Callable[..., BridgeProcess],
) -> None:
    proc = bridge(clock="fast", sets=["buses.kteam.enabled=false"])
    path = proc.endpoints["serial"]["rangefinders"]
    for _ in range(3):
        _client(HOLD_UNREAD, path, "1.0")
        head = bytes.fromhex(_client(FIRST_BYTES, path, "40000"))
        assert head[:2] == SYNC  # a whole frame from the first byte...
        decoder = RangeFrameDecoder()
        frames = decoder.feed(head)
        assert frames and decoder.rejected == 0
        # ...and all fresh: no stale frames the last client left unread, then a gap in seq.
        for kind in {f.kind for f in frames}:
            seqs = [f.seq for f in frames if f.kind == kind]
            assert all((b - a) % 65536 == 1 for a, b in zip(seqs, seqs[1:], strict=False))
    assert proc.stop() == 0
