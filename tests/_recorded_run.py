"""A 60 s simulated run recorded with ``run --record`` on the fast clock, with a K-Team client.

Shared by the recording and replay tests (each module records its own: about 3 s each).
"""

from __future__ import annotations

import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import serial
from conftest import DEFAULT_CONFIG, REPO, bridge_command, free_port, wait_endpoints

DURATION_S = 60.0
KTEAM_COMMANDS = (b"B\r", b"D,20,20\r", b"H\r", b"N\r", b"X\r", b"E\r")


@dataclass
class RecordedRun:
    path: Path
    endpoints: dict[str, Any]
    kteam_exchanges: list[tuple[bytes, bytes]]  # (command, reply) as the client saw them
    log: str


def record_run(
    tmp: Path,
    duration_s: float = DURATION_S,
    clock: str = "fast",
    extra: list[str] | None = None,
) -> RecordedRun:
    """Record ``duration_s`` simulation seconds; a K-Team client asks KTEAM_COMMANDS at the start
    (on the fast clock a run must be long enough, ~10 s or more, for the client to finish)."""
    path = tmp / "run.mcap"
    endpoints_file = tmp / "endpoints.json"
    log_path = tmp / "bridge.log"
    args = [
        "run", "--config", str(DEFAULT_CONFIG), "--clock", clock,
        "--duration", str(duration_s), "--record", str(path),
        "--endpoints-file", str(endpoints_file),
        "--set", f'zenoh.listen=["tcp/127.0.0.1:{free_port()}"]',
        "--set", f"buses.mavlink.port={free_port('udp')}",
        "--set", "buses.can.socketcand_port=0",
        *(extra or []),
    ]
    with log_path.open("wb") as log:
        proc = subprocess.Popen(bridge_command(*args), cwd=REPO, stdout=log,
                                stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
    exchanges: list[tuple[bytes, bytes]] = []
    try:
        endpoints = wait_endpoints(proc, endpoints_file, log_path, timeout=120)
        with serial.Serial(endpoints["serial"]["kteam"], 115200, timeout=5) as port:
            for command in KTEAM_COMMANDS:
                port.write(command)
                exchanges.append((command, port.read_until(b"\r\n")))
        assert proc.wait(timeout=120) == 0, log_path.read_text()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return RecordedRun(path, endpoints, exchanges, log_path.read_text())
