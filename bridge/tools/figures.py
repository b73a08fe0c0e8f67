"""Figures of docs/models.md, regenerated from the models' own functions.

    python -m koala_bridge.tools.figures docs/figures        (or: make figures)

A documentation tool, not part of the simulator: it is the one module of ``sim/`` that writes
files, and it is only run by hand. Matplotlib's Agg backend, a fixed seed, no display needed.
The parameter values are those of config/default.toml unless a figure says otherwise.
"""

from __future__ import annotations

import argparse
import logging
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
from koala_bridge.sim.models import camera as cam
from koala_bridge.sim.models import gyro
from koala_bridge.sim.models import ir as ir_model
from koala_bridge.sim.models import sonar as sonar_model

log = logging.getLogger(__name__)

CAMERA = cam.CameraErrorParams(p_perc=0.01, p_recog=0.01, min_range_m=0.1, max_range_m=4.0,
                               distance_base=2.0, dist=0.05, d_mid_m=1.0, far_doubling_m=1.0,
                               bearing_sigma_deg=2.0)


def _plt():  # type: ignore[no-untyped-def]
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(plt, fig, out: Path) -> None:  # type: ignore[no-untyped-def]
    """Lay ``fig`` out, write it to ``out`` and free it."""
    fig.tight_layout()
    fig.savefig(out)
    plt.close(fig)


def perception_vs_angle(out: Path) -> None:
    """seeds/000 Figures 2–3: miss probability vs viewing angle for several a_max (near range)."""
    plt = _plt()
    a = np.linspace(-180, 180, 721)
    fig, ax = plt.subplots(figsize=(7, 4))
    for a_max in (60, 120, 180, 360, 10000):
        p = cam.miss_probability(np.radians(a), CAMERA.min_range_m, math.radians(a_max), CAMERA)
        ax.plot(a, p, label=f"a_max = {a_max}°")
    ax.set_xlabel("viewing angle a (deg)")
    ax.set_ylabel("P(miss)")
    ax.set_title("Perception error vs angle, p_perc = 0.01, d = d_min (eq. 5)")
    ax.legend()
    ax.grid(alpha=0.3)
    _save(plt, fig, out)


def perception_vs_distance(out: Path) -> None:
    """seeds/000 Figure 4: the distance term f(d) for several bases (eq. 6 as reconstructed)."""
    plt = _plt()
    d = np.linspace(0, 4.2, 400)
    fig, ax = plt.subplots(figsize=(7, 4))
    for base in (1.0, 2.0, 4.0, 16.0):
        params = cam.CameraErrorParams(min_range_m=0.1, max_range_m=4.0, distance_base=base)
        ax.plot(d, cam.distance_term(d, params), label=f"base {base:g}")
    ax.set_xlabel("distance d (m)")
    ax.set_ylabel("f(d)")
    ax.set_title("Distance term of the perception error, d_min = 0.1 m, d_max = 4 m (eq. 6)")
    ax.legend()
    ax.grid(alpha=0.3)
    _save(plt, fig, out)


def perception_surface(out: Path) -> None:
    """seeds/000 Figure 6: P_miss over (distance, angle), a_max = 120°."""
    plt = _plt()
    d = np.linspace(0.1, 4.0, 60)
    a = np.linspace(-70, 70, 71)
    dd, aa = np.meshgrid(d, a)
    p = cam.miss_probability(np.radians(aa), dd, math.radians(120.0), CAMERA)
    fig = plt.figure(figsize=(7, 5))
    ax = fig.add_subplot(projection="3d")
    ax.plot_surface(dd, aa, p, cmap="viridis", linewidth=0)
    ax.set_xlabel("distance (m)")
    ax.set_ylabel("angle (deg)")
    ax.set_zlabel("P(miss)")
    ax.set_title("Perception error, a_max = 120°, p_perc = 0.01 (eq. 8)")
    _save(plt, fig, out)


def distance_error(out: Path, d_max: float, title: str) -> None:
    """seeds/000 Figures 7–8: estimated distance (mean, ±1 std, samples) vs true distance."""
    plt = _plt()
    rng = np.random.default_rng(0)
    d = np.linspace(0.1, d_max, 60)
    params = cam.CameraErrorParams(p_perc=0.0, p_recog=0.0, min_range_m=0.0, max_range_m=100.0,
                                   dist=CAMERA.dist, d_mid_m=CAMERA.d_mid_m,
                                   far_doubling_m=CAMERA.far_doubling_m)
    n = 40
    dd = np.repeat(d, n)
    m = cam.measure(np.ones(dd.size, dtype=int), dd, np.zeros(dd.size), np.zeros(dd.size),
                    np.full(dd.size, math.pi), np.array([1]), params, rng)
    mean = d + cam.distance_error_mean(d, params)
    sd = cam.distance_error_std(d, params)
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.scatter(dd[m.source], m.ranges, s=2, alpha=0.3, color="grey", label="samples")
    ax.plot(d, d, "k--", lw=1, label="true distance")
    ax.plot(d, mean, "C0", label="mean estimate")
    ax.fill_between(d, mean - sd, mean + sd, color="C0", alpha=0.2, label="±1 std")
    ax.set_xlabel("true distance (m)")
    ax.set_ylabel("estimated distance (m)")
    ax.set_title(title)
    ax.legend()
    ax.grid(alpha=0.3)
    _save(plt, fig, out)


def range_error_tables(out: Path) -> None:
    """seeds/004 IR (±3 %) and ultrasonic (±6.6 %) distance error tables, interpolated."""
    plt = _plt()
    irp = ir_model.IrErrorParams()
    usp = sonar_model.SonarErrorParams()
    r = np.linspace(0, 1.2, 300)
    fig, ax = plt.subplots(figsize=(7, 4))
    for name, table, c in (("IR (±3 %)", irp.distance_error, "C3"),
                           ("ultrasonic (±6.6 %)", usp.distance_error, "C0")):
        ax.plot(r * 100, table.value(r) * 100, c, label=name)
        ax.plot(table.x * 100, table.y * 100, "o", color=c)
    ax.set_xlabel("range (cm)")
    ax.set_ylabel("distance error sigma (cm)")
    ax.set_title("Range error tables of seeds/004 (points), linear interpolation")
    ax.legend()
    ax.grid(alpha=0.3)
    _save(plt, fig, out)


def gyro_heading_error(out: Path) -> None:
    """Integrated gyro heading error at rest: ARW (sqrt t) and bias random walk (t^1.5)."""
    plt = _plt()
    p = gyro.GyroErrorParams(gyroscope_noise_density=1.6968e-4, gyroscope_random_walk=1.9393e-5,
                             turn_on_bias_sigma=0.0, scale_noise=0.0)  # the two densities only
    dt, n, runs = 0.01, 6000, 400
    rng = np.random.default_rng(1)
    rates, _ = gyro.measure_batch(np.zeros((runs, n)), dt, np.zeros(runs), p, rng)
    heading = np.cumsum(rates, axis=1) * dt
    t = np.arange(1, n + 1) * dt
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.loglog(t, heading.std(axis=0), "k", label=f"simulated ({runs} runs)")
    ax.loglog(t, p.gyroscope_noise_density * np.sqrt(t), "C0--", label="ARW: sigma_g sqrt(t)")
    ax.loglog(t, p.gyroscope_random_walk * t**1.5 / math.sqrt(3), "C1--",
              label="bias RW: sigma_bg t^1.5 / sqrt(3)")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("heading error std (rad)")
    ax.set_title("Gyro at rest, Kalibr example densities (ADIS16448)")
    ax.legend()
    ax.grid(alpha=0.3, which="both")
    _save(plt, fig, out)


FIGURES: dict[str, Callable[[Path], None]] = {
    "camera_perception_angle.png": perception_vs_angle,
    "camera_perception_distance.png": perception_vs_distance,
    "camera_perception_surface.png": perception_surface,
    "camera_distance_error_near.png": lambda p: distance_error(
        p, 1.0, "Distance error, near landmarks (eq. 10–12)"),
    "camera_distance_error_far.png": lambda p: distance_error(
        p, 4.0, "Distance error, far landmarks (eq. 10–12)"),
    "range_error_tables.png": range_error_tables,
    "gyro_heading_error.png": gyro_heading_error,
}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m koala_bridge.tools.figures",
        description="Regenerate the figures of docs/models.md. Example: "
                    "python -m koala_bridge.tools.figures docs/figures",
    )
    ap.add_argument("outdir", type=Path, help="directory for the PNG files")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    args.outdir.mkdir(parents=True, exist_ok=True)
    for name, make in FIGURES.items():
        make(args.outdir / name)
        log.info("wrote %s", args.outdir / name)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
