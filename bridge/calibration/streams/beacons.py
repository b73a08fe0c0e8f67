"""Range beacons (UWB anchors, ultrasonic beacons): ranges from the robot to surveyed beacons.

A bundle gives them in one of two forms (docs/bundle-format.md):

* ``range.csv`` rows of ``kind = uwb`` with ``true_range``: a range stream like any other
  (:func:`koala_bridge.calibration.streams.build_ranges`; the declared sonar's echo rule and
  range limits are not applied to them);
* ``landmarks.csv`` readings with a range and no bearing, ``landmark_map.csv`` the beacon
  positions and ``truth_pose.csv`` the robot's positions: the true range is computed here,
  ``|p_beacon - p_robot(t)|`` (robot position interpolated linearly at ``t``), and the stream is
  held against it with the identity model ``y = r`` (no camera model: a beacon is not the
  camera). Effects that apply: ``scale`` (a wrong propagation speed or clock rate: ``y =
  (1 + s) r``), ``bias`` (antenna delay: ``y = r + b``), ``range_dependent``, ``offset_per:
  landmark_id`` (a delay per beacon), ``glitch``, covariates.

Which ``landmarks.csv`` rows are beacon readings: with a ``kind`` column, rows whose kind is not
``camera`` (the kind names the stream: ``range:uwb``); without one, every row when the file has
no bearing at all (no ``bearing`` column, or all empty): kind ``uwb``.
"""

from __future__ import annotations

import numpy as np
from koala_bridge.calibration.bundle import Bundle, Table
from koala_bridge.calibration.effects.common import categorical_levels
from koala_bridge.calibration.effects.time_offset import (
    CLOCK_ROWS,
    clock_grid,
    clock_pick,
    clocks_note,
)
from koala_bridge.calibration.model import DeclaredModel
from koala_bridge.calibration.problem import FORMAT_DOC, MIN_ROWS, SkippedStream, Split
from koala_bridge.calibration.problem import skip_stream as _skip
from koala_bridge.calibration.streams.scalar import ScalarProblem
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

#: The kind of range-only ``landmarks.csv`` readings without a ``kind`` column.
DEFAULT_BEACON_KIND = "uwb"


def beacon_rows(obs: Table) -> NDArray[np.bool_]:
    """Rows of ``landmarks.csv`` that are range-beacon readings (module docstring)."""
    if "kind" in obs.text:
        kind = np.char.lower(obs.text["kind"])
        return np.asarray((kind != "camera") & (kind != ""), dtype=bool)
    bearing = obs.columns.get("bearing")
    no_bearing = bearing is None or not np.isfinite(bearing).any()
    return np.full(len(obs), no_bearing and "range" in obs.columns, dtype=bool)


def _kinds(obs: Table) -> NDArray[np.str_]:
    if "kind" in obs.text:
        return np.asarray(np.char.lower(obs.text["kind"]))
    return np.full(len(obs), DEFAULT_BEACON_KIND)


def _range_csv_kinds(bundle: Bundle) -> set[str]:
    table = bundle.get("range")
    if table is None or "kind" not in table.text:
        return set()
    return {str(k).lower() for k in np.unique(table.text["kind"])}


def _stream_name(kind: str, range_kinds: set[str]) -> str:
    """``range:<kind>``; ``landmark_range:<kind>`` when ``range.csv`` holds that kind too (a name
    is one stream)."""
    return f"range:{kind}" if kind not in range_kinds else f"landmark_range:{kind}"


def beacon_streams(bundle: Bundle) -> list[str]:
    """The name of each beacon stream ``landmarks.csv`` holds (rows with a range)."""
    obs = bundle.get("landmarks")
    if obs is None or "range" not in obs.columns:
        return []
    rows = beacon_rows(obs) & np.isfinite(obs["range"])
    range_kinds = _range_csv_kinds(bundle)
    return [_stream_name(k, range_kinds) for k in sorted(set(_kinds(obs)[rows].tolist()))]


def beacon_clocks(
    t: FloatArray,
    y: FloatArray,
    bx: FloatArray,
    by: FloatArray,
    truth: tuple[FloatArray, FloatArray, FloatArray],
    fit: NDArray[np.bool_],
) -> tuple[float, float, float] | None:
    """``(tau, r, r_near)`` when the ranges ``y`` (at ``t``, to beacons at ``bx, by``) and the
    robot's positions ``truth`` ``(t, x, y)`` look stamped on clocks seconds apart: on the fit
    part's readings, the ranges' correlation with the true ranges of the robot shifted by each
    ``tau`` of :func:`.time_offset.clock_grid`, picked by :func:`.time_offset.clock_pick` as a
    scalar stream's clocks are (a new user's lawn-mower log with its ranges 2 s late:
    scale fitted 6.1 % for 7.0 %, 9.8 times a hand fit's error, and nothing said)."""
    tt, tx, ty = truth
    tf = t[fit]
    if tf.size < 10 or tt.size < 2:
        return None
    grid = clock_grid(np.unique(tf), tt)
    if grid is None:
        return None
    taus, _, span = grid
    reach = float(np.max(np.abs(taus)))
    keep = np.flatnonzero((tf >= tt[0] + reach) & (tf <= tt[-1] - reach))
    rows = keep[:: max(1, keep.size // CLOCK_ROWS)]
    if rows.size < 10:
        return None
    tr, yr, bxr, byr = tf[rows], y[fit][rows], bx[fit][rows], by[fit][rows]
    r = np.array([
        _correlation(yr, np.hypot(bxr - np.interp(tr - tau, tt, tx),
                                  byr - np.interp(tr - tau, tt, ty)))
        for tau in taus
    ])
    return clock_pick(taus, r, span)


def _correlation(a: FloatArray, b: FloatArray) -> float:
    a, b = a - a.mean(), b - b.mean()
    d = float(np.sqrt(np.dot(a, a) * np.dot(b, b)))
    return float(np.dot(a, b)) / d if d > 0 else float("nan")


def build_beacons(
    bundle: Bundle, model: DeclaredModel, skipped: list[SkippedStream] | None = None
) -> list[ScalarProblem]:
    """One range stream per beacon kind of ``landmarks.csv`` (module docstring); a stream
    without the beacon map and the robot's positions, or with too few readings, is recorded in
    ``skipped`` with what it lacks."""
    names = beacon_streams(bundle)
    obs, lmap, truth = bundle.get("landmarks"), bundle.get("landmark_map"), bundle.get("truth_pose")
    if not names or obs is None:
        return []
    if lmap is None or truth is None:
        lacking = [
            f for f, v in (("landmark_map.csv", lmap), ("truth_pose.csv", truth)) if v is None
        ]
        for name in names:
            _skip(
                skipped,
                name,
                f"no reference: the bundle has no {' and no '.join(lacking)}",
                "add landmark_map.csv (id,x,y: the beacon positions, m) and truth_pose.csv "
                f"(t,x,y: where the robot was); see {FORMAT_DOC}",
            )
        return []
    obs = obs.select(beacon_rows(obs))
    ok = np.isfinite(truth["x"]) & np.isfinite(truth["y"])
    tt, tx, ty = truth["t"][ok], truth["x"][ok], truth["y"][ok]
    order = np.argsort(lmap["id"])
    ids = lmap["id"][order]
    idx = np.clip(np.searchsorted(ids, obs["landmark_id"]), 0, ids.size - 1)
    known = ids[idx] == obs["landmark_id"]
    t = obs["t"]
    during = (t >= tt[0]) & (t <= tt[-1]) if tt.size else np.zeros(t.size, dtype=bool)
    use = known & np.isfinite(obs["range"]) & during
    kinds = _kinds(obs)
    range_kinds = _range_csv_kinds(bundle)
    out = []
    for kind in sorted(set(kinds[np.isfinite(obs["range"])].tolist())):
        name = _stream_name(kind, range_kinds)
        m = use & (kinds == kind)
        if int(m.sum()) < MIN_ROWS:
            of_kind = kinds == kind
            _skip(
                skipped,
                name,
                f"{int(m.sum())} usable readings, at least {MIN_ROWS} needed: "
                f"{int((of_kind & ~known).sum())} name a landmark_id not in landmark_map.csv, "
                f"{int((of_kind & known & ~during).sum())} lie outside truth_pose.csv's time span",
                "give every beacon its row in landmark_map.csv and stamp every file on one "
                f"clock; see {FORMAT_DOC}",
            )
            continue
        sub = obs.select(m)
        j = order[idx[m]]
        ts = sub["t"]
        true_range = np.hypot(
            lmap["x"][j] - np.interp(ts, tt, tx), lmap["y"][j] - np.interp(ts, tt, ty)
        )
        split = Split.of(ts)
        fit = split.mask(ts, "fit")
        extras = {
            k: v
            for k, v in sub.columns.items()
            if k not in ("t", "range", "bearing") and np.isfinite(v).any()
        }
        problem = ScalarProblem(
            name,
            "scalar",
            "rms_error",
            "m",
            f"sensors.{kind}",
            split,
            t=ts,
            y=sub["range"],
            u=true_range,
            columns=extras,
            covariate_names=tuple(k for k in sorted(extras) if k != "landmark_id"),
            categorical_names=tuple(
                k for k in sorted(extras) if categorical_levels(extras[k][fit]) is not None
            ),
            is_range=True,
            quantity=f"{kind} range",
        )
        problem.notes.append(
            "reference: true range from landmark_map.csv beacon positions and truth_pose.csv "
            "robot positions (interpolated at each reading)"
        )
        unknown = int((~known & (kinds == kind)).sum())
        if unknown:
            problem.notes.append(f"{unknown} readings of beacons not in landmark_map.csv dropped")
        outside = int((known & ~during & (kinds == kind) & np.isfinite(obs["range"])).sum())
        if outside:
            problem.notes.append(
                f"{outside} readings outside truth_pose.csv's time span "
                f"({tt[0]:.6g}-{tt[-1]:.6g} s) dropped: nothing says where the robot was"
            )
        clocks = beacon_clocks(ts, sub["range"], lmap["x"][j], lmap["y"][j], (tt, tx, ty),
                               fit)
        if clocks is not None:
            problem.notes.append(clocks_note(*clocks, "correlation", fitted=False))
        out.append(problem)
    return out
