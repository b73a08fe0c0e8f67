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
* **a truth heading in degrees**: beyond ±(2π + 0.5), which no wrapped heading in radians
  reaches, and either wrapping by about 360 between two samples (a heading in [-180, 180) or
  [0, 360) crossing its cut) or turning faster than :data:`MAX_TURN_RATE` (20 rad/s, three
  turns a second) on a tenth of its samples. An unwrapped heading in radians passes: it never
  jumps by 360 and turns as fast as the robot. The ``theta`` column is set aside; the streams
  that can do without it (odometry: the angle that best turns each window's travel onto the
  reference's) go on;
* **bearings in degrees**: a bearing is an angle to a landmark, so beyond ±(2π + 0.5) it is
  not one in radians. The ``landmark_bearing`` stream is not calibrated (the column stays:
  ranges of rows with a bearing are a camera's, not a beacon's).

Nothing is converted: a guessed unit would hide a wrong file. A unit the numbers cannot show
(degrees of a heading that stays within ±6 deg, positions in cm) stays the user's to get right.
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
#: rad/s: no robot body turns faster (about three turns a second)
MAX_TURN_RATE = 20.0
#: the share of samples the speed or the turn rate must exceed its bound on
FAST_SHARE = 0.1
#: beyond this, an angle is not a wrapped one in radians (2 pi, and a margin for noise)
MAX_RADIANS = 2 * math.pi + 0.5
#: a step between two samples this close to 360 is a heading in degrees crossing its cut
WRAP_360_TOLERANCE = 30.0

#: streams held against the reference's positions
_POSITION_STREAMS = ("odometry", "landmark_range", "landmark_bearing")


@dataclass(frozen=True)
class Misread:
    """What :func:`misread_units` found: the bundle with a misread heading set aside, a note
    for every stream, whether the streams held against the reference's positions are built at
    all, and the streams not calibrated (each with why and the fix)."""

    bundle: Bundle
    notes: list[str] = field(default_factory=list)
    skip_positions: bool = False
    skipped: list[SkippedStream] = field(default_factory=list)


def _p90_speed(t: NDArray[np.float64], x: NDArray[np.float64], y: NDArray[np.float64]) -> float:
    """The 90th percentile of the travel over :data:`SPEED_SPAN_S` spans, per second."""
    j = np.searchsorted(t, t + SPEED_SPAN_S)
    i = np.flatnonzero(j < t.size)
    if i.size == 0:
        return 0.0
    j = j[i]
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


def heading_in_degrees(truth: Table) -> str | None:
    """Why ``truth_pose.theta`` is not radians, or None (module docstring)."""
    if "theta" not in truth.columns:
        return None
    ok = np.isfinite(truth["theta"])
    th, t = truth["theta"][ok], truth["t"][ok]
    if th.size < 3 or float(np.max(np.abs(th))) <= MAX_RADIANS:
        return None
    step = np.diff(th)
    wraps = int(np.sum(np.abs(np.abs(step) - 360.0) < WRAP_360_TOLERANCE))
    dt = np.diff(t)
    moving = dt > 0
    rate = np.abs(np.diff(np.unwrap(th, period=360.0)))[moving] / dt[moving]
    fast = float(np.quantile(rate, 1.0 - FAST_SHARE)) if rate.size else 0.0
    if not wraps and fast <= MAX_TURN_RATE:
        return None
    how = (
        f"wraps by about 360 between two samples {wraps} time(s)"
        if wraps
        else f"turns {fast:.3g} rad/s (90th percentile), beyond any robot ({MAX_TURN_RATE:g})"
    )
    return (
        f"truth_pose.theta reaches {float(np.max(np.abs(th))):.4g} and {how}: degrees? "
        "(a heading in radians stays within 2 pi unless unwrapped, and then never jumps by 360)"
    )


def bearings_in_degrees(landmarks: Table) -> str | None:
    """Why ``landmarks.bearing`` is not radians, or None (module docstring)."""
    if "bearing" not in landmarks.columns:
        return None
    b = landmarks["bearing"][np.isfinite(landmarks["bearing"])]
    if b.size == 0 or float(np.max(np.abs(b))) <= MAX_RADIANS:
        return None
    return (
        f"landmarks.bearing reaches {float(np.max(np.abs(b))):.4g}, beyond 2 pi: degrees? "
        "(a bearing is an angle to a landmark)"
    )


def _without(table: Table, column: str) -> Table:
    return replace(
        table, columns={k: v for k, v in table.columns.items() if k != column}, derived={}
    )


def misread_units(bundle: Bundle, streams: list[str], beacons: list[str]) -> Misread:
    """The bundle's columns in another unit than SI, set aside (module docstring).

    ``streams``: every stream the bundle holds (``streams.bundle_streams``); ``beacons``: its
    range-beacon streams (held against the reference's positions too)."""
    tables = dict(bundle.tables)
    notes: list[str] = []
    skipped: list[SkippedStream] = []
    truth, obs = bundle.get("truth_pose"), bundle.get("landmarks")
    positions = positions_in_mm(truth) if truth is not None else None
    if positions is not None:
        notes.append(positions + "; the streams held against them are not calibrated")
        fix = f"give truth_pose.csv's x, y in metres (m = mm / 1000); see {FORMAT_DOC}"
        skipped += [
            SkippedStream(s, positions, fix)
            for s in streams
            if s in _POSITION_STREAMS or s in beacons
        ]
    heading = heading_in_degrees(truth) if truth is not None else None
    if heading is not None:
        notes.append(
            heading + "; it is set aside: no stream is held against it (convert it: "
            f"rad = deg x pi / 180; {FORMAT_DOC})"
        )
        tables["truth_pose"] = _without(tables["truth_pose"], "theta")
        if "landmark_bearing" in streams and positions is None:  # a bearing needs the heading
            skipped.append(SkippedStream(
                "landmark_bearing", heading,
                f"give truth_pose.csv's theta in radians (rad = deg x pi / 180); see {FORMAT_DOC}",
            ))
    bearing = bearings_in_degrees(obs) if obs is not None else None
    if bearing is not None and not skipped and "landmark_bearing" in streams:
        # the column stays: without bearings, a camera's range rows would read as beacons'
        skipped.append(SkippedStream(
            "landmark_bearing", bearing,
            f"give landmarks.csv's bearing in radians (rad = deg x pi / 180); see {FORMAT_DOC}",
        ))
    if not notes and not skipped:
        return Misread(bundle)
    return Misread(replace(bundle, tables=tables), notes, positions is not None, skipped)
