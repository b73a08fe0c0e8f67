"""The checks that decide a run's verdict, and the run's figures.

Built-in checks (``[checks]`` keys, docs/campaigns.md) judge the recording's truth, never what
the firmware says about itself (except the localisation check, which compares the firmware's
reported estimates with the truth):

``exit_code``                the firmware exited 0 within the wall-clock timeout
``sim_time_advanced``        simulated time moved past 0 (a run where nothing was simulated --
                             the firmware never sent a cycle message -- proves nothing)
``sim_time_min_s``           simulated time reached at least X s
``no_wall_contact``          the body circle (``robot.body_radius_m``) never reached a wall
``coverage_min_percent``     the truth passed near the centre of at least X % of the cells
                             reachable from where the robot started
``localisation_error_max_m`` every estimate of the firmware's report within Y m of the truth
``no_bus_errors``            the robot rejected no frame the firmware sent (``status``)

A user check is ``MODULE:FUNCTION`` or ``FILE.py:FUNCTION``; the function gets a
:class:`RunOutcome` and returns ``True``/``False`` or ``(passed, message)``. It is imported where
the case runs (a cluster worker: the module must be importable there, the file present).
"""

from __future__ import annotations

import importlib
import importlib.util
import math
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from koala_bridge.campaign.spec import ChecksTable, _user_check_spec
from koala_bridge.campaign.truth import (
    body_clearance_bound,
    estimate_errors,
    firmware_bus_rejections,
    first_visits,
    outcome_digest,
    reachable_cells,
    truth_track,
    wall_segments,
)
from koala_bridge.core.grid import Grid
from koala_bridge.recording.mcap_file import Recording, RecordingError, open_recording


@dataclass(frozen=True)
class CheckResult:
    name: str
    passed: bool
    message: str = ""


@dataclass
class RunOutcome:
    """What a run left behind, as a user check sees it."""

    case_id: str
    axes: dict[str, Any]
    run_dir: Path
    recording: Path                 # the bridge's MCAP recording
    config: dict[str, Any]          # the bridge configuration the run used
    report: dict[str, Any]          # the firmware's JSON report ({} if it wrote none)
    returncode: int | None          # the firmware's exit status (None: killed at the timeout)
    timed_out: bool
    _recording: Recording | None = field(default=None, repr=False)

    def open(self) -> Recording:
        """The recording, read once (``recording.topic("/truth/pose")``, ...)."""
        if self._recording is None:
            self._recording = open_recording(self.recording)
        return self._recording


def judge(run: RunOutcome, checks: ChecksTable, campaign_dir: Path
          ) -> tuple[list[CheckResult], dict[str, Any]]:
    """Every enabled check of ``checks`` on ``run``, and the run's figures (numbers for
    results.json: simulated time, coverage, clearance, localisation error, rejections, the
    outcome digest)."""
    results: list[CheckResult] = []
    if checks.exit_code:
        if run.timed_out:
            results.append(CheckResult("exit_code", False, "wall-clock timeout"))
        else:
            results.append(CheckResult("exit_code", run.returncode == 0,
                                       f"the firmware exited {run.returncode}"))
    try:
        rec = run.open()
    except (RecordingError, OSError) as e:
        rec = None
        figures: dict[str, Any] = {"recording_error": str(e)}
    else:
        figures = _figures(run, rec)
    needs_recording = [name for name, on in (
        ("sim_time_advanced", checks.sim_time_advanced),
        ("sim_time_min_s", checks.sim_time_min_s is not None),
        ("no_wall_contact", checks.no_wall_contact),
        ("coverage_min_percent", checks.coverage_min_percent is not None),
        ("localisation_error_max_m", checks.localisation_error_max_m is not None),
        ("no_bus_errors", checks.no_bus_errors)) if on]
    if rec is None:
        results += [CheckResult(n, False, "no readable recording") for n in needs_recording]
    else:
        results += _sim_time_checks(run, checks, figures.get("sim_time_s"))
        if checks.no_wall_contact:
            c = figures.get("min_clearance_m")
            results.append(CheckResult(
                "no_wall_contact", c is not None and c > 0,
                "no truth" if c is None else (
                    f"closest body-to-wall distance {c:+.4f} m at t = "
                    f"{figures['min_clearance_t_s']:.2f} s"
                    + (" (wall contact)" if c <= 0 else " (closest approach, no contact)"))))
        if checks.coverage_min_percent is not None:
            cov = figures.get("coverage_percent")
            results.append(CheckResult(
                "coverage_min_percent", cov is not None and cov >= checks.coverage_min_percent,
                "no truth" if cov is None else
                f"covered {cov:.1f} % of {figures['reachable_cells']} reachable cells "
                f"(>= {checks.coverage_min_percent:g} % needed)"))
        if checks.localisation_error_max_m is not None:
            err = figures.get("localisation_error_max_m")
            results.append(CheckResult(
                "localisation_error_max_m",
                err is not None and err <= checks.localisation_error_max_m,
                "the firmware reported no estimate" if err is None else
                f"largest estimate error {err:.3f} m (<= "
                f"{checks.localisation_error_max_m:g} m allowed)"))
        if checks.no_bus_errors:
            bad = {b: n for b, n in figures.get("rejected_frames", {}).items() if n}
            results.append(CheckResult(
                "no_bus_errors", not bad,
                "no frame rejected" if not bad else
                "rejected: " + ", ".join(f"{b} {n}" for b, n in bad.items())))
    for spec in checks.user:
        results.append(run_user_check(spec, run, campaign_dir))
    return results, figures


def _sim_time_checks(run: RunOutcome, checks: ChecksTable, t: float | None
                     ) -> list[CheckResult]:
    """``sim_time_advanced`` and ``sim_time_min_s``: how far simulated time went (the last truth
    sample's time), said as what happened."""
    out: list[CheckResult] = []
    ended = ("the firmware exited" if run.returncode is not None and not run.timed_out
             else "the run ended")
    reached = 0.0 if t is None else t
    if checks.sim_time_advanced:
        if reached > 0:
            out.append(CheckResult("sim_time_advanced", True, f"simulated {reached:g} s"))
        else:
            lockstep = run.config.get("lockstep", {})
            what = f"{lockstep.get('cycle_bus', 'kteam')} {lockstep.get('cycle_message', 'D')!r}"
            out.append(CheckResult(
                "sim_time_advanced", False,
                f"{ended} after {reached:.1f} s of simulated time: it never sent a cycle "
                f"message ({what}, [lockstep] in docs/protocols.md section 6)"))
    if checks.sim_time_min_s is not None:
        out.append(CheckResult(
            "sim_time_min_s", reached >= checks.sim_time_min_s,
            f"{ended} after {reached:g} s of simulated time (>= {checks.sim_time_min_s:g} s "
            "needed)"))
    return out


def _figures(run: RunOutcome, rec: Recording) -> dict[str, Any]:
    track = truth_track(rec)
    out: dict[str, Any] = {"digest": outcome_digest(rec), "truth_samples": len(track)}
    if len(track) == 0:
        return out
    out["sim_time_s"] = round(float(track[-1, 0]), 6)
    out["distance_m"] = round(float(np.sum(np.hypot(*np.diff(track[:, 1:3], axis=0).T))), 6)
    radius = float(run.config.get("robot", {}).get("body_radius_m", 0.0))
    try:
        segments = wall_segments(rec)
    except ValueError:
        segments = np.empty((0, 4))
    bound = body_clearance_bound(track, segments)
    if len(bound) and np.isfinite(bound).any():
        worst = int(np.argmin(bound))
        out["min_clearance_m"] = round(float(bound[worst] - radius), 6)
        # the time of closest approach (a wall contact only when min_clearance_m <= 0)
        out["min_clearance_t_s"] = round(float(track[worst, 0]), 6)
    world = Grid.from_dict(run.config["world"])
    start = world.cell_of(track[0, 1], track[0, 2])
    reachable = reachable_cells(world, start)
    visits = first_visits(track, world)
    out["reachable_cells"] = len(reachable)
    out["visited_cells"] = len(reachable & set(visits))
    out["coverage_percent"] = round(100.0 * out["visited_cells"] / len(reachable), 6)
    errors = estimate_errors(run.report, track)
    if len(errors):
        out["localisation_error_max_m"] = round(float(errors[:, 1].max()), 6)
        out["localisation_error_final_m"] = round(float(errors[-1, 1]), 6)
    out["rejected_frames"] = firmware_bus_rejections(rec)
    return out


def run_user_check(spec: str, run: RunOutcome, campaign_dir: Path) -> CheckResult:
    """Import and call the user check ``spec``; an exception is a failed check saying so."""
    try:
        func = load_user_check(spec, campaign_dir)
        answer = func(run)
    except Exception as e:  # a user's bug fails its check, not the campaign
        return CheckResult(spec, False, f"the check raised {type(e).__name__}: {e}")
    if isinstance(answer, tuple) and len(answer) == 2:
        return CheckResult(spec, bool(answer[0]), str(answer[1]))
    if isinstance(answer, bool | np.bool_):
        return CheckResult(spec, bool(answer))
    return CheckResult(spec, False, f"the check returned {answer!r}, not a bool or "
                                    "(bool, message)")


def load_user_check(spec: str, campaign_dir: Path) -> Callable[[RunOutcome], Any]:
    where, name = _user_check_spec(spec, campaign_dir)
    if where.endswith(".py"):
        module_name = f"koala_campaign_check_{abs(hash(where))}"
        mspec = importlib.util.spec_from_file_location(module_name, where)
        if mspec is None or mspec.loader is None:
            raise ImportError(f"cannot load {where}")
        module = importlib.util.module_from_spec(mspec)
        mspec.loader.exec_module(module)
    else:
        module = importlib.import_module(where)
    func = getattr(module, name)
    if not callable(func):
        raise TypeError(f"{spec} is not a function")
    return func  # type: ignore[no-any-return]


def verdict(results: list[CheckResult]) -> str:
    return "pass" if all(r.passed for r in results) else "fail"


def jsonable(value: Any) -> Any:
    """``value`` with dataclasses as dicts and non-finite floats as None (strict JSON)."""
    if isinstance(value, CheckResult):
        return asdict(value)
    if isinstance(value, Mapping):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [jsonable(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, np.generic):
        return jsonable(value.item())
    return value
