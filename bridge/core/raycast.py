"""Vectorised 2-D ray casting and point-to-segment distances against the world's walls.

The hot path of the simulator: every range sensor's rays of one step (IR cones, sonar cones,
camera line-of-sight checks) go through one call of :func:`cast_rays`, evaluated as an
``(R rays) x (M segments)`` array expression in numpy.

Geometry (world frame, metres): a ray is ``o + t d`` with ``|d| = 1``, ``t >= 0``; a wall segment
is ``a + u e`` with ``e = b - a``, ``0 <= u <= 1``. Solving ``o + t d = a + u e`` with the 2-D cross
product ``a x b = a_x b_y - a_y b_x`` gives (Cramer's rule)::

    den = d x e,   t = ((a - o) x e) / den,   u = ((a - o) x d) / den

The incidence angle is the angle between the ray and the surface normal ``n`` of the segment it
hits: ``cos(incidence) = |d . n| = |d x e| / |e| = |den| / |e|`` (0 = head-on, pi/2 = grazing).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
from koala_bridge.core.geometry import TAU


@numba.njit(cache=True, nogil=True)
def wrap_angle_compiled(a: float) -> float:  # pragma: no cover - compiled
    """:func:`koala_bridge.core.geometry.wrap_angle` for the compiled kernels (the camera's
    visibility test, the sonar and camera error models): the same formula, to (-pi, pi] (numba
    has ``np.fmod``, not ``math.fmod``; both are C's exact fmod). tests/unit/test_geometry.py
    checks the two agree bit for bit."""
    w = np.fmod(a, TAU)
    if w > math.pi:
        w -= TAU
    elif w <= -math.pi:
        w += TAU
    return w


@dataclass(frozen=True)
class SegmentSet:
    """Wall segments prepared for ray casting: ``(M, 4)`` ``[x0, y0, x1, y1]`` plus cached terms.

    Build once per world with :meth:`from_segments`; ``merge=True`` joins collinear, touching
    axis-aligned segments (a grid wall of many cell edges becomes one segment), which shrinks
    ``M`` several-fold without changing any hit point.
    """

    segments: np.ndarray    # (M, 4)
    ax: np.ndarray          # (1, M) start point
    ay: np.ndarray
    ex: np.ndarray          # (1, M) direction b - a
    ey: np.ndarray
    inv_len: np.ndarray     # (M,) 1 / |e|
    inv_len2: np.ndarray    # (M,) 1 / |e|^2
    packed: np.ndarray      # (5, M) C-contiguous rows ax, ay, ex, ey, inv_len (compiled kernels)

    @classmethod
    def from_segments(cls, segments: np.ndarray, merge: bool = True) -> SegmentSet:
        segs = np.asarray(segments, dtype=float).reshape(-1, 4)
        if merge:
            segs = merge_collinear(segs)
        ex = segs[:, 2] - segs[:, 0]
        ey = segs[:, 3] - segs[:, 1]
        len2 = ex * ex + ey * ey
        if np.any(len2 <= 0):
            raise ValueError("wall segments must have non-zero length")
        return cls(
            segments=segs,
            ax=segs[None, :, 0].copy(),
            ay=segs[None, :, 1].copy(),
            ex=ex[None, :],
            ey=ey[None, :],
            inv_len=1.0 / np.sqrt(len2),
            inv_len2=1.0 / len2,
            packed=np.ascontiguousarray(
                np.stack([segs[:, 0], segs[:, 1], ex, ey, 1.0 / np.sqrt(len2)])
            ).reshape(5, -1),
        )

    def __len__(self) -> int:
        return int(self.segments.shape[0])

    def with_circles(self, circles: np.ndarray, sides: int) -> SegmentSet:
        """These segments followed by the :func:`circle_polygons` of ``circles`` ``(K, 3)``
        (``x, y, r``), the derived arrays appended directly rather than rebuilt for every
        segment by :meth:`from_segments` (once per robot and step in a fleet). Indices below
        ``len(self)`` keep naming the same segments."""
        c = np.asarray(circles, dtype=float).reshape(-1, 3)
        if c.shape[0] == 0:
            return self
        polygons = circle_polygons(c, sides)
        ax, ay, bx, by = (np.ascontiguousarray(polygons[:, i]) for i in range(4))
        ex = bx - ax
        ey = by - ay
        len2 = ex * ex + ey * ey
        inv_len = 1.0 / np.sqrt(len2)
        return SegmentSet(
            segments=np.concatenate([self.segments, np.column_stack([ax, ay, bx, by])]),
            ax=np.concatenate([self.ax, ax[None, :]], axis=1),
            ay=np.concatenate([self.ay, ay[None, :]], axis=1),
            ex=np.concatenate([self.ex, ex[None, :]], axis=1),
            ey=np.concatenate([self.ey, ey[None, :]], axis=1),
            inv_len=np.concatenate([self.inv_len, inv_len]),
            inv_len2=np.concatenate([self.inv_len2, 1.0 / len2]),
            packed=np.concatenate([self.packed, np.stack([ax, ay, ex, ey, inv_len])], axis=1),
        )


def circle_polygons(circles: np.ndarray, sides: int) -> np.ndarray:
    """``(K * sides, 4)`` segments: for each row ``x, y, r`` of ``circles`` ``(K, 3)``, the
    regular polygon of ``sides`` sides circumscribed about the circle (apothem ``r``: its edges
    touch the circle at their midpoints, its vertices lie at ``r / cos(pi / sides)``), with a
    vertex at angle 0."""
    c = np.asarray(circles, dtype=float).reshape(-1, 3)
    a = np.arange(sides + 1) * (2.0 * math.pi / sides)
    rv = c[:, 2:3] * (1.0 / math.cos(math.pi / sides))     # (K, 1) vertex radius
    vx = c[:, 0:1] + rv * np.cos(a)                         # (K, sides + 1)
    vy = c[:, 1:2] + rv * np.sin(a)
    return np.stack([vx[:, :-1], vy[:, :-1], vx[:, 1:], vy[:, 1:]], axis=-1).reshape(-1, 4)


def merge_collinear(segments: np.ndarray) -> np.ndarray:
    """Join horizontal and vertical segments that lie on one line and touch or overlap.

    Other segments are kept as they are. The result covers exactly the same points.
    """
    segs = np.asarray(segments, dtype=float).reshape(-1, 4)
    out: list[tuple[float, float, float, float]] = []
    horiz: dict[float, list[tuple[float, float]]] = {}
    vert: dict[float, list[tuple[float, float]]] = {}
    for x0, y0, x1, y1 in segs.tolist():
        if y0 == y1 and x0 != x1:
            horiz.setdefault(y0, []).append((min(x0, x1), max(x0, x1)))
        elif x0 == x1 and y0 != y1:
            vert.setdefault(x0, []).append((min(y0, y1), max(y0, y1)))
        else:
            out.append((x0, y0, x1, y1))
    for y, spans in sorted(horiz.items()):
        for lo, hi in _merge_spans(spans):
            out.append((lo, y, hi, y))
    for x, spans in sorted(vert.items()):
        for lo, hi in _merge_spans(spans):
            out.append((x, lo, x, hi))
    return np.array(out, dtype=float).reshape(-1, 4)


def _merge_spans(spans: list[tuple[float, float]]) -> list[tuple[float, float]]:
    spans = sorted(spans)
    merged = [spans[0]]
    for lo, hi in spans[1:]:
        plo, phi = merged[-1]
        if lo <= phi + 1e-12:
            merged[-1] = (plo, max(phi, hi))
        else:
            merged.append((lo, hi))
    return merged


@dataclass(frozen=True)
class RayHits:
    """Result of :func:`cast_rays` for ``R`` rays."""

    range: np.ndarray       # (R,) distance to the first hit, m; inf when nothing within max range
    index: np.ndarray       # (R,) int, index into SegmentSet.segments of the hit; -1 when none
    incidence: np.ndarray   # (R,) rad, angle between the ray and the hit surface normal; nan: none


def cast_rays_numpy(
    walls: SegmentSet,
    ox: np.ndarray,
    oy: np.ndarray,
    dx: np.ndarray,
    dy: np.ndarray,
    max_range: float | np.ndarray = np.inf,
) -> RayHits:
    """First intersection of each ray with the walls: the numpy reference of :func:`cast_rays`.

    Args:
        walls: prepared wall segments.
        ox, oy: ``(R,)`` ray origins, world frame, m.
        dx, dy: ``(R,)`` unit ray directions.
        max_range: scalar or ``(R,)``; hits farther than this are ignored.

    Returns:
        :class:`RayHits` with ``(R,)`` arrays. A ray starting exactly on a wall sees it at range 0.
    """
    r = ox.shape[0]
    if len(walls) == 0 or r == 0:
        return RayHits(np.full(r, np.inf), np.full(r, -1, dtype=np.intp), np.full(r, np.nan))
    ox_ = ox[:, None]
    oy_ = oy[:, None]
    dx_ = dx[:, None]
    dy_ = dy[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        den = dx_ * walls.ey - dy_ * walls.ex    # d x e, (R, M)
        wx = walls.ax - ox_
        wy = walls.ay - oy_
        inv = 1.0 / den                          # parallel rays: +-inf, then t, u are inf/nan
        t = (wx * walls.ey - wy * walls.ex) * inv
        u = (wx * dy_ - wy * dx_) * inv
        # Misses: behind the origin, off either end of the segment, or parallel (nan).
        t[~((t >= 0.0) & (u >= 0.0) & (u <= 1.0))] = np.inf
    idx = t.argmin(axis=1)
    rows = np.arange(r)
    rng = t[rows, idx]
    hit = (rng <= max_range) & (rng < np.inf)
    rng[~hit] = np.inf
    cos_inc = np.minimum(np.abs(den[rows, idx]) * walls.inv_len[idx], 1.0)
    incidence = np.where(hit, np.arccos(cos_inc), np.nan)
    index = np.where(hit, idx, -1)
    return RayHits(rng, index, incidence)


@numba.njit(cache=True, nogil=True)
def first_hit(
    seg: np.ndarray, ox: float, oy: float, dx: float, dy: float, max_range: float
) -> tuple[float, int, float]:  # pragma: no cover - compiled; tested through cast_rays
    """The equations of :func:`cast_rays_numpy` for one ray, skipping farther segments early
    (compiled; callable from other compiled kernels, e.g. the sonar's specular second leg).
    ``seg`` is :attr:`SegmentSet.packed`. Returns (range, wall index, incidence); (inf, -1, nan)
    when nothing lies within ``max_range``."""
    best = np.inf
    best_m = -1
    best_den = 0.0
    for m in range(seg.shape[1]):
        ex = seg[2, m]
        ey = seg[3, m]
        den = dx * ey - dy * ex
        if den == 0.0:
            continue
        wx = seg[0, m] - ox
        wy = seg[1, m] - oy
        t = (wx * ey - wy * ex) / den
        if not (t >= 0.0 and t < best):
            continue
        u = (wx * dy - wy * dx) / den
        if not (u >= 0.0 and u <= 1.0):
            continue
        best = t
        best_m = m
        best_den = den
    if best_m >= 0 and best <= max_range:
        return best, best_m, np.arccos(min(abs(best_den) * seg[4, best_m], 1.0))
    return np.inf, -1, np.nan


@numba.njit(cache=True, nogil=True)
def _cast_kernel(
    seg: np.ndarray, rays: np.ndarray, max_range: np.ndarray, out: np.ndarray, out_index: np.ndarray
) -> None:  # pragma: no cover - compiled
    # rays: (4, R) ox, oy, dx, dy. out: (2, R) range, incidence.
    for r in range(rays.shape[1]):
        t, m, inc = first_hit(seg, rays[0, r], rays[1, r], rays[2, r], rays[3, r], max_range[r])
        out[0, r] = t
        out[1, r] = inc
        out_index[r] = m


@numba.njit(cache=True, nogil=True)
def _fan_kernel(
    seg: np.ndarray, body: np.ndarray, max_range: np.ndarray, x: float, y: float, theta: float,
    out: np.ndarray, out_index: np.ndarray,
) -> None:  # pragma: no cover - compiled
    # body: (3, R) body-frame origin x, y and angle. out: (6, R) ox, oy, dx, dy, range, incidence.
    c = np.cos(theta)
    s = np.sin(theta)
    for r in range(body.shape[1]):
        bx = body[0, r]
        by = body[1, r]
        ox = x + c * bx - s * by
        oy = y + s * bx + c * by
        a = body[2, r] + theta
        dx = np.cos(a)
        dy = np.sin(a)
        t, m, inc = first_hit(seg, ox, oy, dx, dy, max_range[r])
        out[0, r] = ox
        out[1, r] = oy
        out[2, r] = dx
        out[3, r] = dy
        out[4, r] = t
        out[5, r] = inc
        out_index[r] = m


def cast_rays(
    walls: SegmentSet,
    ox: np.ndarray,
    oy: np.ndarray,
    dx: np.ndarray,
    dy: np.ndarray,
    max_range: float | np.ndarray = np.inf,
) -> RayHits:
    """First intersection of each ray with the walls (compiled with numba; the numpy
    expression of the same equations is :func:`cast_rays_numpy`, the test reference).

    Args:
        walls: prepared wall segments.
        ox, oy: ``(R,)`` ray origins, world frame, m.
        dx, dy: ``(R,)`` unit ray directions.
        max_range: scalar or ``(R,)``; hits farther than this are ignored.

    Returns:
        :class:`RayHits` with ``(R,)`` arrays: range (inf: no hit), wall index (-1: none) and
        incidence angle (nan: none). A ray starting exactly on a wall sees it at range 0.
    """
    r = ox.shape[0]
    rays = np.empty((4, r))
    rays[0] = ox
    rays[1] = oy
    rays[2] = dx
    rays[3] = dy
    out = np.empty((2, r))
    index = np.empty(r, dtype=np.intp)
    mr = np.empty(r)
    mr[:] = max_range
    _cast_kernel(walls.packed, rays, mr, out, index)
    return RayHits(out[0], index, out[1])


def cast_fan_arrays(
    walls: SegmentSet, body: np.ndarray, max_range: np.ndarray, x: float, y: float, theta: float
) -> tuple[np.ndarray, np.ndarray]:
    """Cast rays given in the body frame from a robot at ``(x, y, theta)``: the simulator's one
    compiled call per step for every range sensor due.

    Args:
        body: ``(3, R)`` C-contiguous: ray origin x, y (body frame FLU, m) and angle (rad).
        max_range: ``(R,)``.

    Returns:
        ``(6, R)`` rows: world-frame origin x, y, unit direction x, y, range (inf: no hit within
        max range), incidence (nan: none); and the ``(R,)`` wall index (-1: none).
    """
    r = body.shape[1]
    out = np.empty((6, r))
    index = np.empty(r, dtype=np.intp)
    _fan_kernel(walls.packed, body, max_range, x, y, theta, out, index)
    return out, index


def cast_fan(
    walls: SegmentSet, body: np.ndarray, max_range: np.ndarray, x: float, y: float, theta: float
) -> tuple[RayHits, np.ndarray]:
    """:func:`cast_fan_arrays` as :class:`RayHits` and the world-frame rays ``(4, R)``: origin
    x, y and unit direction x, y."""
    out, index = cast_fan_arrays(walls, body, max_range, x, y, theta)
    return RayHits(out[4], index, out[5]), out[:4]


@numba.njit(cache=True, nogil=True)
def _distances_kernel(seg: np.ndarray, px: float, py: float, out: np.ndarray) -> None:
    # pragma: no cover - compiled; the equations of point_segment_distances
    for m in range(seg.shape[1]):
        wx = px - seg[0, m]
        wy = py - seg[1, m]
        ex = seg[2, m]
        ey = seg[3, m]
        il = seg[4, m]
        u = (wx * ex + wy * ey) * il * il
        u = min(max(u, 0.0), 1.0)
        cx = wx - u * ex
        cy = wy - u * ey
        out[m] = np.sqrt(cx * cx + cy * cy)


@numba.njit(cache=True, nogil=True)
def sweep_circle(
    seg: np.ndarray,
    x0: float, y0: float, c: float, s: float, dx_b: float, dy_b: float, radius: float,
) -> tuple[float, bool]:  # pragma: no cover - compiled; tested through sim.robot.step
    """How far a circle of ``radius`` can move from ``(x0, y0)`` by the body-frame displacement
    ``(dx_b, dy_b)`` (``c, s``: cos and sin of the heading) before it penetrates a wall.

    The rule of :mod:`sim.robot`: a pose is blocked when some wall is nearer than ``radius`` *and*
    nearer than it was at the last safe pose (moving away from a touched wall is allowed). The
    move is split into sub-steps no longer than ``radius / 2`` (no tunnelling), and the first
    blocked sub-step is bisected to 0.1 um. Returns ``(fraction done, stopped by a wall)``.
    """
    wx = c * dx_b - s * dy_b
    wy = s * dx_b + c * dy_b
    length = np.sqrt(wx * wx + wy * wy)
    m = seg.shape[1]
    d_old = np.empty(m)
    d_new = np.empty(m)
    _distances_kernel(seg, x0, y0, d_old)
    n_sub = max(1, int(np.ceil(length / (0.5 * radius))))
    done = 0.0
    for i in range(1, n_sub + 1):
        frac = i / n_sub
        _distances_kernel(seg, x0 + frac * wx, y0 + frac * wy, d_new)
        blocked = False
        for j in range(m):
            if d_new[j] < radius and d_new[j] < d_old[j]:
                blocked = True
                break
        if not blocked:
            done = frac
            d_old[:] = d_new
            continue
        lo = done
        hi = frac
        while (hi - lo) * length > 1e-7:
            mid = 0.5 * (lo + hi)
            _distances_kernel(seg, x0 + mid * wx, y0 + mid * wy, d_new)
            blocked = False
            for j in range(m):
                if d_new[j] < radius and d_new[j] < d_old[j]:
                    blocked = True
                    break
            if blocked:
                hi = mid
            else:
                lo = mid
        return lo, True
    return done, False


def point_segment_distances(walls: SegmentSet, px: float, py: float) -> np.ndarray:
    """``(M,)`` Euclidean distances from the point ``(px, py)`` to every wall segment, m:
    ``|w - clip((w . e) / |e|^2, 0, 1) e|`` with ``w = p - a`` (compiled)."""
    out = np.empty(len(walls))
    _distances_kernel(walls.packed, float(px), float(py), out)
    return out


def first_hit_before(
    walls: SegmentSet,
    ox: np.ndarray,
    oy: np.ndarray,
    tx: np.ndarray,
    ty: np.ndarray,
    tolerance_m: float = 1e-9,
) -> np.ndarray:
    """``(R,)`` bool: True where a wall lies strictly between each origin and its target point.

    The line-of-sight test of the camera: ``False`` means the target is visible.
    """
    vx = tx - ox
    vy = ty - oy
    dist = np.hypot(vx, vy)
    safe = np.where(dist > 0, dist, 1.0)
    hits = cast_rays(walls, ox, oy, vx / safe, vy / safe,
                     max_range=np.maximum(dist - tolerance_m, 0))
    return (hits.index >= 0) & (dist > 0)
