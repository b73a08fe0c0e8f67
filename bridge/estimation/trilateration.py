"""Position from landmark observations (seeds/003 "Landmark localization").

Two estimators:

* :func:`trilaterate3` -- the lab's closed form from exactly three landmark ranges. It subtracts
  the circle equations pairwise (landmarks 1-2 and 2-3), which leaves two linear equations
  ``A x + B y = C`` and ``D x + E y = F`` solved by Cramer's rule. It carries no uncertainty and
  fails when the three landmarks are collinear (the two lines are parallel).
* :func:`wls_fix` -- weighted least squares (Gauss-Newton) from ``N >= 3`` ranges, optionally with
  bearings and a heading (compass) observation, returning the estimate's covariance
  ``(J^T W J)^-1`` and the weighted residual ``chi2`` for consistency checks and gating.

Frames (docs/architecture.md): world x east, y north, metres; bearings in radians CCW from the
robot's heading, as :class:`koala_bridge.sim.types.LandmarkObservation` carries them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from koala_bridge.core.geometry import wrap_angle
from koala_bridge.estimation.errors import DegenerateGeometryError, EstimationError
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

# Below this |sin| of the angle between (L2 - L1) and (L3 - L2), three landmarks count as collinear.
COLLINEAR_SIN = 1e-6
# Above this condition number of J^T W J the fix is undetermined (e.g. collinear landmarks).
MAX_CONDITION = 1e10


def trilaterate3(landmarks: ArrayLike, ranges: ArrayLike) -> FloatArray:
    """The robot's position from three landmarks and their ranges: seeds/003, "Landmark
    localization", equations A-F and the two quotients for x and y.

    Args:
        landmarks: ``(3, 2)`` landmark positions ``[x, y]``, metres, world frame.
        ranges: ``(3,)`` measured distances from the robot to each landmark, metres.

    Returns:
        ``(2,)`` position ``[x, y]``, metres. With noisy ranges this is the intersection of the two
        radical lines, not a least-squares estimate; use :func:`wls_fix` for that.

    Raises:
        DegenerateGeometryError: the landmarks are collinear (or two coincide), so the two linear
            equations are parallel and the position is not determined (mirror ambiguity).
    """
    c = np.asarray(landmarks, dtype=float)
    r = np.asarray(ranges, dtype=float)
    if c.shape != (3, 2) or r.shape != (3,):
        raise EstimationError(f"need landmarks (3, 2) and ranges (3,), got {c.shape} and {r.shape}")
    (x1, y1), (x2, y2), (x3, y3) = c
    r1, r2, r3 = r
    a = 2 * x2 - 2 * x1
    b = 2 * y2 - 2 * y1
    cc = r1**2 - r2**2 - x1**2 + x2**2 - y1**2 + y2**2
    d = 2 * x3 - 2 * x2
    e = 2 * y3 - 2 * y2
    f = r2**2 - r3**2 - x2**2 + x3**2 - y2**2 + y3**2
    den = e * a - b * d
    # den = 4 * cross(L2 - L1, L3 - L2); normalised it is the sine of the turn at L2.
    scale = math.hypot(a, b) * math.hypot(d, e)
    if scale == 0.0 or abs(den) < COLLINEAR_SIN * scale:
        raise DegenerateGeometryError(
            "trilateration needs three non-collinear landmarks; got "
            f"{c.tolist()} (collinear or coincident: the position is ambiguous)"
        )
    x = (cc * e - f * b) / den
    y = (cc * d - a * f) / (b * d - a * e)
    return np.array([x, y])


@dataclass(frozen=True)
class LandmarkFix:
    """A weighted least-squares fix.

    Attributes:
        x: ``(2,)`` ``[x, y]`` (ranges only) or ``(3,)`` ``[x, y, theta]`` (with bearings), SI.
        cov: covariance of ``x``, ``(n, n)``, SI units squared.
        chi2: weighted residual sum of squares at the solution; ``~ chi2(dof)`` when the model
            and the stated sigmas are right -- a large value flags a wrong landmark id.
        dof: number of observations minus number of unknowns.
        iterations: Gauss-Newton iterations used.
    """

    x: FloatArray
    cov: FloatArray
    chi2: float
    dof: int
    iterations: int


def _range_only_guess(lm: FloatArray, r: FloatArray) -> FloatArray:
    """Linear least squares on the circle equations minus the first one (the lab's closed form,
    generalised to ``N`` landmarks)."""
    a = 2.0 * (lm[1:] - lm[0])
    b = r[0] ** 2 - r[1:] ** 2 + np.sum(lm[1:] ** 2, axis=1) - np.sum(lm[0] ** 2)
    s = np.linalg.svd(a, compute_uv=False)
    if s.size < 2 or s[0] == 0.0 or s[1] < COLLINEAR_SIN * s[0]:
        raise DegenerateGeometryError(
            "a range-only fix needs at least three non-collinear landmarks; these are collinear "
            "(add a bearing and a heading, or another landmark)"
        )
    sol, *_ = np.linalg.lstsq(a, b, rcond=None)
    return np.asarray(sol, dtype=float)


def wls_fix(
    landmarks: ArrayLike,
    ranges: ArrayLike,
    sigma_range: ArrayLike,
    bearings: ArrayLike | None = None,
    sigma_bearing: ArrayLike | None = None,
    heading: float | None = None,
    sigma_heading: float | None = None,
    *,
    max_iterations: int = 20,
    tolerance_m: float = 1e-9,
) -> LandmarkFix:
    """Weighted least-squares position (and heading) from ``N >= 3`` landmark observations.

    Minimises ``sum((z_i - h_i(x))^2 / sigma_i^2)`` by Gauss-Newton, starting from the linear
    least-squares solution of the range equations. Range model ``r_i = |L_i - p|``; bearing model
    ``b_i = atan2(L_iy - y, L_ix - x) - theta`` (wrapped); heading model ``theta``.

    Args:
        landmarks: ``(N, 2)`` landmark positions, metres, world frame.
        ranges: ``(N,)`` measured ranges, metres.
        sigma_range: standard deviation of each range, metres (scalar or ``(N,)``); the camera's
            distance error grows with distance (seeds/000 eq. 10-12), so pass per-range values.
        bearings: ``(N,)`` measured bearings, rad CCW from the heading; with them the heading is
            estimated too and the result is ``[x, y, theta]``.
        sigma_bearing: standard deviation of each bearing, rad (scalar or ``(N,)``).
        heading: an independent heading observation (compass), rad; only used with bearings.
        sigma_heading: its standard deviation, rad.
        max_iterations: Gauss-Newton iteration cap.
        tolerance_m: stop when the step is shorter than this (metres / radians).

    Returns:
        A :class:`LandmarkFix` with the estimate, its covariance and the residual chi-square.

    Raises:
        DegenerateGeometryError: the observations do not determine the position (collinear
            landmarks without bearings, or a singular normal matrix).
        EstimationError: fewer than three observations or mismatched shapes.
    """
    lm = np.asarray(landmarks, dtype=float)
    r = np.asarray(ranges, dtype=float)
    n_obs = r.shape[0] if r.ndim == 1 else -1
    if lm.ndim != 2 or lm.shape[1] != 2 or lm.shape[0] != n_obs:
        raise EstimationError(f"need landmarks (N, 2) and ranges (N,), got {lm.shape}, {r.shape}")
    if n_obs < 3:
        raise EstimationError(f"a landmark fix needs N >= 3 observations, got {n_obs}")
    sr = np.broadcast_to(np.asarray(sigma_range, dtype=float), (n_obs,))
    use_bearing = bearings is not None
    if use_bearing:
        if sigma_bearing is None:
            raise EstimationError("bearings need sigma_bearing")
        b = np.asarray(bearings, dtype=float)
        if b.shape != (n_obs,):
            raise EstimationError(f"bearings must have shape ({n_obs},), got {b.shape}")
        sb = np.broadcast_to(np.asarray(sigma_bearing, dtype=float), (n_obs,))
    use_heading = use_bearing and heading is not None
    if use_heading and sigma_heading is None:
        raise EstimationError("heading needs sigma_heading")

    try:
        p0 = _range_only_guess(lm, r)
    except DegenerateGeometryError:
        if not use_heading:
            raise
        # Known heading: each range + bearing places the robot directly.
        ang = float(heading) + b  # type: ignore[arg-type]
        p0 = np.mean(lm - r[:, None] * np.column_stack([np.cos(ang), np.sin(ang)]), axis=0)
    if use_bearing:
        if use_heading:
            th0 = float(heading)  # type: ignore[arg-type]
        else:
            d0 = lm - p0
            a0 = np.arctan2(d0[:, 1], d0[:, 0]) - b
            th0 = math.atan2(float(np.mean(np.sin(a0))), float(np.mean(np.cos(a0))))
        x = np.array([p0[0], p0[1], th0])
    else:
        x = p0.copy()
    n_state = x.size

    sig = [sr]
    if use_bearing:
        sig.append(sb)
    if use_heading:
        sig.append(np.array([float(sigma_heading)]))  # type: ignore[arg-type]
    w = 1.0 / np.concatenate(sig) ** 2

    def residual_and_jacobian(xk: FloatArray) -> tuple[FloatArray, FloatArray]:
        d = lm - xk[:2]
        rho = np.hypot(d[:, 0], d[:, 1])
        if np.any(rho == 0.0):
            raise DegenerateGeometryError("the estimate coincides with a landmark")
        res = [r - rho]
        jr = np.zeros((n_obs, n_state))
        jr[:, 0] = -d[:, 0] / rho
        jr[:, 1] = -d[:, 1] / rho
        jac = [jr]
        if use_bearing:
            res.append(wrap_angle(b - (np.arctan2(d[:, 1], d[:, 0]) - xk[2])))
            jb = np.zeros((n_obs, n_state))
            jb[:, 0] = d[:, 1] / rho**2
            jb[:, 1] = -d[:, 0] / rho**2
            jb[:, 2] = -1.0
            jac.append(jb)
        if use_heading:
            res.append(wrap_angle(np.array([float(heading) - xk[2]])))  # type: ignore[arg-type]
            jh = np.zeros((1, n_state))
            jh[0, 2] = 1.0
            jac.append(jh)
        return np.concatenate(res), np.vstack(jac)

    iterations = 0
    for iterations in range(1, max_iterations + 1):  # noqa: B007 -- reported in the result
        res, jac = residual_and_jacobian(x)
        normal = jac.T @ (w[:, None] * jac)
        if np.linalg.cond(normal) > MAX_CONDITION:
            raise DegenerateGeometryError("the observations do not determine the fix")
        step = np.linalg.solve(normal, jac.T @ (w * res))
        x = x + step
        if use_bearing:
            x[2] = float(wrap_angle(x[2]))
        if float(np.max(np.abs(step))) < tolerance_m:
            break
    res, jac = residual_and_jacobian(x)
    normal = jac.T @ (w[:, None] * jac)
    if np.linalg.cond(normal) > MAX_CONDITION:
        raise DegenerateGeometryError("the observations do not determine the fix")
    cov = np.linalg.inv(normal)
    cov = 0.5 * (cov + cov.T)
    return LandmarkFix(
        x=x,
        cov=cov,
        chi2=float(np.sum(w * res**2)),
        dof=int(res.size - n_state),
        iterations=iterations,
    )
