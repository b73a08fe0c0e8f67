"""The calibration report: ``report.json`` (machine), ``report.md`` + residual PNGs (people).

report.json shape (issue 6)::

    {"streams": [{"stream": "gyro", "metric": "...", "unit": "...", "before": X, "after": Y,
                  "split": {"fit": [t0, t1], "score": [t1, t2]},
                  "effects": [{"name": "bias", "params": {...}, "evidence": {...}}]}]}

A stream with a secondary metric (the gyro's windowed heading error) has a second entry with the
same ``stream``, that metric, and the same effects.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from bridge.calibration.pipeline import StreamResult

log = logging.getLogger(__name__)


def _num(v: float) -> float | None:
    return float(f"{v:.6g}") if np.isfinite(v) else None


def stream_entries(res: StreamResult) -> list[dict[str, Any]]:
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
    entries = [
        {
            "stream": p.name,
            "metric": p.metric,
            "unit": p.unit,
            "before": _num(res.before),
            "after": _num(res.after),
            "split": split,
            "effects": effects,
        }
    ]
    for s in res.secondary:
        entries.append(
            {
                "stream": p.name,
                "metric": s.metric,
                "unit": s.unit,
                "before": _num(s.before),
                "after": _num(s.after),
                "split": split,
                "effects": effects,
            }
        )
    return entries


def report_json(results: Sequence[StreamResult]) -> dict[str, Any]:
    return {"streams": [e for r in results for e in stream_entries(r)]}


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


def report_markdown(
    results: Sequence[StreamResult], source: str, diff: str, plots: dict[str, str]
) -> str:
    lines = [
        f"# Calibration report: `{source}`",
        "",
        "Fit on the first 60 % of each stream's time span, scored on the last 40 %. "
        "An effect is added when it lowers the fit-part BIC, passes the held-out "
        "likelihood-ratio test (alpha = 0.01, Bonferroni over the round's candidates, "
        "effective sample size) and lowers the held-out RMS by at least 1 %.",
        "",
        "| stream | metric | unit | before | after | effects |",
        "|---|---|---|---|---|---|",
    ]
    for res in results:
        for e in stream_entries(res):
            lines.append(
                f"| {e['stream']} | {e['metric']} | {e['unit']} | {e['before']} | "
                f"{e['after']} | {', '.join(x['name'] for x in e['effects']) or '-'} |"
            )
    for res in results:
        p = res.problem
        lines += ["", f"## {p.name}", ""]
        lines += [f"- {n}" for n in p.notes]
        lines.append(f"- {json.dumps(p.describe())}")
        lines.append(
            f"- noise lag-1 autocorrelation used for effective sizes: {res.selection.rho:.3g}"
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
        if p.name in plots:
            lines += ["", f"![{p.name} residuals]({plots[p.name]})"]
    lines += ["", "## Model change", "", "```diff", diff.rstrip() or "(no change)", "```", ""]
    return "\n".join(lines)


def write_report(
    out: Path, results: Sequence[StreamResult], source: str, diff: str, plots: bool = True
) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "report.json").write_text(
        json.dumps(report_json(results), indent=2) + "\n", encoding="utf-8"
    )
    names: dict[str, str] = {}
    if plots:
        for res in results:
            fname = f"residuals_{res.problem.name.replace(':', '_')}.png"
            plot_residuals(res, out / fname)
            names[res.problem.name] = fname
    (out / "report.md").write_text(report_markdown(results, source, diff, names), encoding="utf-8")
    log.info("report written to %s", out)
