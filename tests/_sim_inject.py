"""Inject undeclared effects into a bundle exported from a simulator recording.

Each function edits one bundle directory's CSV files in place (numpy on the exported columns,
text columns and empty cells kept as they were), so what the calibration reads is the
simulator's own recording with exactly one known change. Used by
``tests/integration/test_calibration_sim_inject.py``.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

#: The streams calibrate builds from a recording of the simulator under config/default.toml.
STREAMS = frozenset(
    {"gyro", "compass", "odometry", "range:ir", "range:sonar", "landmark_range", "landmark_bearing"}
)


class CsvTable:
    """A bundle CSV as its header and string cells; numeric columns read and written as floats."""

    def __init__(self, path: Path) -> None:
        self.path = path
        with path.open(newline="", encoding="utf-8") as fh:
            rows = list(csv.reader(fh))
        self.header, self.rows = rows[0], rows[1:]

    def __getitem__(self, column: str) -> FloatArray:
        j = self.header.index(column)
        return np.array([float(r[j]) if r[j] else np.nan for r in self.rows])

    def text(self, column: str) -> NDArray[np.str_]:
        j = self.header.index(column)
        return np.array([r[j] for r in self.rows])

    def __setitem__(self, column: str, values: FloatArray) -> None:
        if column not in self.header:
            self.header.append(column)
            for r in self.rows:
                r.append("")
        j = self.header.index(column)
        for r, v in zip(self.rows, values, strict=True):
            r[j] = "" if not np.isfinite(v) else repr(float(v))

    def save(self) -> None:
        with self.path.open("w", newline="", encoding="utf-8") as fh:
            csv.writer(fh, lineterminator="\n").writerows([self.header, *self.rows])


def _edit(bundle: Path, name: str) -> CsvTable:
    return CsvTable(bundle / f"{name}.csv")


# --- gyro -----------------------------------------------------------------------------------


def gyro_bias(bundle: Path, b: float) -> None:
    """``yaw_rate + b`` (rad/s)."""
    g = _edit(bundle, "gyro")
    g["yaw_rate"] = g["yaw_rate"] + b
    g.save()


def gyro_scale(bundle: Path, s: float) -> None:
    """``(1 + s) yaw_rate``: the recorded turn-on bias and noise scale too (the nuisance bias
    absorbs the one, the other is s of the noise)."""
    g = _edit(bundle, "gyro")
    g["yaw_rate"] = (1 + s) * g["yaw_rate"]
    g.save()


def gyro_bias_drift(bundle: Path, d: float) -> None:
    """``yaw_rate + d (t - t_ref)`` (rad/s per s), ``t_ref`` the middle of the fit part (the
    first 60 % of the span), as the effect defines it: a drift about another origin carries a
    bias of ``d (t_ref - origin)`` as well, which the tool then names too (measured: ``d = 5e-4``
    about ``t = 0`` gave ``bias_drift`` and ``bias`` 0.0081 = 18 s x d + the turn-on draw)."""
    g = _edit(bundle, "gyro")
    t = g["t"]
    t_ref = t[0] + 0.3 * (t[-1] - t[0])
    g["yaw_rate"] = g["yaw_rate"] + d * (t - t_ref)
    g.save()


def gyro_covariate(bundle: Path, c: float) -> None:
    """A ``temperature_c`` column, 25 +- 4 degC over a 42 s period (a robot warming and cooling,
    as in the synthetic generator), and ``yaw_rate + c (temperature_c - 25)``."""
    g = _edit(bundle, "gyro")
    temp = 25.0 + 4.0 * np.sin(2 * np.pi * g["t"] / 42.0 + 1.0)
    g["temperature_c"] = temp
    g["yaw_rate"] = g["yaw_rate"] + c * (temp - 25.0)
    g.save()


def gyro_time_offset(bundle: Path, tau: float) -> None:
    """The gyro lags the reference by ``tau`` s: ``yaw_rate(t) <- yaw_rate(t - tau)``, linearly
    interpolated (the first ``tau`` holds the first sample)."""
    g = _edit(bundle, "gyro")
    t = g["t"]
    g["yaw_rate"] = np.interp(t - tau, t, g["yaw_rate"])
    g.save()


# --- compass --------------------------------------------------------------------------------


def hard_iron(bundle: Path, h: tuple[float, float]) -> None:
    """``(mx, my) + h`` (uT)."""
    c = _edit(bundle, "compass")
    c["mx"] = c["mx"] + h[0]
    c["my"] = c["my"] + h[1]
    c.save()


def soft_iron(bundle: Path, e: tuple[float, float], declared: dict[str, Any]) -> None:
    """A soft iron ``A = I + F``, ``F = [[e_xx, e_xy], [e_xy, -e_xx]]``, in the frame the declared
    model corrects to: ``m <- h + S A S^-1 (m - h)`` with the declared hard iron ``h`` and soft
    iron ``S`` (planar blocks). The declared correction ``S^-1 (m - h)`` then sees ``A m_true``,
    and the effect's ``C = (I + E) C_declared`` removes it with ``E = -F`` exactly (``F^2`` is a
    multiple of I in 2-D: ``A^-1 = (I - F) / (1 - e_xx^2 - e_xy^2)``, the factor a gain the
    heading does not see) -- the synthetic generator's convention."""
    h = np.asarray(declared["hard_iron_uT"], dtype=float)[:2]
    s = np.asarray(declared["soft_iron"], dtype=float)[:2, :2]
    a = np.array([[1 + e[0], e[1]], [e[1], 1 - e[0]]])
    t = s @ a @ np.linalg.inv(s)
    c = _edit(bundle, "compass")
    m = np.column_stack([c["mx"], c["my"]]) - h
    m = m @ t.T + h
    c["mx"], c["my"] = m[:, 0], m[:, 1]
    c.save()


# --- odometry -------------------------------------------------------------------------------


def _scale_ticks(bundle: Path, left: float, right: float) -> None:
    o = _edit(bundle, "odometry")
    o["left_ticks"] = np.rint(left * o["left_ticks"])
    o["right_ticks"] = np.rint(right * o["right_ticks"])
    o.save()


def tick_scale(bundle: Path, k: float) -> None:
    """Both wheels count ``(1 + k)`` times the ticks: true ticks per metre = declared (1 + k)."""
    _scale_ticks(bundle, 1 + k, 1 + k)


def wheel_ratio(bundle: Path, rho: float) -> None:
    """Wheel diameters D_l / D_r = ``rho`` with the mean distance per tick kept (the effect's
    definition, ``s_l = dL/tpm 2 rho/(1 + rho)``, ``s_r = dR/tpm 2/(1 + rho)``): the left wheel
    counts ``(1 + rho)/(2 rho)``, the right ``(1 + rho)/2`` times the ticks."""
    _scale_ticks(bundle, (1 + rho) / (2 * rho), (1 + rho) / 2)


def heading_drift(bundle: Path, d: float, wheel_base_m: float, ticks_per_metre: float) -> None:
    """The odometry's heading turns at ``d`` rad/s relative to the truth: opposite tick streams,
    ``d (t - t0) b / 2`` metres of wheel travel taken off the left wheel and added to the right
    (rounded to whole ticks), so ``(s_r - s_l) / b`` gains ``d dt`` per step."""
    o = _edit(bundle, "odometry")
    extra = 0.5 * d * (o["t"] - o["t"][0]) * wheel_base_m * ticks_per_metre
    o["left_ticks"] = np.rint(o["left_ticks"] - extra)
    o["right_ticks"] = np.rint(o["right_ticks"] + extra)
    o.save()


def undeclare_robot_key(bundle: Path, key: str) -> None:
    """Drop a ``[robot]`` key from ``meta.json``, which declares the recorded robot and wins over
    MODEL.toml (bundle precedence), so that MODEL.toml's value is the declared one."""
    path = bundle / "meta.json"
    meta = json.loads(path.read_text(encoding="utf-8"))
    meta["robot"].pop(key)
    path.write_text(json.dumps(meta), encoding="utf-8")


# --- sonar ----------------------------------------------------------------------------------


def _sonar(bundle: Path) -> tuple[CsvTable, NDArray[np.bool_]]:
    r = _edit(bundle, "range")
    return r, r.text("kind") == "sonar"


def range_dependent(bundle: Path, k: float) -> None:
    """Sonar ``measured + k true_range^2`` (m; the effect's form)."""
    r, sonar = _sonar(bundle)
    tr = r["true_range"]
    r["measured"] = np.where(sonar, r["measured"] + k * tr**2, r["measured"])
    r.save()


def glitch(bundle: Path, probability: float, value: float, seed: int = 0) -> None:
    """Each sonar reading that had an echo reads ``value`` (max range) with ``probability``
    (independent draws of a generator seeded with ``seed``)."""
    r, sonar = _sonar(bundle)
    y = r["measured"]
    hit = sonar & np.isfinite(y) & (np.random.default_rng(seed).random(y.size) < probability)
    y[hit] = value
    r["measured"] = y
    r.save()
