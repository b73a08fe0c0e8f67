"""Small plane-geometry helpers that the simulator, the estimators, calibration and the tools share.

The lowest layer (core): stdlib and numpy only, so the firmware-side code (``estimation/``) can
use them without the simulator. Angles are radians, CCW from +x (docs/architecture.md, Frames).
"""

from __future__ import annotations

import math
from typing import overload

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

TAU = 2.0 * math.pi


@overload
def wrap_angle(a: float) -> float: ...


@overload
def wrap_angle(a: ArrayLike) -> FloatArray: ...


def wrap_angle(a: float | ArrayLike) -> float | FloatArray:
    """Wrap an angle (or an array of them) to (-pi, pi].

    One formula for scalars (``math``, the hot path of the filters) and arrays (``numpy``), bit
    for bit the same: ``fmod(a, 2 pi)`` is exact (IEEE 754), which leaves ``(-2 pi, 2 pi)``, then
    one shift by ``2 pi`` lands in ``(-pi, pi]``. So ``pi`` stays ``pi`` and ``-pi`` becomes
    ``pi``. The simulator's numba kernels call ``core/raycast.py`` ``wrap_angle_compiled``, the
    same formula compiled (numba has ``np.fmod`` but not ``math.fmod``). NaN stays NaN.
    """
    if isinstance(a, float | int):  # np.float64 is a float
        w = math.fmod(a, TAU)
        if w > math.pi:
            w -= TAU
        elif w <= -math.pi:
            w += TAU
        return w
    src = np.asarray(a, dtype=float)
    arr = np.empty_like(src)  # (an array for a 0-d input too, where fmod gives a scalar)
    np.fmod(src, TAU, out=arr)
    # the shifts in place, where they apply (three times faster than np.where's copies)
    np.subtract(arr, TAU, out=arr, where=arr > math.pi)
    np.add(arr, TAU, out=arr, where=arr <= -math.pi)
    return arr


def circle_centre(points: ArrayLike) -> FloatArray:
    """Centre ``(d,)`` of the circle (d = 2) or sphere (d = 3) through ``points`` ``(N, d)``.

    The algebraic (Kasa) least-squares fit: ``|m|^2 = 2 h.m + c`` is linear in the centre ``h``
    and ``c = r^2 - |h|^2`` (I. Kasa, "A circle fitting procedure and its error analysis", IEEE
    Trans. Instrum. Meas. 25(1), 1976). A magnetometer's hard-iron offset is the centre of the
    circle the horizontal field draws while the robot turns. Needs ``N >= d + 1`` points not all
    on one line (plane).
    """
    m = np.asarray(points, dtype=float)
    a = np.column_stack([2 * m, np.ones(len(m))])
    sol, *_ = np.linalg.lstsq(a, np.sum(m**2, axis=1), rcond=None)
    return np.asarray(sol[:-1], dtype=float)


def wall_clearance(points: ArrayLike, walls: ArrayLike) -> FloatArray:
    """``(T,)`` distance from each ``(x, y)`` of ``points`` ``(T, >=2)`` to the nearest wall
    segment of ``walls`` ``(M, 4)`` rows ``x0, y0, x1, y1``, m (``inf`` without walls)."""
    p = np.asarray(points, dtype=float)[:, None, :2]
    w = np.asarray(walls, dtype=float).reshape(-1, 4)
    if len(w) == 0:
        return np.full(p.shape[0], np.inf)
    a, b = w[None, :, :2], w[None, :, 2:4]
    ab = b - a
    u = np.clip(np.sum((p - a) * ab, axis=2) / np.maximum(np.sum(ab * ab, axis=2), 1e-300),
                0.0, 1.0)
    nearest = a + u[:, :, None] * ab
    return np.asarray(np.min(np.linalg.norm(p - nearest, axis=2), axis=1), dtype=float)
