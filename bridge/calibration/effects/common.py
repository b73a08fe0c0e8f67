"""Helpers shared by the effect modules (config keys, categorical columns)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from koala_bridge.calibration.effects.base import EffectInstance
from koala_bridge.core.geometry import wrap_angle


def config_name(name: str) -> str:
    """A TOML-friendly key for an effect name (``covariate:temperature_c`` -> ``covariate_...``)."""
    return name.replace(":", "_")


def scalar_config(
    inst: EffectInstance, params: Sequence[float], problem: Any, combine: str = "add"
) -> dict[str, Any]:
    """The native key with the total value, or ``calibration.<name>`` with named parameters.

    A native key ``"*key"`` is a declared value (or list) the effect multiplies by
    ``1 + p``: an IR sensor's gain is its response curve's counts, scaled."""
    native = problem.native_keys.get(inst.name)
    if native is not None and native.startswith("*") and len(params) == 1:
        declared_list = problem.declared_values.get(native)
        if declared_list is not None:
            factor = 1 + float(params[0])
            return {native[1:]: [_round(float(v) * factor) for v in declared_list]}
    elif native is not None and len(params) == 1:
        declared = problem.declared_values.get(inst.name, 0.0)
        if combine == "add":
            total = declared + float(params[0])
        else:  # multiplicative scale errors: (1 + declared)(1 + p) - 1
            total = (1 + declared) * (1 + float(params[0])) - 1
        return {native: _round(total)}
    return {
        f"calibration.{config_name(inst.name)}": {
            n: _round(float(v)) for n, v in zip(inst.param_names, params, strict=True)
        }
    }


def _round(v: float) -> float:
    return float(f"{v:.6g}")


def categorical_levels(values: np.ndarray, max_levels: int = 32) -> np.ndarray | None:
    """Sorted levels if ``values`` is integer valued with 2..max_levels distinct values."""
    v = values[np.isfinite(values)]
    if v.size == 0 or not np.all(v == np.round(v)):
        return None
    levels = np.unique(v)
    return levels if 2 <= levels.size <= max_levels else None


#: Smallest orientation spread (``CompassProblem.orientation_spread`` in calibration/streams/
#: compass.py) at which the iron effects are proposed: below it the data cannot tell them from the
#: constant. Here, not in the stream module, because effects sit below the streams that use them.
MIN_ORIENTATION_SPREAD = 0.1


def enough_orientations(problem: Any, harmonic: int, effect: str) -> bool:
    """Whether the compass stream's orientations can determine an iron effect
    (:meth:`calibration.streams.compass.CompassProblem.orientation_spread`); when not, a
    note on the stream says why the effect was not tried."""
    spread = float(problem.orientation_spread(harmonic))
    if spread >= MIN_ORIENTATION_SPREAD:
        return True
    note_once(
        problem,
        f"{effect} not tried: the orientations vary too little to tell it from the constant "
        f"(spread {spread:.3g} < {MIN_ORIENTATION_SPREAD:g}; turn the sensor through more angles)",
    )
    return False


def note_once(problem: Any, note: str) -> None:
    """Add ``note`` to the stream's notes unless it is there (effects are proposed once per
    round of some loops, and per stage)."""
    if note not in problem.notes:
        problem.notes.append(note)


#: The largest share of the reference's variance that may be unshared with the readings
#: (:func:`reference_noise_share`) when a gain or a time shift is fitted through it. The share
#: bounds the attenuation of a fitted gain from above (it counts any fast variation the
#: readings do not follow: the reference's noise, and also censored readings or a latency's
#: smoothing); beyond a quarter the reference is mostly not signal, and the fitted gain could be
#: off by more than any scale error of a working sensor. Measured: a still gyro against a
#: differentiated optical heading 0.83-0.95; the simulator's streams (default.toml, with and
#: without an injected latency) 0-0.04; the real bundles of tests/data/real 0-0.0013.
MAX_REFERENCE_NOISE_SHARE = 0.25
#: the share above which the report says a fitted gain may be attenuated by it
NOTE_REFERENCE_NOISE_SHARE = 0.01
#: fixed-point steps of the gain the share is measured with (:func:`reference_noise_share`)
SHARE_ITERATIONS = 20
#: rows the share is measured on at most (a contiguous block of the fit part)
MAX_SHARE_ROWS = 20_000
#: the largest latency between readings and reference looked through (s; effects/time_offset.py)
MAX_LAG_S = 0.5


def reference_noise_share(problem: Any, u: Any = None) -> float:
    """Share of the fit part's reference variance that is noise of the reference's own (0
    without a reference), in the declared prediction's units (``base_gain * curve(u)``).

    Differences within each series of the stream (the rows of one value of its categorical
    columns, or its ``series``: a sensor, a beacon, a landmark; interleaved series would count
    as noise) separate fast variation from the slow: ``dp`` of the prediction, ``dy`` of the
    readings. Fast variation that is motion (a drive's per-step jitter) is in the readings too,
    ``cov(dp, dy) ~ var(dp_motion)`` for a gain near 1; noise of the reference is not. So the
    reference's white noise is ``sigma^2 ~ (var(dp) - cov(dp, dy)) / 2`` (differences of white
    noise have twice its variance), and the share is that over ``var(p)``. ``u``: the reference
    at the stream's rows in place of the stream's own (read at a latency:
    ``pipeline._aligned_share``).
    """
    u = getattr(problem, "u", None) if u is None else u
    y = getattr(problem, "y", None)
    if u is None or y is None or not hasattr(problem, "t"):
        return 0.0
    rows = np.flatnonzero(problem.split.mask(problem.t, "fit"))
    if rows.size > MAX_SHARE_ROWS:
        # a contiguous block from the middle of the fit part: consecutive rows, as sampled
        start = (rows.size - MAX_SHARE_ROWS) // 2
        rows = rows[start : start + MAX_SHARE_ROWS]
    sparse = getattr(problem, "sparse_reference_t", None)
    if sparse is not None and sparse.size > 2 and rows.size > 2:
        # a reference sparse beside the readings (a 12.5 Hz log against a 100 Hz gyro): the
        # readings between two of its samples share its interpolation, whose differences hide
        # its noise (a clean gyro got a -14 % scale against 0.02 rad of heading noise). One row
        # per reference interval, nearest its middle, where the rate is the interval's own.
        tr = np.asarray(problem.t, dtype=float)[rows]
        mid = 0.5 * (sparse[1:] + sparse[:-1])
        mid = mid[(mid >= tr[0]) & (mid <= tr[-1])]
        j = np.clip(np.searchsorted(tr, mid), 1, tr.size - 1)
        j = j - (mid - tr[j - 1] < tr[j] - mid)
        rows = rows[np.unique(j)]
    uf = np.asarray(u, dtype=float)[rows]
    curve = getattr(problem, "curve", None)
    pf = getattr(problem, "base_gain", 1.0) * (curve(uf) if curve is not None else uf)
    yf = np.asarray(y, dtype=float)[rows]
    ok = np.isfinite(pf) & np.isfinite(yf)
    cats = series_columns(problem, rows)
    if cats is not None:
        ok &= np.all(np.isfinite(cats), axis=1)
        keys = np.unique(cats[ok], axis=0, return_inverse=True)[1].ravel()
    else:
        keys = np.zeros(int(ok.sum()), dtype=np.intp)
    pf, yf = pf[ok], yf[ok]
    t_ok = np.asarray(problem.t, dtype=float)[rows][ok]
    if pf.size < 3:
        return 0.0
    var = float(np.var(pf))
    if var <= 0.0:
        return np.inf
    angle = bool(getattr(problem, "angle", False))
    several = bool(keys.size and np.any(keys != keys[0]))
    step = float(np.median(np.diff(t_ok))) if t_ok.size > 1 else 0.0
    k_max = min(int(MAX_LAG_S / step), pf.size // 4) if step > 0 else 0

    def unshared(gain: float) -> float:
        if several:
            # several series: first differences within each, at lag 0
            order = np.argsort(keys, kind="stable")
            same = np.diff(keys[order]) == 0
            dp, dy = np.diff(pf[order])[same], np.diff(yf[order])[same]
            return _unshared(dp, dy / gain, angle, 0)
        # one series: the readings may lag the reference (what time_offset fits), which
        # decorrelates fast motion at lag 0, by a fraction of a sample too; differences over
        # m = 1, 2, 4, ... samples, each at the lag (within MAX_LAG_S) it is shared best at,
        # and the scale that leaves the least unshared (white noise differences have 2 sigma^2
        # at every scale)
        noise = np.inf
        m = 1
        while m <= max(k_max, 1) and m < pf.size // 2:
            noise = min(noise, _unshared(pf[m:] - pf[:-m], (yf[m:] - yf[:-m]) / gain, angle,
                                         k_max))
            m *= 2
        return noise

    # the readings follow the reference times a gain (a scale error, a reflectivity): the
    # shared fast variation is cov(dp, dy) / g. g from the levels is pulled towards 0 by the
    # very noise measured (errors in the variables: by the share), which then looked shared:
    # a gyro against a heading whose differenced rate was half noise read 0.13. So g is the
    # levels' regression over the share's complement, to a fixed point, held within 2:1.
    # Readings that run against the reference (a sign convention: a gain of -1) share its
    # motion as much as readings that follow it: the gain keeps its sign, its size within 2:1
    # (held at +0.5 for those, their shared motion read as noise and hid the sign's note).
    pc, yc = pf - pf.mean(), yf - yf.mean()
    pp, py = float(np.dot(pc, pc)), float(np.dot(pc, yc))
    sign = -1.0 if py < 0 else 1.0

    def held(g: float) -> float:
        return sign * float(np.clip(abs(g), 0.5, 2.0))

    gain = 1.0 if angle or pp <= 0 else held(py / pp)
    noise = unshared(gain)
    for _ in range(0 if angle or pp <= 0 else SHARE_ITERATIONS):
        share = 0.5 * noise / var if np.isfinite(noise) else 0.0
        better = held(py / (pp * max(1.0 - share, 0.1)))
        if abs(better - gain) < 1e-3 * abs(gain):
            break
        gain = better
        noise = unshared(gain)
    return 0.5 * float(noise) / var if np.isfinite(noise) else 0.0


def series_columns(problem: Any, rows: np.ndarray) -> np.ndarray | None:
    """``(len(rows), k)``: the columns naming the series each of ``rows`` belongs to (one
    sensor, landmark, tag...: the stream's categorical columns together, else its ``sensor``
    column, and its ``series``), None for a stream of one series. Increments, differences and
    lags are taken within a series, never across two."""
    columns = getattr(problem, "columns", {})
    names = [n for n in getattr(problem, "categorical_names", ()) if n in columns] or [
        n for n in ("sensor",) if n in columns]
    cols = [np.asarray(columns[n], dtype=float)[rows] for n in names]
    series = getattr(problem, "series", None)
    if series is not None:
        cols.append(np.asarray(series, dtype=float)[rows])
    return np.column_stack(cols) if cols else None


def _unshared(dp: np.ndarray, dy: np.ndarray, angle: bool, k_max: int) -> float:
    """``var(dp) - max_k cov(dp_t, dy_t+k)`` over lags ``|k| <= k_max`` (at least 0)."""
    if angle:
        dp, dy = wrap_angle(dp), wrap_angle(dy)
    if dp.size < 2:
        return float("inf")
    dp, dy = dp - dp.mean(), dy - dy.mean()
    shared = float(np.mean(dp * dy))
    k = min(k_max, dp.size // 4)
    if k > 0:
        # every lag at once: the cross-covariance by FFT (entry j pairs dp_t with dy_t+j)
        n = dp.size
        size = 1 << int(np.ceil(np.log2(2 * n)))  # zero-padded: no wrap-around
        cc = np.fft.irfft(np.fft.rfft(dy, size) * np.conj(np.fft.rfft(dp, size)), size) / n
        lags = np.r_[cc[: k + 1], cc[-k:]]  # lags 0..k and -k..-1
        shared = max(shared, float(np.max(lags)))
    return max(float(np.mean(dp * dp)) - shared, 0.0)


def stream_share(problem: Any) -> float:
    """:func:`reference_noise_share` of the stream, measured once (kept as its
    ``reference_share``, which the pipeline sets from the whole stream for a decimated subset):
    scale, time_offset, k r^2 and the write check ask."""
    share = getattr(problem, "reference_share", None)
    if share is None:
        share = reference_noise_share(problem)
        if hasattr(problem, "reference_share"):
            problem.reference_share = share
    return float(share)


def gain_share(problem: Any) -> float:
    """The noise share a gain fitted on the stream is pulled towards 0 by: for a gyro compared
    in heading space with a dense reference (``streams.to_heading_space``) the heading's
    (``heading_share``), as the heading's path is then the regressor; else the rate's
    (:func:`stream_share`). A time shift still smooths the rate's noise: it keeps the rate's."""
    heading = getattr(problem, "heading_share", None)
    if heading is not None and getattr(problem, "integrate_window_s", None) is not None:
        return float(heading)
    return stream_share(problem)


def _one_value_per_level(problem: Any) -> tuple[str, int] | None:
    """``(column, levels)`` of a categorical column of the fit part within each of whose
    levels the reference holds one value, its variation all between the levels; None."""
    part = problem.part("fit")
    u = np.asarray(part.u, dtype=float)
    if u.size < 2 or not np.all(np.isfinite(u)) or float(np.ptp(u)) == 0.0:
        return None
    tol = 1e-9 * float(np.max(np.abs(u)))
    for col in getattr(problem, "categorical_names", ()):
        z = np.asarray(part.columns[col])
        levels = np.unique(z[np.isfinite(z)])
        if levels.size < 2:
            continue
        if all(float(np.ptp(u[z == v])) <= tol for v in levels):
            return col, int(levels.size)
    return None


def reference_dominates(problem: Any, effect: str) -> bool:
    """Whether a scalar stream's reference varies enough beyond its own noise to determine an
    effect fitted through it (a gain, a range-squared term, a time offset: a reference that is
    constant on the fit part determines none of them; :func:`reference_noise_share` at most
    :data:`MAX_REFERENCE_NOISE_SHARE`, for a gain :func:`gain_share`); when not, a note on the
    stream says why the effect was not tried.

    Nor does a reference that holds one value per level of a categorical column (each sensor
    held at its own distance): through it, a gain or a range-squared term is one offset per
    level, which ``offset_per`` names. Two time-of-flight rangers held at 256 and 265 mm got a
    ``scale`` of +1.6 there, and the report called it a unit error."""
    confounded = _one_value_per_level(problem)
    if confounded is not None:
        col, levels = confounded
        note_once(
            problem,
            f"{effect} not tried: the reference holds one value per {col} on the fit part "
            f"({levels} values): fitted through it, an effect is an offset per {col}, which "
            f"offset_per:{col} names; record several distances (speeds) per {col}",
        )
        return False
    share = gain_share(problem) if effect == "scale" else stream_share(problem)
    if share <= MAX_REFERENCE_NOISE_SHARE:
        if share > NOTE_REFERENCE_NOISE_SHARE and effect == "scale":
            note_once(
                problem,
                f"the reference's fast variation is {100 * share:.2g} % unshared with the "
                "readings (its own noise, or readings that do not follow it): a fitted scale may "
                "be pulled towards 0 by up to that share",
            )
        return True
    if not np.isfinite(share):
        note_once(
            problem,
            f"{effect} not tried: the reference does not vary on the fit part (one value): "
            "fitted through it, an effect is an offset there and only the held-out part's "
            "extrapolation would choose it; record several distances (speeds) in both parts",
        )
    else:
        note_once(
            problem,
            f"{effect} not tried: the reference varies too little beyond its own noise (noise "
            f"{100 * min(share, 1.0):.3g} % of its variance on the fit part, the readings do not "
            "follow it; fitted through it, a gain is pulled towards 0 by about that share and a "
            "time shift smooths the noise): record motion over a wider range, or a reference "
            "with less noise",
        )
    return False
