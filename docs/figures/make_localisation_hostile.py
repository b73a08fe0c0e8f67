"""docs/figures/localisation_hostile.png: the localisation node on the hostile drive (issue 15).

    .venv/bin/python docs/figures/make_localisation_hostile.py [OUT.png] [--seed N] [--no-kidnap]

Runs :func:`koala_bridge.tools.drive_scenario.run_scenario` (the bridge's simulated robot on
config/default.toml, fast clock, the estimator fed from its buses; the "hostile" script with the
~4 s wall push and, unless ``--no-kidnap``, the kidnap at 40 s) and draws:

* the map (walls, camera landmarks), the true and the estimated path, the wall contact and
  the kidnap;
* the position error over time with the 0.2 m recovery threshold, the heading error, and the
  NEES of ``(x, y, theta)`` (log scale) with the 95 % chi-square band of 3 dof;
* shaded bands: wall contact (grey) and, if the node publishes ``estimate/health``, its state.

Matplotlib's Agg backend; the run is deterministic for a seed. Regenerate after changing the
estimator.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

OUT = Path(__file__).resolve().parent / "localisation_hostile.png"
HEALTH_COLOURS = {"tracking": "#ffffff", "uncertain": "#fff2b3", "lost": "#f7c6c6",
                  "relocalising": "#cfd8f7"}


def health_spans(samples: list[tuple[float, Mapping[str, Any]]], t_end: float
                 ) -> list[tuple[float, float, str]]:
    """``estimate/health`` messages as ``(t0, t1, state)`` spans (the state is read from the
    payload's ``state``, else ``status``)."""
    spans: list[tuple[float, float, str]] = []
    for k, (t, msg) in enumerate(samples):
        state = str(msg.get("state", msg.get("status", "?")))
        t1 = samples[k + 1][0] if k + 1 < len(samples) else t_end
        if spans and spans[-1][2] == state and math.isclose(spans[-1][1], t):
            spans[-1] = (spans[-1][0], t1, state)
        else:
            spans.append((t, t1, state))
    return spans


def draw(result: Any, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from koala_bridge.estimation.metrics import chi2_band, nees

    a = result.aligned()
    err = a.position_error
    e = a.error
    eps = nees(e, a.cov)
    lo, hi = chi2_band(3)
    metrics = result.metrics()
    rec = result.recovery()

    fig = plt.figure(figsize=(13, 7.5))
    grid = fig.add_gridspec(3, 2, width_ratios=[1.0, 1.35])
    ax_map = fig.add_subplot(grid[:, 0])
    ax_err = fig.add_subplot(grid[0, 1])
    ax_hdg = fig.add_subplot(grid[1, 1], sharex=ax_err)
    ax_nees = fig.add_subplot(grid[2, 1], sharex=ax_err)

    for x0, y0, x1, y1 in result.walls:
        ax_map.plot([x0, x1], [y0, y1], color="k", lw=2.5, solid_capstyle="butt")
    for i, (lid, lx, ly) in enumerate(result.landmarks):
        ax_map.plot(lx, ly, "*", color="tab:orange", ms=11, mec="k", mew=0.5,
                    label="camera landmark" if i == 0 else None)
        ax_map.annotate(f"{lid:.0f}", (lx, ly), textcoords="offset points", xytext=(-9, -12),
                        fontsize=8)
    tt, truth = result.truth_t, result.truth
    k_t = result.kidnap.t_s if result.kidnap is not None else math.inf
    for part in (tt <= k_t, tt > k_t):
        ax_map.plot(truth[part, 0], truth[part, 1], color="k", lw=1.2,
                    label="truth" if part[0] else None)
    ax_map.plot(result.estimate[:, 0], result.estimate[:, 1], color="tab:blue", lw=1.0,
                alpha=0.85, label="estimate/pose")
    for i, (t0, t1) in enumerate(result.contact):
        sel = (tt >= t0) & (tt <= t1)
        ax_map.plot(truth[sel, 0], truth[sel, 1], color="tab:red", lw=5, alpha=0.5,
                    label="wall contact (truth)" if i == 0 else None)
        x, y = truth[sel][-1, :2]
        ax_map.add_patch(plt.Circle((x, y), result.body_radius_m, fill=False, color="tab:red",
                                    ls="--", lw=1))
    if result.kidnap is not None and result.kidnap_from is not None:
        (fx, fy), k = result.kidnap_from, result.kidnap
        ax_map.annotate("", xy=(k.x, k.y), xytext=(fx, fy),
                        arrowprops={"arrowstyle": "->", "color": "tab:purple", "lw": 1.5,
                                    "ls": "--"})
        ax_map.plot([], [], color="tab:purple", ls="--",
                    label=f"kidnap at {k.t_s:g} s ({result.kidnap_distance_m:.2f} m)")
    ax_map.plot(*truth[0, :2], "o", color="k", ms=5)
    ax_map.set_aspect("equal")
    ax_map.set_xlabel("x (m)")
    ax_map.set_ylabel("y (m)")
    ax_map.legend(loc="upper center", bbox_to_anchor=(0.5, -0.1), ncol=2, fontsize=8)
    ax_map.set_title(f"hostile drive, seed {result.seed}: map, truth and estimate")

    spans = health_spans(result.estimates.get("estimate/health", []), result.sim_s)
    for ax in (ax_err, ax_hdg, ax_nees):
        for t0, t1, state in spans:
            ax.axvspan(t0, t1, color=HEALTH_COLOURS.get(state, "#eeeeee"), lw=0, zorder=0)
        for t0, t1 in result.contact:
            ax.axvspan(t0, t1, color="0.6", alpha=0.45, lw=0, zorder=0.5)
        if result.kidnap is not None:
            ax.axvline(result.kidnap.t_s, color="tab:purple", ls="--", lw=1)
        ax.grid(alpha=0.3)

    ax_err.plot(a.t, err, color="tab:blue", lw=1)
    ax_err.axhline(0.2, color="tab:green", ls=":", lw=1, label="0.2 m (recovery)")
    ax_err.axhline(0.10, color="tab:orange", ls=":", lw=1, label="0.10 m (RMSE target)")
    text = f"RMSE {metrics.pose_rmse_m:.3f} m"
    if rec is not None:
        text += ("; kidnap: never back within 0.2 m" if rec.duration_s is None
                 else f"; kidnap: back within 0.2 m after {rec.duration_s:.1f} s")
    ax_err.set_title(text, fontsize=10)
    ax_err.set_ylabel("position error (m)")
    ax_err.legend(loc="upper left", fontsize=8)
    if spans:
        from matplotlib.patches import Patch

        states = list(dict.fromkeys(state for _, _, state in spans))
        ax_hdg.legend(handles=[Patch(color=HEALTH_COLOURS.get(s, "#eeeeee"), label=s)
                               for s in states], loc="upper left", fontsize=8,
                      title="estimate/health", title_fontsize=8)

    ax_hdg.plot(a.t, np.degrees(e[:, 2]), color="tab:blue", lw=1)
    ax_hdg.axhline(5, color="tab:orange", ls=":", lw=1)
    ax_hdg.axhline(-5, color="tab:orange", ls=":", lw=1)
    ax_hdg.set_ylabel("heading error (deg)")
    ax_hdg.set_title(f"heading RMSE {metrics.heading_rmse_deg:.2f} deg (target 5)", fontsize=10)

    shown = np.clip(eps, 1e-3, 1e12)
    ax_nees.semilogy(a.t, shown, color="tab:blue", lw=0.8)
    ax_nees.axhspan(lo, hi, color="tab:green", alpha=0.15, lw=0)
    ax_nees.axhline(lo, color="tab:green", lw=0.8)
    ax_nees.axhline(hi, color="tab:green", lw=0.8)
    assert metrics.nees is not None
    ax_nees.set_title(f"NEES (x, y, θ): {100 * metrics.nees.fraction_in_band:.1f} % inside the "
                      f"95 % band [{lo:.3f}, {hi:.2f}] (target >= 90 %)", fontsize=10)
    ax_nees.set_ylabel("NEES")
    ax_nees.set_xlabel("simulated time (s); grey: wall contact"
                       + ("; colours: estimate/health" if spans else ""))

    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", nargs="?", type=Path, default=OUT, help=f"(default {OUT.name})")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--no-kidnap", action="store_true", help="the drive without the kidnap")
    args = ap.parse_args(argv)
    from koala_bridge.tools.drive_scenario import HOSTILE, HOSTILE_KIDNAP, run_scenario

    result = run_scenario(HOSTILE, seed=args.seed,
                          kidnap=None if args.no_kidnap else HOSTILE_KIDNAP)
    draw(result, args.out)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
