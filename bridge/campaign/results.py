"""What a campaign leaves in its output folder for people and CI.

* ``results.json``: one record per finished run (axes, verdict, checks, figures, wall time,
  recording path), rewritten atomically after each run, so an interrupted campaign keeps what it
  finished and ``--resume`` runs only the rest;
* ``junit.xml``: each run a ``<testcase>`` (a failed check is its ``<failure>``), the format CI
  systems show (GitLab, Jenkins, GitHub actions that publish test reports);
* ``recordings/CASE.mcap`` for failures (all runs with ``--keep-all``), ``logs/CASE/`` the tails
  of the bridge's and the firmware's logs of a failure.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
import xml.etree.ElementTree as ET
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from koala_bridge.campaign.checks import jsonable
from koala_bridge.campaign.runner import CaseResult, CaseTask

RESULTS_VERSION = 1


def n_runs(n: int) -> str:
    """``"1 run"``, ``"4 runs"``."""
    return f"{n} run{'' if n == 1 else 's'}"


def fingerprint(task: CaseTask) -> str:
    """What makes a run's outcome: the case's config and faults, the firmware command, the
    duration and the checks. ``--resume`` reuses a record only when this is unchanged."""
    what = {"config": task.case.config, "firmware": task.firmware,
            "sim_duration_s": task.sim_duration_s, "checks": repr(task.checks)}
    return hashlib.sha256(json.dumps(jsonable(what), sort_keys=True).encode()).hexdigest()[:16]


def record_of(result: CaseResult, task: CaseTask, recording: str | None) -> dict[str, Any]:
    """A results.json record of ``result``."""
    return jsonable({
        "case_id": result.case_id,
        "axes": result.axes,
        "verdict": result.verdict,
        "checks": result.checks,
        "figures": result.figures,
        "wall_s": round(result.wall_s, 3),
        "startup_s": None if result.startup_s is None else round(result.startup_s, 3),
        "firmware_exit": result.returncode,
        "timed_out": result.timed_out,
        "host": result.host,
        "recording": recording,
        "fingerprint": fingerprint(task),
    })


def write_results(path: Path, campaign: Mapping[str, Any], records: Iterable[Mapping[str, Any]],
                  complete: bool) -> None:
    """results.json, atomically (a temporary file, then a rename)."""
    doc = {"version": RESULTS_VERSION, **campaign, "complete": complete,
           "runs": sorted(records, key=lambda r: campaign["order"].index(r["case_id"])
                          if r["case_id"] in campaign["order"] else 1 << 30)}
    doc.pop("order")
    _atomic_write(path, json.dumps(doc, indent=2, allow_nan=False) + "\n")


def read_results(path: Path) -> dict[str, Any] | None:
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(doc, dict) or doc.get("version") != RESULTS_VERSION:
        return None
    return doc


def write_junit(path: Path, name: str, records: list[Mapping[str, Any]]) -> None:
    """JUnit XML: one ``<testsuite>`` per campaign, a ``<testcase>`` per run, classname
    ``CAMPAIGN.WORLD``; a failed run's checks in ``<failure>``, its figures in
    ``<system-out>``."""
    failures = sum(r["verdict"] != "pass" for r in records)
    total_s = sum(float(r["wall_s"]) for r in records)
    suites = ET.Element("testsuites", name=name, tests=str(len(records)),
                        failures=str(failures), errors="0", time=f"{total_s:.3f}")
    suite = ET.SubElement(suites, "testsuite", name=name, tests=str(len(records)),
                          failures=str(failures), errors="0", skipped="0", time=f"{total_s:.3f}")
    for r in records:
        case = ET.SubElement(suite, "testcase", classname=f"{name}.{r['axes']['world']}",
                             name=r["case_id"], time=f"{float(r['wall_s']):.3f}")
        props = ET.SubElement(case, "properties")
        for key, value in r["axes"].items():
            ET.SubElement(props, "property", name=key, value=str(value))
        if r["verdict"] != "pass":
            failed = [c for c in r["checks"] if not c["passed"]]
            message = "; ".join(f"{c['name']}: {c['message']}" for c in failed) or r["verdict"]
            fail = ET.SubElement(case, "failure", message=message, type="check")
            fail.text = "\n".join(f"{'ok  ' if c['passed'] else 'FAIL'} {c['name']}: "
                                  f"{c['message']}" for c in r["checks"])
            if r.get("recording"):
                fail.text += f"\nrecording: {r['recording']}"
        out = ET.SubElement(case, "system-out")
        out.text = json.dumps(r["figures"], sort_keys=True)
    ET.indent(suites)
    _atomic_write(path, ET.tostring(suites, encoding="unicode", xml_declaration=True) + "\n")


def _atomic_write(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
