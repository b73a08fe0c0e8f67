"""Firmware test programs run one after another against the K-Team pty of a running bridge
(a subprocess, fast clock): what one program leaves behind -- a half-sent command, replies it never
read -- does not reach the next (issue 12). Each client is its own process, as in a firmware
team's test suite; nothing waits in between but the next program's start-up."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable

from conftest import BridgeProcess

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


def test_each_program_gets_its_own_replies(bridge: Callable[..., BridgeProcess]) -> None:
    proc = bridge(clock="fast", sets=["buses.rangefinders.enabled=false"])
    path = proc.endpoints["serial"]["kteam"]
    for _ in range(3):
        _client(LEAVE_HALF_SENT, path)
        assert _client(ASK, path, "H").startswith("h,")
        _client(NEVER_READ, path)
        assert _client(ASK, path, "B").startswith("b,koala-bridge")
    assert proc.stop() == 0
