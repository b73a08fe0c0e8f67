"""Hand fits of the real bundles of tests/data/real that bench/real_data converts: what a careful
analyst does with numpy/scipy, to hold ``koala-bridge calibrate`` against.

Each ``fit_<bundle>()`` fits on the first 60 % of the stream's time span and scores on the last
40 %, in the metric the tool reports for that stream (docs/calibration.md, "Streams and
metrics"), and returns one :class:`HandFit` per stream. The model of each fit is chosen from the
physics of the sensor before looking at the held-out part (no selection on held-out data).

    python -m bench.hand_fits            # table of every bundle present
    python -m bench.hand_fits --json     # the same as JSON

The bundles are written by ``python -m bench.real_data`` (from fetched upstream snapshots); a
bundle that is not present is reported as missing.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

Array = NDArray[np.float64]
DATA = Path(__file__).resolve().parents[1] / "tests" / "data" / "real"
FIT_FRACTION = 0.6
ODOMETRY_WINDOW_S = 5.0  # the CLI's --window-s default


@dataclass(frozen=True)
class HandFit:
    """One stream's hand fit: held-out metric under the declared model and after the fit."""

    bundle: str
    stream: str  # the tool's stream name (report.json)
    metric: str  # the tool's metric name, or what differs
    unit: str
    before: float
    after: float
    effects: str  # what the fit adds to the declared model
    params: dict[str, float] = field(default_factory=dict)


# --- shared helpers ---------------------------------------------------------------------------


def read_table(path: Path) -> dict[str, NDArray]:
    """A bundle CSV as columns: floats where every cell is a number, else strings."""
    with path.open(newline="", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    out: dict[str, NDArray] = {}
    for key in rows[0]:
        cells = [r[key] for r in rows]
        try:
            out[key] = np.array([float(c) if c else np.nan for c in cells])
        except ValueError:
            out[key] = np.array(cells)
    return out


def split(t: Array) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """Fit part ``t < t0 + 0.6 (t1 - t0)`` and score part (the rest)."""
    t1 = t.min() + FIT_FRACTION * (t.max() - t.min())
    return t < t1, t >= t1


def rms(e: Array) -> float:
    return float(np.sqrt(np.mean(np.square(e))))


def one_hot(levels: Array, drop_first: bool = False) -> Array:
    values = np.unique(levels)[1 if drop_first else 0:]
    return (levels[:, None] == values[None, :]).astype(float)


def linear_range_fit(y: Array, u: Array, design: Array, fit: NDArray[np.bool_],
                     f_scale: float) -> Array:
    """``y - u = design @ p`` on the fit rows, robust (soft L1, Huber-like, scale ``f_scale``):
    outliers (multipath, dropouts) weigh linearly, not quadratically."""
    res = least_squares(lambda p: design[fit] @ p - (y - u)[fit], np.zeros(design.shape[1]),
                        loss="soft_l1", f_scale=f_scale)
    return np.asarray(res.x)


# --- odometry: dead reckoning in re-anchored windows (the tool's window_position_rms) ---------


def _window_labels(t: Array, window_s: float) -> NDArray[np.intp]:
    label = np.floor((t - t[0]) / window_s).astype(np.intp)
    return np.unique(label, return_inverse=True)[1]


def window_position_rms(t_odo: Array, ds: Array, dth: Array, t_ref: Array, p_ref: Array,
                        part: NDArray[np.bool_], window_s: float) -> tuple[float, Array]:
    """Dead reckoning from increments ``ds, dth`` (per odometry interval), re-anchored at the
    reference position of each window's first sample; without a reference heading each window's
    start heading is the rotation that best aligns it (2-D Procrustes). Returns the RMS position
    error over the windows of ``part`` and the error vectors."""
    th = np.r_[0.0, np.cumsum(dth)]
    mid = th[:-1] + 0.5 * dth
    x = np.r_[0.0, np.cumsum(ds * np.cos(mid))]
    y = np.r_[0.0, np.cumsum(ds * np.sin(mid))]
    idx = np.flatnonzero(part & (t_ref >= t_odo[0]) & (t_ref <= t_odo[-1]))
    label = _window_labels(t_ref[idx], window_s)
    anchor = idx[np.r_[0, np.flatnonzero(np.diff(label)) + 1]][label]
    xi, yi, ti = (np.interp(t_ref, t_odo, v) for v in (x, y, th))
    c, s = np.cos(ti[anchor]), np.sin(ti[anchor])
    dx, dy = xi[idx] - xi[anchor], yi[idx] - yi[anchor]
    body = np.column_stack([c * dx + s * dy, -s * dx + c * dy])
    q = p_ref[idx] - p_ref[anchor]
    n = int(label.max()) + 1
    cross = np.bincount(label, body[:, 0] * q[:, 1] - body[:, 1] * q[:, 0], n)
    dot = np.bincount(label, body[:, 0] * q[:, 0] + body[:, 1] * q[:, 1], n)
    phi = np.arctan2(cross, dot)[label]
    pred = np.column_stack([np.cos(phi) * body[:, 0] - np.sin(phi) * body[:, 1],
                            np.sin(phi) * body[:, 0] + np.cos(phi) * body[:, 1]])
    e = q - pred
    return float(np.sqrt(np.mean(np.sum(e**2, axis=1)))), e


def fit_speed_odometry(bundle: str, odo: dict[str, NDArray], truth: dict[str, NDArray],
                       wheel_base_m: float) -> HandFit:
    """Body-speed odometry: a distance scale and a yaw scale (wheel base) by least squares on
    the windowed dead-reckoning error of the fit part. The yaw scale is started from +1 and
    from -1 (a left/right swap is a sign, which a local solver started at +1 cannot cross);
    the start with the lower fit-part cost is kept."""
    t = odo["t"]
    dt = np.diff(t)
    ds0 = 0.5 * (odo["v"][1:] + odo["v"][:-1]) * dt  # trapezoid, as the tool integrates
    dth0 = 0.5 * (odo["omega"][1:] + odo["omega"][:-1]) * dt
    t_ref, p_ref = truth["t"], np.column_stack([truth["x"], truth["y"]])
    inside = (t_ref >= t[0]) & (t_ref <= t[-1])
    fit, score = split(t_ref[inside])
    fit_m, score_m = np.zeros_like(inside), np.zeros_like(inside)
    fit_m[inside], score_m[inside] = fit, score
    window = min(ODOMETRY_WINDOW_S, 0.4 * (t_ref[inside].max() - t_ref[inside].min()) / 2)

    def err(p: Array, part: NDArray[np.bool_]) -> Array:
        return window_position_rms(t, ds0 * p[0], dth0 * p[1], t_ref, p_ref, part, window)[1]

    fits = [least_squares(lambda p: err(p, fit_m).ravel(), [1.0, k]) for k in (1.0, -1.0)]
    best = min(fits, key=lambda r: r.cost)
    k_s, k_w = (float(v) for v in best.x)
    before = window_position_rms(t, ds0, dth0, t_ref, p_ref, score_m, window)[0]
    after = window_position_rms(t, ds0 * k_s, dth0 * k_w, t_ref, p_ref, score_m, window)[0]
    # the check of each effect on the held-out part: the yaw scale alone, fitted the same way
    yaw = [least_squares(lambda q: err([1.0, q[0]], fit_m).ravel(), [k]) for k in (1.0, -1.0)]
    k_y = float(min(yaw, key=lambda r: r.cost).x[0])
    yaw_only = window_position_rms(t, ds0, dth0 * k_y, t_ref, p_ref, score_m, window)[0]
    n_windows = int(np.unique(np.floor((t_ref[score_m] - t_ref[score_m][0]) / window)).size)
    return HandFit(bundle, "odometry", "window_position_rms", "m", before, after,
                   "tick_scale + wheel_base"
                   + (" (negative: left/right swapped or mirrored frame)" if k_w < 0 else ""),
                   {"distance_scale": k_s, "yaw_scale": k_w,
                    "wheel_base_m": wheel_base_m / abs(k_w), "window_s": window,
                    "held_out_yaw_scale_only": yaw_only, "held_out_windows": n_windows})


# --- compass: constant field magnitude ----------------------------------------------------------


def _spread_percent(m: Array) -> float:
    norm = np.linalg.norm(m, axis=1)
    return float(100.0 * norm.std() / norm.mean())


def _sym(p: Array) -> Array:
    a, b, c, d, e, f = p
    return np.array([[a, b, c], [b, d, e], [c, e, f]])


def ellipsoid_fit(m: Array) -> tuple[Array, Array]:
    """Hard iron ``h`` and soft-iron correction ``A`` (symmetric) with ``|A (m - h)| = 1``,
    least squares on the magnitude residual, started from the centroid and the mean radius."""
    h0 = m.mean(axis=0)
    r0 = np.linalg.norm(m - h0, axis=1).mean()
    p0 = np.r_[h0, 1 / r0, 0, 0, 1 / r0, 0, 1 / r0]

    def res(p: Array) -> Array:
        return np.linalg.norm((m - p[:3]) @ _sym(p[3:]), axis=1) - 1.0

    p = least_squares(res, p0, x_scale="jac").x
    return p[:3], _sym(p[3:])


def fit_compass_sphere(bundle: str, compass: dict[str, NDArray]) -> HandFit:
    """Turned through many orientations: hard + soft iron ellipsoid (the standard 9-parameter
    magnetometer calibration), scored by the held-out spread of |m|."""
    m = np.column_stack([compass["mx"], compass["my"], compass["mz"]])
    fit, score = split(compass["t"])
    h, a = ellipsoid_fit(m[fit])
    w, _ = np.linalg.eigh(a)
    return HandFit(bundle, "compass", "field_magnitude_spread", "%",
                   _spread_percent(m[score]), _spread_percent((m[score] - h) @ a),
                   "hard_iron + soft_iron",
                   {"h_x": h[0], "h_y": h[1], "h_z": h[2],
                    "axis_ratio_min": float(w.min() / w.max())})


def ellipse_fit(p: Array) -> tuple[Array, Array]:
    """2-D hard iron ``c`` and soft-iron correction ``A`` (symmetric 2 x 2) with
    ``|A (p - c)| = 1``, least squares on the magnitude residual."""
    c0 = p.mean(axis=0)
    r0 = np.linalg.norm(p - c0, axis=1).mean()

    def res(q: Array) -> Array:
        a = np.array([[q[2], q[3]], [q[3], q[4]]])
        return np.linalg.norm((p - q[:2]) @ a, axis=1) - 1.0

    q = least_squares(res, np.r_[c0, 1 / r0, 0.0, 1 / r0], x_scale="jac").x
    return q[:2], np.array([[q[2], q[3]], [q[3], q[4]]])


# --- the bundles --------------------------------------------------------------------------------


def fit_labyrinth_uwb(d: Path) -> list[HandFit]:
    """UWB: antenna-delay offset + scale (the two terms of a two-way-ranging error model),
    robust loss; odometry: distance and yaw scale."""
    meta = json.loads((d / "meta.json").read_text())
    r = read_table(d / "range.csv")
    fit, score = split(r["t"])
    u, y = r["true_range"], r["measured"]
    design = np.column_stack([np.ones_like(u), u])
    p = linear_range_fit(y, u, design, fit, f_scale=0.1)
    uwb = HandFit(d.name, "range:uwb", "rms_error", "m", rms((y - u)[score]),
                  rms((y - u - design @ p)[score]), "bias + scale",
                  {"bias_m": p[0], "scale_error": p[1]})
    odo = fit_speed_odometry(d.name, read_table(d / "odometry.csv"),
                             read_table(d / "truth_pose.csv"), meta["robot"]["wheel_base_m"])
    return [uwb, odo]


def fit_lias_uwb_trolley(d: Path) -> list[HandFit]:
    """Two-way ranging: each range carries the anchor's and the tag's antenna delay (additive),
    plus a common scale; robust loss for the NLOS/dropout readings."""
    r = read_table(d / "range.csv")
    ok = np.isfinite(r["measured"]) & (r["true_range"] > 0)
    t, y, u = r["t"][ok], r["measured"][ok], r["true_range"][ok]
    fit, score = split(t)
    design = np.column_stack([u, one_hot(r["sensor"][ok]), one_hot(r["tag"][ok], True)])
    p = linear_range_fit(y, u, design, fit, f_scale=0.05)
    e = (y - u - design @ p)[score]
    return [HandFit(d.name, "range:uwb", "rms_error", "m", rms((y - u)[score]), rms(e),
                    "scale + offset per anchor + offset per tag",
                    {"scale_error": p[0], "anchor_offset_min_m": float(p[1:9].min()),
                     "anchor_offset_max_m": float(p[1:9].max()),
                     "held_out_rms_inliers_m": rms(e[np.abs(e) < 0.3])})]


def fit_hcsr04_sweeps(d: Path) -> list[HandFit]:
    """Sonar: offset + scale (speed of sound, trigger latency), robust loss for the echoes off
    nearer objects; the held-out RMS counts every reading, as the tool's does."""
    r = read_table(d / "range.csv")
    fit, score = split(r["t"])
    u, y = r["true_range"], r["measured"]
    design = np.column_stack([np.ones_like(u), u])
    p = linear_range_fit(y, u, design, fit, f_scale=0.01)
    e = (y - u - design @ p)[score]
    inlier = np.abs(e) < 0.1
    # the check of each effect on the held-out part: the offset alone, fitted the same way
    p1 = linear_range_fit(y, u, design[:, :1], fit, f_scale=0.01)
    e1 = (y - u - design[:, :1] @ p1)[score]
    return [HandFit(d.name, "range:sonar", "rms_error", "m", rms((y - u)[score]), rms(e),
                    "bias + scale (robust)",
                    {"bias_m": p[0], "scale_error": p[1],
                     "held_out_rms_inliers_m": rms(e[inlier]),
                     "held_out_median_abs_m": float(np.median(np.abs(e))),
                     "held_out_outlier_fraction": float(1 - inlier.mean()),
                     "bias_only_m": p1[0], "bias_only_held_out_rms_m": rms(e1),
                     "bias_only_held_out_rms_inliers_m": rms(e1[np.abs(e1) < 0.1]),
                     "bias_only_held_out_median_abs_m": float(np.median(np.abs(e1)))})]


def fit_mag_ellipsoid_bazhin(d: Path) -> list[HandFit]:
    return [fit_compass_sphere(d.name, read_table(d / "compass.csv"))]


def fit_roomba_spin(d: Path) -> list[HandFit]:
    """A spin about one axis shows the field only in one plane: a 3-D ellipsoid is not
    identifiable from it (a centre far along the rotation axis makes |m| constant). The analyst
    fits the horizontal field (mx, my) with a 2-D hard + soft iron ellipse and scores the
    held-out spread of its magnitude (the tool's 2-D metric)."""
    c = read_table(d / "compass.csv")
    m = np.column_stack([c["mx"], c["my"], c["mz"]])
    fit, score = split(c["t"])
    centre, a = ellipse_fit(m[fit, :2])
    flat = (m[:, :2] - centre) @ a
    norm = np.linalg.norm(flat, axis=1)
    horizontal = np.linalg.norm(m[:, :2], axis=1)
    compass = HandFit(d.name, "compass", "horizontal_field_magnitude_spread (tool: 3-D)", "%",
                      float(100 * horizontal[score].std() / horizontal[score].mean()),
                      float(100 * norm[score].std() / norm[score].mean()),
                      "hard_iron + soft_iron (2-D)",
                      {"h_x": centre[0], "h_y": centre[1],
                       "axis_ratio": float(np.divide(*sorted(np.linalg.eigvalsh(a))))}
                      | _planarity(m[fit]))
    return [compass]


def _planarity(m: Array) -> dict[str, float]:
    """How far 3-D readings of a spin about one axis are from an affine image of a circle
    (``S R(psi) f + h``, hard and soft iron of any kind), which lies in a plane: the spread
    out of the readings' best plane (smallest principal axis), and the amplitude of its first
    and second harmonics of the in-plane angle ``psi`` -- a wobble of the plane or a field
    that moves with the wheels, which no iron model describes."""
    c = m.mean(axis=0)
    _, vec = np.linalg.eigh(np.cov(m.T))
    out = (m - c) @ vec[:, 0]
    inplane = (m - c) @ vec[:, 1:]
    psi = np.arctan2(inplane[:, 1], inplane[:, 0])
    design = np.column_stack([np.ones_like(psi), np.cos(psi), np.sin(psi),
                              np.cos(2 * psi), np.sin(2 * psi)])
    coef = np.linalg.lstsq(design, out, rcond=None)[0]
    return {"out_of_plane_std": float(out.std()),
            "in_plane_radius": float(np.median(np.linalg.norm(inplane, axis=1))),
            "out_of_plane_h1": float(np.hypot(coef[1], coef[2])),
            "out_of_plane_h2": float(np.hypot(coef[3], coef[4]))}


def fit_sharp_gp2y0a02_sweep(d: Path) -> list[HandFit]:
    """IR triangulation sensor against its datasheet curve: offset + gain of the declared
    curve, robust loss, fitted only inside the datasheet's specified range (below 20 cm the
    output folds back and the curve does not describe it)."""
    ir = json.loads((d / "meta.json").read_text())["sensor"]["ir"]
    r = read_table(d / "range.csv")
    fit, score = split(r["t"])
    lo, hi = ir["datasheet_range_m"]
    rated = (r["true_range"] >= lo) & (r["true_range"] <= hi)
    y = r["measured"]
    u = np.interp(r["true_range"], ir["datasheet_curve_range_m"], ir["datasheet_curve_counts"])
    design = np.column_stack([np.ones_like(u), u])
    p = linear_range_fit(y, u, design, fit & rated, f_scale=5.0)
    return [HandFit(d.name, "range:ir", "rms_error", "counts", rms((y - u)[score]),
                    rms((y - u - design @ p)[score]), "bias + scale (robust, rated range)",
                    {"bias_counts": p[0], "scale_error": p[1]})]


HAND_FITS: dict[str, Callable[[Path], list[HandFit]]] = {
    "labyrinth_uwb": fit_labyrinth_uwb,
    "lias_uwb_trolley": fit_lias_uwb_trolley,
    "hcsr04_sweeps": fit_hcsr04_sweeps,
    "mag_ellipsoid_bazhin": fit_mag_ellipsoid_bazhin,
    "roomba_spin": fit_roomba_spin,
    "sharp_gp2y0a02_sweep": fit_sharp_gp2y0a02_sweep,
}


def run(data: Path = DATA) -> tuple[list[HandFit], list[str]]:
    fits: list[HandFit] = []
    missing = []
    for name, fn in HAND_FITS.items():
        if (data / name / "meta.json").is_file():
            fits.extend(fn(data / name))
        else:
            missing.append(name)
    return fits, missing


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=DATA, help="directory of the bundles")
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    args = parser.parse_args(argv)
    fits, missing = run(args.data)
    if args.json:
        print(json.dumps({"fits": [asdict(f) for f in fits], "missing": missing}, indent=2))
        return 0
    print(f"{'bundle':22s} {'stream':12s} {'metric':44s} {'before':>10s} {'after':>10s}  effects")
    for f in fits:
        print(f"{f.bundle:22s} {f.stream:12s} {f.metric + ' (' + f.unit + ')':44s} "
              f"{f.before:10.4g} {f.after:10.4g}  {f.effects}")
        print(" " * 36 + ", ".join(f"{k} {v:.4g}" for k, v in f.params.items()))
    for name in missing:
        print(f"{name:22s} missing: python -m bench.real_data.convert_{name}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
