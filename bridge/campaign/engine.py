"""Run a campaign's cases on an executor and keep the results (docs/campaigns.md).

One code path for the local pool and a Dask cluster: every case is one
``executor.submit(run_case, task)``, results are taken as they complete
(:func:`concurrent.futures.as_completed`), and each is written out at once: results.json after
every run (so Ctrl-C loses only the runs in flight, and ``--resume`` finishes the rest), the
recording of a failure (all with ``--keep-all``) beside it. At the end, junit.xml and report.md.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Executor, Future, wait
from contextlib import AbstractContextManager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from koala_bridge.campaign.results import (
    fingerprint,
    n_runs,
    read_results,
    record_of,
    write_junit,
    write_results,
)
from koala_bridge.campaign.runner import CaseResult, CaseTask, StopSignal, run_case
from koala_bridge.campaign.spec import Campaign
from koala_bridge.core.errors import ConfigError
from koala_bridge.core.resources import config_dir

log = logging.getLogger(__name__)

#: An executor, its stop signal and what sets the signal (campaign/executors.py).
ExecutorFactory = Callable[[], AbstractContextManager[
    tuple[Executor, StopSignal, Callable[[], None]]]]


@dataclass
class CampaignOutcome:
    records: list[dict[str, Any]]     # every record of results.json, in campaign order
    selected: list[str]               # the cases this call was asked for (all, or --only's)
    ran: int                          # runs done this time
    complete: bool                    # every selected case has a record
    campaign_complete: bool           # every case of the campaign has one (results.json)
    results: Path
    junit: Path
    report: Path

    @property
    def selected_records(self) -> list[dict[str, Any]]:
        wanted = set(self.selected)
        return [r for r in self.records if r["case_id"] in wanted]

    @property
    def failed(self) -> int:
        """Failed runs among the selected cases."""
        return sum(r["verdict"] != "pass" for r in self.selected_records)


def tasks_of(campaign: Campaign, keep_all: bool, stop: StopSignal | None,
             only: Sequence[str] = ()) -> list[CaseTask]:
    """The campaign's cases (``only``: those ids, in the given order) as tasks."""
    cases = [campaign.case(c) for c in only] if only else list(campaign.cases)
    t = campaign.table
    return [CaseTask(c, t.firmware, t.sim_duration_s, t.wall_timeout_s, campaign.checks,
                     str(campaign.folder), str(config_dir()), keep_all, stop) for c in cases]


def run_campaign(
    campaign: Campaign,
    out: Path,
    executor: ExecutorFactory,
    *,
    only: Sequence[str] = (),
    resume: bool = False,
    keep_all: bool = False,
    on_result: Callable[[dict[str, Any]], None] = lambda record: None,
) -> CampaignOutcome:
    """Run the campaign's cases (``only`` those ids) into ``out``; ``resume``: keep the records
    of an earlier results.json whose fingerprint still matches and run only the others.

    With ``only``, the other cases' records of an earlier results.json of this campaign are kept
    (those whose fingerprint still matches): the re-run cases' records are replaced, and
    results.json, junit.xml and report.md hold the merged set ("complete" only when every case
    of the campaign has a record).

    ``on_result`` is called with each record as it is written (the progress bar). Ctrl-C
    (KeyboardInterrupt) sets the stop signal, lets the runs in flight end their processes,
    writes what finished and raises KeyboardInterrupt again."""
    out.mkdir(parents=True, exist_ok=True)
    results_path = out / "results.json"
    every = tasks_of(campaign, keep_all, None)
    tasks = tasks_of(campaign, keep_all, None, only) if only else every
    order = [t.case.case_id for t in every]
    selected = [t.case.case_id for t in tasks]
    doc = read_results(results_path) if resume or only else None
    if resume:
        if doc is None:
            raise ConfigError(f"--resume: no results.json of a campaign in {out}")
        if doc.get("campaign") != campaign.name:
            raise ConfigError(f"--resume: {results_path} is campaign {doc.get('campaign')!r}, "
                              f"not {campaign.name!r}")
    earlier: dict[str, dict[str, Any]] = {}
    if doc is not None and doc.get("campaign") == campaign.name:
        wanted = {t.case.case_id: fingerprint(t) for t in every}
        earlier = {r["case_id"]: r for r in doc.get("runs", [])
                   if wanted.get(r["case_id"]) == r.get("fingerprint")}
    elif doc is not None:
        log.warning("%s is campaign %r: replaced by %r's results", results_path,
                    doc.get("campaign"), campaign.name)
    previous = {c: r for c, r in earlier.items() if c in selected} if resume else {}
    # the records this call keeps: with --only, the other cases' too
    records = {c: r for c, r in earlier.items() if resume or c not in selected}
    header = {"campaign": campaign.name, "file": str(campaign.path), "order": order,
              "cases": len(order)}
    todo = [t for t in tasks if t.case.case_id not in previous]
    log.info("campaign %s: %s (%d already done)", campaign.name, n_runs(len(todo)),
             len(previous))
    interrupted = False
    ran = 0
    with executor() as (pool, stop, set_stop):
        futures: dict[Future[CaseResult], CaseTask] = {
            pool.submit(run_case, _with_stop(t, stop)): t for t in todo}
        try:
            for result, task in _completed(futures):
                if result.verdict == "interrupted":
                    continue
                record = _store(out, result, task)
                records[result.case_id] = record
                ran += 1
                write_results(results_path, header, records.values(), complete=False)
                on_result(record)
        except KeyboardInterrupt:
            interrupted = True
            set_stop()
            for f in futures:
                f.cancel()
            for result, task in _completed(futures, quiet=True):
                if result.verdict != "interrupted":  # finished before it saw the signal
                    records[result.case_id] = _store(out, result, task)
                    ran += 1
    campaign_complete = not interrupted and all(c in records for c in order)
    write_results(results_path, header, records.values(), complete=campaign_complete)
    ordered = [records[c] for c in order if c in records]
    junit = out / "junit.xml"
    write_junit(junit, campaign.name, ordered)
    from koala_bridge.campaign.report import write_report

    report = write_report(out, campaign.name, ordered,
                          {t.case.case_id: t.case.config for t in every}, campaign_complete)
    if interrupted:
        raise KeyboardInterrupt
    complete = all(c in records for c in selected)
    return CampaignOutcome(ordered, selected, ran, complete, campaign_complete, results_path,
                           junit, report)


def _with_stop(task: CaseTask, stop: StopSignal) -> CaseTask:
    from dataclasses import replace

    return replace(task, stop=stop)


def _completed(futures: dict[Future[CaseResult], CaseTask], quiet: bool = False
               ) -> Iterator[tuple[CaseResult, CaseTask]]:
    """Each future's result as it completes; a task that raised (a worker lost, a bug) is
    logged and skipped (no record: ``--resume`` runs it again); cancelled ones are skipped."""
    pending = set(futures)
    while pending:
        done, pending = wait(pending, return_when=FIRST_COMPLETED)
        for f in done:
            if f.cancelled():
                continue
            try:
                yield f.result(), futures[f]
            except Exception as e:  # noqa: BLE001 - reported, the campaign goes on
                if not quiet:
                    log.error("case %s did not run: %s: %s", futures[f].case.case_id,
                              type(e).__name__, e)


def _store(out: Path, result: CaseResult, task: CaseTask) -> dict[str, Any]:
    """Write the result's recording and, for a failure, its logs and firmware report into
    ``out``; its results.json record."""
    recording = None
    if result.recording is not None:
        path = out / "recordings" / f"{result.case_id}.mcap"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(result.recording)
        recording = path.relative_to(out).as_posix()
    if result.verdict != "pass":
        logs = out / "logs" / result.case_id
        logs.mkdir(parents=True, exist_ok=True)
        for name, text in result.logs.items():
            (logs / name).write_text(text, encoding="utf-8")
        if result.report:
            import json

            (logs / "report.json").write_text(json.dumps(result.report, indent=1))
    record = record_of(result, task, recording)
    log.info("%s: %s (%.1f s)", result.case_id, result.verdict, result.wall_s)
    return record
