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
from koala_bridge.sim.noise import LookupTable

log = logging.getLogger(__name__)

CAMERA = cam.CameraErrorParams(p_perc=0.01, p_recog=0.01, min_range_m=0.1, max_range_m=4.0,
                               distance_base=2.0, dist=0.05, d_mid_m=1.0, far_doubling_m=2.0,
                               bearing_sigma_deg=2.0)
SONAR = sonar_model.SonarErrorParams()
SONAR_MAX_RANGE_M = 2.5           # [sensors.sonar] max_range_m
SONAR_APERTURE_DEG = 22.9         # [sensors.sonar] aperture_deg (seeds/004)
SPEED_OF_SOUND_M_S = 343.0


def additive_miss_probability(a_rad: np.ndarray | float, d_m: np.ndarray | float,
                              a_max_rad: float, p: cam.CameraErrorParams) -> np.ndarray:
    """The additive reading of seeds/000 eq. 5–8 that the camera model used before 2026-11
    (docs/models.md "Seed readings decided on purpose"), for the before/after figure only:
    ``min(1, 4 a^2/a_max^2 + p_perc + (b^u - 1)/(b - 1))``, ``u = (d - d_min)/(d_max - d_min)``."""
    d = np.asarray(d_m, dtype=float)
    u = np.clip((d - p.min_range_m) / (p.max_range_m - p.min_range_m), 0.0, 1.0)
    b = p.distance_base
    f = (np.power(b, u) - 1.0) / (b - 1.0)
    return np.minimum(1.0, cam.angle_term(a_rad, a_max_rad) + p.p_perc + f)


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
    """seeds/000 Figures 4–5: the distance factor g(d) for several bases (eq. 6) and eq. 7's
    square-root-free approximation of the base-2 one."""
    plt = _plt()
    d = np.linspace(0, 4.0, 400)
    fig, ax = plt.subplots(figsize=(7, 4))
    for base in (1.5, 2.0, 4.0, 16.0):
        params = cam.CameraErrorParams(min_range_m=0.1, max_range_m=4.0, distance_base=base)
        ax.plot(d, cam.distance_factor(d, params), label=f"base {base:g} (eq. 6)")
    ax.plot(d, 2.0 ** ((d**2 - 16.0) / (2 * 16.0)), "k:", label="base 2, eq. 7 approximation")
    ax.set_xlabel("distance d (m)")
    ax.set_ylabel("g(d), factor on p_perc")
    ax.set_title("Distance factor of the perception error, d_max = 4 m (eq. 6, 7)")
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
    ax.set_title("Perception error, a_max = 120°, p_perc = 0.01 (eq. 8, multiplicative)")
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
    """seeds/004 IR (±3 %) and ultrasonic (±6.6 %) distance error tables, interpolated (the
    ultrasonic one with its relative error held beyond the last row)."""
    plt = _plt()
    irp = ir_model.IrErrorParams()
    usp = SONAR
    r = np.linspace(0, SONAR_MAX_RANGE_M, 300)
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.plot(r * 100, irp.distance_error.value(r) * 100, "C3", label="IR (±3 %, held beyond)")
    ax.plot(irp.distance_error.x * 100, irp.distance_error.y * 100, "o", color="C3")
    t = usp.distance_error
    ax.plot(r * 100, sonar_model.distance_sigma(r, t.x, t.y) * 100, "C0",
            label="ultrasonic (±6.6 %, relative beyond)")
    ax.plot(t.x * 100, t.y * 100, "o", color="C0")
    ax.set_xlabel("range (cm)")
    ax.set_ylabel("distance error sigma (cm)")
    ax.set_title("Range error tables of seeds/004 (points), linear interpolation")
    ax.legend()
    ax.grid(alpha=0.3)
    _save(plt, fig, out)


# --------------------------------------------- seed readings decided on purpose (docs/models.md)


def seed_camera_perception(out: Path) -> None:
    """Before/after of the camera perception and recognition reading: P_miss (= P_wrong with
    p_recog = p_perc) head-on vs distance, additive (before) and multiplicative (now)."""
    plt = _plt()
    d = np.linspace(CAMERA.min_range_m, CAMERA.max_range_m, 400)
    a_max = math.radians(120.0)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for ax, a_deg in zip(axes, (0.0, 20.0), strict=True):
        a = math.radians(a_deg)
        before = additive_miss_probability(a, d, a_max, CAMERA)
        now = cam.miss_probability(a, d, a_max, CAMERA)
        ax.plot(d, before * 100, "C3", label="before: additive, f(d) at full weight")
        ax.plot(d, now * 100, "C0", label="now: p_perc · 2^((d − d_max)/d_max)")
        for x in (1.0, 2.0):
            for curve, c in ((additive_miss_probability(a, x, a_max, CAMERA), "C3"),
                             (cam.miss_probability(a, x, a_max, CAMERA), "C0")):
                v = float(curve) * 100
                ax.plot([x], [v], "o", color=c)
                ax.annotate(f"{v:.2f} %", (x, v), textcoords="offset points", xytext=(4, 4),
                            fontsize=8, color=c)
        ax.set_yscale("log")
        ax.set_xlabel("distance d (m)")
        ax.set_ylabel("P(miss) = P(wrong id | seen)  (%)")
        ax.set_title(f"viewing angle a = {a_deg:g}°")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8, loc="center right")
    fig.suptitle("Camera perception/recognition, seeds/000 eq. 5–9: the two readings\n"
                 "a_max = 120°, p_perc = p_recog = 0.01, d_min = 0.1 m, d_max = 4 m")
    _save(plt, fig, out)


def seed_camera_far_doubling(out: Path) -> None:
    """Before/after of eq. 11's doubling distance: far sigma and mean distance error vs d."""
    plt = _plt()
    d = np.linspace(0.1, CAMERA.max_range_m, 300)
    before = cam.CameraErrorParams(p_perc=0.0, p_recog=0.0, far_doubling_m=1.0)
    now = cam.CameraErrorParams(p_perc=0.0, p_recog=0.0, far_doubling_m=2.0)
    fig, ax = plt.subplots(figsize=(7, 4))
    for p, c, name in ((before, "C3", "before: doubles every 1 m"),
                       (now, "C0", "now: doubles every 2 m (the text's /2)")):
        ax.plot(d, cam.distance_error_mean(d, p) * 100, c, label=f"mean error, {name}")
        ax.plot(d, cam.distance_error_std(d, p) * 100, c, ls="--", label=f"std, {name}")
    x = 3.9
    ratio = float(cam.far_sigma(x, before) / cam.far_sigma(x, now))
    ax.annotate(f"at {x} m: far error × {ratio:.2f}", (x, float(cam.distance_error_mean(x, before))
                                                        * 100), textcoords="offset points",
                xytext=(-150, -10), fontsize=8)
    ax.set_yscale("log")
    ax.set_xlabel("true distance d (m)")
    ax.set_ylabel("distance error (cm)")
    ax.set_title("eps_far = dist · d_mid · 2^((d − d_mid)/D), seeds/000 eq. 11")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3, which="both")
    _save(plt, fig, out)


def seed_sonar_beyond_table(out: Path) -> None:
    """Before/after of the ultrasonic error beyond the seed's table (1 m): held absolute 6.6 cm
    (before), relative 6.6 % (now), the table's d^2 trend (rejected)."""
    plt = _plt()
    t = SONAR.distance_error
    r = np.linspace(0.0, SONAR_MAX_RANGE_M, 300)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    held = np.interp(r, t.x, t.y)
    now = sonar_model.distance_sigma(r, t.x, t.y)
    trend = 0.066 * r**2
    for ax, scale, unit in ((axes[0], 100.0, "cm"), (axes[1], None, "% of range")):
        def y(v: np.ndarray, scale: float | None = scale) -> np.ndarray:
            if scale is not None:
                return v * scale
            with np.errstate(invalid="ignore", divide="ignore"):
                return np.where(r > 0, v / r * 100, np.nan)
        ax.plot(r, y(held), "C3", label="before: 6.6 cm held beyond 1 m")
        ax.plot(r, y(now), "C0", lw=2, label="now: 6.6 % of the range beyond 1 m")
        ax.plot(r, y(trend), "C2", ls=":", label="d² trend 6.6 cm·(d/1 m)² (rejected)")
        tx = np.asarray(t.x)
        ty = np.asarray(t.y)
        if scale is not None:
            ax.plot(tx, ty * scale, "ko", label="seeds/004 table")
        else:
            ax.plot(tx[1:], ty[1:] / tx[1:] * 100, "ko", label="seeds/004 table")
        ax.axvline(1.0, color="grey", lw=0.8)
        ax.set_xlabel("range (m)")
        ax.set_ylabel(f"sigma ({unit})")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    axes[1].set_ylim(0, 20)
    fig.suptitle("Ultrasonic distance error beyond the seed's table (seeds/004 '±6.6 %')")
    _save(plt, fig, out)


def seed_sonar_vertical_rays(out: Path) -> None:
    """The seed's 3 horizontal + 2 vertical sonar rays in a 2-D world: side view, and the reading
    vs wall angle of 5 horizontal rays (before) and the 3 horizontal ones (now)."""
    plt = _plt()
    half = math.radians(SONAR_APERTURE_DEG) / 2
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    ax = axes[0]
    h, wall = 0.05, 1.0                   # illustrative sensor height (m), wall distance (m)
    ax.plot([0, wall], [0, 0], "C0", label="centre (horizontal) ray: D")
    ax.plot([0, wall], [0, wall * math.tan(half)], "C1",
            label=f"up ray, +{math.degrees(half):.2f}°: D / cos e, incidence ≥ e")
    floor = h / math.tan(half)
    ax.plot([0, floor], [0, -h], "C2",
            label=f"down ray: floor at {floor:.2f} m, incidence {90 - math.degrees(half):.1f}°"
                  " > 22.5°: lost")
    ax.axvline(wall, color="k", lw=2)
    ax.axhline(-h, color="grey", lw=1)
    ax.set_xlabel("distance along the sensor axis (m)")
    ax.set_ylabel("height above the sensor (m)")
    ax.set_title("Side view: the seed's vertical pair (sensor 5 cm above the floor)")
    ax.legend(fontsize=7, loc="upper left")
    ax.set_ylim(-0.1, 0.3)
    ax = axes[1]
    t = np.radians(np.linspace(0.0, 45.0, 451))
    p = sonar_model.SonarErrorParams(
        distance_error=LookupTable.from_rows([[0.0, 0.0], [1.0, 0.0]]),
        late_echo_probability=0.0, crosstalk_probability=0.0, glitch_probability=0.0)
    rng = np.random.default_rng(0)
    for k, c, name in ((5, "C3", "before: 5 horizontal rays"),
                       (3, "C0", "now: the seed's 3 horizontal rays")):
        az = np.linspace(-half, half, k)
        inc = np.abs(t[:, None] + az[None, :])
        dist = 1.0 / np.cos(inc)
        m = sonar_model.measure(dist, inc, 10.0, p, rng)
        ax.plot(np.degrees(t), m.ranges, c, label=name)
    ax.set_xlabel("wall angle to the sensor axis (deg)")
    ax.set_ylabel("reading / perpendicular distance")
    ax.set_title("Noise-free reading off a wall (lost: no echo)")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    _save(plt, fig, out)


def seed_sonar_firing_order(out: Path) -> None:
    """The Koala 2.5 firing order: 9 slots of 20 ms, the longest in-range round trip inside each."""
    plt = _plt()
    slot = 0.020
    trip = 2 * SONAR_MAX_RANGE_M / SPEED_OF_SOUND_M_S
    fig, ax = plt.subplots(figsize=(9, 3.5))
    for i in range(9):
        ax.broken_barh([(i * slot * 1e3, slot * 1e3)], (i - 0.4, 0.8), color="0.85")
        ax.broken_barh([(i * slot * 1e3, trip * 1e3)], (i - 0.3, 0.6), color="C0")
    ax.set_xlabel("time in the 180 ms ring cycle (ms)")
    ax.set_ylabel("sonar (firing order)")
    ax.set_title(f"Sequential firing (Koala 2.5 manual §4.1), 20 ms slots (grey): echoes from\n"
                 f"≤ {SONAR_MAX_RANGE_M} m return within {trip * 1e3:.1f} ms (blue), so no "
                 "crosstalk")
    ax.set_yticks(range(9))
    ax.grid(alpha=0.3, axis="x")
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
    "seed_camera_perception.png": seed_camera_perception,
    "seed_camera_far_doubling.png": seed_camera_far_doubling,
    "seed_sonar_beyond_table.png": seed_sonar_beyond_table,
    "seed_sonar_vertical_rays.png": seed_sonar_vertical_rays,
    "seed_sonar_firing_order.png": seed_sonar_firing_order,
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
