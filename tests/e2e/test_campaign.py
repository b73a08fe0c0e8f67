"""``koala-bridge campaign`` end to end (issue 17): a small campaign run as a subprocess on the
local pool, the same campaign on a real Dask cluster on loopback (``dask scheduler`` and one
``dask worker`` started as processes), ``--only`` reproducing one case bit for bit, and Ctrl-C
followed by ``--resume``.

The firmware is ``_campaign_firmware.py`` (K-Team only): seed 0 stands still (passes), seed 1
drives into a wall (fails ``no_wall_contact``); 10 simulated seconds a run. The verdicts, the
figures and each run's outcome digest (SHA-256 over the truth, every sensor and every frame the
robot sent: ``campaign/truth.py``) must be the same wherever a case runs.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

FIRMWARE = Path(__file__).with_name("_campaign_firmware.py")
CAMPAIGN = f"""\
[campaign]
name = "tiny"
firmware = ["{{python}}", "{FIRMWARE}", "{{endpoints}}", "--seed", "{{seed}}",
            "--duration", "{{duration_s}}", "--period", "0.05", "--report", "{{report}}"]
sim_duration_s = 10.0
wall_timeout_s = 120.0
set = ["lockstep.period_s=0.05", "buses.rangefinders.enabled=false"]
[matrix]
worlds = ["lab_walls_1"]
seeds = [0, 1]
[matrix.faults]
none = []
can_drop = ["drop:can:probability=0.1"]
[checks]
exit_code = true
no_wall_contact = true
coverage_min_percent = 0.0
no_bus_errors = true
"""
CASES = ["lab_walls_1-s0-none-base", "lab_walls_1-s0-can_drop-base",
         "lab_walls_1-s1-none-base", "lab_walls_1-s1-can_drop-base"]


def campaign(tmp: Path, *args: str, check: int | None = None,
             env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    p = subprocess.run([sys.executable, "-m", "koala_bridge", "campaign", str(tmp / "c.toml"),
                        *args], capture_output=True, text=True, timeout=300, env=env)
    if check is not None:
        assert p.returncode == check, p.stdout + p.stderr
    return p


def runs(out: Path) -> dict[str, dict[str, Any]]:
    doc = json.loads((out / "results.json").read_text())
    return {r["case_id"]: r for r in doc["runs"]}


def no_process_mentions(text: str) -> list[str]:
    """Command lines of processes that mention ``text`` (a run's temporary folder)."""
    found = []
    for pid in os.listdir("/proc"):
        try:
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
        except OSError:
            continue
        if text in cmd and pid != str(os.getpid()):
            found.append(cmd)
    return found


@pytest.fixture(scope="module")
def local(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The tiny campaign on the local pool (2 workers)."""
    tmp = tmp_path_factory.mktemp("campaign")
    (tmp / "c.toml").write_text(CAMPAIGN)
    campaign(tmp, "--out", str(tmp / "local"), "--workers", "2", check=1)
    return tmp


def test_local_pool_judges_every_run_and_writes_results_junit_and_report(local: Path) -> None:
    out = local / "local"
    r = runs(out)
    assert list(r) == CASES
    assert {c: r[c]["verdict"] for c in CASES} == {
        CASES[0]: "pass", CASES[1]: "pass", CASES[2]: "fail", CASES[3]: "fail"}
    failed = {c["name"] for c in r[CASES[2]]["checks"] if not c["passed"]}
    assert failed == {"no_wall_contact"}
    assert r[CASES[2]]["figures"]["min_clearance_m"] <= 0 < r[CASES[0]]["figures"][
        "min_clearance_m"]
    assert r[CASES[0]]["figures"]["sim_time_s"] == pytest.approx(10.0)
    # the time of the closest approach, named so that a passing run's cannot read as a contact
    assert "contact_t_s" not in r[CASES[0]]["figures"]
    assert 0 <= r[CASES[0]]["figures"]["min_clearance_t_s"] <= 10.0
    (clear,) = [c for c in r[CASES[0]]["checks"] if c["name"] == "no_wall_contact"]
    assert clear["message"].endswith("(closest approach, no contact)")
    assert all(r[c]["startup_s"] > 0 and r[c]["firmware_exit"] == 0 for c in CASES)
    # recordings for failures only; the report plots them
    assert r[CASES[0]]["recording"] is None
    assert (out / r[CASES[2]]["recording"]).stat().st_size > 0
    assert sorted(p.name for p in (out / "recordings").iterdir()) == sorted(
        f"{c}.mcap" for c in CASES[2:])
    assert (out / "plots" / f"{CASES[2]}.png").stat().st_size > 0
    report = (out / "report.md").read_text()
    assert "| lab_walls_1 | 0 | pass | pass |" in report
    assert "| lab_walls_1 | 1 | **FAIL** | **FAIL** |" in report
    assert f"plots/{CASES[3]}.png" in report
    suite = ET.parse(out / "junit.xml").getroot().find("testsuite")
    assert suite is not None and (suite.get("tests"), suite.get("failures")) == ("4", "2")
    # the dropped CAN frames change the run: different outcome digests
    assert r[CASES[2]]["figures"]["digest"] != r[CASES[3]]["figures"]["digest"]


def test_only_reproduces_cases_bit_for_bit_and_keep_all_keeps_every_recording(
        local: Path) -> None:
    out = local / "only"
    campaign(local, "--only", CASES[3], "--only", CASES[0], "--keep-all", "--out", str(out),
             "--workers", "2", check=1)
    again, first = runs(out), runs(local / "local")
    assert list(again) == [CASES[0], CASES[3]]  # in campaign order
    assert json.loads((out / "results.json").read_text())["complete"] is False  # 2 of 4
    for case in (CASES[3], CASES[0]):
        assert again[case]["figures"] == first[case]["figures"]  # the digest included
        assert again[case]["verdict"] == first[case]["verdict"]
        assert (out / again[case]["recording"]).stat().st_size > 0  # a pass's too


def test_only_into_an_earlier_out_folder_merges_its_record_with_the_others(
        local: Path) -> None:
    out = local / "merged"
    shutil.copytree(local / "local", out)
    doc = json.loads((out / "results.json").read_text())
    doc["runs"][0]["wall_s"] = 12345.0  # marks the record the re-run must replace
    (out / "results.json").write_text(json.dumps(doc))
    p = campaign(local, "--only", CASES[0], "--out", str(out), "--workers", "1", check=0)
    assert "1 of 1 run passed (1 run now); results.json holds 4 of 4 cases;" in p.stdout
    merged, first = runs(out), runs(local / "local")
    assert list(merged) == CASES
    assert merged[CASES[0]]["wall_s"] != 12345.0
    assert merged[CASES[0]]["figures"] == first[CASES[0]]["figures"]
    for case in CASES[1:]:
        assert merged[case] == first[case]
    assert json.loads((out / "results.json").read_text())["complete"] is True
    suite = ET.parse(out / "junit.xml").getroot().find("testsuite")
    assert suite is not None and (suite.get("tests"), suite.get("failures")) == ("4", "2")
    report = (out / "report.md").read_text()
    assert "2 of 4 runs passed." in report
    assert "| lab_walls_1 | 1 | **FAIL** | **FAIL** |" in report


@pytest.fixture
def dask_cluster(tmp_path: Path) -> Iterator[str]:
    """A Dask scheduler and one worker (1 process, 1 thread) on 127.0.0.1, as processes in
    their own groups; killed at the end. Yields the scheduler file's path."""
    sched_file = tmp_path / "scheduler.json"
    common = dict(cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                  start_new_session=True)
    procs = [subprocess.Popen(
        [sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1",
         "--port", "0", "--no-dashboard", "--scheduler-file", str(sched_file)], **common)]
    try:
        deadline = time.monotonic() + 60
        while not sched_file.exists():
            assert procs[0].poll() is None and time.monotonic() < deadline, "no scheduler"
            time.sleep(0.1)
        procs.append(subprocess.Popen(
            [sys.executable, "-m", "distributed.cli.dask_worker", "--scheduler-file",
             str(sched_file), "--nworkers", "1", "--nthreads", "1", "--host", "127.0.0.1",
             "--no-dashboard", "--local-directory", str(tmp_path / "dask")], **common))
        yield str(sched_file)
    finally:
        for p in reversed(procs):
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGTERM)
                try:
                    p.wait(timeout=20)
                except subprocess.TimeoutExpired:
                    os.killpg(p.pid, signal.SIGKILL)
                    p.wait()
            try:
                os.killpg(p.pid, signal.SIGKILL)  # a nanny's worker left behind
            except ProcessLookupError:
                pass


def test_a_dask_cluster_on_loopback_gives_the_local_verdicts_and_figures(
        local: Path, dask_cluster: str) -> None:
    out = local / "cluster"
    p = campaign(local, "--cluster", dask_cluster, "--out", str(out), check=1)
    assert "on the Dask cluster" in p.stderr
    on_cluster, on_pool = runs(out), runs(local / "local")
    assert list(on_cluster) == CASES
    for case in CASES:
        assert on_cluster[case]["verdict"] == on_pool[case]["verdict"], case
        assert on_cluster[case]["checks"] == on_pool[case]["checks"], case
        assert on_cluster[case]["figures"] == on_pool[case]["figures"], case
    # failures ship their recordings back to the submitting machine
    assert sorted(p.name for p in (out / "recordings").iterdir()) == sorted(
        f"{c}.mcap" for c in CASES[2:])


def test_resources_no_worker_offers_fail_at_once_instead_of_waiting_for_ever(
        tmp_path: Path, dask_cluster: str) -> None:
    """The fixture's worker offers no resources; a campaign asking for one would wait for ever
    (Dask keeps such tasks pending): it fails before submitting, exit 2, one line."""
    text = CAMPAIGN.replace("wall_timeout_s = 120.0", "wall_timeout_s = 120.0\n"
                            "resources = { simulators = 1 }")
    (tmp_path / "c.toml").write_text(text)
    p = campaign(tmp_path, "--cluster", dask_cluster, "--out", str(tmp_path / "out"), check=2)
    assert "offers the campaign's resources simulators=1 (what its workers offer: none)" in (
        p.stderr)
    assert "--resources \"simulators=1\"" in p.stderr
    assert not (tmp_path / "out" / "results.json").exists()


def _ignore_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)


@pytest.mark.parametrize("sigint_ignored", [False, True], ids=["foreground", "background"])
def test_ctrl_c_stops_cleanly_and_resume_runs_the_rest(tmp_path: Path,
                                                       sigint_ignored: bool) -> None:
    """Ctrl-C, and SIGINT to a campaign started with SIGINT ignored: what a non-interactive
    shell does to `koala-bridge campaign c.toml &` (Python then keeps SIG_IGN)."""
    (tmp_path / "c.toml").write_text(CAMPAIGN)
    runs_tmp = tmp_path / "tmp"
    runs_tmp.mkdir()
    env = {**os.environ, "TMPDIR": str(runs_tmp)}  # where the runs' folders go
    out = tmp_path / "out"
    proc = subprocess.Popen(
        [sys.executable, "-m", "koala_bridge", "campaign", str(tmp_path / "c.toml"),
         "--out", str(out), "--workers", "1"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
        preexec_fn=_ignore_sigint if sigint_ignored else None)
    try:
        deadline = time.monotonic() + 120
        while not ((out / "results.json").exists() and runs(out)):
            assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
            time.sleep(0.05)
        proc.send_signal(signal.SIGINT)  # as Ctrl-C in a terminal
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 130, err
    assert "--resume" in err
    doc = json.loads((out / "results.json").read_text())
    assert doc["complete"] is False
    done = [r["case_id"] for r in doc["runs"]]
    assert 1 <= len(done) < len(CASES)
    assert not no_process_mentions(str(runs_tmp)), "a bridge or firmware outlived the campaign"
    assert not list(runs_tmp.iterdir()), "a run's folder was left behind"

    p = campaign(tmp_path, "--out", str(out), "--resume", "--workers", "2", check=1, env=env)
    doc = json.loads((out / "results.json").read_text())
    assert doc["complete"] is True
    assert [r["case_id"] for r in doc["runs"]] == CASES
    assert f"({len(CASES) - len(done)} run now)" in p.stdout


def test_one_case_of_the_example_campaign_runs_with_the_coverage_firmware(
        tmp_path: Path) -> None:
    """The example (examples/campaign_coverage.toml) cut to 15 simulated seconds: the coverage
    firmware finds every bus on its free port (MAVLink on udpout: it says hello first), calibrates
    and starts localising; it does not finish in 15 s, so exit_code fails and the others pass."""
    examples = Path(__file__).resolve().parents[2] / "examples"
    text = (examples / "campaign_coverage.toml").read_text()
    firmware = json.dumps(str(examples / "coverage_firmware.py"))
    text = text.replace('"coverage_firmware.py"', firmware)
    text = text.replace("sim_duration_s = 450.0", "sim_duration_s = 15.0")
    (tmp_path / "c.toml").write_text(text)
    case = "lab_walls_1-s0-gyro_bias_step-base"
    campaign(tmp_path, "--only", case, "--out", str(tmp_path / "out"), check=1)
    (run,) = runs(tmp_path / "out").values()
    checks = {c["name"]: c["passed"] for c in run["checks"]}
    assert checks == {"exit_code": False, "sim_time_advanced": True, "no_wall_contact": True,
                      "coverage_min_percent": False,
                      "localisation_error_max_m": False, "no_bus_errors": True}, run["checks"]
    assert run["firmware_exit"] == 1 and not run["timed_out"]
    # the firmware ended on its budget (the bridge runs 1 s past it, campaign/runner.py)
    assert run["figures"]["sim_time_s"] == pytest.approx(15.0, abs=0.05)
    log = (tmp_path / "out" / "logs" / case / "report.json").read_text()
    assert json.loads(log)["ended"] == "robot-time budget"


def test_a_firmware_that_never_cycles_fails_sim_time_advanced(tmp_path: Path) -> None:
    """The firmware reads the endpoints file and exits 0 without a cycle message: nothing was
    simulated (held at t = 0), which must not pass -- whatever the other checks say."""
    text = CAMPAIGN.replace('"--report", "{report}"]', '"--report", "{report}", "--no-cycle"]')
    text = text.replace("[checks]\n", "[checks]\nsim_time_min_s = 5.0\n")
    (tmp_path / "c.toml").write_text(text)
    case = CASES[0]
    campaign(tmp_path, "--only", case, "--out", str(tmp_path / "out"), check=1)
    (run,) = runs(tmp_path / "out").values()
    assert run["verdict"] == "fail" and run["firmware_exit"] == 0
    checks = {c["name"]: c for c in run["checks"]}
    assert checks["exit_code"]["passed"] and checks["no_wall_contact"]["passed"]
    assert not checks["sim_time_advanced"]["passed"]
    assert checks["sim_time_advanced"]["message"].startswith(
        "the firmware exited after 0.0 s of simulated time: it never sent a cycle message")
    assert not checks["sim_time_min_s"]["passed"]
