"""`koala-bridge run --record` with [[robots]]: the recording holds every robot's Zenoh keys
and bus frames under its name, with the keys' schemas, and names the robots in its metadata;
the endpoints file holds one entry per robot."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import free_port
from koala_bridge.core.topics import IrMessage, TruthPose
from koala_bridge.recording.mcap_file import open_recording
from mcap.reader import make_reader

REPO = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.slow


def test_run_records_every_robot(tmp_path: Path) -> None:
    out, endpoints = tmp_path / "fleet.mcap", tmp_path / "ep.json"
    done = subprocess.run(
        [sys.executable, "-m", "koala_bridge", "run",
         "--config", str(REPO / "examples" / "two_robots.toml"), "--clock", "fast",
         "--duration", "1", "--record", str(out), "--endpoints-file", str(endpoints),
         "--set", f'zenoh.listen=["tcp/127.0.0.1:{free_port()}"]',
         "--set", "localisation.enabled=false",
         "--set", f"buses.mavlink.port={free_port('udp')}"],
        capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stderr
    assert "Simulating 2 robots (alpha, beta)" in done.stdout
    ep = json.loads(endpoints.read_text())
    assert list(ep["robots"]) == ["alpha", "beta"]
    assert ep["robots"]["beta"]["zenoh"]["prefix"] == "koala/beta"
    assert ep["robots"]["alpha"]["serial"]["kteam"] != ep["robots"]["beta"]["serial"]["kteam"]

    rec = open_recording(out)
    robots = json.loads(rec.metadata["koala-bridge"]["robots"])
    assert [r["name"] for r in robots] == ["alpha", "beta"]
    counts = rec.counts()
    for name in ("alpha", "beta"):
        assert counts[f"/{name}/truth/pose"] == 51          # 50 Hz over 1 s, and t = 0
        assert counts[f"/{name}/sensors/ir"] == 21
        assert counts[f"/bus/{name}/can"] > 0
        assert counts[f"/bus/{name}/serial/rangefinders"] > 0
    alpha = [m.json()["x"] for m in rec.topic("/alpha/truth/pose")]
    beta = [m.json()["x"] for m in rec.topic("/beta/truth/pose")]
    assert alpha[0] == 1.3 and beta[0] == 2.2
    with out.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    titles = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
    assert titles["/beta/sensors/ir"] == IrMessage.TITLE
    assert titles["/alpha/truth/pose"] == TruthPose.TITLE
