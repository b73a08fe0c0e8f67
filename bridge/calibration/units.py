"""Columns whose numbers are in another unit than the bundle format's, found before any fit.

The bundle format is SI: metres, radians, seconds (docs/bundle-format.md). A converter that
kept a motion-capture system's millimetres, or a tracker's heading in degrees, gives numbers
that every stream reads as metres and radians, and the fits then "find" what the unit makes:
positions in mm gave a landmark range a scale of -0.995 and its bearings a written bias of
1.59 rad; a truth heading in degrees gave the gyro a written bias of -10.4 rad/s. Where the
numbers themselves show the unit, no sensor can explain them, and calibrating against them
can only mislead, so the column is set aside before any stream is built, and the report says
why and what to fix:

* **truth positions beyond any ground vehicle's speed**: the 90th percentile of the
  reference's speed over spans of :data:`SPEED_SPAN_S` (the motion, not a tracker's jitter)
  beyond :data:`MAX_GROUND_SPEED` (150 m/s, 540 km/h). Millimetres read as metres make a
  robot at 0.3 m/s travel 300 m/s. The streams held against the reference's positions
  (odometry, landmarks, range beacons) are not calibrated;
* **a truth heading in degrees**: beyond :data:`MAX_RADIANS`, which no wrapped heading in
  radians reaches, and either wrapping by about 360 between two samples (a heading in [-180,
  180) or [0, 360) crossing its cut: a heading in radians would have to turn 360 rad between
  two samples), or both turning :data:`DEGREES_PER_RADIAN` times as far as the gyro
  integrates to over the same spans (a factor of 1.5 either way) and, read as radians,
  faster than :data:`MAX_BODY_TURN` on a tenth of them. Either alone is ambiguous: a rate
  table turns a gyro at 26 rad/s (and stamps taken in bursts make any heading "fast" between
  them, hence spans), and a gyro converted from deg/s twice, or read on another axis, makes
  a radian heading turn 57 times as far as it.
  The ``theta`` column is set aside; the streams that can do without it go on (the gyro
  against the compass, the odometry's windows turned by the best angle), and landmark
  bearings, which need the heading, are not calibrated;
* **bearings in degrees**: a bearing is an angle to a landmark, wrapped to one turn, so beyond
  :data:`MAX_RADIANS` it is not one in radians. The ``landmark_bearing`` stream is not
  calibrated (the column stays: ranges of rows with a bearing are a camera's, not a beacon's).

Nothing is converted: a guessed unit would hide a wrong file. A unit the numbers cannot show
(degrees of a heading that never wraps in a bundle without a gyro, or that stays within ±6
deg; positions in cm) stays the user's to get right.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
from koala_bridge.calibration.bundle import Bundle, Table
from koala_bridge.calibration.problem import FORMAT_DOC, SkippedStream
from numpy.typing import NDArray

#: m/s: no ground vehicle's reference moves faster (540 km/h)
MAX_GROUND_SPEED = 150.0
#: s: the speed is the travel over spans this long (a tracker's jitter between neighbouring
#: samples, in mm read as m, would be fast too; the motion is what the unit scales)
SPEED_SPAN_S = 1.0
#: the share of spans the speed must exceed its bound on
FAST_SHARE = 0.1
#: spans the speed's percentile is read on at most, evenly spread (an hour at 100 Hz has
#: 360 000; a tenth of a few thousand is as clear)
MAX_SPANS = 5000
#: a wrapped angle in radians stays within one turn, [-pi, pi] or [0, 2 pi); the margin (0.5
#: rad, 29 deg) takes a noisy tracker's overshoot at the cut, and no degree value of interest
#: hides below it but headings within ±6 deg
MAX_RADIANS = 2 * math.pi + 0.5
#: a step between two samples this close to 360 is a heading in degrees crossing its cut
WRAP_360_TOLERANCE = 30.0
DEGREES_PER_RADIAN = 180.0 / math.pi
#: the truth heading's turn over the gyro's, within this factor of DEGREES_PER_RADIAN: degrees
DEGREES_RATIO_TOLERANCE = 1.5
#: s: the spans the truth heading's turn is compared with the gyro's over
TURN_SPAN_S = 1.0
#: rad/s: a robot body turning a full turn a second on a tenth of its 1 s spans is no robot's
#: (a robot turning at 0.11 rad/s, read in degrees, turns this fast)
MAX_BODY_TURN = 2 * math.pi

_DEGREES_FIX = "rad = deg x pi / 180"
#: streams that use the truth heading where the bundle has one
_HEADING_STREAMS = ("compass", "gyro", "gyro:level", "odometry", "landmark_bearing")
#: streams held against the reference's positions (and the range beacons)
_POSITION_STREAMS = ("odometry", "landmark_range", "landmark_bearing")


@dataclass(frozen=True)
class Misread:
    """What :func:`misread_units` found: the bundle with a misread heading set aside, why the
    heading was set aside (None: it was not), whether the streams held against the reference's
    positions are built at all, and the streams not calibrated (each with why and the fix)."""

    bundle: Bundle
    heading: str | None = None
    skip_positions: bool = False
    skipped: list[SkippedStream] = field(default_factory=list)

    def notes_for(self, stream: str) -> list[str]:
        """The note a calibrated stream gets: the heading set aside, where it could use it."""
        if self.heading is None or stream not in _HEADING_STREAMS:
            return []
        return [f"{self.heading}; it is set aside: no stream is held against it "
                f"({_DEGREES_FIX}; {FORMAT_DOC})"]

    def explained(self, skipped: SkippedStream) -> SkippedStream:
        """A builder's skip that the heading set aside caused ("no theta") says why."""
        if self.heading is None or skipped.stream not in _HEADING_STREAMS:
            return skipped
        if "theta" not in skipped.missing:
            return skipped
        return replace(skipped, missing=f"{skipped.missing} (it was set aside: {self.heading})",
                       fix=f"give truth_pose.csv's theta in radians ({_DEGREES_FIX}); "
                           + skipped.fix)


def _p90_speed(t: NDArray[np.float64], x: NDArray[np.float64], y: NDArray[np.float64]) -> float:
    """The 90th percentile of the travel over :data:`SPEED_SPAN_S` spans, per second, from at
    most :data:`MAX_SPANS` starts."""
    starts = np.arange(0, t.size, max(1, t.size // MAX_SPANS))
    j = np.searchsorted(t, t[starts] + SPEED_SPAN_S)
    i = starts[j < t.size]
    j = j[j < t.size]
    if i.size == 0:
        return 0.0
    dt = t[j] - t[i]
    ok = dt > 0
    if not ok.any():
        return 0.0
    v = np.hypot(x[j] - x[i], y[j] - y[i])[ok] / dt[ok]
    return float(np.quantile(v, 1.0 - FAST_SHARE))


def positions_in_mm(truth: Table) -> str | None:
    """Why ``truth_pose``'s positions are not metres, or None (module docstring)."""
    ok = np.isfinite(truth["x"]) & np.isfinite(truth["y"])
    if ok.sum() < 2:
        return None
    speed = _p90_speed(truth["t"][ok], truth["x"][ok], truth["y"][ok])
    if speed <= MAX_GROUND_SPEED:
        return None
    return (
        f"truth_pose's positions travel {speed:.3g} m/s (90th percentile over "
        f"{SPEED_SPAN_S:g} s), beyond any ground vehicle ({MAX_GROUND_SPEED:g} m/s): "
        "millimetres read as metres? (a robot at 0.3 m/s tracked in mm travels 300)"
    )


def _turn_ratio(
    t: NDArray[np.float64], theta: NDArray[np.float64], gyro: Table
) -> tuple[float, float] | None:
    """The truth heading's turn over the gyro's integrated turn on :data:`TURN_SPAN_S` spans
    (least squares through 0), and the 90th percentile of the heading's turn per span per
    second; None where the gyro does not turn over the heading's span."""
    if not {"t", "yaw_rate"} <= set(gyro.columns):
        return None
    ok = np.isfinite(gyro["yaw_rate"])
    tg, w = gyro["t"][ok], gyro["yaw_rate"][ok]
    if tg.size < 3:
        return None
    turned = np.r_[0.0, np.cumsum(0.5 * (w[1:] + w[:-1]) * np.diff(tg))]
    lo, hi = max(t[0], tg[0]), min(t[-1], tg[-1])
    if hi - lo < 2 * TURN_SPAN_S:
        return None
    edges = np.arange(lo, hi, TURN_SPAN_S)
    d_truth = np.diff(np.interp(edges, t, theta))
    d_gyro = np.diff(np.interp(edges, tg, turned))
    denominator = float(np.dot(d_gyro, d_gyro))
    if denominator <= 0:
        return None
    rate = float(np.quantile(np.abs(d_truth), 1.0 - FAST_SHARE)) / TURN_SPAN_S
    return abs(float(np.dot(d_truth, d_gyro)) / denominator), rate


def heading_in_degrees(truth: Table, gyro: Table | None = None) -> str | None:
    """Why ``truth_pose.theta`` is not radians, or None (module docstring)."""
    if "theta" not in truth.columns:
        return None
    ok = np.isfinite(truth["theta"])
    th, t = truth["theta"][ok], truth["t"][ok]
    if th.size < 3 or float(np.max(np.abs(th))) <= MAX_RADIANS:
        return None
    reach = f"truth_pose.theta reaches {float(np.max(np.abs(th))):.4g}"
    wraps = int(np.sum(np.abs(np.abs(np.diff(th)) - 360.0) < WRAP_360_TOLERANCE))
    if wraps:
        return (f"{reach} and jumps by about 360 between two samples {wraps} time(s): "
                "degrees? (in radians that would be 57 turns between two samples)")
    turns = None if gyro is None else _turn_ratio(t, th, gyro)
    if turns is None:
        return None
    ratio, rate = turns
    if (DEGREES_PER_RADIAN / DEGREES_RATIO_TOLERANCE < ratio
            < DEGREES_PER_RADIAN * DEGREES_RATIO_TOLERANCE) and rate > MAX_BODY_TURN:
        return (f"{reach}, turns {ratio:.3g} times as far as the gyro integrates to over the "
                f"same {TURN_SPAN_S:g} s spans, and {rate:.3g} rad/s read as radians "
                f"(90th percentile): degrees? (180 / pi = 57.3)")
    return None


def bearings_in_degrees(landmarks: Table) -> str | None:
    """Why ``landmarks.bearing`` is not radians, or None (module docstring)."""
    if "bearing" not in landmarks.columns:
        return None
    b = landmarks["bearing"][np.isfinite(landmarks["bearing"])]
    if b.size == 0 or float(np.max(np.abs(b))) <= MAX_RADIANS:
        return None
    return (
        f"landmarks.bearing reaches {float(np.max(np.abs(b))):.4g}, beyond one turn in "
        "radians: degrees? (a bearing is an angle to a landmark)"
    )


def _without(table: Table, column: str) -> Table:
    return replace(
        table, columns={k: v for k, v in table.columns.items() if k != column}, derived={}
    )


def misread_units(bundle: Bundle, streams: list[str], beacons: list[str]) -> Misread:
    """The bundle's columns in another unit than SI, set aside (module docstring).

    ``streams``: every stream the bundle holds (``streams.bundle_streams``); ``beacons``: its
    range-beacon streams (held against the reference's positions too)."""
    truth, obs = bundle.get("truth_pose"), bundle.get("landmarks")
    positions = positions_in_mm(truth) if truth is not None else None
    heading = heading_in_degrees(truth, bundle.get("gyro")) if truth is not None else None
    bearing = bearings_in_degrees(obs) if obs is not None else None
    if positions is None and heading is None and bearing is None:
        return Misread(bundle)
    # (stream set aside, why, the fix): a stream may be set aside for several columns
    reasons: list[tuple[str, str, str]] = []
    if positions is not None:
        reasons += [(s, positions, "give truth_pose.csv's x, y in metres (m = mm / 1000)")
                    for s in (*_POSITION_STREAMS, *beacons)]
    if heading is not None:
        reasons.append(("landmark_bearing", heading,
                        f"give truth_pose.csv's theta in radians ({_DEGREES_FIX})"))
    if bearing is not None:
        reasons.append(("landmark_bearing", bearing,
                        f"give landmarks.csv's bearing in radians ({_DEGREES_FIX})"))
    skipped = [
        SkippedStream(s, "; and ".join(r for n, r, _ in reasons if n == s),
                      "; ".join(f for n, _, f in reasons if n == s) + f"; see {FORMAT_DOC}")
        for s in streams if any(n == s for n, _, _ in reasons)
    ]
    tables = dict(bundle.tables)
    if heading is not None:
        tables["truth_pose"] = _without(tables["truth_pose"], "theta")
    return Misread(replace(bundle, tables=tables), heading, positions is not None, skipped)
