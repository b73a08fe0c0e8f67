"""Lockstep determinism (issue 14): the same config, seed and firmware give bit-identical sensor
and truth channels in the recording, however loaded the machine and however long the firmware
is stopped.

Two runs of the bridge (``run --clock lockstep --record``, a subprocess) against the same
firmware (``_lockstep_firmware.py``, another process, written from pyserial/python-can/cantools/
pymavlink docs). The second run has a CPU hog beside it (one busy process per core) and its
firmware is stopped with SIGSTOP for over a second mid-run, then continued, as a debugger would.
Every channel a run's outcome depends on must then be identical, message for message and time
stamp for time stamp: the truth, every sensor, the estimator's output, and every frame the
robot put on a bus. (``status`` carries the real-time factor, a wall-clock figure, and the
firmware's own input arrives in chunks that depend on scheduling: both are left out, by name.)
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import pytest
import tomli_w
from conftest import free_port
from koala_bridge.recording.mcap_file import open_recording, outcome_messages

ROOT = Path(__file__).resolve().parents[2]
FIRMWARE = Path(__file__).with_name("_lockstep_firmware.py")
CYCLES = 2000
HOG = "import itertools\nfor _ in itertools.count(): pass"


def config(tmp: Path) -> Path:
    d = tomllib.loads((ROOT / "config" / "default.toml").read_text())
    d["world"] = tomllib.loads(
        (ROOT / "config" / "worlds" / "lab_walls_1.toml").read_text())["world"]
    d["buses"]["can"].update(socketcand_port=0, slcan=False, virtual=False)
    d["buses"]["mavlink"]["port"] = free_port("udp")
    d["zenoh"]["listen"] = [f"tcp/127.0.0.1:{free_port()}"]
    path = tmp / "lockstep.toml"
    path.write_bytes(tomli_w.dumps(d).encode())
    return path


def run(tmp: Path, name: str, hostile: bool) -> tuple[Path, dict[str, object]]:
    cfg = config(tmp)
    endpoints = tmp / f"{name}.json"
    mcap = tmp / f"{name}.mcap"
    hogs: list[subprocess.Popen[bytes]] = []
    bridge = subprocess.Popen(
        [sys.executable, "-m", "koala_bridge", "run", "--config", str(cfg), "--clock",
         "lockstep", "--duration", "60", "--endpoints-file", str(endpoints), "--record",
         str(mcap), "--log-level", "WARNING"],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
    )
    firmware = None
    try:
        if hostile:
            hogs = [subprocess.Popen([sys.executable, "-c", HOG])
                    for _ in range(os.cpu_count() or 2)]
        deadline = time.monotonic() + 120
        while not endpoints.exists():
            assert bridge.poll() is None, bridge.stderr.read().decode()[-2000:]
            assert time.monotonic() < deadline, "the bridge did not start"
            time.sleep(0.05)
        firmware = subprocess.Popen(
            [sys.executable, str(FIRMWARE), str(endpoints), "--cycles", str(CYCLES)],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )
        if hostile:
            time.sleep(0.5)          # some cycles in, then stopped as a debugger would
            firmware.send_signal(signal.SIGSTOP)
            time.sleep(1.5)
            firmware.send_signal(signal.SIGCONT)
        out, err = firmware.communicate(timeout=300)
        assert firmware.returncode == 0, err[-2000:]
        # the firmware closed its ports: the lockstep run ends by itself
        assert bridge.wait(timeout=60) == 0, bridge.stderr.read().decode()[-2000:]
        return mcap, json.loads(out)
    finally:
        for p in [*hogs, firmware, bridge]:
            if p is not None and p.poll() is None:
                if p is firmware:
                    p.send_signal(signal.SIGCONT)
                p.kill()
                p.wait()
        if bridge.stderr is not None:
            bridge.stderr.close()


def channels(mcap: Path) -> dict[str, list[tuple[int, bytes]]]:
    """The run's outcome (``outcome_messages``: every channel but the wall-clock ones and the
    Foxglove scene; bus channels with the frames the robot sent), as (time stamp, bytes) per
    channel."""
    out: dict[str, list[tuple[int, bytes]]] = {}
    for m in outcome_messages(open_recording(mcap)):
        out.setdefault(m.topic, []).append((m.log_time_ns, m.data))
    return out


@pytest.mark.e2e
@pytest.mark.slow
def test_two_lockstep_runs_one_beside_a_cpu_hog_with_the_firmware_stopped_are_identical(
    tmp_path: Path,
) -> None:
    quiet, report_a = run(tmp_path, "quiet", hostile=False)
    hostile, report_b = run(tmp_path, "hostile", hostile=True)
    a, b = channels(quiet), channels(hostile)
    # the firmware did something worth comparing: it met walls and turned
    assert report_a["turns"] >= 1, report_a
    assert report_a == report_b
    assert {"/truth/pose", "/sensors/ir", "/sensors/gyro", "/sensors/compass"} <= set(a)
    assert any(t.startswith("/bus/") for t in a), sorted(a)
    assert sorted(a) == sorted(b)
    for topic in a:
        assert len(a[topic]) == len(b[topic]), topic
        assert a[topic] == b[topic], f"{topic} differs"
    # simulated time advanced exactly one period per D (plus the firmware's last D,0,0)
    last = a["/sensors/gyro"][-1][0]          # the gyro samples every 10 ms step
    assert last == pytest.approx((CYCLES + 1) * 0.01 * 1e9, abs=1e3)
