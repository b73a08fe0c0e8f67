"""Build one :class:`koala_bridge.calibration.problem.StreamProblem` per stream of a bundle.

What each stream is held against (the *reference*), in the order the bundle allows:

* gyro: the rate of the reference heading, ``truth_pose.theta``; without one, the heading of the
  bundle's compass after its own calibration (smoothed over 0.25 s); otherwise skipped.
* compass: ``truth_pose.theta`` if present, else the physical constancy of the field magnitude.
* odometry: ``truth_pose`` positions (and heading when present), windows re-anchored.
* range: ``true_range`` through the declared curve (identity for metric sensors).
* landmarks: range and bearing from the reference pose to the mapped landmark.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import replace
from difflib import get_close_matches
from typing import Any

import numpy as np
from koala_bridge.calibration.bundle import REQUIRED_COLUMNS, Bundle, Table
from koala_bridge.calibration.effects.common import categorical_levels
from koala_bridge.calibration.model import DeclaredModel
from koala_bridge.calibration.problem import (
    FORMAT_DOC,
    MIN_ROWS,
    FloatArray,
    SkippedStream,
    Split,
)
from koala_bridge.calibration.problem import skip_stream as _skip
from koala_bridge.calibration.robust import mad_sigma
from koala_bridge.calibration.streams.beacons import (
    beacon_rows,
    beacon_streams,
    build_beacons,
)
from koala_bridge.calibration.streams.compass import CompassProblem
from koala_bridge.calibration.streams.odometry import (
    OdometryProblem,
    backward_wheel,
    metres_per_tick,
    reference_jumps,
)
from koala_bridge.calibration.streams.scalar import (
    ScalarProblem,
    fit_shared_curve,
    running_heading_metric,
)
from koala_bridge.core.geometry import wrap_angle
from numpy.typing import NDArray
from scipy.integrate import cumulative_trapezoid

log = logging.getLogger(__name__)

__all__ = [
    "CompassProblem",
    "OdometryProblem",
    "ScalarProblem",
    "build_beacons",
    "build_compass",
    "build_gyro",
    "build_landmarks",
    "build_odometry",
    "build_ranges",
    "bundle_streams",
    "heading_reference",
    "unknown_files",
]

#: Heading-error windows for the gyro's secondary metric (shortened on short recordings).
HEADING_WINDOW_S = 10.0
#: an odometry window must span this many of the reference's sample intervals: with fewer,
#: it holds its anchor and one later sample at most, or none where the window is one interval
#: long (a reviewer's clean bundles against a reference every 4.5-5 s got wheel_ratio,
#: heading_drift or time_offset on half the seeds at one interval)
WINDOW_REFERENCE_INTERVALS = 2
#: Smoothing of a compass-derived heading before it is differentiated into a reference rate.
COMPASS_SMOOTHING_S = 0.25


def _range_kinds(table: Table) -> NDArray[np.str_]:
    """The sensor kinds of ``range.csv`` (its ``kind`` column; ``""``: a single kind)."""
    return np.unique(table.text["kind"]) if "kind" in table.text else np.array([""])


def _range_name(kind: str) -> str:
    return f"range:{kind}" if kind else "range"


def bundle_streams(bundle: Bundle) -> list[str]:
    """The name of every measured stream ``bundle`` holds, as the report names it: each must
    end calibrated or skipped with a reason (:func:`koala_bridge.calibration.pipeline.calibrate`).
    References (``truth_pose``, ``landmark_map``) are not streams."""
    out = [name for name in ("compass", "gyro", "odometry") if bundle.get(name) is not None]
    ranges = bundle.get("range")
    if ranges is not None:
        out += [_range_name(str(k)) for k in _range_kinds(ranges)]
    obs = bundle.get("landmarks")
    if obs is not None:
        out += beacon_streams(bundle)  # range-only rows: streams/beacons.py
        camera = obs.select(~beacon_rows(obs))
        for column, name in (("range", "landmark_range"), ("bearing", "landmark_bearing")):
            if column in camera.columns and np.isfinite(camera[column]).any():
                out.append(name)
    return out


def _extras(table: Table, known: set[str]) -> dict[str, FloatArray]:
    return {k: v for k, v in table.columns.items() if k not in known and np.any(np.isfinite(v))}


def _unit(meta: Mapping[str, Any], key: str) -> str:
    units = meta.get("units", {})
    return str(units.get(key, "")) if isinstance(units, Mapping) else ""


def heading_reference(bundle: Bundle) -> tuple[FloatArray, FloatArray] | None:
    """``(t, theta unwrapped)`` from ``truth_pose`` when it has a heading."""
    truth = bundle.get("truth_pose")
    if truth is None or "theta" not in truth.columns:
        return None
    if "heading" not in truth.derived:  # unwrapped once per table (four builders ask)
        ok = np.isfinite(truth["theta"])
        truth.derived["heading"] = (
            None if ok.sum() < 2 else (truth["t"][ok], np.unwrap(truth["theta"][ok]))
        )
    ref: tuple[FloatArray, FloatArray] | None = truth.derived["heading"]
    return ref


#: a dense reference heading is read on the regular clock its stamps jitter around
#: (:func:`regular_clock`) when its differenced rate's noise there falls below this share of the
#: stamped one's
REGULAR_CLOCK_GAIN = 0.5
#: stamps whose intervals spread (:func:`mad_sigma`) less than this share of their median are
#: regular
REGULAR_STAMP_SPREAD = 1e-3


def regular_clock(t: FloatArray) -> FloatArray | None:
    """The regular clock stamps ``t`` jitter around, or None: already regular (their intervals'
    spread under :data:`REGULAR_STAMP_SPREAD` of the median), or no such clock (a sample's
    stamp half a period or more from it, stamps that do not advance).

    The period ``b`` is the one whose phases ``2 pi t / b`` agree best (the Rayleigh test's
    resultant length, searched coarse to fine: over the first 1024 median intervals within 1 %
    of the median, then over spans four times longer, each within the last one's resolution
    ``b^2 / span``). Dropped samples leave the phases alone, and a jitter of 0.2 of the period
    still leaves a resultant of 0.45, where counting intervals between stamps goes wrong as
    soon as two neighbours jitter apart by half a period. The offset ``a`` is the mean phase,
    each stamp's sample number ``n = round((t - a) / b)``, and the clock ``a + b n`` is refitted
    by least squares (a drift of the reference's clock against the gyro's is kept).
    """
    if t.size < 16:
        return None
    d = np.diff(t)
    period = float(np.median(d))
    if not period > 0:
        return None
    if mad_sigma(d) < REGULAR_STAMP_SPREAD * period:
        return None
    rel = t - t[0]
    # first over 1024 median intervals, within 1 % of the median in steps of a quarter of the
    # resolution: the median of intervals that jitter by a third of the period is that close
    b, span = period, 1024 * period
    grid = period * (1.0 + np.arange(-0.01, 0.01, 0.25 * period / span))
    while True:
        part = rel[rel <= span]
        resultant = [abs(np.exp(2j * np.pi * part / g).mean()) for g in grid]
        b = float(grid[int(np.argmax(resultant))])
        if span >= rel[-1]:
            break
        span *= 4
        grid = b + np.linspace(-2.0, 2.0, 41) * b * b / span
        grid = grid[grid > 0]
    a = float(t[0]) + b * float(np.angle(np.exp(2j * np.pi * rel / b).mean())) / (2 * np.pi)
    n = np.round((t - a) / b)
    b, a = (float(v) for v in np.polyfit(n, t, 1))
    if not b > 0:
        return None
    n = np.round((t - a) / b)
    if np.any(np.diff(n) <= 0):
        return None
    clock = a + b * n
    if float(np.max(np.abs(t - clock))) >= 0.5 * b:
        return None
    return np.asarray(clock, dtype=float)


def _rate_noise(t: FloatArray, theta: FloatArray) -> float:
    """The robust spread (:func:`mad_sigma`) of the second differences of a heading's
    differenced rate ``d theta / d t``: its white part (a smooth motion's second differences
    are small at a dense reference's rate)."""
    dt = np.diff(t)
    ok = dt > 0
    return mad_sigma(np.diff(np.diff(theta)[ok] / dt[ok], n=2))


def on_regular_clock(
    table: Table, ref: tuple[FloatArray, FloatArray]
) -> tuple[tuple[FloatArray, FloatArray], str | None]:
    """``ref`` (a dense heading, :func:`heading_reference` of ``table``) read on the regular
    clock its stamps jitter around (:func:`regular_clock`) when its differenced rate is far less
    noisy there (below :data:`REGULAR_CLOCK_GAIN` of the stamped one's), with a note; else
    ``ref`` as stamped and None.

    Stamps a host takes on receipt jitter around the sensor's clock: 2 ms at 100 Hz make the
    differenced rate wrong by a fifth of the rate, which attenuates a fitted gain (-7 %) and hides
    a bias in rate space. Stamps that are right where the sampling is irregular (an event-driven
    tracker) make the rate on a regular clock the noisier one, and stay.
    """
    if "regular" not in table.derived:  # once per table: a decimated subset shares it
        table.derived["regular"] = (ref, None)
        clock = regular_clock(ref[0])
        if clock is not None:
            stamped, regular = _rate_noise(*ref), _rate_noise(clock, ref[1])
            if stamped > 0 and regular < REGULAR_CLOCK_GAIN * stamped:
                jitter = float(np.std(ref[0] - clock))
                table.derived["regular"] = ((clock, ref[1]), (
                    f"the reference's stamps jitter around a regular "
                    f"{1 / float(np.median(np.diff(clock))):.4g} Hz clock (by "
                    f"{1e3 * jitter:.3g} ms RMS): its heading is read on that clock, "
                    f"where its differenced rate's noise is {regular / stamped:.2g} of the stamped "
                    "one's (a host that stamps on receipt; stamped jitter would attenuate a "
                    "fitted gain and hide a bias)"
                ))
    out: tuple[tuple[FloatArray, FloatArray], str | None] = table.derived["regular"]
    return out


def _rate_of(t: FloatArray, theta: FloatArray, t_out: FloatArray) -> FloatArray:
    """Rate of a heading series at ``t_out``: finite differences at midpoints, interpolated."""
    dt = np.diff(t)
    ok = dt > 0
    mid = 0.5 * (t[1:] + t[:-1])[ok]
    rate = (np.diff(theta)[ok]) / dt[ok]
    return np.interp(t_out, mid, rate)


#: the held-out part's heading span, as a share of the fit part's, below which the report says
#: the held-out part holds little motion
STILL_HELDOUT_SHARE = 0.1


def _note_still_heldout(problem: ScalarProblem, t: FloatArray, theta: FloatArray) -> None:
    """Say so when one part of the split holds little of the motion the other holds: a gain or
    a time offset is then fitted (the fit part) or scored (the held-out part) there only
    through what it does to the bias (a new user's gyro turned once, by hand, in the first 60 %
    of the recording; another's level segments turned only in the last 40 %). The span is the
    2nd-98th percentile range of the reference heading at the stream's rows of each part (so
    that its own noise does not count as motion, nor the tilted stretches a level stream
    leaves out)."""
    heading = np.interp(problem.t, t, theta)
    fit_rows = problem.split.mask(problem.t, "fit")

    def span(rows: np.ndarray) -> float:
        th = heading[rows]
        return float(np.subtract(*np.percentile(th, [98, 2]))) if th.size > 1 else 0.0

    fit, held = span(fit_rows), span(~fit_rows)
    if fit > 0 and held < STILL_HELDOUT_SHARE * fit:
        problem.notes.append(
            f"the held-out part holds little motion (its heading spans {held:.3g} rad, the fit "
            f"part's {fit:.3g}): a gain or a time offset is scored there only through what it "
            "does to the bias; record turns in the last 40 % of the time too"
        )
    elif held > 0 and fit < STILL_HELDOUT_SHARE * held:
        problem.notes.append(
            f"the fit part holds little motion (its heading spans {fit:.3g} rad, the held-out "
            f"part's {held:.3g}): a gain or a time offset is fitted there only through what it "
            "does to the bias; record turns in the first 60 % of the time too"
        )


#: a step of the reference heading between two of its samples that differs from the readings'
#: integral over it by more than this (rad) is a jump of the reference
HEADING_JUMP_RAD = 0.5 * np.pi


def _note_heading_jumps(problem: ScalarProblem, t: FloatArray, theta: FloatArray) -> None:
    """Say so when the reference heading jumps where the gyro does not turn: between two of its
    samples at most a second apart it changes by more than :data:`HEADING_JUMP_RAD` from what
    the readings integrate to. The heading of a sensor tilted past 90 deg is not defined, and
    one derived from an orientation flips by pi there (a new user's robot arm: four flips in
    31 s, reported as "better by 18 %" in rad/s of 4)."""
    inside = (t >= problem.t[0]) & (t <= problem.t[-1])
    if inside.sum() < 2:
        return
    tr, th = t[inside], theta[inside]
    turned = np.interp(tr, problem.t, cumulative_trapezoid(problem.y, problem.t, initial=0.0))
    # samples at most a second apart: across a gap a gyro's bias alone may add up to that;
    # and the reference itself steps that far (a gyro read in deg/s turns 57 times the
    # reference's smooth path: that is the readings' unit, not a jump of the reference)
    step = np.diff(th)
    off = ((np.abs(step - np.diff(turned)) > HEADING_JUMP_RAD)
           & (np.abs(step) > HEADING_JUMP_RAD) & (np.diff(tr) <= 1.0))
    if off.any():
        first = float(tr[np.flatnonzero(off)[0]])
        problem.notes.append(
            f"the reference heading jumps {int(off.sum())} time(s) where the gyro does not turn "
            f"(by more than {HEADING_JUMP_RAD:.3g} rad between two of its samples, first at "
            f"t = {first:.6g} s): a heading derived from an orientation tilted past 90 deg "
            "flips by pi there, and a heading is not defined; give the heading of a level "
            "segment, or of the sensor's own axis (docs/bundle-format.md)"
        )


def heading_window(split: Split) -> float:
    """:data:`HEADING_WINDOW_S`, or a quarter of the held-out part where that is shorter (3
    significant digits): the rate-space heading metric's window, and heading space's on the
    level segments of a gyro moved in 3-D (:mod:`.level`)."""
    return float(f"{min(HEADING_WINDOW_S, (split.t2 - split.t1) / 4):.3g}")


def _in_heading_space(problem: ScalarProblem) -> None:
    """A gyro scored by its heading over :data:`HEADING_WINDOW_S` windows, the residual rate
    integrated (:attr:`ScalarProblem.integrate_window_s`), instead of by its rate.

    Level segments (:attr:`ScalarProblem.window_gap_s` set) are short and held out a few at
    most, and so is a recording against a tracker whose held-out part is shorter than two
    windows: their windows are :func:`heading_window`'s, so that the held-out part holds four
    at least. A real IMU's last still segment, 13 s, was one 10 s window held out, about 1.25
    independent units: its -0.011 rad/s bias, 94 % better there, could not pass; a navX gyro's
    15 s against motion capture (6 s held out) kept a 37 ms latency unnamed for the same reason,
    where a hand fit's held-out error was 76 % lower. Against a compass heading the windows
    stay 10 s: its errors (iron, tilt) are bounded, not growing with the window, and over 2.4 s
    windows they hid the bias a still recording had measured (``mpu6050_turns``)."""
    held_out = problem.split.t2 - problem.split.t1
    short = problem.window_gap_s is not None or (
        problem.tracker_heading and held_out < 2 * HEADING_WINDOW_S)
    window = heading_window(problem.split) if short else HEADING_WINDOW_S
    problem.metric = running_heading_metric(window)
    problem.unit = "rad"
    problem.heading_window_s = None
    problem.integrate_window_s = window


def to_heading_space(problem: ScalarProblem, share: float, of_residual: float = 0.0) -> None:
    """Compare a gyro with its dense reference in heading space, as with a compass: over
    :data:`HEADING_WINDOW_S` windows, the residual rate integrated
    (:attr:`ScalarProblem.integrate_window_s`). For a reference whose differenced rate is
    mostly its own noise (``share``, ``effects.common.reference_noise_share`` above
    ``effects.common.MAX_REFERENCE_NOISE_SHARE``): white noise grows with differencing and shrinks
    with integration, so rates compared with it say nothing. An MPU-6050 turned by hand against
    its accelerometer's roll angle (81 % noise) kept a 0.057 rad/s bias unnamed in rate space;
    in heading space the bias is found as a hand fit finds it. A scale is then judged against
    the heading's noise share in heading space (``heading_share``, measured by
    :meth:`ScalarProblem.heading_noise_share` on the whole stream: the pipeline sets it;
    ``effects.common.reference_dominates``): the heading's path over a window is its regressor.
    A time offset stays judged against the rate's share: a time shift smooths the reference's
    noise. ``of_residual``: that noise over the rate residual's variance
    (``pipeline._reference_noise``) when it, not ``share``, sent the stream here (0 else)."""
    _in_heading_space(problem)
    if not of_residual:
        what = f"the reference rate is {100 * share:.3g} % its own noise once differenced"
    else:
        what = (f"the reference rate's own noise once differenced, {100 * share:.3g} % of its "
                f"variance (the robot turns fast), is {100 * min(of_residual, 1.0):.3g} % of "
                "the rate residual's")
    problem.notes.append(
        f"compared in heading space ({problem.integrate_window_s:g} s windows): {what} "
        f"(white noise grows with "
        "differencing, shrinks with integration), so rates compared with it would say nothing; "
        "a reference with less noise, or more motion, is compared rate with rate. No Allan "
        "analysis and no noise density (--write-noise) come from it: the residual's noise "
        "would be the reference's"
    )


def _interval_means(t: FloatArray, y: FloatArray, t_ref: FloatArray) -> FloatArray:
    """Readings ``y`` at ``t`` as the reference's differenced rate is: their mean over each
    interval between the reference's samples ``t_ref`` (trapezoid), at its middle, interpolated
    to ``t`` as :func:`_rate_of` interpolates the reference's. NaN where an interval the rows
    draw on is not covered by readings (a gap of half the reference's median interval or more:
    a level stream's tilted stretches left out; a link that delivers readings in bursts leaves
    gaps of a few of their intervals, which do not count)."""
    if t.size < 2 or t_ref.size < 2:
        return np.full(t.shape, np.nan)
    gaps = np.diff(t)
    big = np.r_[0, np.cumsum(gaps >= 0.5 * float(np.median(np.diff(t_ref))))]
    lo, hi = np.searchsorted(t, t_ref[:-1]), np.searchsorted(t, t_ref[1:])
    covered = (lo >= 1) & (hi <= t.size - 1) & (t_ref[1:] > t_ref[:-1])
    covered[covered] &= big[hi[covered]] == big[lo[covered] - 1]
    at = np.interp(t_ref, t, cumulative_trapezoid(y, t, initial=0.0))
    width = np.diff(t_ref)
    means = np.where(covered, np.diff(at) / np.where(width > 0, width, 1.0), np.nan)
    mid = 0.5 * (t_ref[1:] + t_ref[:-1])
    ok = width > 0
    return np.asarray(np.interp(t, mid[ok], means[ok]), dtype=float)


#: a dense reference is sparse beside the readings when its median sample interval is at least
#: this many of theirs (:attr:`ScalarProblem.sparse_reference_t`)
SPARSE_REFERENCE_RATIO = 3.0


def _sparse_means(
    bundle: Bundle,
    ref: tuple[FloatArray, FloatArray],
    t: FloatArray,
    readings: FloatArray,
    average: bool,
) -> tuple[bool, FloatArray | None]:
    """Whether the dense reference ``ref`` is sparse beside the gyro's readings
    (:data:`SPARSE_REFERENCE_RATIO`), and, when it is, ``average`` asks for it and it turns,
    the readings' means over its intervals at ``t`` (:func:`_interval_means`; NaN where not
    covered), else None. A decimated subset decides, and takes the means, on the whole stream's
    consecutive rows (``bundle.whole``: its random rows are not sparse beside a 25 Hz reference
    where the stream's are). A reference that does not turn (a still gyro against a constant
    heading every 30 s) makes an instantaneous reading its interval's mean, and the readings
    keep their noise for the Allan analysis."""
    whole = bundle.whole.get("gyro") if bundle.whole is not None else None
    t_all, y_all = t, readings
    if whole is not None:
        tw, yw = whole["t"], whole["yaw_rate"]
        ok = np.isfinite(yw) & (tw >= ref[0][0]) & (tw <= ref[0][-1])
        t_all, y_all = tw[ok], yw[ok]
    if ref[0].size < 2 or t_all.size < 2:
        return False, None
    if np.median(np.diff(ref[0])) < SPARSE_REFERENCE_RATIO * np.median(np.diff(t_all)):
        return False, None
    during = ref[1][(ref[0] >= t[0]) & (ref[0] <= t[-1])]
    if not average or during.size < 2 or np.ptp(during) <= 0:
        return True, None
    means = _interval_means(t_all, y_all, ref[0])
    # at the subset's rows, which are among the whole stream's
    return True, means if whole is None else np.interp(t, t_all, means)


#: the share of held-out readings beyond an IR response curve's ranges that is said
BEYOND_CURVE_SHARE = 0.1


def _note_beyond_curve(problem: ScalarProblem, ranges: FloatArray, fitted: bool) -> str | None:
    """A note when :data:`BEYOND_CURVE_SHARE` or more of the held-out readings' true ranges lie
    outside the response curve's (where it is held at its end values). An IR sensor logged
    while the robot drove away from a wall put 0.10-0.50 m in the fit part and 0.50-0.88 m in
    the held-out one: the curve fitted on the first was held flat over the second, every
    candidate failed, and the report said "unchanged"."""
    score = ~problem.split.mask(problem.t, "fit")
    u = problem.u[score]
    u = u[np.isfinite(u)]
    if u.size == 0 or ranges.size < 2:
        return None
    lo, hi = float(np.min(ranges)), float(np.max(ranges))
    outside = float(np.mean((u < lo) | (u > hi)))
    if outside < BEYOND_CURVE_SHARE:
        return None
    why = (
        "fitted on the fit part's readings: the two parts cover other ranges (a sweep "
        "towards or away from a wall, split in time). Record both parts over the same ranges "
        "(sweep out and back), or declare the curve ([sensors.ir] response_range_m and "
        "response_counts)"
        if fitted else
        "declared: the readings reach beyond it (the sensor's rated range?). Leave them out, "
        "or declare the curve over their ranges"
    )
    return (
        f"{100 * outside:.0f} % of the held-out readings' true ranges "
        f"({float(np.min(u)):.3g}-{float(np.max(u)):.3g} m) lie beyond the response curve's "
        f"{lo:.3g}-{hi:.3g} m, where it is held at its end value and the held-out error "
        f"measures that, not the sensor. The curve is {why}"
    )


def _sample_means(
    t: FloatArray, values: FloatArray, t_ref: FloatArray
) -> tuple[NDArray[np.intp], FloatArray, NDArray[np.intp]]:
    """Readings ``values`` (N, k) at ``t`` averaged over each reference sample's share of time
    (from the midpoint with the sample before to the one with the sample after): the indices
    of the reference samples that got readings, the means (M, k) and how many each averaged.
    A compass against a sparse heading reference is compared at the reference's samples: an
    affine model (hard and soft iron, a declared disturbance) of the mean is the mean of the
    model, and the readings' noise averages down instead of being counted once per reading
    against one interpolated heading. A share reaches at most half the reference's median
    interval from its sample: across a gap in the reference (a tracker that lost the robot for
    3 s) the samples at its edges would otherwise average the turning of half the gap each
    (0.42 rad of error on a steady turn), and readings farther from any sample are left out."""
    mid = 0.5 * (t_ref[1:] + t_ref[:-1])
    k = np.searchsorted(mid, t, side="right")  # the reference sample each reading belongs to
    near = np.abs(t - t_ref[k]) <= 0.5 * float(np.median(np.diff(t_ref)))
    k, values = k[near], values[near]
    counts = np.bincount(k, minlength=t_ref.size)
    means = np.column_stack([np.bincount(k, values[:, j], t_ref.size) for j in
                             range(values.shape[1])])
    got = np.flatnonzero(counts)
    return got, means[got] / counts[got, None], counts[got]


def _moving_average(v: FloatArray, n: int) -> FloatArray:
    if n <= 1:
        return v
    pad = np.pad(v, (n // 2, n - 1 - n // 2), mode="edge")
    return np.convolve(pad, np.ones(n) / n, mode="valid")


def unknown_files(bundle: Bundle) -> list[SkippedStream]:
    """A :class:`SkippedStream` for each CSV file of the bundle directory the format does not
    know (``bundle.unknown_files``): its rows were not read, and the report says so, with the
    file it most likely should be (range beacons under ``uwb.csv`` once left a bundle with
    truth_pose alone: 'no stream has a reference')."""
    out = []
    for name in bundle.unknown_files:
        stem = name.removesuffix(".csv")
        close = get_close_matches(stem, list(REQUIRED_COLUMNS), n=1, cutoff=0.6)
        if close:
            fix = (
                f"if it holds that stream, name it {close[0]}.csv with the columns "
                f"{','.join(REQUIRED_COLUMNS[close[0]])}"
            )
        else:
            fix = (
                "put its measurements into a file of the format: range.csv (t,sensor,measured,"
                "true_range, a kind column such as uwb for range beacons), landmarks.csv with "
                "landmark_map.csv (beacons or landmarks at surveyed positions), gyro.csv, "
                "compass.csv or odometry.csv"
            )
        out.append(
            SkippedStream(
                name, "not a file of the bundle format: not read", f"{fix}; see {FORMAT_DOC}"
            )
        )
    return out


def build_gyro(
    bundle: Bundle,
    model: DeclaredModel,
    compass_heading: tuple[FloatArray, FloatArray] | None = None,
    skipped: list[SkippedStream] | None = None,
) -> ScalarProblem | None:
    gyro = bundle.get("gyro")
    if gyro is None:
        return None
    ref = heading_reference(bundle)
    source = "truth_pose.theta"
    if ref is None and compass_heading is not None:
        # Resample to a uniform grid first: compass stamps are irregular and readings repeat.
        t_c, th_c = compass_heading
        step = COMPASS_SMOOTHING_S / 5
        grid = np.arange(t_c[0], t_c[-1], step)
        ref = (grid, _moving_average(np.interp(grid, t_c, np.unwrap(th_c)), 5))
        source = "calibrated compass heading (no truth heading in the bundle)"
    if ref is None:
        truth = bundle.get("truth_pose")
        if truth is None:
            no_truth = "no truth_pose.csv"
        elif "theta" not in truth.columns:
            no_truth = "truth_pose.csv has no theta column"
        else:
            no_truth = "truth_pose.csv's theta is empty"
        no_compass = (
            "no compass.csv"
            if bundle.get("compass") is None
            else "compass.csv gives no heading (its field varies in 3-D: the sensor tilted)"
        )
        _skip(
            skipped,
            "gyro",
            f"no heading reference: {no_truth}, and {no_compass}",
            "add theta (rad, counter-clockwise from the world x axis) per row to truth_pose.csv, "
            f"or a compass.csv turning in the horizontal plane; see {FORMAT_DOC}",
        )
        return None
    dense = source == "truth_pose.theta"
    clock_note = None
    if dense:
        ref, clock_note = on_regular_clock(bundle.tables["truth_pose"], ref)
    t = gyro["t"]
    inside = (t >= ref[0][0]) & (t <= ref[0][-1]) & np.isfinite(gyro["yaw_rate"])
    if inside.sum() < MIN_ROWS:
        _skip(
            skipped,
            "gyro",
            f"{int(inside.sum())} rows with a yaw_rate inside the reference's time span "
            f"{ref[0][0]:.6g}..{ref[0][-1]:.6g} s ({source}); at least {MIN_ROWS} needed",
            f"stamp every file on one clock (t in seconds), and record the reference while the "
            f"gyro runs; see {FORMAT_DOC}",
        )
        return None
    table = gyro.select(inside)
    outside = int((~inside).sum())
    t = table["t"]
    interval = model.gyro_sample_interval_s
    if interval is not None and dense:
        # The declared sample is the mean rate over the interval before its stamp.
        rate_ref = (np.interp(t, *ref) - np.interp(t - interval, *ref)) / interval
    else:
        rate_ref = _rate_of(ref[0], ref[1], t)
    clipped = saturated(table["yaw_rate"], rate_ref)
    if clipped is not None:
        table, t, rate_ref = table.select(~clipped[0]), t[~clipped[0]], rate_ref[~clipped[0]]
    spiked = spikes(table["yaw_rate"], rate_ref)
    if spiked is not None:
        table, t, rate_ref = table.select(~spiked[0]), t[~spiked[0]], rate_ref[~spiked[0]]
    readings = table["yaw_rate"]
    sparse, means = _sparse_means(bundle, ref, t, readings, interval is None) if dense else (
        False, None)
    averaged = False
    if means is not None:
        keep = np.isfinite(means)
        if keep.sum() >= MIN_ROWS:
            averaged = True
            table, t, rate_ref, readings = table.select(keep), t[keep], rate_ref[keep], means[keep]
    ref_series = (t.copy(), rate_ref.copy())
    extras = _extras(table, {"t", "yaw_rate"})
    split = Split.of(t)
    window = heading_window(split)
    problem = ScalarProblem(
        "gyro",
        "scalar",
        "rms_rate_error",
        "rad/s",
        "sensors.gyro",
        split,
        t=t,
        y=readings,
        u=rate_ref,
        columns=extras,
        covariate_names=tuple(sorted(extras)),
        categorical_names=tuple(
            k
            for k in sorted(extras)
            if categorical_levels(extras[k][split.mask(t, "fit")]) is not None
        ),
        reference=ref_series,
        base_gain=1.0 + model.gyro_scale_error,
        base_add=model.gyro_bias_rad_s,
        heading_window_s=window,
        quantity="yaw rate",
        native_keys={"bias": "bias_rad_s", "scale": "scale_factor_error"},
        declared_values={"bias": model.gyro_bias_rad_s, "scale": model.gyro_scale_error},
        turn_on_bias_sigma=model.gyro_turn_on_bias_sigma,
        # readings averaged over the reference's intervals are no sample's noise
        noise_key=None if averaged else "gyroscope_noise_density",
        known_rotation=_known_rotation(bundle.meta),
        heading_ref=ref,
        tracker_heading=dense,
        heading_interval_s=interval if dense else None,
        sparse_reference_t=ref[0] if sparse else None,
    )
    if bundle.faults is not None and len(bundle.faults) and t.size > 2:
        # readings a fault log set aside leave gaps (a kidnap's, a stuck window's) the
        # reference turned across: heading windows start again after each (a kidnap turning
        # the robot in the held-out part read a right bias as 1.3 % worse, 0.94 rad)
        problem.window_gap_s = FAULT_GAP_INTERVALS * float(np.median(np.diff(t)))
    problem.notes.append(f"reference: {source}")
    for aside in (clipped, spiked):
        if aside is not None:
            problem.notes.append(aside[1])
    if outside:
        problem.notes.append(
            f"{outside} gyro.csv row(s) outside the reference's time span "
            f"({ref[0][0]:.6g}-{ref[0][-1]:.6g} s) or with an empty yaw_rate left out"
        )
    if means is not None and not averaged:
        problem.notes.append(
            "not compared as means over the reference's intervals, as a sparse reference asks: "
            "too few of its intervals are covered by readings without a gap of half an "
            "interval (readings that arrive in bursts?); an instantaneous reading is larger "
            "than the reference's differenced rate by the motion's sinc, and a scale may show it"
        )
    if averaged:
        problem.notes.append(
            f"compared as means over the reference's intervals (every "
            f"{float(np.median(np.diff(ref[0]))):.3g} s, sparse beside the readings' "
            f"{float(np.median(np.diff(t))):.3g} s): a rate differenced from the reference is "
            "such a mean, an instantaneous reading is not (a clean gyro read +1.3 % of scale "
            "against a 4 Hz reference); no noise density comes from them"
        )
    if clock_note is not None:
        problem.notes.append(clock_note)
    if not dense:
        _in_heading_space(problem)
        problem.notes.append(
            "a compass heading holds errors of its own (tilt, iron) that can hide a gyro bias "
            "or scale: measure those on a recording with a better reference (the sensor lying "
            "still) and give it first, `koala-bridge calibrate STILL THIS` (staged, "
            "docs/calibration.md)"
        )
    if interval is not None and dense:
        problem.notes.append(f"declared sample: mean rate over the {interval:g} s before it")
    if dense:
        _note_still_heldout(problem, *ref)
        _note_heading_jumps(problem, *ref)
    if model.gyro_turn_on_bias_sigma > 0:
        problem.notes.append(
            "declared turn-on bias N(bias_rad_s, "
            f"{model.gyro_turn_on_bias_sigma:g}^2) fitted as a nuisance"
        )
    return problem


def _known_rotation(meta: Mapping[str, Any]) -> tuple[float, float, float] | None:
    """``meta.json`` ``reference``: ``total_rotation_rad`` from ``from_t`` to ``to_t`` (a net
    rotation known without a continuous reference, e.g. "two full turns")."""
    ref = meta.get("reference")
    if not isinstance(ref, Mapping):
        return None
    vals = [ref.get(k) for k in ("from_t", "to_t", "total_rotation_rad")]
    if not all(isinstance(v, int | float) and not isinstance(v, bool) for v in vals):
        return None
    return (float(vals[0]), float(vals[1]), float(vals[2]))  # type: ignore[arg-type]


def _declared_sonar_sigma(model: DeclaredModel, true_range: FloatArray) -> FloatArray | None:
    """The declared sonar's noise sigma at each true range (its distance-error table), if any."""
    if model.sonar_distance_error is None:
        return None
    from koala_bridge.sim.models.sonar import distance_sigma

    xs, ys = model.sonar_distance_error
    return np.asarray(distance_sigma(true_range, np.asarray(xs), np.asarray(ys)), dtype=float)


def _range_unit(meta: Mapping[str, Any], kind: str) -> str:
    """The unit of ``range.measured`` for one kind: ``units["range.measured"]`` is a string, or
    a ``{kind: unit}`` table (bundles exported from recordings), or ``range.measured.<kind>``."""
    units = meta.get("units", {})
    if not isinstance(units, Mapping):
        return ""
    if kind and isinstance(units.get(f"range.measured.{kind}"), str):
        return str(units[f"range.measured.{kind}"])
    value = units.get("range.measured", "")
    if isinstance(value, Mapping):
        return str(value.get(kind, ""))
    return str(value)


#: length units a user may declare for a range column, with their size in metres
LENGTH_UNITS = {"mm": 1e-3, "millimetre": 1e-3, "millimetres": 1e-3, "millimeter": 1e-3,
                "millimeters": 1e-3, "cm": 1e-2, "centimetre": 1e-2, "centimetres": 1e-2,
                "centimeter": 1e-2, "centimeters": 1e-2, "in": 0.0254, "inch": 0.0254,
                "inches": 0.0254, "ft": 0.3048, "feet": 0.3048, "km": 1e3}
#: voltage units an IR sensor's output may be declared in
VOLTAGE_UNITS = ("v", "volt", "volts", "mv", "millivolt", "millivolts")


def _range_unit_notes(meta: Mapping[str, Any], kind: str, counts: bool) -> list[str]:
    """Notes for ``range.csv`` columns whose declared unit (``meta.json`` ``units``) is not the
    one they are read in: ``true_range`` (and a metric ``measured``) are read as metres, an IR
    sensor's ``measured`` as counts. A user's bundle declared ``"range.true_range": "cm"``, and
    the notes blamed the recording ("the reference does not vary"); another declared its IR
    readings in volts, and a scale of 0.0054 was reported as found."""
    out = []
    truth = _unit(meta, "range.true_range").strip().lower()
    measured = _range_unit(meta, kind).strip().lower()
    for column, unit, metric in (("true_range", truth, True), ("measured", measured, not counts)):
        first = unit.split()[0].strip("(),;:") if unit else ""
        if metric and first in LENGTH_UNITS:
            out.append(
                f"{column} is declared in {unit!r} (meta.json units) and read as metres, the "
                f"bundle format's unit: convert it (x {LENGTH_UNITS[first]:g}); see {FORMAT_DOC}"
            )
        elif column == "measured" and counts and first in VOLTAGE_UNITS:
            out.append(
                f"measured is declared in {unit!r} (meta.json units) and read as counts, as an "
                "IR sensor's output is: convert it to the ADC's counts (a 10-bit ADC at 5 V: "
                f"x 1023 / 5), or the response curve and every offset are in volts; see "
                f"{FORMAT_DOC}"
            )
    return out


#: the Earth's field at its surface (uT, total): a compass's readings far outside it (by 3x) are
#: likely in another unit than the one they are read in
EARTH_FIELD_UT = (25.0, 65.0)


def _compass_unit(meta: Mapping[str, Any]) -> tuple[str, float]:
    u = _unit(meta, "compass.mx").lower()
    if "milligauss" in u or u.startswith("mg"):
        return "mG", 0.1
    if "gauss" in u:
        return "gauss", 100.0
    if "nt" in u.split() or u.startswith("nt"):
        return "nT", 0.001
    return "uT", 1.0


def build_compass(
    bundle: Bundle, model: DeclaredModel, skipped: list[SkippedStream] | None = None
) -> CompassProblem | None:
    compass = bundle.get("compass")
    if compass is None:
        return None
    ok = np.isfinite(compass["mx"]) & np.isfinite(compass["my"])
    compass = compass.select(ok)
    t = compass["t"]
    mz = compass["mz"] if "mz" in compass.columns else np.zeros_like(t)
    m = np.column_stack([compass["mx"], compass["my"], np.nan_to_num(mz)])
    unit, uT = _compass_unit(bundle.meta)
    ref = heading_reference(bundle)
    theta = None
    direction = None
    level_note = sparse_note = None
    reading_dt: float | None = None
    disturbance: FloatArray | None = None
    if ref is not None:
        inside = (t >= ref[0][0]) & (t <= ref[0][-1])
        if inside.sum() < MIN_ROWS:
            _skip(
                skipped,
                "compass",
                f"{int(inside.sum())} rows inside truth_pose.csv's time span "
                f"{ref[0][0]:.6g}..{ref[0][-1]:.6g} s; at least {MIN_ROWS} needed",
                "stamp every file on one clock (t in seconds), or leave theta out of "
                f"truth_pose.csv to calibrate on the field magnitude alone; see {FORMAT_DOC}",
            )
            return None
        t, m = t[inside], m[inside]
        level = _compass_level(bundle, t)
        if level is not None:
            keep, how = level
            if int(keep.sum()) < MIN_ROWS:
                _skip(
                    skipped,
                    "compass",
                    f"the sensor tilts: {int(keep.sum())} of {keep.size} readings level "
                    f"({how}), at least {MIN_ROWS} needed; a tilted magnetometer's x and y do "
                    "not give the heading",
                    "record stretches with the sensor level (turning about the vertical), or "
                    "leave theta out of truth_pose.csv to calibrate the 3-D field magnitude; "
                    f"see {FORMAT_DOC}",
                )
                return None
            level_note = (
                f"level readings only ({how}): {int(keep.sum())} of {keep.size}; a tilted "
                "magnetometer's x and y do not give the heading"
            )
            t, m = t[keep], m[keep]
        disturbance = _declared_motor_field(bundle, model, t, uT)
        theta = np.interp(t, ref[0], ref[1])
        span = (ref[0] >= t[0]) & (ref[0] <= t[-1])
        if (
            span.sum() >= MIN_ROWS
            and np.median(np.diff(ref[0])) >= SPARSE_REFERENCE_RATIO * np.median(np.diff(t))
        ):
            t_ref, theta_ref = ref[0][span], ref[1][span]
            cols = m if disturbance is None else np.column_stack([m, disturbance])
            got, means, counts = _sample_means(t, cols, t_ref)
            sparse_note = (
                f"the reference heading is sparse beside the compass (every "
                f"{np.median(np.diff(t_ref)):.3g} s against {np.median(np.diff(t)):.3g} s): "
                f"compared at its {got.size} samples, each with the mean of its share of the "
                f"{t.size} readings (median {int(np.median(counts))}, {int(counts.sum())} in "
                "all: none farther than half its interval from a sample); between its samples "
                "the interpolated heading would be shared by every reading"
            )
            reading_dt = float(np.median(np.diff(t)))
            t, theta = t_ref[got], theta_ref[got]
            m = means[:, :3]
            disturbance = None if disturbance is None else means[:, 3:]
        mode = "heading"
        direction = _declared_field_direction(bundle, model, t)
    else:
        horiz = float(min(np.std(m[:, 0]), np.std(m[:, 1])))
        mode = "magnitude_3d" if np.std(m[:, 2]) > 0.25 * horiz else "magnitude_2d"
    problem = CompassProblem(
        "compass",
        "compass",
        "rms_heading_error"
        if mode == "heading"
        else (
            "field_magnitude_spread"
            if mode == "magnitude_3d"
            else "horizontal_field_magnitude_spread"
        ),
        "rad" if mode == "heading" else "%",
        "sensors.compass",
        Split.of(t),
        t=t,
        m=m,
        mode=mode,
        theta_ref=theta,
        h_declared=np.asarray(model.compass_hard_iron, dtype=float) / uT,
        C_declared=np.linalg.inv(np.asarray(model.compass_soft_iron, dtype=float)),
        uT_per_unit=uT,
        data_unit=unit,
        disturbance=disturbance if mode == "heading"
        else _declared_motor_field(bundle, model, t, uT),
        field_direction=direction,
        gyro_heading=_declared_gyro_heading(bundle, model, t) if mode == "magnitude_2d" else None,
        ref_t=None if ref is None else ref[0],
        ref_heading=None if ref is None else ref[1],
        reading_dt=reading_dt,
    )
    problem.notes.append(f"mode: {mode}; field unit {unit}")
    field = float(np.median(np.linalg.norm(m, axis=1))) * uT
    if not EARTH_FIELD_UT[0] / 3 <= field <= 3 * EARTH_FIELD_UT[1]:
        declared = _unit(bundle.meta, "compass.mx")
        problem.notes.append(
            f"the field's median magnitude reads {field:.3g} uT "
            + (f"(compass.mx declared as {declared!r}, read as {unit})" if declared
               else "(no unit declared: read as uT)")
            + f", where the Earth's is {EARTH_FIELD_UT[0]:g}-{EARTH_FIELD_UT[1]:g} uT: if the "
            "readings are in another unit (nT, gauss, mG, raw counts), declare it in meta.json "
            '(units: {"compass.mx": "nT"}); a heading does not depend on it, the hard iron\'s '
            "size in uT and the written config do"
        )
    if level_note is not None:
        problem.notes.append(level_note)
    if sparse_note is not None:
        problem.notes.append(sparse_note)
    if problem.gyro_heading is not None:
        problem.notes.append(
            "second metric: heading against the gyro integrated under its declared model "
            f"(bias {model.gyro_bias_rad_s:g} rad/s, scale error {model.gyro_scale_error:g})"
        )
    if problem.disturbance is not None:
        problem.notes.append("declared motor-current field subtracted (speeds from the ticks)")
    if direction is not None:
        problem.notes.append("declared local magnetic sources: field direction per position")
    return problem


def _compass_level(bundle: Bundle, t: FloatArray) -> tuple[NDArray[np.bool_], str] | None:
    """Which compass readings (stamps ``t``) were taken at the sensor's usual attitude, by the
    accelerometer of ``gyro.csv`` (:func:`streams.level.mounting_mask`: gravity within a few
    degrees of its median direction), and how that was found; None when the bundle has no
    accelerometer or the attitude held throughout (then nothing is set aside). A reading counts
    when the accelerometer samples on both sides of it do."""
    from koala_bridge.calibration.streams.level import mounting_mask

    gyro = bundle.get("gyro")
    if gyro is None or t.size == 0:
        return None
    found = mounting_mask(gyro)
    if found is None:
        return None
    mask, how = found
    tg = gyro["t"]
    order = np.argsort(tg, kind="stable")
    inside = (t >= tg[order[0]]) & (t <= tg[order[-1]])
    level = inside & (np.interp(t, tg[order], mask[order].astype(float)) >= 1.0)
    return level, how


def _declared_gyro_heading(
    bundle: Bundle, model: DeclaredModel, t_out: FloatArray
) -> FloatArray | None:
    """Heading integrated (trapezoid) from the gyro's yaw rate under the declared model,
    ``(yaw_rate - bias) / (1 + scale)``, at ``t_out`` (held at the ends, where the two streams'
    first and last stamps differ); None without a gyro over most of that span."""
    gyro = bundle.get("gyro")
    if gyro is None or t_out.size < 2:
        return None
    ok = np.isfinite(gyro["yaw_rate"])
    t, w = gyro["t"][ok], gyro["yaw_rate"][ok]
    span = float(t_out[-1] - t_out[0])
    if t.size < 2 or min(t[-1], t_out[-1]) - max(t[0], t_out[0]) < 0.9 * span:
        return None
    rate = (w - model.gyro_bias_rad_s) / (1.0 + model.gyro_scale_error)
    theta = cumulative_trapezoid(rate, t, initial=0.0)
    return np.asarray(np.interp(t_out, t, theta), dtype=float)


def _declared_field_direction(
    bundle: Bundle, model: DeclaredModel, t: FloatArray
) -> FloatArray | None:
    """World-frame direction of the declared horizontal field at the reference positions."""
    truth = bundle.get("truth_pose")
    if model.compass_world is None or truth is None or "x" not in truth.columns:
        return None
    from koala_bridge.sim.sensors.compass import field_world

    earth, sources, dmin = model.compass_world
    x, y = np.interp(t, truth["t"], truth["x"]), np.interp(t, truth["t"], truth["y"])
    b = np.array(
        [
            field_world(float(a), float(c), earth, sources, dmin)[:2]
            for a, c in zip(x, y, strict=True)
        ]
    )
    north = np.arctan2(earth[1], earth[0])
    return np.asarray(np.arctan2(b[:, 1], b[:, 0]) - north, dtype=float)


def _declared_motor_field(
    bundle: Bundle, model: DeclaredModel, t: FloatArray, uT_per_unit: float
) -> FloatArray | None:
    """(N, 3) the declared motor-current field at ``t`` (data unit), from the wheel speeds the
    odometry ticks give (each the mean over the interval before its sample, as the simulator's)."""
    odo = bundle.get("odometry")
    if (
        model.compass_motor_uT_per_mps is None
        or odo is None
        or not {"left_ticks", "right_ticks"} <= set(odo.columns)
        or model.ticks_per_metre is None
        or len(odo) < 2
    ):
        return None
    to = odo["t"]
    dt = np.diff(to)
    ok = dt > 0
    k = np.array(metres_per_tick(model.ticks_per_metre, model.wheel_diameter_ratio))
    v = np.column_stack([np.diff(odo["left_ticks"]), np.diff(odo["right_ticks"])])[ok]
    v = v / dt[ok, None] * k
    tv = to[1:][ok]
    speeds = np.column_stack([np.interp(t, tv, v[:, 0]), np.interp(t, tv, v[:, 1])])
    return np.asarray(speeds @ np.asarray(model.compass_motor_uT_per_mps).T / uT_per_unit)


#: an odometry that counts less than this travel and this turn over a whole recording never
#: moved: nothing in it shows the geometry (a run nothing drove reported "0 -> 0 m")
STILL_TRAVEL_M = 0.01
STILL_TURN_RAD = 0.05

#: odometry.csv's column sets, in the order a stream takes the first it has
ODOMETRY_FORMS = (("left_ticks", "right_ticks"), ("v", "omega"), ("x", "y", "theta"))


#: a gap of this many median intervals between a gyro's readings, in a bundle with a fault
#: log, starts a new heading window (the fault log's set-aside readings leave at least 4)
FAULT_GAP_INTERVALS = 3

#: readings equal to the stream's largest (smallest) value are a saturated sensor's when at
#: least SATURATED_ROWS of them, and SATURATED_SHARE of the readings, repeat it, and the
#: reference is beyond it on most of them
SATURATED_ROWS = 3
SATURATED_SHARE = 1e-3
#: ... and the reference over them spreads by at least this share of the extreme value
SATURATED_SPREAD = 0.1


def saturated(y: FloatArray, u: FloatArray) -> tuple[NDArray[np.bool_], str] | None:
    """The readings ``y`` pinned at the sensor's range's end, and a note; None when there are
    none. A reading that repeats the stream's extreme value while the reference ``u`` (in the
    readings' unit) is beyond it says "at least this much", not a value: a gyro clipped at
    +-250 deg/s read as a scale error the model lacked (7.6 % of readings pinned hid a real 2 %
    scale, unsaid). Set aside and counted; readings of another unit (the reference never
    beyond them) are kept."""
    ok = np.isfinite(y)
    if ok.sum() < 10:
        return None
    pinned = np.zeros(y.size, dtype=bool)
    ends = []
    for sign, end in ((1.0, float(np.max(y[ok]))), (-1.0, float(np.min(y[ok])))):
        hit = y == end  # the very value repeated (a NaN equals nothing)
        n = int(hit.sum())
        if n < max(SATURATED_ROWS, SATURATED_SHARE * ok.sum()) or n > 0.5 * ok.sum():
            continue
        beyond = sign * u[hit] > sign * end
        if end == 0.0 or sign * end < 0 or beyond.mean() < 0.5:
            continue
        # a sensor pinned while the motion goes on beyond it, not the top of its noise on a
        # plateau (an under-reading gyro rounded to 0.01 at a steady 1 rad/s spin)
        if float(np.ptp(u[hit])) < SATURATED_SPREAD * abs(end):
            continue
        pinned |= hit
        ends.append(f"{end:+.4g}")
    if not pinned.any():
        return None
    return pinned, (
        f"{int(pinned.sum())} readings pinned at the sensor's range's end ({', '.join(ends)}, "
        "where the reference turned faster) set aside: a saturated reading says 'at least "
        "this much', not a value"
    )


#: a reading is a spike when its residual is off both neighbours' by more than SPIKE_SD robust
#: standard deviations of the residual's second differences; set aside only while they are at
#: most SPIKE_SHARE of the readings (more is the noise's own tail)
SPIKE_SD = 30.0
SPIKE_SHARE = 0.01


def spikes(y: FloatArray, u: FloatArray) -> tuple[NDArray[np.bool_], str] | None:
    """Isolated readings far off their neighbours (a bus glitch: one sample of 30 rad/s between
    two of 0.1) and a note; None when there are none. Six such among 6000 readings (0.1 %) hid
    a real 3 % scale of a gyro: least squares is fitted robustly, but the selection's
    likelihood counts every residual, and theirs outweighed the rest. The residual against the
    reference ``u`` (in the readings' unit or not: a unit error is smooth) is compared with the
    mean of its two neighbours', against the robust spread of that difference over the stream."""
    ok = np.isfinite(y) & np.isfinite(u)
    if ok.sum() < 20:
        return None
    idx = np.flatnonzero(ok)
    r = y[idx] - u[idx]
    d = r[1:-1] - 0.5 * (r[:-2] + r[2:])
    sd = mad_sigma(d)
    if not sd > 0:
        return None
    far = np.abs(d) > SPIKE_SD * sd
    # off both neighbours: a step (a turn's start the reference is late for) is off one only
    far &= (np.abs(r[1:-1] - r[:-2]) > SPIKE_SD * sd) & (np.abs(r[1:-1] - r[2:]) > SPIKE_SD * sd)
    n = int(far.sum())
    if n == 0 or n > SPIKE_SHARE * idx.size:
        return None
    out = np.zeros(y.size, dtype=bool)
    out[idx[1:-1][far]] = True
    return out, (
        f"{n} isolated spike(s) set aside: readings off both neighbours by more than "
        f"{SPIKE_SD:g} robust standard deviations (up to {float(np.max(np.abs(d[far]))):.4g} "
        "in the readings' unit; a bus or conversion glitch, not the sensor's model)"
    )


#: unwrap_counter: the steps each side whose rate a wrap's step is held against, and how far
#: (a share of the counter's range) from what that rate expects it may lie
UNWRAP_NEIGHBOURS = 10
UNWRAP_TOLERANCE = 1 / 16


def unwrap_counter(
    c: FloatArray, t: FloatArray | None = None
) -> tuple[FloatArray, int | None, int]:
    """Cumulative encoder counts ``c`` (at times ``t``) unwrapped where a 16-, 24- or 32-bit
    counter wrapped, the counter's bits (None: no wrap) and how many wraps. A step beyond half the
    counter's range is a wrap when the step a whole range away is the one the neighbouring
    steps' rate expects over its interval (within ``UNWRAP_TOLERANCE`` of the range, or 8
    spreads of the neighbours' rate): a gap in the log across which the wheels counted 54 000
    ticks is no wrap, a counter reset from 60 000 to 0 is none either, and one long step does
    not keep the rest from being unwrapped. A 16-bit count's wrap read as wheels spinning
    against a wall: 12 spans, 16 % of the run, set aside as stalls."""
    d = np.diff(c)
    if d.size < 3 or not np.all(np.isfinite(c)):
        return c, None, 0
    dt = np.diff(t) if t is not None and t.size == c.size else np.ones(d.size)
    for bits in (16, 24, 32):
        m = float(2**bits)
        jumps = np.flatnonzero(np.abs(d) > m / 2)
        if jumps.size == 0 or float(np.max(c) - np.min(c)) >= 2 * m:
            continue
        plain = np.ones(d.size, dtype=bool)
        plain[jumps] = False
        rate = np.where(dt > 0, d / np.where(dt > 0, dt, 1.0), 0.0)
        out = d.copy()
        n = 0
        for j in jumps:
            lo = max(0, int(j) - UNWRAP_NEIGHBOURS)
            near = lo + np.flatnonzero(plain[lo:j + UNWRAP_NEIGHBOURS + 1])
            local = rate[near] if near.size else rate[plain]
            if local.size == 0:
                continue
            expected = float(np.median(local)) * float(dt[j])
            spread = 8 * float(np.median(np.abs(local - np.median(local)))) * float(dt[j])
            k = float(np.round(d[j] / m))
            wrapped, kept = abs(d[j] - k * m - expected), abs(d[j] - expected)
            if wrapped < kept and wrapped <= max(UNWRAP_TOLERANCE * m, spread):
                out[j] = d[j] - k * m
                n += int(abs(k))
        if n:
            return np.r_[c[0], c[0] + np.cumsum(out)], bits, n
    return c, None, 0



def _filled_rows(odo: Table) -> tuple[Table, str | None]:
    """``odo`` without the rows whose form's columns (:data:`ODOMETRY_FORMS`) have an empty
    cell, and a note saying which were left out (None when none were). One empty tick cell made
    every dead-reckoned window NaN, and the stream "not comparable" with no word why; cumulative
    counts lose nothing but that row's time, speeds and poses that sample."""
    for cols in ODOMETRY_FORMS:
        if all(c in odo.columns for c in cols):
            filled = np.all([np.isfinite(odo[c]) for c in cols], axis=0)
            if filled.all():
                return odo, None
            gone = np.flatnonzero(~filled)
            lines = ("" if odo.lines is None else " (line " + ", ".join(
                str(int(v)) for v in odo.lines[gone][:3]) + (", ..." if gone.size > 3 else "")
                + ")")
            return odo.select(filled), (
                f"{gone.size} odometry.csv row(s) with an empty {'/'.join(cols)} cell left "
                f"out{lines}: the rows on either side are dead-reckoned across them"
            )
    return odo, None


def build_odometry(
    bundle: Bundle,
    model: DeclaredModel,
    window_s: float = 10.0,
    skipped: list[SkippedStream] | None = None,
) -> OdometryProblem | None:
    odo, truth = bundle.get("odometry"), bundle.get("truth_pose")
    if odo is not None and truth is None:
        # e.g. a real robot's recording: nothing says where the wheels took it
        _skip(
            skipped,
            "odometry",
            "no reference pose: the bundle has no truth_pose.csv",
            "add truth_pose.csv (t,x,y[,theta] in m and rad: a tracker, or the positions of a "
            f"measured path); see {FORMAT_DOC}",
        )
    if odo is None or truth is None:
        return None
    t = odo["t"]
    keep = np.r_[True, np.diff(t) > 0]
    odo = odo.select(keep)
    odo, emptied = _filled_rows(odo)
    read_notes = [emptied] if emptied else []  # how the columns were read, said on the stream
    t = odo["t"]
    kw: dict[str, Any] = {}
    if "left_ticks" in odo.columns and "right_ticks" in odo.columns:
        if model.ticks_per_metre is None or model.wheel_base_m is None:
            lacking = [
                k
                for k, v in (
                    ("ticks_per_metre", model.ticks_per_metre),
                    ("wheel_base_m", model.wheel_base_m),
                )
                if v is None
            ]
            robot = bundle.meta.get("robot")
            diameter = robot.get("wheel_diameter_m") if isinstance(robot, dict) else None
            _skip(
                skipped,
                "odometry",
                f"encoder ticks, but the declared model has no {' and no '.join(lacking)}"
                + (
                    f" (meta.json's wheel_diameter_m {diameter:g} alone does not give the "
                    "distance per tick)"
                    if "ticks_per_metre" in lacking and isinstance(diameter, int | float)
                    else ""
                ),
                f"declare {' and '.join(lacking)} in meta.json's robot section, or in [robot] "
                f"of --config"
                + (
                    " (ticks_per_metre = ticks per wheel turn / (pi x wheel diameter), or "
                    "tick_size_m, metres per tick)"
                    if "ticks_per_metre" in lacking
                    else ""
                )
                + f"; see {FORMAT_DOC}",
            )
            return None
        form = "ticks"
        wrapped = []
        for side in ("left_ticks", "right_ticks"):
            counts, bits, n = unwrap_counter(odo[side], odo["t"])
            if bits:
                odo = replace(odo, columns={**odo.columns, side: counts})
                wrapped.append(f"{side} wraps {n} time(s) at 2^{bits} (a {bits}-bit counter)")
        if wrapped:
            read_notes.append("; ".join(wrapped) + ": unwrapped")
        kw.update(
            d_left=np.diff(odo["left_ticks"]),
            d_right=np.diff(odo["right_ticks"]),
            tpm=model.ticks_per_metre,
            wheel_base=model.wheel_base_m,
            ratio=model.wheel_diameter_ratio,
        )
    elif "v" in odo.columns and "omega" in odo.columns:
        form = "speeds"
        dt = np.diff(t)
        kw.update(
            ds=0.5 * (odo["v"][1:] + odo["v"][:-1]) * dt,
            dtheta=0.5 * (odo["omega"][1:] + odo["omega"][:-1]) * dt,
        )
    elif all(c in odo.columns for c in ("x", "y", "theta")):
        form = "pose"
        th = np.unwrap(odo["theta"])
        dx, dy = np.diff(odo["x"]), np.diff(odo["y"])
        mid = 0.5 * (th[1:] + th[:-1])
        kw.update(ds=dx * np.cos(mid) + dy * np.sin(mid), dtheta=np.diff(th))
    else:
        _skip(
            skipped,
            "odometry",
            "odometry.csv has none of left_ticks,right_ticks / v,omega / x,y,theta (it has "
            f"{','.join(odo.columns) or 'no numeric column'})",
            f"add one of these column sets: cumulative ticks, body speeds or a dead-reckoned "
            f"pose; see {FORMAT_DOC}",
        )
        return None
    ok = np.isfinite(truth["x"]) & np.isfinite(truth["y"])
    truth = truth.select(ok)
    overlap = (truth["t"] >= t[0]) & (truth["t"] <= t[-1])
    if overlap.sum() < MIN_ROWS:
        _skip(
            skipped,
            "odometry",
            f"{int(overlap.sum())} truth_pose.csv rows with x,y inside odometry.csv's time span "
            f"{t[0]:.6g}..{t[-1]:.6g} s; at least {MIN_ROWS} needed",
            f"stamp every file on one clock (t in seconds), and record the reference while the "
            f"robot drives; see {FORMAT_DOC}",
        )
        return None
    ref = heading_reference(bundle)
    theta = np.interp(truth["t"], ref[0], ref[1]) if ref is not None else None
    t_ref = truth["t"]
    p_ref = np.column_stack([truth["x"], truth["y"]])
    if form == "ticks":
        backward = backward_wheel(
            t, odo["left_ticks"], odo["right_ticks"],
            metres_per_tick(kw["tpm"], kw["ratio"]), t_ref, p_ref, kw["wheel_base"], theta,
        )
        if backward is not None:
            _skip(
                skipped,
                "odometry",
                backward[0],
                f"negate {backward[1]} in odometry.csv: the bundle format counts forward as "
                f"up on both wheels (a log whose encoder counts the other way, or a motor "
                f"mounted mirrored); see {FORMAT_DOC}",
            )
            return None
    inside = (t_ref >= t[0]) & (t_ref <= t[-1])
    if form == "ticks":
        counted = float(np.nansum(np.abs(kw["d_left"]) + np.abs(kw["d_right"]))) / (
            2 * kw["tpm"])
        turned = float(np.nansum(np.abs(kw["d_right"] - kw["d_left"]))) / (
            kw["tpm"] * kw["wheel_base"])
    else:
        counted = float(np.nansum(np.abs(kw["ds"])))
        turned = float(np.nansum(np.abs(kw["dtheta"])))
    if counted < STILL_TRAVEL_M and turned < STILL_TURN_RAD:
        steps = np.hypot(*np.diff(p_ref[inside], axis=0).T)
        t_step = t_ref[inside][1:]
        for a, b in bundle.odometry_faulted:  # a kidnap is no motion of the wheels
            steps = np.where((t_step >= a) & (t_step <= b), 0.0, steps)
        moved = float(np.nansum(steps))
        _skip(
            skipped,
            "odometry",
            f"the wheels never turned: the odometry counts {counted:.3g} m and "
            f"{turned:.3g} rad over the recording"
            + (f", while the reference moved {moved:.3g} m (encoders not read, or a robot "
               "carried?)" if moved >= STILL_TRAVEL_M else ", and the reference stayed put"),
            "record a run in which the robot drives: with `koala-bridge run`, a client or "
            "firmware on its buses commands the wheels (docs/protocols.md); nothing moves it "
            "otherwise",
        )
        return None
    split = Split.of(t_ref[inside])
    window = min(window_s, (split.t2 - split.t1) / 2)
    dt_ref = float(np.median(np.diff(t_ref[inside])))
    if window < WINDOW_REFERENCE_INTERVALS * dt_ref:
        _skip(
            skipped,
            "odometry",
            f"truth_pose's samples are {dt_ref:.3g} s apart (median), so a {window:.3g} s "
            "dead-reckoning window holds one sample after its anchor at most: too little "
            "travel to hold the odometry against (t in milliseconds read as seconds puts a "
            "20 Hz reference 50 s apart)",
            f"give t in seconds (t_ms / 1000), or a --window-s of at least "
            f"{WINDOW_REFERENCE_INTERVALS * dt_ref:.3g} s; see {FORMAT_DOC}",
        )
        return None
    problem = OdometryProblem(
        "odometry",
        "odometry",
        "window_position_rms",
        "m",
        "sensors.odometry",
        split,
        t_odo=t,
        t_ref=t_ref,
        p_ref=p_ref,
        theta_ref=theta,
        window_s=float(f"{window:.3g}"),
        form=form,
        start_pose=(float(t_ref[inside][0]), model.start_pose.theta, 0.0)
        if model.start_pose is not None and theta is None
        else None,
        faulted=bundle.odometry_faulted,
        **kw,
    )
    windows = problem.describe()["windows"]
    parts = {"fit": "fit part (first 60 %)", "score": "held-out part (last 40 %)"}
    empty = [label for part, label in parts.items() if windows[part] == 0]
    if empty:
        aside = problem.set_aside.seconds
        _skip(
            skipped,
            "odometry",
            f"no dead-reckoning window left in the {' or the '.join(empty)}"
            + (f": {aside:.1f} s of the recording set aside (stalls, wheel slip, faults)"
               if aside else ""),
            "record more driving where the wheels grip, in both parts of the time span (or "
            f"give a shorter --window-s); see {FORMAT_DOC}",
        )
        return None
    problem.notes.extend(read_notes)
    jumps = reference_jumps(t_ref[inside], problem.p_ref[inside], problem.faulted)
    if jumps:
        problem.notes.append(jumps)
    problem.notes.append(
        f"windows of {problem.window_s:g} s re-anchored to the reference"
        + (
            ""
            if theta is not None
            else "; no reference heading: heading dead-reckoned from the declared start heading"
            if problem.start_pose is not None
            else "; no reference heading: each window's start heading aligned (Procrustes)"
        )
    )
    return problem


def build_ranges(
    bundle: Bundle, model: DeclaredModel, skipped: list[SkippedStream] | None = None
) -> list[ScalarProblem]:
    table = bundle.get("range")
    if table is None:
        return []
    out = []
    for kind in _range_kinds(table):
        sub = table.select(table.text["kind"] == kind) if kind else table
        counts = "count" in _range_unit(bundle.meta, str(kind)).lower() or kind == "ir"
        section_kind = kind or ("ir" if counts else "sonar")
        name = _range_name(str(kind))
        if not np.isfinite(sub["true_range"]).any():
            recorded = str(bundle.meta.get("source", "")).startswith("koala-bridge recording")
            _skip(
                skipped,
                name,
                "true_range is empty in every row: nothing says what it should have read"
                + (" (a recording of this bridge leaves it empty where no wall was within the "
                   "sensor's range: it saw nothing all run)" if recorded else ""),
                "record a run that drives near walls" if recorded else
                "add true_range (m) per row, the distance to what the sensor faces (from the "
                f"truth pose and a map, or measured); see {FORMAT_DOC}",
            )
            continue
        ok = np.isfinite(sub["measured"]) & np.isfinite(sub["true_range"]) & (sub["true_range"] > 0)
        dropped = int((~ok).sum())
        # A sonar's range below 0 is no echo's time of flight (an error code, a signed
        # overflow): 2 % of negated readings hid a 5 % scale, unsaid. Set aside and counted. (A
        # UWB's two-way ranging with antenna delays reads below 0 close by: kept.)
        negative = int((ok & (sub["measured"] < 0)).sum()) if section_kind == "sonar" else 0
        if negative:
            ok &= ~(sub["measured"] < 0)
        below = ok & (sub["measured"] < 0) if not counts else np.zeros(len(sub), dtype=bool)
        beyond = 0
        # The sonar's declared echo rules are the sonar's: a UWB or lidar range beyond the
        # sonar's 2.5 m is no censored echo (every UWB reading once went, unreported).
        sonar = not counts and section_kind == "sonar"
        critical = model.sonar_critical_angle_rad
        if sonar and critical is not None and "incidence_angle" in sub.columns:
            # The declared echo rule (sim/models/sonar.py): beyond the critical incidence there is
            # no direct echo; what is read there (late echo, crosstalk) is the model's, not a
            # residual of the direct-echo range.
            inc = np.abs(sub["incidence_angle"])
            far = np.isfinite(inc) & (inc > critical)
            beyond = int((ok & far).sum())
            ok &= ~far
        if sonar and model.sonar_range_m is not None:
            # Readings the declared range limits could censor (0 below min_range_m, no echo
            # beyond max_range_m): keep only true ranges 3 sigma inside both limits, so the
            # dropped no-echo readings do not bias the rest.
            lo, hi = model.sonar_range_m
            tr = sub["true_range"]
            sig = np.zeros_like(tr)
            if model.sonar_distance_error is not None:
                # the model's sigma: the table, its relative error held beyond the last row
                from koala_bridge.sim.models.sonar import distance_sigma

                xs, ys = model.sonar_distance_error
                sig = distance_sigma(tr, np.asarray(xs), np.asarray(ys))
            edge = (tr - 3 * sig < lo) | (tr + 3 * sig > hi)
            beyond += int((ok & edge).sum())
            ok &= ~edge
        closer = 0
        near_limit = ir_curve_start(model.ir_curve) if counts else 0.0
        if near_limit > 0:
            # The declared curve says nothing closer than where its single-valued part starts
            # (ir_curve_start): readings there are set aside, counted in the report, as the
            # sonar's are outside its range limits (a far end held flat is the declared
            # baseline -- nothing reflected -- and stays).
            near = ok & (sub["true_range"] < near_limit)
            closer = int(near.sum())
            ok &= ~near
        if int(ok.sum()) < MIN_ROWS:
            _skip(skipped, name, *_too_few_ranges(len(sub), int(ok.sum()), dropped, beyond,
                                                  closer))
            continue
        sub = sub.select(ok)
        t = sub["t"]
        split = Split.of(t)
        extras = _extras(sub, {"t", "measured", "true_range"})
        fit = split.mask(t, "fit")
        if counts and model.ir_curve is None and not _range_varies(sub, fit):
            _skip(
                skipped,
                name,
                "true_range does not vary for any sensor (the robot stood still), and the "
                "response curve is declared only as a shape: a curve fitted to one distance per "
                "sensor explains every reading, so nothing can be told from it",
                "record while the robot moves towards and away from a wall (several distances "
                "per sensor), or declare the curve ([sensors.ir] response_range_m and "
                f"response_counts in --config); see {FORMAT_DOC}",
            )
            continue
        curve = None
        fitted = False
        base_add: FloatArray | float = 0.0
        base_gain = 1.0
        if counts:
            base_gain = model.ir_gain
            if model.ir_curve is not None:
                curve = (np.asarray(model.ir_curve[0]), np.asarray(model.ir_curve[1]))
            else:
                xs, ys = fit_shared_curve(sub["true_range"][fit], sub["measured"][fit])
                curve = (xs, ys / model.ir_gain)  # the declared gain multiplies the response
                fitted = True
            if model.ir_per_sensor_offset:
                off = np.asarray(model.ir_per_sensor_offset)
                idx = sub["sensor"].astype(int)
                base_add = np.where(
                    (idx >= 0) & (idx < off.size), off[np.clip(idx, 0, off.size - 1)], 0.0
                )
        problem = ScalarProblem(
            name,
            "scalar",
            "rms_error",
            "counts" if counts else "m",
            f"sensors.{section_kind}",
            split,
            t=t,
            y=sub["measured"],
            u=sub["true_range"],
            columns=extras,
            covariate_names=tuple(k for k in sorted(extras) if k != "sensor"),
            categorical_names=tuple(
                k for k in sorted(extras) if categorical_levels(extras[k][fit]) is not None
            ),
            is_range=True,
            # The declared sonar's spurious readings (effects/outlier.py): its range limits,
            # glitch share and noise sigma per reading; the sonar's only, not another kind's.
            range_limits=model.sonar_range_m if sonar else None,
            declared_outlier_probability=model.sonar_glitch_probability if sonar else 0.0,
            noise_sigma=_declared_sonar_sigma(model, sub["true_range"]) if sonar else None,
            curve_points=curve,
            curve_fitted=fitted,
            base_add=base_add,
            base_gain=base_gain,
            quantity="IR counts" if counts else "range",
            # Offsets common to all sensors (bias) and per sensor both go to the simulator's
            # per-sensor offsets, as increments ("+": config_update adds the declared ones).
            native_keys={
                "offset_per:sensor": "+per_sensor_offset_counts",
                "bias": "+per_sensor_offset_counts",
                # a gain of a declared curve: its counts, scaled (the simulator's response)
                **({"scale": "*response_counts"} if model.ir_curve is not None else {}),
            }
            if counts
            else {},
            noise_key="count_noise_sigma" if counts else None,
            declared_values={
                "+per_sensor_offset_counts": model.ir_per_sensor_offset,
                "*response_counts": None if model.ir_curve is None else model.ir_curve[1],
                "n_sensors": max(
                    model.ir_sensor_count or 0,
                    len(model.ir_per_sensor_offset),
                    int(np.nanmax(sub["sensor"])) + 1 if "sensor" in sub.columns else 0,
                ),
            }
            if counts
            else {},
        )
        if fitted:
            problem.notes.append(
                "response curve declared only as a shape: shared curve fitted "
                "on the fit part first (binned means)"
            )
        outside = None if curve is None else _note_beyond_curve(problem, curve[0], fitted)
        if outside:
            problem.notes.append(outside)
        problem.notes.extend(_range_unit_notes(bundle.meta, str(kind), counts))
        if dropped:
            problem.notes.append(
                f"{dropped} readings with measured or true_range empty, or true_range <= 0, "
                "dropped"
            )
        if negative:
            problem.notes.append(
                f"{negative} readings below 0 m set aside: a range cannot be negative (an error "
                "code, or a signed overflow?)"
            )
        if below.any():
            problem.notes.append(
                f"{int(below.sum())} reading(s) below 0 m kept (the lowest "
                f"{float(np.min(sub['measured'][below])):.4g} m): two-way ranging with antenna "
                "delays reads a little below 0 close by; far below is a corrupt reading, which "
                "a robust fit discounts"
            )
        if beyond:
            problem.notes.append(
                f"{beyond} readings beyond the declared critical incidence angle or within "
                "3 sigma of the declared range limits dropped"
            )
        if closer:
            problem.notes.append(
                f"{closer} readings at true ranges closer than {near_limit:g} m set aside: "
                "the declared response curve is single-valued only from there (its first "
                "point, or its peak where the output folds back: a count there is read at two "
                "ranges). A ranger whose output peaks near its minimum range (a Sharp's) "
                "cannot tell those readings from farther ones; where the sensor's output does "
                "fall from 0 m, declare the curve from there to have them used"
            )
        out.append(problem)
    return out


def ir_curve_start(curve: tuple[Sequence[float], Sequence[float]] | None) -> float:
    """The closest true range (m) at which a declared IR response curve ``(ranges, counts)``
    says what a reading is: 0 for none or for a curve declared from 0 m that falls from there.

    * A table declared from ``r0 > 0`` says nothing closer than ``r0``: holding it flat there
      is the simulator's convention, not a declared response.
    * A curve that first rises to a peak and then falls (a triangulating ranger such as the
      Sharp GP2Y0A02YK, whose datasheet output peaks near 15 cm and folds back closer; its rated
      range starts beyond the peak) is single-valued only from the peak: a count on the rising
      branch is also read at a range beyond the peak, so a robot cannot use it as a range, and
      the offset and gain of the falling branch (what calibration fits) do not describe the
      fold. The first maximum counts, so a curve saturated flat from 0 m starts at 0.
    """
    if curve is None or len(curve[0]) == 0:
        return 0.0
    ranges = np.asarray(curve[0], dtype=float)
    counts = np.asarray(curve[1], dtype=float)
    order = np.argsort(ranges, kind="stable")
    ranges, counts = ranges[order], counts[order]
    peak = int(np.argmax(counts))
    if peak == ranges.size - 1:  # rises throughout: no fold-back declared, nothing to cut
        return float(ranges[0])
    return float(max(ranges[0], ranges[peak]))


def _too_few_ranges(
    n: int, usable: int, dropped: int, beyond: int, closer: int = 0
) -> tuple[str, str]:
    """``(missing, fix)`` for a range stream left with fewer than :data:`MIN_ROWS` rows."""
    missing = f"{usable} usable rows of {n}, at least {MIN_ROWS} needed"
    fixes = []
    if closer:
        missing += (f"; {closer} closer than where the declared IR response curve is "
                    "single-valued (its first point, or its peak)")
        fixes.append(
            "declare [sensors.ir] response_range_m / response_counts down to the closest "
            "distance recorded"
        )
    if dropped:
        missing += f"; {dropped} with measured or true_range empty, or true_range <= 0"
        fixes.append("fill measured and true_range (> 0 m) in every row")
    if beyond:
        missing += (
            f"; {beyond} beyond the declared sonar's critical incidence angle or within 3 sigma "
            "of its range limits"
        )
        fixes.append(
            "record within the declared [sensors.sonar] min_range_m..max_range_m and "
            "critical_angle_deg of --config; for another sensor (range beacons, lidar) give "
            "range.csv a kind column (e.g. uwb): the limits are the sonar's"
        )
    if not fixes:
        fixes.append("record more readings")
    return missing, "; ".join(fixes) + f"; see {FORMAT_DOC}"


def _range_varies(table: Table, fit: NDArray[np.bool_]) -> bool:
    """Whether any sensor saw two different true ranges in the fit part (by more than 1 mm):
    a response curve fitted from the data needs that to be told from per-sensor offsets."""
    tr = table["true_range"][fit]
    sensors = table["sensor"][fit] if "sensor" in table.columns else np.zeros_like(tr)
    for s in np.unique(sensors):
        r = tr[sensors == s]
        if r.size > 1 and float(np.ptp(r)) > 1e-3:
            return True
    return False


def build_landmarks(
    bundle: Bundle, model: DeclaredModel, skipped: list[SkippedStream] | None = None
) -> list[ScalarProblem]:
    obs, lmap, truth = bundle.get("landmarks"), bundle.get("landmark_map"), bundle.get("truth_pose")
    if obs is None:
        return []
    present = [n for n in bundle_streams(bundle) if n.startswith("landmark_")]
    if lmap is None or truth is None:
        refs = (("landmark_map.csv", lmap), ("truth_pose.csv", truth))
        lacking = [f for f, v in refs if v is None]
        for name in present:
            _skip(
                skipped,
                name,
                f"no reference: the bundle has no {' and no '.join(lacking)}",
                "add landmark_map.csv (id,x,y: the surveyed landmark positions, m) and "
                "truth_pose.csv (t,x,y,theta: where the robot was); see " + FORMAT_DOC,
            )
        return []
    obs = obs.select(~beacon_rows(obs))  # range beacons are streams/beacons.py's
    if len(obs) == 0:
        return []
    nan = np.full(len(obs), np.nan)
    obs = Table(obs.name, {"range": nan, "bearing": nan, **obs.columns}, obs.text, obs.lines)
    ids = lmap["id"]
    idx = np.searchsorted(ids, obs["landmark_id"], sorter=np.argsort(ids))
    order = np.argsort(ids)
    idx = order[np.clip(idx, 0, ids.size - 1)]
    known = ids[idx] == obs["landmark_id"]
    t = obs["t"]
    during = (t >= truth["t"][0]) & (t <= truth["t"][-1])
    inside = known & during
    why = (
        f"{int((~known).sum())} of {known.size} observations name a landmark_id not in "
        f"landmark_map.csv, {int((known & ~during).sum())} more lie outside truth_pose.csv's "
        "time span"
    )
    reach = (
        "give every observed landmark_id its row in landmark_map.csv, stamp every file on one "
        "clock"
    )
    fix = f"{reach}, and record at least {MIN_ROWS} observations; see {FORMAT_DOC}"
    obs, idx, t = obs.select(inside), idx[inside], t[inside]
    px = np.interp(t, truth["t"], truth["x"])
    py = np.interp(t, truth["t"], truth["y"])
    ref = heading_reference(bundle)
    if model.camera_wrong_ids and ref is not None and lmap["id"].size > 1:
        idx = _reassociate(obs, lmap, px, py, np.interp(t, ref[0], ref[1]), model)
    lx, ly = lmap["x"][idx] - px, lmap["y"][idx] - py
    true_range = np.hypot(lx, ly)
    range_bias: FloatArray | float = 0.0
    if model.camera_far is not None:
        dist, d_mid, doubling = model.camera_far
        range_bias = dist * d_mid * 2.0 ** ((true_range - d_mid) / doubling) * np.sqrt(2 / np.pi)
    extras = _extras(obs, {"t", "range", "bearing", "landmark_id"})
    out: list[ScalarProblem] = []
    ok = np.isfinite(obs["range"])
    if ok.sum() < MIN_ROWS and "landmark_range" in present:
        _skip(skipped, "landmark_range", f"{int(ok.sum())} usable ranges ({why})", fix)
    if ok.sum() >= MIN_ROWS:
        sub_split = Split.of(t[ok])
        out.append(
            ScalarProblem(
                "landmark_range",
                "scalar",
                "rms_range_error",
                "m",
                "sensors.camera",
                sub_split,
                t=t[ok],
                y=obs["range"][ok],
                u=true_range[ok],
                columns={k: v[ok] for k, v in extras.items()},
                covariate_names=tuple(sorted(extras)),
                is_range=True,
                base_add=np.broadcast_to(range_bias, t.shape)[ok],
                quantity="landmark range",
                series=obs["landmark_id"][ok],
            )
        )
    if ref is None and "landmark_bearing" in present:
        _skip(
            skipped,
            "landmark_bearing",
            "no reference heading: truth_pose.csv has no theta",
            "add theta (rad, counter-clockwise from the world x axis) per row to "
            f"truth_pose.csv; see {FORMAT_DOC}",
        )
    if ref is not None:
        theta = np.interp(t, ref[0], ref[1])
        bearing = wrap_angle(np.arctan2(ly, lx) - theta)
        okb = np.isfinite(obs["bearing"])
        if okb.sum() < MIN_ROWS and "landmark_bearing" in present:
            _skip(skipped, "landmark_bearing", f"{int(okb.sum())} usable bearings ({why})", fix)
    if ref is not None and okb.sum() >= MIN_ROWS:
        out.append(
            ScalarProblem(
                "landmark_bearing",
                "scalar",
                "rms_bearing_error",
                "rad",
                "sensors.camera",
                Split.of(t[okb]),
                t=t[okb],
                y=obs["bearing"][okb],
                u=bearing[okb],
                columns={k: v[okb] for k, v in extras.items()},
                covariate_names=tuple(sorted(extras)),
                angle=True,
                quantity="landmark bearing",
                series=obs["landmark_id"][okb],
            )
        )
    if not inside.all():
        # nothing set aside without a word: the observations no reference reaches
        for problem in out:
            problem.notes.append(f"set aside: {why} ({reach})")
    return out


def _reassociate(
    obs: Table,
    lmap: Table,
    px: FloatArray,
    py: FloatArray,
    theta: FloatArray,
    model: DeclaredModel,
) -> np.ndarray:
    """Map index of the landmark each observation most likely saw, when the declared camera
    reports wrong ids (sim/models/camera.py, recognition): the nearest in (range, bearing)
    normalised by the declared spreads (nearest-neighbour data association)."""
    dx = lmap["x"][None, :] - px[:, None]
    dy = lmap["y"][None, :] - py[:, None]
    r = np.hypot(dx, dy)
    b = wrap_angle(np.arctan2(dy, dx) - theta[:, None])
    dist = model.camera_far[0] if model.camera_far is not None else 0.05
    sr = np.maximum(dist * r, 0.02)
    sb = max(model.camera_bearing_sigma_rad, 0.01)
    er = (np.nan_to_num(obs["range"], nan=0.0)[:, None] - r) / sr
    eb = wrap_angle(np.nan_to_num(obs["bearing"], nan=0.0)[:, None] - b) / sb
    er = np.where(np.isfinite(obs["range"])[:, None], er, 0.0)
    return np.asarray(np.argmin(er**2 + eb**2, axis=1))
