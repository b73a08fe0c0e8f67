"""Noise identification of a rate stream by Allan variance (:mod:`koala_bridge.calibration.allan`),
for the report: which series, the terms read from it, report.json/report.md and the Allan plot.

The series is the stream's residual under the calibrated model (after), over its whole span:
on a still recording that is the raw rate minus its bias, so the terms are the sensor's own; in
motion against a truth heading it also holds what the reference's differentiated heading and
any unmodelled effect add, so the terms are then upper bounds on the sensor's. Rate-like streams
are the scalar streams in a unit per second (the gyro, ``gyro:level``) held against a rate
reference; a gyro compared in heading space (against a compass heading) has no rate residual and
gets none. Samples are taken as equally spaced at the mean interval (a logger's irregular stamps
jitter about the sensor's rate, which is what the Allan variance needs); a series with breaks
(intervals beyond :data:`BREAK_FACTOR` median ones, as ``gyro:level`` has) is analysed on its
longest unbroken stretch.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from koala_bridge.calibration.allan import MISFIT_Z, TAU_K_S, TAU_N_S, AllanFit, allan_noise
from koala_bridge.calibration.problem import StreamProblem
from koala_bridge.calibration.selection import VARIANCE_ALPHA, Fit, variance_blocks
from koala_bridge.calibration.streams.scalar import ScalarProblem

#: Stamps whose largest interval exceeds this many mean intervals are noted as irregular
GAP_FACTOR = 3.0
#: An interval longer than this many median intervals breaks the series (not a logger's jitter)
BREAK_FACTOR = 10.0
#: A residual whose sd exceeds the readings' by this factor comes from a model that misses
#: something large: no Allan analysis (a sign-flipped gyro's is about 2; a still gyro's residual
#: is its readings less a constant, equal to rounding, which a bare comparison flipped on 1.5 %)
RESIDUAL_OVER_READINGS = 1.25


@dataclass(frozen=True)
class StreamNoise:
    """The Allan deviation of one stream's residual and the noise terms fitted to it."""

    stream: str
    unit: str  # of the rate (rad/s)
    tau0: float  # s, the mean sample interval
    samples: int
    fit: AllanFit
    notes: tuple[str, ...] = ()


def rate_like(problem: StreamProblem) -> bool:
    """A scalar stream in a unit per second compared in rate space (module docstring)."""
    return (
        isinstance(problem, ScalarProblem)
        and problem.unit.endswith("/s")
        and problem.integrate_window_s is None
    )


def identify_noise(problem: StreamProblem, fit: Fit) -> StreamNoise | None:
    """The Allan noise terms of ``problem``'s residual under ``fit`` (module docstring); None for
    a stream that is not rate-like or too short (fewer than 3 octaves of 10 clusters)."""
    if not rate_like(problem):
        return None
    t, r = problem.residual_series(fit.insts, fit.x)
    ok = np.isfinite(r)
    t, r = t[ok], r[ok]
    if t.size < 30:
        return None
    assert isinstance(problem, ScalarProblem)
    y = problem.y[np.isfinite(problem.y)]
    rc = r - float(np.mean(r))
    sd_r, sd_y = float(np.sqrt(np.mean(rc * rc))), float(np.std(y))
    if y.size > 1 and sd_r > RESIDUAL_OVER_READINGS * sd_y:
        # a sign-flipped gyro's residual is twice its motion: K and B of that are no noise
        problem.notes.append(
            f"no Allan analysis: the residual varies more than the readings themselves (sd "
            f"{sd_r:.3g} against {sd_y:.3g} {problem.unit}): the model "
            "misses something large (a sign, a unit, a clock), and the curve would describe "
            "that, not the sensor's noise"
        )
        return None
    notes = []
    starts = variance_blocks(rc)
    if starts is not None:
        sizes = np.diff(np.r_[starts, r.size])
        sd = np.sqrt(np.add.reduceat(rc * rc, starts) / sizes)
        notes.append(
            f"the residual's noise changes over time (its spread differs between {sizes.size} "
            f"blocks beyond chance, Brown-Forsythe at {VARIANCE_ALPHA:g}: sd {float(sd.min()):.3g} "
            f"to {float(sd.max()):.3g} {problem.unit}): the terms below, and --write-noise's "
            "density, average the quiet and the noisy stretches; the sensor's own noise is "
            "nearer the quiet one (a gyro shaking while its motors run)"
        )
    u = getattr(problem, "u", None)
    if u is not None and float(np.nanstd(u)) > 0:
        notes.append(
            "the reference varies (motion, or its own noise): the residual holds the "
            "reference's differentiated noise and any effect the model lacks besides the "
            "sensor's, so the terms are upper bounds on the sensor's; a still recording "
            "against a constant reference gives the sensor's own"
        )
    gaps = np.flatnonzero(np.diff(t) > BREAK_FACTOR * np.median(np.diff(t)))
    if gaps.size:  # a series with breaks (level segments only): its longest unbroken stretch
        bounds = np.r_[0, gaps + 1, t.size]
        k = int(np.argmax(np.diff(bounds)))
        t, r = t[bounds[k] : bounds[k + 1]], r[bounds[k] : bounds[k + 1]]
        notes.append(
            f"{gaps.size} break(s) in the series: its longest unbroken stretch, "
            f"{t[-1] - t[0]:.4g} s"
        )
        if t.size < 30:
            return None
    tau0 = float((t[-1] - t[0]) / (t.size - 1))
    allan = allan_noise(r, tau0)
    if allan is None:
        return None
    gap = float(np.max(np.diff(t)))
    if gap > GAP_FACTOR * tau0:
        notes.append(
            f"irregular stamps (largest interval {gap:.3g} s, mean {tau0:.3g} s): samples taken "
            "as equally spaced at the mean interval"
        )
    if fit.insts:
        notes.append(f"residual after {', '.join(i.name for i in fit.insts)}")
    return StreamNoise(problem.name, problem.unit, tau0, int(r.size), allan, tuple(notes))


def _num(v: float) -> float | None:
    return float(f"{v:.4g}") if np.isfinite(v) else None


def noise_json(noise: StreamNoise) -> dict[str, Any]:
    """The report.json ``allan`` object of a stream."""
    f, u = noise.fit, noise.unit
    return {
        "series": "residual (after)",
        "sample_interval_s": _num(noise.tau0),
        "samples": noise.samples,
        "angle_random_walk": {
            "value": _num(f.angle_random_walk),
            "se": _num(f.angle_random_walk_se),
            "unit": f"{u}/sqrt(Hz)",
            "read_at_tau_s": TAU_N_S,
        },
        "bias_instability": {
            "value": _num(f.bias_instability),
            "unit": u,
            "tau_s": _num(f.bias_instability_tau),
            "floor_reached": f.floor_reached,
            "fitted_flat_term": _num(f.bias_instability_fitted),
        },
        "lines_fit_the_curve": not f.misfit,
        "rate_random_walk": {
            "value": _num(f.rate_random_walk),
            "se": _num(f.rate_random_walk_se),
            "unit": f"{u}*sqrt(Hz)",
            "read_at_tau_s": TAU_K_S,
        },
        "curve": {
            "tau_s": [_num(v) for v in f.tau],
            "adev": [_num(v) for v in f.adev],
            "clusters": [int(v) for v in f.clusters],
        },
        "notes": list(noise.notes),
    }


def noise_markdown(noise: StreamNoise, plot: str | None) -> list[str]:
    """report.md lines of a stream's Allan analysis."""
    f, u = noise.fit, noise.unit

    def pm(v: float, se: float) -> str:
        if not np.isfinite(se) or se >= v:
            return f"{v:.4g} (not resolved: SE {se:.2g})"
        return f"{v:.4g} ± {se:.2g}"

    lines = [
        "",
        f"Noise by Allan variance (IEEE Std 952 Annex C) of the residual, {noise.samples} samples "
        f"every {noise.tau0:.4g} s, τ {f.tau[0]:.3g}–{f.tau[-1]:.3g} s:",
        "",
        "| term | value | unit | read |",
        "|---|---|---|---|",
        f"| angle random walk N | {pm(f.angle_random_walk, f.angle_random_walk_se)} | "
        f"{u}/√Hz | slope −1/2 at τ = {TAU_N_S:g} s |",
        f"| bias instability B | {f.bias_instability:.4g}"
        + ("" if f.floor_reached else " (an upper bound)")
        + f" | {u} | minimum / 0.664 at τ = {f.bias_instability_tau:.3g} s"
        + ("" if f.floor_reached else ", the longest: no floor reached")
        + f" (fitted flat term {f.bias_instability_fitted:.3g}) |",
        f"| rate random walk K | {pm(f.rate_random_walk, f.rate_random_walk_se)} | {u}·√Hz | "
        f"slope +1/2 at τ = {TAU_K_S:g} s |",
    ]
    lines += [f"- {n}" for n in noise.notes]
    if f.misfit:
        off = int(np.sum(np.abs(f.misfit_z) > MISFIT_Z))
        lines.append(
            f"- the three lines do not describe this curve: {off} of {f.tau.size} points lie "
            f"beyond {MISFIT_Z:g} standard deviations of the fitted curve (largest "
            f"{float(np.max(np.abs(f.misfit_z))):.3g}), a shape no sum of white noise, flicker "
            "and random walk makes (a correlated process, a vibration's bump); N and K are "
            "the lines' readings at their τ, and the fitted flat term is no floor"
        )
    if plot is not None:
        lines += ["", f"![{noise.stream} Allan deviation]({plot})"]
    return lines


def plot_allan(noise: StreamNoise, path: Path) -> None:
    """Log-log Allan deviation with the fitted lines (Agg backend)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    f = noise.fit
    tau = np.geomspace(f.tau[0], f.tau[-1], 200)
    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    fig.subplots_adjust(left=0.14, right=0.97, top=0.92, bottom=0.12)  # fixed: see report.py
    # the 1-sigma band of each point from its independent clusters (IEEE 952 C.1)
    err = f.adev / np.sqrt(2 * np.maximum(f.clusters - 1, 1))
    ax.errorbar(f.tau, f.adev, yerr=err, fmt="o", ms=3, color="k", label="overlapping ADEV")
    ax.loglog(tau, f.model_adev(tau), color="tab:gray", lw=1, label="fit (sum of terms)")
    if f.angle_random_walk > 0:
        ax.loglog(
            tau,
            f.angle_random_walk / np.sqrt(tau),
            "--",
            color="tab:blue",
            label=f"N = {f.angle_random_walk:.3g} (slope −1/2)",
        )
        ax.plot([TAU_N_S], [f.angle_random_walk], "s", color="tab:blue")
    ax.loglog(
        tau,
        np.full_like(tau, 0.664 * f.bias_instability),
        ":",
        color="tab:green",
        label=f"0.664 B, B = {f.bias_instability:.3g}",
    )
    if f.rate_random_walk > 0:
        ax.loglog(
            tau,
            f.rate_random_walk * np.sqrt(tau / 3),
            "--",
            color="tab:red",
            label=f"K = {f.rate_random_walk:.3g} (slope +1/2)",
        )
        ax.plot([TAU_K_S], [f.rate_random_walk], "s", color="tab:red")
    ax.set_xlim(tau[0] / 1.5, tau[-1] * 1.5)
    ax.set_ylim(0.5 * float(np.min(f.adev)), 2 * float(np.max(f.adev)))
    ax.set_xlabel("τ [s]")
    ax.set_ylabel(f"Allan deviation [{noise.unit}]")
    ax.grid(which="both", alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(f"{noise.stream}: Allan deviation of the residual", fontsize=10)
    fig.savefig(path, dpi=90)
    plt.close(fig)
