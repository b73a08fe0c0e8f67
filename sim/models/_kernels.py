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
from koala_bridge.core.raycast import first_hit, wrap_angle_compiled


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


@numba.njit(cache=True, nogil=True)
def table_sigma(x: float, xs: np.ndarray, ys: np.ndarray) -> float:  # pragma: no cover
    """``sonar.distance_sigma`` for one range: :func:`interp` within the table, the last row's
    relative error ``ys[-1] / xs[-1]`` held beyond it (seeds/004 "+-6.6 %")."""
    n = xs.shape[0]
    if x > xs[n - 1] and xs[n - 1] > 0.0:
        return x * ys[n - 1] / xs[n - 1]
    return interp(x, xs, ys)


# ---------------------------------------------------------------------------------------- IR
@numba.njit(cache=True, nogil=True)
def ir_kernel(d: np.ndarray, z: np.ndarray, w: np.ndarray, rho: np.ndarray, rx: np.ndarray,
              ry: np.ndarray, ex: np.ndarray, ey: np.ndarray, fp: np.ndarray, off: np.ndarray,
              out: np.ndarray) -> None:  # pragma: no cover - compiled
    """``d`` (n, k) ray ranges; ``z`` (3 n,) normals: distance, count and ambient noise of sensor
    ``i`` at ``z[i]``, ``z[n + i]``, ``z[2 n + i]`` (unused when ideal). ``fp``: ideal (0/1),
    gain, count sigma, ambient, ambient sigma, max counts. ``off`` (n,) per-sensor count offsets
    or (0,) for none. ``out`` (3, n) int64: counts, ambient, truth counts."""
    has_off = off.shape[0] > 0
    ideal = fp[0] != 0.0
    gain = fp[1]
    count_sigma = fp[2]
    ambient = fp[3]
    ambient_sigma = fp[4]
    max_counts = fp[5]
    out_counts = out[0]
    out_ambient = out[1]
    out_truth = out[2]
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
            c = c * gain
            if has_off:
                c += off[i]
            c += count_sigma * z[n + i]
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
                    ang = wrap_angle_compiled(ang)
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
            r = max(e + table_sigma(e, tx, ty) * z[i], 0.0)
        if u[n + i] < p_glitch:
            r = min_range + (max_range - min_range) * u[2 * n + i]
            out_kind[i] = 4
        if r > max_range:
            r = np.nan
            out_kind[i] = 0
        out_range[i] = r


@numba.njit(cache=True, nogil=True)
def _second_leg(seg: np.ndarray, ox: float, oy: float, dx: float, dy: float, rr: float, m: int,
                max_range: float) -> float:  # pragma: no cover - compiled
    """Specular path of one ray: first hit (range ``rr`` on wall ``m``) -> second surface ->
    back to the origin; its length beyond the first hit (inf: none)."""
    if m < 0 or not math.isfinite(rr):
        return np.inf
    il = seg[4, m]
    nx = -seg[3, m] * il
    ny = seg[2, m] * il
    dot = dx * nx + dy * ny
    rx = dx - 2.0 * dot * nx
    ry = dy - 2.0 * dot * ny
    # Start a hair off the wall so the cast does not hit the wall it leaves.
    sx = ox + dx * rr + 1e-6 * rx
    sy = oy + dy * rr + 1e-6 * ry
    t, _m2, _inc = first_hit(seg, sx, sy, rx, ry, max_range)
    if t < np.inf:
        return t + math.hypot(sx + rx * t - ox, sy + ry * t - oy)
    return np.inf


@numba.njit(cache=True, nogil=True)
def sonar_ring_kernel(seg: np.ndarray, rays: np.ndarray, index: np.ndarray, start: int, n: int,
                      k: int, fp: np.ndarray, flags: np.ndarray, tx: np.ndarray, ty: np.ndarray,
                      cycle: np.ndarray, u: np.ndarray, z: np.ndarray, out: np.ndarray
                      ) -> None:  # pragma: no cover - compiled
    """The sonar ring from the simulator's cast, in one call: ``rays`` (6, R) rows origin x, y,
    direction x, y, range, incidence (:func:`core.raycast.cast_fan_arrays`), ``index`` (R,) wall
    hit; the ring's rays start at ``start``. Computes the specular second legs and the crosstalk
    geometry when needed and runs :func:`sonar_kernel`; readings nearer than ``min_reading``
    become 0 (the Koala's "too close"). Writes ``out`` (3, n): ranges, truth ranges, truth
    incidence. Few arguments and one output: each costs time at every call.

    ``fp``: max_range, min_reading, critical angle (rad), p_late, p_cross, p_glitch, glitch
    minimum, half aperture (rad). ``flags``: ideal, use_leg, use_cross. ``u``: the 3 n uniforms
    of :func:`sonar_kernel` followed, with crosstalk, by its n^2 ``u_cross``; ``z`` (n,)."""
    max_range = fp[0]
    ideal = flags[0] != 0
    use_leg = flags[1] != 0
    use_cross = flags[2] != 0
    crit = fp[2]
    d = np.empty((n, k))
    inc = np.empty((n, k))
    leg = np.empty((n, k)) if use_leg else np.empty((0, 0))
    for i in range(n):
        direct = False
        for j in range(k):
            r = start + i * k + j
            d[i, j] = rays[4, r]
            inc[i, j] = rays[5, r]
            if d[i, j] <= max_range and abs(inc[i, j]) <= crit:
                direct = True
        if not use_leg:
            continue
        # sonar_kernel reads a sensor's second legs only for a late echo (no direct echo and
        # u < p_late): cast the specular paths for those sensors only.
        late = not ideal and not direct and u[i] < fp[3]
        for j in range(k):
            r = start + i * k + j
            leg[i, j] = (_second_leg(seg, rays[0, r], rays[1, r], rays[2, r], rays[3, r],
                                     rays[4, r], index[r], max_range) if late else np.inf)
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
    kind = np.zeros(n, dtype=np.int8)
    sonar_kernel(d, inc, max_range, tx, ty, fp[2], fp[3], fp[4], fp[5], fp[6], ideal, use_leg,
                 leg, use_cross, hit_xy, sensor_xy, heading, fp[7], cycle, u[:3 * n], z,
                 u[3 * n:], out[0], out[1], out[2], kind)
    for i in range(n):
        if out[0, i] < fp[1]:                   # nan stays nan: no echo
            out[0, i] = 0.0


# ------------------------------------------------------------------------------------ camera
@numba.njit(cache=True, nogil=True)
def _distance_factor(d: float, dmax: float, base: float) -> float:
    """``g(d)`` of ``camera.distance_factor`` (seeds/000 eq. 6)."""
    return base ** ((d - dmax) / dmax)


@numba.njit(cache=True, nogil=True)
def camera_kernel(rows: np.ndarray, all_ids: np.ndarray, fp: np.ndarray, u: np.ndarray,
                  z: np.ndarray, out: np.ndarray) -> int:  # pragma: no cover - compiled
    """``rows`` (m, 5): per landmark in view its true id, range, bearing, viewing angle, a_max
    (:class:`sim.sensors.camera.CameraTruth`). ``fp``: p_perc, p_recog, d_min, d_max, distance
    base, dist, d_mid, far doubling, bearing sigma (rad). Variates of landmark ``q``: uniforms
    ``u[3q:3q+3]`` (miss, wrong id, which id), normals ``z[3q:3q+3]`` (near, far, bearing).
    Writes the perceived landmarks into ``out`` (m, 4): reported id, range, bearing, source row;
    returns their number."""
    p_perc = fp[0]
    p_recog = fp[1]
    dmin = fp[2]
    dmax = fp[3]
    base = fp[4]
    dist = fp[5]
    dmid = fp[6]
    fdoub = fp[7]
    bsig = fp[8]
    m = rows.shape[0]
    n_all = all_ids.shape[0]
    c = 0
    for q in range(m):
        true_id = np.int64(rows[q, 0])
        d = rows[q, 1]
        a = abs(rows[q, 3])
        amax = rows[q, 4]
        ang = 4.0 * a * a / (amax * amax)
        if d < dmin or d > dmax:
            continue                                   # out of sight: not perceived
        g = _distance_factor(d, dmax, base)
        if u[3 * q] < min(1.0, ang + p_perc * g):
            continue                                   # not perceived
        lid = true_id
        if n_all > 1 and u[3 * q + 1] < min(1.0, ang + p_recog * g):
            j = min(int(u[3 * q + 2] * (n_all - 1)), n_all - 2)
            # the j-th id of all_ids skipping the true one
            seen = 0
            for i in range(n_all):
                if all_ids[i] == true_id:
                    continue
                if seen == j:
                    lid = all_ids[i]
                    break
                seen += 1
        near = dist * d
        far = dist * dmid * 2.0 ** ((d - dmid) / fdoub)
        out[c, 0] = lid
        out[c, 1] = max(d + near * z[3 * q] + far * abs(z[3 * q + 1]), 0.0)
        bb = rows[q, 2] + bsig * z[3 * q + 2]
        out[c, 2] = wrap_angle_compiled(bb)
        out[c, 3] = q
        c += 1
    return c
