"""``bench/fuzz.py`` (``make fuzz``) with tiny counts, so the soak/fuzz script cannot rot: it
starts a bridge, attacks every bus, stops it, and reports in the documented shape."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def test_fuzz_bench_runs_and_reports_no_crash(tmp_path: Path) -> None:
    report_path = tmp_path / "report.json"
    counts = {"kteam": 60, "socketcand": 60, "mavlink": 60, "zenoh": 10}
    args = [f"--{bus}={n}" for bus, n in counts.items()]
    done = subprocess.run(
        [sys.executable, str(REPO / "bench" / "fuzz.py"), *args, "--reconnects=2", "--batch=30",
         "--silent-clients=1", "--json", str(report_path), "--workdir", str(tmp_path / "run")],
        cwd=REPO, capture_output=True, text=True, timeout=280,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    for line in ("inputs tried", "crashes", "hangs", "rejected", "peak RSS"):
        assert line in done.stdout
    report = json.loads(report_path.read_text())
    assert report["ok"] is True
    assert report["crashes"] == [] and report["hangs"] == []
    assert report["client_errors"] == []
    assert {bus: report["inputs"][bus] for bus in counts} == counts
    assert report["probes"] >= 2  # after each K-Team batch and at the end
    assert set(report["reconnects"]) >= {"kteam", "rangefinders", "socketcand", "zenoh"}
    assert report["status_seen"] is True
    # Every bus the bridge serves is in its counters, and the garbage was counted as such.
    assert {"kteam", "mavlink", "can.socketcand"} <= set(report["rejected"])
    assert report["rejected"]["kteam"] > 0 and report["rejected"]["mavlink"] > 0
    assert report["peak_rss_kib"] is None or report["peak_rss_kib"] > 0
