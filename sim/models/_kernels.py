"""Compiled (numba) inner loops of the IR, sonar and camera models.

The equations are those of the modules' docstrings and of their numpy helper functions
(``camera.miss_probability``, ``ir.counts_from_distances``, ...); the statistical tests hold the
public ``measure`` functions, which call these kernels, against those helpers. The kernels draw
nothing: the callers draw every variate from the sensor's ``numpy.random.Generator`` in a fixed
number of calls and pass them in, so the streams stay the callers' (same seed, same readings).
Why compiled: at 100 Hz per sensor the per-step cost of ~100 small numpy calls dominated the
simulator (bench/bench_sim.py).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from sim.raycast import first_hit


@numba.njit(cache=True, nogil=True)
def interp(x: float, xs: np.ndarray, ys: np.ndarray) -> float:  # pragma: no cover - compiled
    """``np.interp`` for one point (ends held)."""
    n = xs.shape[0]
    if x <= xs[0]:
        return ys[0]
    if x >= xs[n - 1]:
        return ys[n - 1]
    i = 1
    while xs[i] < x:
        i += 1
    t = (x - xs[i - 1]) / (xs[i] - xs[i - 1])
    return ys[i - 1] + t * (ys[i] - ys[i - 1])


# ---------------------------------------------------------------------------------------- IR
@numba.njit(cache=True, nogil=True)
def ir_kernel(d: np.ndarray, w: np.ndarray, rho: np.ndarray, rx: np.ndarray, ry: np.ndarray,
              ex: np.ndarray, ey: np.ndarray, z: np.ndarray, ideal: bool, gain: float,
              count_sigma: float, ambient: float, ambient_sigma: float, max_counts: float,
              out_counts: np.ndarray, out_ambient: np.ndarray, out_truth: np.ndarray
              ) -> None:  # pragma: no cover - compiled
    """``d`` (n, k) ray ranges; ``z`` (3 n,) normals: distance, count and ambient noise of sensor
    ``i`` at ``z[i]``, ``z[n + i]``, ``z[2 n + i]`` (unused when ``ideal``). Outputs int64 (n,)."""
    n, k = d.shape
    last = rx[rx.shape[0] - 1]
    for i in range(n):
        c = 0.0
        ct = 0.0
        for j in range(k):
            dj = d[i, j]
            if math.isfinite(dj):
                dt = dj
                dn = dj if ideal else max(dj + interp(dj, ex, ey) * z[i], 0.0)
            else:
                dt = last
                dn = last
            ct += w[j] * rho[i, j] * interp(dt, rx, ry)
            c += w[j] * rho[i, j] * interp(dn, rx, ry)
        out_truth[i] = np.int64(min(max(np.rint(ct), 0.0), max_counts))
        if ideal:
            out_counts[i] = out_truth[i]
            out_ambient[i] = np.int64(min(max(np.rint(ambient), 0.0), max_counts))
        else:
            c = c * gain + count_sigma * z[n + i]
            out_counts[i] = np.int64(min(max(np.rint(c), 0.0), max_counts))
            a = ambient + ambient_sigma * z[2 * n + i]
            out_ambient[i] = np.int64(min(max(np.rint(a), 0.0), max_counts))


# ------------------------------------------------------------------------------------- sonar
@numba.njit(cache=True, nogil=True)
def sonar_kernel(d: np.ndarray, inc: np.ndarray, max_range: float, tx: np.ndarray,
                 ty: np.ndarray, crit: float, p_late: float, p_cross: float, p_glitch: float,
                 min_range: float, ideal: bool, use_leg: bool, leg: np.ndarray, use_cross: bool,
                 hit_xy: np.ndarray, sensor_xy: np.ndarray, heading: np.ndarray,
                 half_ap: float, cycle: np.ndarray, u: np.ndarray, z: np.ndarray,
                 u_cross: np.ndarray, out_range: np.ndarray, out_truth: np.ndarray,
                 out_inc: np.ndarray, out_kind: np.ndarray) -> None:  # pragma: no cover
    """``d``, ``inc`` (n, k); variates ``u`` (3 n,): late echo, glitch, glitch value of sensor
    ``i`` at ``u[i]``, ``u[n + i]``, ``u[2 n + i]``; ``z`` (n,) distance noise; ``u_cross``
    (n n,) pair ``(i, j)`` at ``i n + j``. Unused when ``ideal``."""
    n, k = d.shape
    echo = np.empty(n)
    for i in range(n):
        best = np.inf
        bi = -1
        e = np.inf
        for j in range(k):
            dj = d[i, j]
            if not (dj <= max_range):          # inf (no hit) or beyond range
                continue
            if dj < best:
                best = dj
                bi = j
            if abs(inc[i, j]) <= crit and dj < e:
                e = dj
        if bi >= 0:
            out_truth[i] = best
            out_inc[i] = inc[i, bi]
        else:
            out_truth[i] = np.nan
            out_inc[i] = np.nan
        if ideal:
            out_range[i] = out_truth[i]
            out_kind[i] = 1 if bi >= 0 else 0
            continue
        kind = 1 if e < np.inf else 0
        if kind == 0 and bi >= 0 and use_leg and u[i] < p_late:
            late = np.inf
            for j in range(k):
                if d[i, j] <= max_range and math.isfinite(leg[i, j]):
                    late = min(late, 0.5 * (d[i, j] + leg[i, j]))
            if late < np.inf:
                e = late
                kind = 2
        echo[i] = e
        out_kind[i] = kind
    if ideal:
        return
    if use_cross:
        for i in range(n):
            best = echo[i]
            took = False
            for jj in range(n):
                if jj == i or not cycle[i, jj] or not (u_cross[i * n + jj] < p_cross):
                    continue
                for q in range(k):
                    if not (d[jj, q] <= max_range and abs(inc[jj, q]) <= crit):
                        continue
                    vx = hit_xy[jj, q, 0] - sensor_xy[i, 0]
                    vy = hit_xy[jj, q, 1] - sensor_xy[i, 1]
                    ang = math.atan2(vy, vx) - heading[i]
                    ang = math.atan2(math.sin(ang), math.cos(ang))
                    if abs(ang) > half_ap:
                        continue
                    p = 0.5 * (d[jj, q] + math.hypot(vx, vy))
                    if p < best:
                        best = p
                        took = True
            if took:
                echo[i] = best
                out_kind[i] = 3
    for i in range(n):
        e = echo[i]
        r = np.nan
        if e < np.inf:
            r = max(e + interp(e, tx, ty) * z[i], 0.0)
        if u[n + i] < p_glitch:
            r = min_range + (max_range - min_range) * u[2 * n + i]
            out_kind[i] = 4
        if r > max_range:
            r = np.nan
            out_kind[i] = 0
        out_range[i] = r


@numba.njit(cache=True, nogil=True)
def second_leg_kernel(seg: np.ndarray, ox: np.ndarray, oy: np.ndarray, dx: np.ndarray,
                      dy: np.ndarray, rr: np.ndarray, wall: np.ndarray, max_range: float,
                      out: np.ndarray) -> None:  # pragma: no cover - compiled
    """Specular path first hit -> second surface -> sensor, per ray (flat arrays); inf: none."""
    for r in range(rr.shape[0]):
        out[r] = np.inf
        m = wall[r]
        if m < 0 or not math.isfinite(rr[r]):
            continue
        il = seg[4, m]
        nx = -seg[3, m] * il
        ny = seg[2, m] * il
        dot = dx[r] * nx + dy[r] * ny
        rx = dx[r] - 2.0 * dot * nx
        ry = dy[r] - 2.0 * dot * ny
        # Start a hair off the wall so the cast does not hit the wall it leaves.
        sx = ox[r] + dx[r] * rr[r] + 1e-6 * rx
        sy = oy[r] + dy[r] * rr[r] + 1e-6 * ry
        t, _m2, _inc = first_hit(seg, sx, sy, rx, ry, max_range)
        if t < np.inf:
            back = math.hypot(sx + rx * t - ox[r], sy + ry * t - oy[r])
            out[r] = t + back


@numba.njit(cache=True, nogil=True)
def sonar_ring_kernel(seg: np.ndarray, rays: np.ndarray, index: np.ndarray, start: int, n: int,
                      k: int, max_range: float, min_reading: float, tx: np.ndarray,
                      ty: np.ndarray, crit: float, p_late: float, p_cross: float,
                      p_glitch: float, glitch_min: float, ideal: bool, use_leg: bool,
                      use_cross: bool, cycle: np.ndarray, half_ap: float, u: np.ndarray,
                      z: np.ndarray, u_cross: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    # pragma: no cover - compiled
    """The sonar ring from the simulator's cast, in one call: ``rays`` (6, R) rows origin x, y,
    direction x, y, range, incidence (:func:`sim.raycast.cast_fan`), ``index`` (R,) wall hit;
    the ring's rays start at ``start``. Computes the specular second legs (``use_leg``) and the
    crosstalk geometry (``use_cross``) and runs :func:`sonar_kernel`; readings nearer than
    ``min_reading`` become 0 (the Koala's "too close"). Returns ranges, truth ranges, truth
    incidence, kind."""
    nk = n * k
    d = np.empty((n, k))
    inc = np.empty((n, k))
    for r in range(nk):
        d[r // k, r % k] = rays[4, start + r]
        inc[r // k, r % k] = rays[5, start + r]
    leg = np.empty((n, k)) if use_leg else np.empty((0, 0))
    if use_leg:
        ox = np.ascontiguousarray(rays[0, start:start + nk])
        oy = np.ascontiguousarray(rays[1, start:start + nk])
        dx = np.ascontiguousarray(rays[2, start:start + nk])
        dy = np.ascontiguousarray(rays[3, start:start + nk])
        rr = np.ascontiguousarray(rays[4, start:start + nk])
        wall = np.ascontiguousarray(index[start:start + nk])
        flat = np.empty(nk)
        second_leg_kernel(seg, ox, oy, dx, dy, rr, wall, max_range, flat)
        for r in range(nk):
            leg[r // k, r % k] = flat[r]
    hit_xy = np.empty((n, k, 2)) if use_cross else np.empty((0, 0, 2))
    sensor_xy = np.empty((n, 2)) if use_cross else np.empty((0, 2))
    heading = np.empty(n) if use_cross else np.empty(0)
    if use_cross:
        for i in range(n):
            for j in range(k):
                r = start + i * k + j
                t = rays[4, r] if math.isfinite(rays[4, r]) else 0.0
                hit_xy[i, j, 0] = rays[0, r] + rays[2, r] * t
                hit_xy[i, j, 1] = rays[1, r] + rays[3, r] * t
            c = start + i * k + k // 2
            sensor_xy[i, 0] = rays[0, c]
            sensor_xy[i, 1] = rays[1, c]
            heading[i] = math.atan2(rays[3, c], rays[2, c])
    out_range = np.empty(n)
    out_truth = np.empty(n)
    out_inc = np.empty(n)
    kind = np.zeros(n, dtype=np.int8)
    sonar_kernel(d, inc, max_range, tx, ty, crit, p_late, p_cross, p_glitch, glitch_min, ideal,
                 use_leg, leg, use_cross, hit_xy, sensor_xy, heading, half_ap, cycle, u, z,
                 u_cross, out_range, out_truth, out_inc, kind)
    for i in range(n):
        if out_range[i] < min_reading:          # nan stays nan: no echo
            out_range[i] = 0.0
    return out_range, out_truth, out_inc, kind


# ------------------------------------------------------------------------------------ camera
@numba.njit(cache=True, nogil=True)
def _distance_term(d: float, dmin: float, dmax: float, base: float) -> float:
    if d < dmin or d > dmax:
        return 1.0
    u = (d - dmin) / (dmax - dmin)
    if abs(base - 1.0) < 1e-12:
        return u
    return (base**u - 1.0) / (base - 1.0)


@numba.njit(cache=True, nogil=True)
def camera_kernel(ids: np.ndarray, d: np.ndarray, b: np.ndarray, a: np.ndarray,
                  amax: np.ndarray, all_ids: np.ndarray, p_perc: float, p_recog: float,
                  dmin: float, dmax: float, base: float, dist: float, dmid: float,
                  fdoub: float, bsig: float, u: np.ndarray, z: np.ndarray, out_ids: np.ndarray,
                  out_r: np.ndarray, out_b: np.ndarray, out_src: np.ndarray
                  ) -> int:  # pragma: no cover - compiled
    m = ids.shape[0]
    n_all = all_ids.shape[0]
    c = 0
    for k in range(m):
        ang = 4.0 * a[k] * a[k] / (amax[k] * amax[k])
        f = _distance_term(d[k], dmin, dmax, base)
        if u[k, 0] < min(1.0, ang + p_perc + f):
            continue                                   # not perceived
        lid = ids[k]
        if n_all > 1 and u[k, 1] < min(1.0, ang + p_recog + f):
            j = min(int(u[k, 2] * (n_all - 1)), n_all - 2)
            # the j-th id of all_ids skipping the true one
            seen = 0
            for q in range(n_all):
                if all_ids[q] == ids[k]:
                    continue
                if seen == j:
                    lid = all_ids[q]
                    break
                seen += 1
        near = dist * d[k]
        far = dist * dmid * 2.0 ** ((d[k] - dmid) / fdoub)
        out_ids[c] = lid
        out_r[c] = max(d[k] + near * z[k, 0] + far * abs(z[k, 1]), 0.0)
        bb = b[k] + bsig * z[k, 2]
        out_b[c] = math.atan2(math.sin(bb), math.cos(bb))
        out_src[c] = k
        c += 1
    return c
