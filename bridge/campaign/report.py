"""``report.md``: the campaign at a glance -- counts, a pass/fail matrix (rows world x seed,
columns fault set x override set), the failures with their checks, and for each failure a
figure (``plots/CASE.png``): the true trajectory over the map's walls (with the firmware's
estimates), the coverage of the reachable cells over time and the localisation error over time.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from koala_bridge.campaign.results import n_runs
from koala_bridge.campaign.truth import (
    estimate_errors,
    first_visits,
    reachable_cells,
    truth_track,
    wall_segments,
)
from koala_bridge.core.grid import Grid
from koala_bridge.recording.mcap_file import RecordingError, open_recording

MARK = {"pass": "pass", "fail": "**FAIL**"}


def write_report(out: Path, name: str, records: Sequence[Mapping[str, Any]],
                 configs: Mapping[str, Mapping[str, Any]], complete: bool) -> Path:
    """Write ``out/report.md`` (and ``out/plots/*.png`` for failures); returns the report's
    path. ``configs``: each case's bridge configuration (its world), by case id."""
    passed = sum(r["verdict"] == "pass" for r in records)
    lines = [f"# Campaign {name}", ""]
    lines.append(f"{passed} of {n_runs(len(records))} passed"
                 + ("" if complete else " (incomplete: `--resume` runs the rest)") + ".")
    lines += ["", "## Matrix", ""] + _matrix(records)
    failures = [r for r in records if r["verdict"] != "pass"]
    if failures:
        lines += ["", "## Failures", ""]
    for r in failures:
        lines += [f"### {r['case_id']}", ""]
        lines += [f"- {'ok' if c['passed'] else '**FAIL**'} `{c['name']}`: {c['message']}"
                  for c in r["checks"]]
        figures = {k: v for k, v in r["figures"].items() if k != "rejected_frames"}
        lines.append(f"- figures: `{json.dumps(figures, sort_keys=True)}`")
        if r.get("recording"):
            lines.append(f"- recording: `{r['recording']}` (`koala-bridge export` / `replay`)")
        png = _plot_failure(out, r, configs.get(r["case_id"]))
        if png is not None:
            lines += ["", f"![{r['case_id']}]({png.relative_to(out).as_posix()})"]
        lines.append("")
    path = out / "report.md"
    path.write_text("\n".join(lines).rstrip() + "\n", encoding="utf-8")
    return path


def _matrix(records: Sequence[Mapping[str, Any]]) -> list[str]:
    rows = list(dict.fromkeys((r["axes"]["world"], r["axes"]["seed"]) for r in records))
    cols = list(dict.fromkeys((r["axes"]["faults"], r["axes"]["overrides"]) for r in records))
    one_override = len({c[1] for c in cols}) == 1
    cell = {((r["axes"]["world"], r["axes"]["seed"]),
             (r["axes"]["faults"], r["axes"]["overrides"])): r["verdict"] for r in records}
    head = ["world", "seed"] + [f if one_override else f"{f} / {o}" for f, o in cols]
    out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for row in rows:
        marks = [MARK.get(cell.get((row, c), ""), cell.get((row, c), "-")) for c in cols]
        out.append(f"| {row[0]} | {row[1]} | " + " | ".join(marks) + " |")
    return out


def _plot_failure(out: Path, record: Mapping[str, Any],
                  config: Mapping[str, Any] | None) -> Path | None:
    """Three panels from the failure's recording; None without a readable recording."""
    if not record.get("recording") or config is None:
        return None
    try:
        rec = open_recording(out / record["recording"])
    except (RecordingError, OSError):
        return None
    track = truth_track(rec)
    if len(track) == 0:
        return None
    import matplotlib

    matplotlib.use("Agg")  # files only, never a window
    from matplotlib.figure import Figure

    world = Grid.from_dict(dict(config["world"]))
    report_path = out / "logs" / record["case_id"] / "report.json"
    report = json.loads(report_path.read_text()) if report_path.exists() else {}
    fig = Figure(figsize=(13, 4.2), layout="constrained")
    ax_map, ax_cov, ax_err = fig.subplots(1, 3)
    try:
        segments = wall_segments(rec)
    except ValueError:
        segments = np.empty((0, 4))
    for x0, y0, x1, y1 in segments:
        ax_map.plot([x0, x1], [y0, y1], color="black", lw=2)
    ax_map.plot(track[:, 1], track[:, 2], lw=1, label="truth")
    ax_map.plot(track[0, 1], track[0, 2], "o", color="green", label="start")
    ax_map.plot(track[-1, 1], track[-1, 2], "s", color="red", label="end")
    estimates = np.asarray([e[:3] for e in report.get("estimates") or ()], dtype=float)
    if len(estimates):
        ax_map.plot(estimates[:, 1], estimates[:, 2], ".", ms=3, label="firmware estimate")
    contact = record["figures"].get("min_clearance_t_s")  # a contact when the clearance <= 0
    if record["figures"].get("min_clearance_m", 1.0) <= 0 and contact is not None:
        i = int(np.argmin(np.abs(track[:, 0] - contact)))
        ax_map.plot(track[i, 1], track[i, 2], "x", color="red", ms=10, label="wall contact")
    ax_map.set_aspect("equal")
    ax_map.set_title("trajectory over the map")
    ax_map.set_xlabel("x (m)")
    ax_map.set_ylabel("y (m)")
    ax_map.legend(fontsize=7, loc="best")

    start = world.cell_of(track[0, 1], track[0, 2])
    reachable = reachable_cells(world, start)
    times = sorted(t for c, t in first_visits(track, world).items() if c in reachable)
    ax_cov.step([0.0, *times, float(track[-1, 0])],
                [0.0, *(100.0 * np.arange(1, len(times) + 1) / len(reachable)),
                 100.0 * len(times) / len(reachable)], where="post")
    ax_cov.set_ylim(0, 105)
    ax_cov.set_title("coverage of the reachable cells")
    ax_cov.set_xlabel("t (s)")
    ax_cov.set_ylabel("%")

    errors = estimate_errors(report, track)
    if len(errors):
        ax_err.plot(errors[:, 0], errors[:, 1], ".-", ms=3)
    else:
        ax_err.text(0.5, 0.5, "no estimate reported", ha="center", va="center",
                    transform=ax_err.transAxes)
    ax_err.set_title("localisation error")
    ax_err.set_xlabel("t (s)")
    ax_err.set_ylabel("m")
    fig.suptitle(f"{record['case_id']}: FAIL")
    png = out / "plots" / f"{record['case_id']}.png"
    png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png, dpi=80)
    return png
