"""One case, run where a worker runs it: the bridge and the firmware as two process groups in a
temporary folder of their own, then the checks; back comes a small :class:`CaseResult` (and the
recording's bytes for a failure, or for every run with ``--keep-all``).

Isolation: every port is 0 (the bridge binds free ones and names them in its endpoints file),
each run has its own ptys, Zenoh prefix and folder, so any number of runs share a host. Every run
is lockstep (docs/protocols.md §6): the same case gives the same outcome, bit for bit.

:func:`run_case` is the function the pool or the Dask cluster calls: a module-level function of
picklable arguments. It never raises for a run that went wrong (that is a failed verdict); it
returns ``verdict = "interrupted"`` when the campaign's stop signal is set mid-run.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import tomli_w
from koala_bridge.campaign.checks import CheckResult, RunOutcome, judge, verdict
from koala_bridge.campaign.spec import Case, ChecksTable
from koala_bridge.core.resources import config_dir

log = logging.getLogger(__name__)

#: Wall seconds the bridge may take to announce its endpoints.
START_TIMEOUT_S = 60.0
#: After the bridge ended (its --duration), wall seconds the firmware gets to notice its link
#: is gone and end by itself (writing its report).
GRACE_S = 20.0
#: After the firmware ended, wall seconds the bridge gets to end by itself: in lockstep nothing
#: can advance it any more. The firmware closing its port ends it at once; one that never
#: opened it (exited before its first cycle) leaves it held at t = 0, and SIGTERM stops it as
#: cleanly (its recording closed), so waiting longer only wastes the run's wall time.
BRIDGE_GRACE_S = 3.0
#: Between SIGTERM and SIGKILL of a process group.
TERM_WAIT_S = 10.0
POLL_S = 0.05
#: The bridge runs this many simulated seconds past ``sim_duration_s``: a firmware told its
#: budget (``{duration_s}``) and ending when it has passed it then ends by itself, its report
#: written, instead of losing its link in the middle of its last cycle.
DURATION_MARGIN_S = 1.0
LOG_TAIL = 4000


class StopSignal(Protocol):
    """Set when the campaign is stopped (Ctrl-C); a run polls it and ends its processes."""

    def is_set(self) -> bool: ...


@dataclass(frozen=True)
class CaseTask:
    """Everything a worker needs to run one case (picklable; no file of the submitting machine
    is read on the worker, except the firmware and user checks the campaign names)."""

    case: Case
    firmware: tuple[str, ...]
    sim_duration_s: float
    wall_timeout_s: float
    checks: ChecksTable
    campaign_dir: str
    shipped_dir: str            # config_dir() where the campaign was loaded
    keep_recording: bool        # send the recording back even when the run passes
    stop: StopSignal | None = None


@dataclass
class CaseResult:
    case_id: str
    axes: dict[str, Any]
    verdict: str                # pass | fail | interrupted
    checks: list[CheckResult]
    figures: dict[str, Any]
    wall_s: float
    startup_s: float | None     # bridge start until its endpoints file appeared
    returncode: int | None
    timed_out: bool
    host: str
    report: dict[str, Any] = field(default_factory=dict)
    logs: dict[str, str] = field(default_factory=dict)   # tails of bridge.log, firmware.log
    recording: bytes | None = None


class _Interrupted(Exception):
    pass


def run_case(task: CaseTask) -> CaseResult:
    """Run ``task``'s case in a fresh temporary folder, judge it, remove the folder."""
    t0 = time.monotonic()
    if task.stop is not None and task.stop.is_set():  # stopped before it started
        return CaseResult(task.case.case_id, task.case.axes, "interrupted", [], {}, 0.0, None,
                          None, False, socket.gethostname())
    run_dir = Path(tempfile.mkdtemp(prefix=f"koala-campaign-{task.case.case_id}-"))
    try:
        return _run_in(task, run_dir, t0)
    finally:
        shutil.rmtree(run_dir, ignore_errors=True)


def _run_in(task: CaseTask, run_dir: Path, t0: float) -> CaseResult:
    case = task.case
    config = _rerooted(case.config, task.shipped_dir)
    paths = {name: run_dir / f for name, f in (
        ("config", "bridge.toml"), ("world", "world.toml"), ("endpoints", "endpoints.json"),
        ("recording", "run.mcap"), ("report", "report.json"))}
    paths["config"].write_bytes(tomli_w.dumps(config).encode())
    paths["world"].write_bytes(tomli_w.dumps({"world": config["world"]}).encode())
    campaign_dir = Path(task.campaign_dir)
    cwd = campaign_dir if campaign_dir.is_dir() else run_dir
    values = {"python": sys.executable, "seed": str(case.seed),
              "duration_s": f"{task.sim_duration_s:g}", "run_dir": str(run_dir),
              "campaign_dir": str(campaign_dir),
              **{k: str(paths[k]) for k in ("endpoints", "config", "world", "report")}}
    firmware_cmd = [word.format_map(values) for word in task.firmware]
    env = {**os.environ, "KOALA_ENDPOINTS_FILE": values["endpoints"],
           "KOALA_CONFIG": values["config"], "KOALA_WORLD": values["world"],
           "KOALA_SEED": values["seed"], "KOALA_REPORT": values["report"],
           "KOALA_RUN_DIR": values["run_dir"]}
    bridge_cmd = [sys.executable, "-m", "koala_bridge", "run", "--clock", "lockstep",
                  "--config", str(paths["config"]), "--seed", str(case.seed),
                  "--duration", f"{task.sim_duration_s + DURATION_MARGIN_S!r}",
                  "--record", str(paths["recording"]),
                  "--endpoints-file", str(paths["endpoints"]), "--log-level", "WARNING"]
    startup_s: float | None = None
    returncode: int | None = None
    timed_out = False
    deadline = t0 + task.wall_timeout_s
    procs: list[subprocess.Popen[bytes]] = []
    try:
        with open(run_dir / "bridge.log", "wb") as blog, \
                open(run_dir / "firmware.log", "wb") as flog:
            bridge = subprocess.Popen(bridge_cmd, stdout=blog, stderr=subprocess.STDOUT,
                                      stdin=subprocess.DEVNULL, start_new_session=True)
            procs.append(bridge)
            start_deadline = min(deadline, time.monotonic() + START_TIMEOUT_S)
            while not paths["endpoints"].exists():
                _check_stop(task)
                if bridge.poll() is not None or time.monotonic() > start_deadline:
                    break
                time.sleep(POLL_S)
            if paths["endpoints"].exists():
                startup_s = time.monotonic() - t0
                firmware = subprocess.Popen(firmware_cmd, cwd=cwd, env=env, stdout=flog,
                                            stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                            start_new_session=True)
                procs.append(firmware)
                returncode, timed_out = _wait_both(task, bridge, firmware, deadline)
            else:
                flog.write(b"(not started: the bridge did not announce its endpoints)\n")
                timed_out = bridge.poll() is None
    except _Interrupted:
        end_groups(procs)
        return CaseResult(case.case_id, case.axes, "interrupted", [], {},
                          time.monotonic() - t0, startup_s, None, False, socket.gethostname())
    except OSError as e:  # the firmware command cannot start: a failed run that says why
        (run_dir / "firmware.log").write_text(f"cannot start {firmware_cmd}: {e}\n")
        returncode = None
    finally:
        end_groups(procs)
    report = _read_report(paths["report"])
    outcome = RunOutcome(case.case_id, case.axes, run_dir, paths["recording"], config, report,
                         returncode, timed_out)
    results, figures = judge(outcome, task.checks, Path(task.campaign_dir))
    if startup_s is None:
        results.insert(0, CheckResult("bridge_started", False,
                                      "the bridge did not announce its endpoints"))
    result = CaseResult(
        case.case_id, case.axes, verdict(results), results, figures,
        time.monotonic() - t0, startup_s, returncode, timed_out, socket.gethostname(), report,
    )
    if result.verdict != "pass":
        result.logs = {name: _tail(run_dir / name) for name in ("bridge.log", "firmware.log")}
    if (result.verdict != "pass" or task.keep_recording) and paths["recording"].exists():
        result.recording = paths["recording"].read_bytes()
    return result


def _wait_both(task: CaseTask, bridge: subprocess.Popen[bytes],
               firmware: subprocess.Popen[bytes], deadline: float) -> tuple[int | None, bool]:
    """Wait for both processes; the firmware's exit status and whether the wall clock ran out."""
    first_end: float | None = None
    while True:
        _check_stop(task)
        fw, br = firmware.poll(), bridge.poll()
        now = time.monotonic()
        if fw is not None and br is not None:
            return fw, False
        if now > deadline:
            end_groups([firmware, bridge])
            return firmware.poll() if fw is not None else None, True
        if fw is not None or br is not None:
            first_end = first_end or now
            grace = BRIDGE_GRACE_S if br is None else GRACE_S
            if now - first_end > grace:  # the other side did not follow: end it
                end_groups([firmware, bridge])
                return firmware.returncode, False
        time.sleep(POLL_S)


def _check_stop(task: CaseTask) -> None:
    if task.stop is not None and task.stop.is_set():
        raise _Interrupted


def end_groups(procs: Sequence[subprocess.Popen[bytes]]) -> None:
    """SIGTERM each still-running process's group (the bridge then closes its recording), then,
    in order, SIGKILL each group still there after :data:`TERM_WAIT_S` (processes started with
    ``start_new_session``)."""
    for p in procs:
        if p.poll() is None:
            _signal_group(p, signal.SIGTERM)
    for p in procs:
        try:
            p.wait(timeout=TERM_WAIT_S)
        except subprocess.TimeoutExpired:
            _signal_group(p, signal.SIGKILL)
            p.wait()
        _signal_group(p, signal.SIGKILL)  # children the leader left behind


def _signal_group(p: subprocess.Popen[bytes], sig: int) -> None:
    try:
        os.killpg(p.pid, sig)  # start_new_session: the group id is the leader's pid
    except (ProcessLookupError, PermissionError):
        pass


def _read_report(path: Path) -> dict[str, Any]:
    try:
        report = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return report if isinstance(report, dict) else {}


def _tail(path: Path) -> str:
    try:
        return path.read_bytes()[-LOG_TAIL:].decode("utf-8", "replace")
    except OSError:
        return ""


def _rerooted(config: dict[str, Any], shipped_dir: str) -> dict[str, Any]:
    """``config`` with file paths into the submitting machine's shipped config folder moved to
    this machine's (a cluster worker may have koala-bridge installed elsewhere)."""
    here = str(config_dir())
    if shipped_dir == here:
        return config
    import copy

    from koala_bridge.runtime.settings import PATH_KEYS

    out = copy.deepcopy(config)
    for keys in PATH_KEYS:
        table: Any = out
        for k in keys[:-1]:
            table = table.get(k) if isinstance(table, dict) else None
        value = table.get(keys[-1]) if isinstance(table, dict) else None
        if isinstance(value, str) and value.startswith(shipped_dir) and not Path(value).exists():
            table[keys[-1]] = here + value[len(shipped_dir):]
    return out
