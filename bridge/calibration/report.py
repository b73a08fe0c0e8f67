"""The calibration report: ``report.json`` (machine), ``report.md`` + residual PNGs (people).

report.json shape (issue 6)::

    {"streams": [{"stream": "gyro", "metric": "...", "unit": "...", "before": X, "after": Y,
                  "split": {"fit": [t0, t1], "score": [t1, t2]},
                  "effects": [{"name": "bias", "params": {...}, "evidence": {...}}]}]}

A stream with a secondary metric (the gyro's windowed heading error) has a second entry with the
same ``stream``, that metric, and the same effects. In a staged run (several inputs,
:mod:`koala_bridge.calibration.stages`) the document also lists ``inputs``, and each entry names its
``input`` and ``stage``, lists the effects carried from earlier stages (``evidence.carried_from``),
and gives ``before_with_carried``, the stage's own starting point, while ``before`` stays the
metric under the user's declared model.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from dataclasses import astuple
from pathlib import Path
from typing import Any

import numpy as np
from koala_bridge.calibration.pipeline import StreamResult
from koala_bridge.calibration.stages import Stage

log = logging.getLogger(__name__)


def _num(v: float) -> float | None:
    return float(f"{v:.6g}") if np.isfinite(v) else None


def _carried(stage: Stage, res: StreamResult) -> list[dict[str, Any]]:
    return [
        {
            "name": c.name,
            "params": dict(c.params),
            "evidence": {"carried_from": c.source, "stage": c.stage, "config": dict(c.keys)},
        }
        for c in stage.carried.get(res.problem.section, [])
    ]


def stream_entries(
    res: StreamResult, stage: Stage | None = None, staged: bool = False
) -> list[dict[str, Any]]:
    """report.json entries of one stream: the issue's shape; ``staged`` adds ``input``,
    ``stage`` and ``before_with_carried`` (module docstring)."""
    p = res.problem
    split = {
        "fit": [_num(p.split.t0), _num(p.split.t1)],
        "score": [_num(p.split.t1), _num(p.split.t2)],
    }
    effects = [
        {"name": inst.name, "params": params, "evidence": {**trial.evidence(), "param_se": se}}
        for (inst, trial), (params, se) in zip(
            res.selection.added, res.effect_params(), strict=True
        )
    ]
    carried = _carried(stage, res) if stage is not None else []
    entries = []
    for metric, unit, before, after in (astuple(m) for m in res.metrics()):
        entry: dict[str, Any] = {"stream": p.name}
        if stage is not None and staged:
            entry["input"] = stage.source
        entry.update(metric=metric, unit=unit, before=_num(before), after=_num(after))
        if stage is not None and staged:
            entry["stage"] = stage.number
        if stage is not None and stage.declared_before:
            entry["before"] = _num(stage.declared_before.get((p.name, metric), float("nan")))
            entry["before_with_carried"] = _num(before)
        entry.update(split=split, effects=carried + effects)
        entries.append(entry)
    return entries


def report_json(stages: Sequence[Stage]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    if len(stages) > 1:
        out["inputs"] = [s.source for s in stages]
    staged = len(stages) > 1
    out["streams"] = [e for s in stages for r in s.results for e in stream_entries(r, s, staged)]
    return out


def plot_residuals(res: StreamResult, path: Path) -> None:
    """Residual over time before and after, the fit/score boundary marked (Agg backend)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    p, sel = res.problem, res.selection
    t0, r0 = p.residual_series(sel.before.insts, sel.before.x)
    t1, r1 = p.residual_series(sel.after.insts, sel.after.x)
    fig, ax = plt.subplots(2, 1, figsize=(8, 4.5), sharex=True, constrained_layout=True)
    # Thousands of points are enough for the eye; keep PNGs small on long recordings.
    step = max(1, t0.size // 5000)
    for a, t, r, label in (
        (ax[0], t0, r0, "before (declared model)"),
        (ax[1], t1, r1, "after: " + (", ".join(i.name for i in res.effects) or "no effect added")),
    ):
        a.plot(t[::step], r[::step], ".", ms=1.5, color="tab:blue" if a is ax[0] else "tab:green")
        a.axvline(p.split.t1, color="k", lw=0.8, ls="--")
        a.set_title(label, fontsize=9)
        a.set_ylabel(f"residual [{p.unit}]" if p.unit != "%" else "residual [1]", fontsize=8)
        a.grid(alpha=0.3)
    ax[1].set_xlabel("t [s]  (dashed: fit | score)")
    fig.suptitle(
        f"{p.name}: {p.metric} {res.before:.4g} -> {res.after:.4g} {p.unit} (held-out)", fontsize=10
    )
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _stream_markdown(res: StreamResult, stage: Stage, plot: str | None, heading: str) -> list[str]:
    p = res.problem
    lines = ["", f"## {heading}", ""]
    lines += [f"- {n}" for n in p.notes]
    lines.append(f"- {json.dumps(p.describe())}")
    lines.append(f"- noise lag-1 autocorrelation used for effective sizes: {res.selection.rho:.3g}")
    carried = _carried(stage, res)
    if carried:
        lines += ["", "Carried from earlier stages (in this stage's declared model):", ""]
        lines += ["| effect | params | found in |", "|---|---|---|"]
        for c in carried:
            ev = c["evidence"]
            lines.append(
                f"| {c['name']} | {json.dumps(c['params'])} | "
                f"stage {ev['stage']}: `{ev['carried_from']}` |"
            )
    if res.effects:
        lines += ["", "| effect | params | evidence |", "|---|---|---|"]
        for (inst, trial), (params, se) in zip(
            res.selection.added, res.effect_params(), strict=True
        ):
            ev = {**trial.evidence(), "param_se": se}
            lines.append(f"| {inst.name} | {json.dumps(params)} | {json.dumps(ev)} |")
    lines += [
        "",
        "Candidates per round (dBIC < 0, LR > threshold, gain >= 1 % to pass):",
        "",
        "| round | candidate | dBIC (fit) | held-out LR | threshold | held-out gain | pass |",
        "|---|---|---|---|---|---|---|",
    ]
    for i, trials in enumerate(res.selection.rounds, 1):
        for t in trials:
            lines.append(
                f"| {i} | {t.name} | {t.delta_bic:.4g} | {t.lr:.4g} | "
                f"{t.lr_threshold:.3g} | {100 * t.relative_gain:.2f} % | "
                f"{'yes' if t.passed else ''} |"
            )
    if plot is not None:
        lines += ["", f"![{p.name} residuals]({plot})"]
    return lines


def _plot_name(stage: Stage, res: StreamResult, staged: bool) -> str:
    prefix = f"stage{stage.number}_" if staged else ""
    return f"{prefix}residuals_{res.problem.name.replace(':', '_')}.png"


def report_markdown(stages: Sequence[Stage], diff: str, plots: bool) -> str:
    staged = len(stages) > 1
    title = " then ".join(f"`{s.source}`" for s in stages)
    lines = [f"# Calibration report: {title}", ""]
    if staged:
        lines += [
            "Staged: each input was calibrated on the model the inputs before it produced "
            "(effects carried through their config keys). *before* is the metric under the "
            "declared model (`--config` and meta.json), *after* with the carried and the found "
            "effects.",
            "",
        ]
    lines += [
        "Fit on the first 60 % of each stream's time span, scored on the last 40 %. "
        "An effect is added when it lowers the fit-part BIC, passes the held-out "
        "likelihood-ratio test (alpha = 0.01, Bonferroni over the round's candidates, "
        "effective sample size) and lowers the held-out RMS by at least 1 %.",
        "",
    ]
    head = "| stream | metric | unit | before | after | effects |"
    if staged:
        head = "| input | " + head[2:]
    lines += [head, "|" + "---|" * (head.count("|") - 1)]
    for stage in stages:
        for res in stage.results:
            for e in stream_entries(res, stage, staged):
                row = (
                    f"| {e['stream']} | {e['metric']} | {e['unit']} | {e['before']} | "
                    f"{e['after']} | {', '.join(x['name'] for x in e['effects']) or '-'} |"
                )
                lines.append(f"| `{stage.source}` " + row if staged else row)
    for stage in stages:
        for res in stage.results:
            heading = res.problem.name
            if staged:
                heading = f"stage {stage.number} (`{stage.source}`): {heading}"
            plot = _plot_name(stage, res, staged) if plots else None
            lines += _stream_markdown(res, stage, plot, heading)
    lines += ["", "## Model change", "", "```diff", diff.rstrip() or "(no change)", "```", ""]
    return "\n".join(lines)


def write_report(out: Path, stages: Sequence[Stage], diff: str, plots: bool = True) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "report.json").write_text(
        json.dumps(report_json(stages), indent=2) + "\n", encoding="utf-8"
    )
    staged = len(stages) > 1
    if plots:
        for stage in stages:
            for res in stage.results:
                plot_residuals(res, out / _plot_name(stage, res, staged))
    (out / "report.md").write_text(report_markdown(stages, diff, plots), encoding="utf-8")
    log.info("report written to %s", out)
