"""MAVProxy, a real ground station, receives the bridge's compass stream.

MAVProxy runs headless (``--daemon --non-interactive``) on the bridge's MAVLink URL, forwards what
it receives to a UDP port of ours (``--out``) and writes its telemetry log (``--logfile``); both
must hold SCALED_IMU from the simulated compass, with the heading of the truth pose.
"""

from __future__ import annotations

import math
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

MAVPROXY = shutil.which("mavproxy.py", path=str(Path(sys.executable).parent)) or shutil.which(
    "mavproxy.py"
)


@pytest.mark.skipif(MAVPROXY is None, reason="MAVProxy is not installed (pip install MAVProxy)")
def test_mavproxy_receives_the_compass(bridge, zenoh_watch, tmp_path: Path,
                                       free_udp_port: int) -> None:
    from pymavlink import mavutil

    b = bridge(clock="realtime")
    watch = zenoh_watch(b)
    pose = watch.wait_for("truth/pose")
    north = math.radians(watch.query("world")["earth_field"]["north_deg"])
    tlog = tmp_path / "mav.tlog"
    out = mavutil.mavlink_connection(f"udpin:127.0.0.1:{free_udp_port}")
    log = open(tmp_path / "mavproxy.log", "wb")  # noqa: SIM115 - closed below
    proc = subprocess.Popen(
        [sys.executable, str(MAVPROXY), f"--master={b.endpoints['mavlink']['url']}",
         f"--out=udp:127.0.0.1:{free_udp_port}", "--daemon", "--non-interactive",
         f"--state-basedir={tmp_path}", f"--logfile={tlog}"],
        stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT, cwd=tmp_path,
        start_new_session=True,
    )
    try:
        msg = out.recv_match(type="SCALED_IMU", blocking=True, timeout=30)
        assert msg is not None, (tmp_path / "mavproxy.log").read_text()
        assert (msg.get_srcSystem(), msg.get_srcComponent()) == (1, 1)
        heading = math.atan2(-msg.ymag, msg.xmag)
        expected = north - pose["theta"]  # clockwise from north; theta is CCW from east
        assert abs(math.remainder(heading - expected, math.tau)) < math.radians(3)
        hb = out.recv_match(type="HEARTBEAT", blocking=True, timeout=10)
        assert hb is not None and hb.get_srcSystem() == 1
        # MAVProxy's log writer flushes the telemetry log in its own time, and a SIGTERM
        # loses what it still buffers: wait for the message on disk before ending it.
        deadline = time.monotonic() + 30
        while not _tlog_holds(tlog, "SCALED_IMU") and time.monotonic() < deadline:
            time.sleep(0.2)
    finally:
        out.close()
        # MAVProxy has no clean shutdown in daemon mode: end its whole process group.
        if proc.poll() is None:
            try:
                os.killpg(proc.pid, signal.SIGTERM)
                proc.wait(10)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(5)
        log.close()
    assert _tlog_holds(tlog, "SCALED_IMU"), (tmp_path / "mavproxy.log").read_text()


def _tlog_holds(tlog: Path, kind: str) -> bool:
    from pymavlink import mavutil

    if not tlog.exists():
        return False
    logged = mavutil.mavlink_connection(str(tlog))
    try:
        return logged.recv_match(type=kind) is not None
    finally:
        logged.close()
