"""The calibration report: ``report.json`` (machine), ``report.md`` + residual PNGs (people).

report.json shape (issue 6, issue 16)::

    {"streams": [{"stream": "gyro", "metric": "...", "unit": "...", "before": X, "after": Y,
                  "change": "better by 63 %", "relative_change": -0.63,
                  "heldout_errors": {"unit": "...", "n": N, "outlier_threshold": T,
                                     "before": {"rms": .., "median_abs": .., "p95_abs": ..,
                                                "outlier_fraction": ..},
                                     "after": {...}},
                  "split": {"fit": [t0, t1], "score": [t1, t2]},
                  "effects": [{"name": "bias", "params": {...}, "evidence": {...},
                               "written": true}]}],
     "not_calibrated": [{"stream": "range:ir", "missing": "...", "fix": "..."}]}

A stream with a secondary metric (the gyro's windowed heading error) has a second entry with the
same ``stream``, that metric, and the same effects; ``heldout_errors`` (robust statistics of the
held-out errors, :mod:`koala_bridge.calibration.metrics`) is in the stream's first entry only.
Every metric is an error: ``change`` compares magnitudes. A metric that can be negative
(``known_rotation_error``) has ``"signed": true``: ``before`` and ``after`` are then its
magnitudes, ``before_signed`` and ``after_signed`` the values, so a sign flip never reads as an
improvement. An effect ``--write-config`` leaves out has ``"written": false`` and
``not_written`` says why (its uncertainty). ``not_calibrated`` lists every stream of the input
that could not be calibrated, with what it lacks and how to add it.

In a staged run (several inputs, :mod:`koala_bridge.calibration.stages`) the document also
lists ``inputs``, and each entry (of ``streams`` and ``not_calibrated``) names its ``input`` and
``stage``; stream entries list the effects carried from earlier stages
(``evidence.carried_from``), and give ``before_with_carried``, the stage's own starting point,
while ``before`` (and ``heldout_errors.before``) stays the metric under the user's declared
model.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from koala_bridge.calibration.metrics import (
    OUTLIER_SIGMAS,
    ErrorStatistics,
    HeldOutStatistics,
    _num,
    change,
    g4,
)
from koala_bridge.calibration.noise import noise_json, noise_markdown, plot_allan
from koala_bridge.calibration.pipeline import StreamResult
from koala_bridge.calibration.problem import SecondaryMetric
from koala_bridge.calibration.selection import Trial
from koala_bridge.calibration.stages import Stage

log = logging.getLogger(__name__)


def _carried(stage: Stage, res: StreamResult) -> list[dict[str, Any]]:
    return [
        {
            "name": c.name,
            "params": dict(c.params),
            "evidence": {"carried_from": c.source, "stage": c.stage, "config": dict(c.keys)},
        }
        for c in stage.carried.get(res.problem.section, [])
    ]


def _effect_entries(res: StreamResult) -> list[dict[str, Any]]:
    out = []
    for (inst, trial), (params, se), reason in zip(
        res.selection.added, res.effect_params(), res.not_written(), strict=True
    ):
        entry: dict[str, Any] = {
            "name": inst.name,
            "params": params,
            "evidence": {**trial.evidence(), "param_se": se},
            "written": reason is None,
        }
        if inst.name.startswith("offset_per:") and "levels" in inst.data:
            # the last level's offset is no free parameter (they sum to 0), but it is the
            # level's: a new user found the fourth UWB anchor's only in the written comment
            last = f"offset_{int(inst.data['levels'][-1])}"
            entry["params"] = {**params, last: float(f"{-sum(params.values()):.6g}")}
            entry["derived"] = {last: "minus the sum of the others: the offsets sum to 0 over "
                                      "the fit part's levels, the common part is bias's"}
        if reason is not None:
            entry["not_written"] = reason
        elif res.is_comment(inst):
            entry["written_as"] = "comment"   # the simulator has no key for it
        out.append(entry)
    return out


def _written_cell(res: StreamResult, inst: Any, e: dict[str, Any]) -> str:
    """The report's ``--write-config`` cell: written, written as a comment (an effect the
    simulator has no key for: the model change's diff shows none), or not written and why."""
    if not e["written"]:
        return f"**not written**: {e['not_written']}"
    if res.is_comment(inst):
        return "written as a comment: the simulator has no key for it"
    return "written"


def _before(stage: Stage | None, res: StreamResult, m: SecondaryMetric) -> float:
    """The metric's *before*: under the user's declared model (a later stage's is measured
    again against it), else the result's own."""
    if stage is not None and stage.declared_before:
        return stage.declared_before.get((res.problem.name, m.metric), float("nan"))
    return m.before


def _is_signed(m: SecondaryMetric, *values: float) -> bool:
    return m.signed or any(v < 0 for v in values)


def heldout_statistics(res: StreamResult, stage: Stage | None = None) -> HeldOutStatistics:
    """The stream's robust held-out statistics; *before* under the user's declared model."""
    declared = None if stage is None else stage.declared_errors.get(res.problem.name)
    return res.heldout_statistics(declared)


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
    effects = _effect_entries(res)
    carried = _carried(stage, res) if stage is not None else []
    stats = heldout_statistics(res, stage)
    entries = []
    for i, m in enumerate(res.metrics()):
        before = _before(stage, res, m)
        signed = _is_signed(m, before, m.after, m.before)
        entry: dict[str, Any] = {"stream": p.name}
        if stage is not None and staged:
            entry["input"] = stage.source
        ch = change(before, m.after)
        entry.update(
            metric=m.metric,
            unit=m.unit,
            before=_num(abs(before) if signed else before),
            after=_num(abs(m.after) if signed else m.after),
            change=ch.text,
            relative_change=_num(ch.relative),
        )
        if signed:
            entry.update(signed=True, before_signed=_num(before), after_signed=_num(m.after))
        if i == 0:
            written = res.after_written()
            if written is not None:  # an effect is left out of --write-config: its model's
                entry["after_written"] = _num(abs(written) if signed else written)
        if stage is not None and staged:
            entry["stage"] = stage.number
        if stage is not None and stage.declared_before:
            entry["before_with_carried"] = _num(abs(m.before) if signed else m.before)
            if signed:
                entry["before_with_carried_signed"] = _num(m.before)
        if i == 0:
            entry["heldout_errors"] = {
                "unit": p.unit,
                "n": stats.n,
                "outlier_threshold": _num(stats.threshold),
                "before": stats.before.as_dict(),
                "after": stats.after.as_dict(),
            }
        entry.update(split=split, effects=carried + effects)
        if res.noise is not None and i == 0:  # once per stream, with its own metric
            entry["allan"] = noise_json(res.noise)
        entries.append(entry)
    return entries


def skipped_entries(stage: Stage, staged: bool = False) -> list[dict[str, Any]]:
    """report.json ``not_calibrated`` entries of one stage."""
    out = []
    for s in stage.skipped:
        entry: dict[str, Any] = {"stream": s.stream}
        if staged:
            entry.update(input=stage.source, stage=stage.number)
        entry.update(missing=s.missing, fix=s.fix)
        out.append(entry)
    return out


def report_json(stages: Sequence[Stage]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    if len(stages) > 1:
        out["inputs"] = [s.source for s in stages]
    staged = len(stages) > 1
    out["streams"] = [e for s in stages for r in s.results for e in stream_entries(r, s, staged)]
    out["not_calibrated"] = [e for s in stages for e in skipped_entries(s, staged)]
    return out


def metric_text(m: SecondaryMetric, before: float) -> tuple[str, str, str, str]:
    """``(metric, before, after, change)`` as people read them: a signed metric by its
    magnitude, ``known_rotation_error magnitude (signed +0.23 -> -0.24)``."""
    ch = change(before, m.after).text
    if _is_signed(m, before, m.after):
        name = f"{m.metric} magnitude (signed {before:+.4g} -> {m.after:+.4g})"
        return name, g4(abs(before)), g4(abs(m.after)), ch
    return m.metric, g4(before), g4(m.after), ch


def metric_lines(stage: Stage, res: StreamResult) -> list[str]:
    """One line per metric of a stream for the log: ``gyro rms_rate_error: 0.0197 -> 0.002
    rad/s, better by 90 % [bias]``."""
    effects = ", ".join(
        [c.name + "*" for c in stage.carried.get(res.problem.section, [])]
        + [i.name for i in res.effects]
    )
    out = []
    written = res.after_written()
    for i, m in enumerate(res.metrics()):
        name, before, after, ch = metric_text(m, _before(stage, res, m))
        tail = (f"; the written model (uncertain, comment-only and unhelpful effects left out): "
                f"{g4(abs(written))}"
                + (" (none of the effects is written: the declared model's)"
                   if written == res.before and res.effects else "")
                if i == 0 and written is not None else "")
        out.append(
            f"{res.problem.name} {name}: {before} -> {after} {m.unit}, {ch} [{effects or '-'}]"
            + tail
        )
    if any(i.effect.mixture for i in res.effects):
        # an outlier effect leaves the prediction (and so the RMS) as it was: what it improves
        # is how well the model expects the readings, the criterion it was selected by
        from koala_bridge.calibration.selection import heldout_score

        sel = res.selection
        b, a = (heldout_score(res.problem, f, True) for f in (sel.before, sel.after))
        out.append(f"{res.problem.name} held-out negative log-likelihood per reading: "
                   f"{b:.4g} -> {a:.4g} (lower is better; the outlier effect's criterion) "
                   f"[{effects}]")
    return out


def _stats_cells(b: ErrorStatistics, a: ErrorStatistics) -> list[str]:
    return [
        f"{g4(b.rms)} -> {g4(a.rms)}",
        f"{g4(b.median_abs)} -> {g4(a.median_abs)}",
        f"{g4(b.p95_abs)} -> {g4(a.p95_abs)}",
        f"{g4(100 * b.outlier_fraction)} % -> {g4(100 * a.outlier_fraction)} %",
    ]


def _heldout_table(stages: Sequence[Stage], staged: bool) -> list[str]:
    head = "| stream | unit | n | RMS | median abs | 95th pct abs | outliers | outlier threshold |"
    if staged:
        head = "| input | " + head[2:]
    lines = [
        "",
        "## Held-out errors, before -> after",
        "",
        "One error per held-out measurement (odometry: the position error per reference "
        "sample; compass magnitude: the deviation from the fitted field in %). An outlier lies "
        f"beyond {OUTLIER_SIGMAS:g} x 1.4826 x MAD of the *after* errors from its own set's "
        "median: the same threshold before and after (docs/calibration.md).",
        "",
        head,
        "|" + "---|" * (head.count("|") - 1),
    ]
    for stage in stages:
        for res in stage.results:
            st = heldout_statistics(res, stage)
            row = [res.problem.name, res.problem.unit, str(st.n)]
            row += _stats_cells(st.before, st.after) + [g4(st.threshold)]
            lines.append(
                ("| `" + stage.source + "` " if staged else "") + "| " + " | ".join(row) + " |"
            )
    return lines


def _skipped_section(stages: Sequence[Stage], staged: bool) -> list[str]:
    items = [(stage, s) for stage in stages for s in stage.skipped]
    if not items:
        return []
    lines = ["", "## Not calibrated", ""]
    for stage, s in items:
        where = f"stage {stage.number} (`{stage.source}`): " if staged else ""
        lines.append(f"- {where}**{s.stream}**: {s.missing}. To add it: {s.fix}.")
    return lines


def plot_residuals(res: StreamResult, path: Path) -> None:
    """Residual over time before and after, the fit/score boundary marked (Agg backend)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    p, sel = res.problem, res.selection
    t0, r0 = p.residual_series(sel.before.insts, sel.before.x)
    t1, r1 = p.residual_series(sel.after.insts, sel.after.x)
    # fixed margins: a layout engine measured every tick label again and took most of the
    # report's time on a 1-hour recording
    fig, ax = plt.subplots(2, 1, figsize=(8, 4.5), sharex=True)
    fig.subplots_adjust(left=0.11, right=0.98, top=0.88, bottom=0.12, hspace=0.3)
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
    fit_units, score_units = res.selection.units
    if fit_units is not None and score_units is not None:
        lines.append(
            f"- effective sizes from the stream's independent units: {fit_units:.4g} (fit), "
            f"{score_units:.4g} (held-out), not the residual's lag-1 autocorrelation "
            f"({res.selection.rho:.3g})"
        )
    else:
        lines.append(
            f"- noise lag-1 autocorrelation used for effective sizes: {res.selection.rho:.3g}"
        )
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
        lines += ["", "| effect | params | evidence | --write-config |", "|---|---|---|---|"]
        for inst, e in zip(res.effects, _effect_entries(res), strict=True):
            lines.append(
                f"| {e['name']} | {json.dumps(e['params'])} | {json.dumps(e['evidence'])} | "
                f"{_written_cell(res, inst, e)} |"
            )
    lines += [
        "",
        "Candidates per round (dBIC < 0, LR > threshold, gain >= 1 % to pass; a gain in "
        "brackets is of the further metric named, asked when the stream's own gain was below "
        "1 %, and must pass a one-sided paired t-test too):",
        "",
        "| round | candidate | dBIC (fit) | held-out LR | threshold | held-out gain | pass |",
        "|---|---|---|---|---|---|---|",
    ]
    for i, trials in enumerate(res.selection.rounds, 1):
        for t in trials:
            lines.append(
                f"| {i} | {t.name} | {t.delta_bic:.4g} | {t.lr:.4g} | "
                f"{t.lr_threshold:.3g} | {_gain_cell(t)} | {'yes' if t.passed else ''} |"
            )
    if plot is not None:
        lines += ["", f"![{p.name} residuals]({plot})"]
    if res.noise is not None:
        lines += noise_markdown(res.noise, plot and plot.replace("residuals_", "allan_", 1))
    return lines


def _gain_cell(t: Trial) -> str:
    cell = f"{100 * t.relative_gain:.2f} %"
    if t.further is not None:
        f = t.further
        cell += f" ({f.metric}: {100 * f.gain:.2f} %, paired t {f.t:.3g}/{f.t_threshold:.3g})"
    return cell


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
        "effective sample size) and lowers the held-out RMS by at least 1 % (a gyro's bias or "
        "bias drift that lowers it by less: its held-out heading by at least 1 %, "
        "significantly).",
        "",
    ]
    lines += [
        "Every metric is an error: *change* compares magnitudes, and a metric that can be "
        "negative is shown by its magnitude, its signed values beside the name.",
        "",
    ]
    head = "| stream | metric | unit | before | after | change | effects |"
    if staged:
        head = "| input | " + head[2:]
    lines += [head, "|" + "---|" * (head.count("|") - 1)]
    for stage in stages:
        prefix = f"| `{stage.source}` " if staged else ""
        for res in stage.results:
            names = [c["name"] for c in _carried(stage, res)]
            names += [
                e["name"] + ("" if e["written"] else " (not written)") for e in _effect_entries(res)
            ]
            written = res.after_written()
            for i, m in enumerate(res.metrics()):
                name, before, after, ch = metric_text(m, _before(stage, res, m))
                if i == 0 and written is not None:
                    after += f" (written model: {g4(abs(written))})"
                lines.append(
                    prefix + f"| {res.problem.name} | {name} | {m.unit} | {before} | {after} | "
                    f"{ch} | {', '.join(names) or '-'} |"
                )
        for s in stage.skipped:
            lines.append(
                prefix + f"| {s.stream} | - | - | - | - | not calibrated | see below: {s.missing} |"
            )
    lines += _heldout_table(stages, staged)
    lines += _skipped_section(stages, staged)
    for stage in stages:
        for res in stage.results:
            heading = res.problem.name
            if staged:
                heading = f"stage {stage.number} (`{stage.source}`): {heading}"
            plot = _plot_name(stage, res, staged) if plots else None
            lines += _stream_markdown(res, stage, plot, heading)
    lines += ["", "## Model change", "", "```diff", diff.rstrip() or "(no change)", "```", ""]
    return "\n".join(lines)


def _finite(v: Any) -> Any:
    """``v`` with every NaN or infinity as ``null``: report.json is strict JSON, which has no
    NaN (a statistic that does not apply, e.g. the BIC of an effect fixed when proposed)."""
    if isinstance(v, float):
        return v if math.isfinite(v) else None
    if isinstance(v, dict):
        return {k: _finite(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [_finite(x) for x in v]
    return v


def write_report(out: Path, stages: Sequence[Stage], diff: str, plots: bool = True) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "report.json").write_text(
        json.dumps(_finite(report_json(stages)), indent=2, allow_nan=False) + "\n",
        encoding="utf-8",
    )
    staged = len(stages) > 1
    if plots:
        for stage in stages:
            for res in stage.results:
                plot_residuals(res, out / _plot_name(stage, res, staged))
                if res.noise is not None:
                    name = _plot_name(stage, res, staged).replace("residuals_", "allan_", 1)
                    plot_allan(res.noise, out / name)
    (out / "report.md").write_text(report_markdown(stages, diff, plots), encoding="utf-8")
    log.info("report written to %s", out)
