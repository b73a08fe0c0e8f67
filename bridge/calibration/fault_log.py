"""The fault log of a koala-bridge recording: readings faulted on purpose are no sensor error.

A run with ``--fault`` (docs/faults.md) records every injection on ``/events/fault``, and
``koala-bridge export`` writes them as ``faults.csv`` (``t,name,kind,target,detail``, ``detail``
as JSON). Calibrating such a recording against the config it ran with must find no effect the
model lacks (issue 16, point 5), so what the log says was faulted is set aside before any
stream is built, and each stream's report says what was set aside and why:

* **sensor faults** on the readings (``stuck``, ``stuck_max``, ``bias``, ``glitch``,
  ``magnetic_anomaly``): the faulted stream's rows inside the fault's window (``start`` to
  ``end`` phase, both included; to the recording's end when it stopped inside the window), of
  the sensors listed (``sensors``; none or empty: all); a ``glitch`` is logged per reading hit,
  so that reading alone (IR / sonar: that sensor's);
* **kidnap** (the robot put elsewhere: the reference jumps, the encoders count nothing): the
  rows of every stream whose reference is read from ``truth_pose`` (gyro, compass, landmarks)
  within :data:`KIDNAP_MARGIN_SAMPLES` reference or stream intervals of it, and an odometry span
  over it, after which the dead-reckoning windows restart;
* **wheel slip** and **stuck encoders**: an odometry span over the window (the wheels counted
  what the body did not do). The calibration's own stall detector finds most slips too
  (``streams.odometry.find_stalls``); the log makes it exact.

Faults on the buses (``drop``, ``corrupt``, ``delay``, ``duplicate``, ``reorder``,
``disconnect``, ``error_frames``, ``bus_off``) change what a firmware received, not the
readings the recording holds: nothing of them is set aside.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from koala_bridge.calibration.bundle import FAULT_LOG, Bundle, Table
from koala_bridge.calibration.errors import BundleError
from numpy.typing import NDArray

#: rows within this many intervals (of the reference or of the stream, the longer) of a kidnap
#: are set aside: a reference rate differenced across the jump, or a reference heading
#: interpolated across it, is neither pose's
KIDNAP_MARGIN_SAMPLES = 2

#: fault kinds that change a sensor's readings, and the bundle table each target is in
SENSOR_FAULTS = frozenset({"stuck", "stuck_max", "bias", "glitch", "magnetic_anomaly"})
_TABLE = {"gyro": "gyro", "compass": "compass", "ir": "range", "sonar": "range"}
#: the streams a table's rows belong to (range rows: by their kind)
_STREAMS = {"gyro": ("gyro",), "compass": ("compass",), "ir": ("range:ir",),
            "sonar": ("range:sonar",), "landmarks": ("landmark_range", "landmark_bearing")}


@dataclass(frozen=True)
class Fault:
    """One injection of the log: a window ``[start, end]`` (``start == end`` for a kidnap or a
    glitch's one reading), its ``sensors`` (None: all)."""

    name: str
    kind: str
    target: str
    start: float
    end: float
    sensors: tuple[int, ...] | None = None

    def label(self) -> str:
        at = (f"at {self.start:.6g} s" if self.end == self.start
              else f"{self.start:.6g}-{self.end:.6g} s" if np.isfinite(self.end)
              else f"from {self.start:.6g} s to the end")
        return f"{self.name or self.kind + ':' + self.target} {at}"


def _detail(text: str, where: str) -> dict[str, Any]:
    if not text:
        return {}
    try:
        value = json.loads(text)
    except json.JSONDecodeError as e:
        raise BundleError(f"{where}: detail is not JSON ({e.msg}): {text[:60]!r}") from e
    return value if isinstance(value, dict) else {}


def read_faults(table: Table, where: str) -> list[Fault]:
    """The injections of a fault log (:data:`koala_bridge.calibration.bundle.FAULT_LOG`):
    windows paired by name from their ``start`` and ``end`` phases, kidnaps and each glitch's
    reading as they come. Raises :class:`BundleError` for a detail that is not JSON."""
    t = table["t"]
    text = {c: table.text.get(c, np.full(len(table), "", dtype=object)) for c in
            ("name", "kind", "target", "detail")}
    out: list[Fault] = []
    open_: dict[str, tuple[float, str, str, tuple[int, ...] | None]] = {}
    for i in np.argsort(t, kind="stable"):
        name, kind, target = (str(text[c][i]) for c in ("name", "kind", "target"))
        line = f"{where} line {int(table.lines[i])}" if table.lines is not None else where
        detail = _detail(str(text["detail"][i]), line)
        ti = float(t[i])
        sensors = detail.get("sensors")
        listed = (tuple(int(v) for v in sensors)
                  if isinstance(sensors, list) and sensors else None)
        if kind == "kidnap":
            out.append(Fault(name, kind, target, ti, ti))
        elif kind == "glitch":
            one = detail.get("sensor")
            out.append(Fault(name, kind, target, ti, ti,
                             (int(one),) if isinstance(one, int) else None))
        elif detail.get("phase") == "start":
            open_[name] = (ti, kind, target, listed)
        elif detail.get("phase") == "end" and name in open_:
            start, kind0, target0, listed0 = open_.pop(name)
            out.append(Fault(name, kind0, target0, start, ti, listed0))
    out.extend(Fault(name, kind, target, start, np.inf, listed)
               for name, (start, kind, target, listed) in open_.items())
    return out


def _interval(t: NDArray[np.float64]) -> float:
    d = np.diff(t)
    d = d[d > 0]
    return float(np.median(d)) if d.size else 0.0


@dataclass
class _Aside:
    """What was set aside of one stream: rows, and per fault its label (a fault logged per
    reading, a glitch, once, with its count)."""

    rows: int = 0
    faults: dict[str, str] = field(default_factory=dict)
    hits: dict[str, int] = field(default_factory=dict)

    def add(self, n: int, fault: Fault) -> None:
        if not n:
            return
        self.rows += n
        if fault.kind == "glitch":
            self.hits[fault.name] = self.hits.get(fault.name, 0) + n
            self.faults[fault.name] = f"{fault.name} on {self.hits[fault.name]} reading(s)"
        else:
            self.faults.setdefault(f"{fault.name} {fault.start}", fault.label())

    def listed(self, most: int = 6) -> str:
        labels = list(self.faults.values())
        more = f" and {len(labels) - most} more" if len(labels) > most else ""
        return "; ".join(labels[:most]) + more


def set_aside_faulted(bundle: Bundle) -> tuple[Bundle, dict[str, list[str]]]:
    """The bundle without the readings its fault log says were faulted on purpose (module
    docstring), the odometry's faulted spans in :attr:`Bundle.odometry_faulted`, and a note per
    stream name saying what was set aside. A bundle without a fault log is returned as is."""
    if bundle.faults is None or len(bundle.faults) == 0:
        return bundle, {}
    faults = read_faults(bundle.faults, str(bundle.path / f"{FAULT_LOG}.csv"))
    truth = bundle.get("truth_pose")
    dt_ref = _interval(truth["t"]) if truth is not None else 0.0
    tables = dict(bundle.tables)
    aside: dict[str, _Aside] = {}
    for name, table in bundle.tables.items():
        if name not in ("gyro", "compass", "range", "landmarks"):
            continue
        t = table["t"]  # non-decreasing (load_bundle checks): windows by binary search
        drop = np.zeros(len(table), dtype=bool)
        margin = KIDNAP_MARGIN_SAMPLES * max(dt_ref, _interval(t))
        kinds = (np.asarray(table.text["kind"]).astype(str) if "kind" in table.text
                 else None)
        for f in faults:
            if f.kind == "kidnap" and name != "range" and truth is not None:
                lo, hi = f.start - margin, f.start + margin
            elif f.kind in SENSOR_FAULTS and _TABLE.get(f.target) == name:
                # a glitch: its one reading's stamp
                lo, hi = (f.start - 1e-6, f.end + 1e-6) if f.start == f.end else (f.start, f.end)
            else:
                continue
            rows = np.arange(np.searchsorted(t, lo, "left"), np.searchsorted(t, hi, "right"))
            if name == "range" and rows.size:
                rows = rows[_of_sensors(table, f, rows, kinds)]
            new = int((~drop[rows]).sum())
            for stream in _STREAMS[f.target if name == "range" else name]:
                aside.setdefault(stream, _Aside()).add(new, f)
            drop[rows] = True
        if drop.any():
            tables[name] = table.select(~drop)
    spans, why = _odometry_spans(bundle, faults, dt_ref)
    notes = {
        stream: [
            f"set aside {a.rows} reading(s) faulted on purpose, as the recording's fault log "
            f"says ({FAULT_LOG}.csv: {a.listed()}): an injected fault is no "
            "error of the sensor model"
        ]
        for stream, a in aside.items() if a.rows
    }
    if spans:
        notes.setdefault("odometry", []).append(
            f"set aside the odometry where {len(spans)} fault(s) were injected, as the "
            f"recording's fault log says ({FAULT_LOG}.csv: {'; '.join(why)}): a robot picked "
            "up, a wheel slipping or encoders stuck on purpose is no error of the odometry "
            "model; windows restart after each"
        )
    return replace(bundle, tables=tables, odometry_faulted=spans), notes


def _of_sensors(
    table: Table, f: Fault, rows: NDArray[np.intp], kinds: NDArray[np.str_] | None
) -> NDArray[np.bool_]:
    """Which of the range ``rows`` are of the fault's kind of sensor (the ``kind`` column; all
    when there is none) and of its ``sensors``."""
    out = np.ones(rows.size, dtype=bool)
    if kinds is not None:
        out &= kinds[rows] == f.target
    if f.sensors is not None and "sensor" in table.columns:
        out &= np.isin(table["sensor"][rows], np.asarray(f.sensors, dtype=float))
    return out


def _odometry_spans(
    bundle: Bundle, faults: list[Fault], dt_ref: float
) -> tuple[tuple[tuple[float, float], ...], list[str]]:
    """Sorted spans of the odometry set aside for kidnaps, wheel slips and stuck encoders,
    each widened by :data:`KIDNAP_MARGIN_SAMPLES` intervals (``OdometryProblem`` merges them
    with its stalls), and the faults' labels."""
    odo = bundle.get("odometry")
    if odo is None:
        return (), []
    margin = KIDNAP_MARGIN_SAMPLES * max(dt_ref, _interval(odo["t"]))
    raw, why = [], []
    for f in faults:
        if f.kind == "kidnap" or f.kind == "wheel_slip" or (
            f.kind in SENSOR_FAULTS and f.target == "encoders"
        ):
            end = min(f.end, float(odo["t"][-1]))
            raw.append((f.start - margin, end + margin))
            why.append(f.label())
    return tuple(sorted(raw)), why
