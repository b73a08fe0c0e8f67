"""Global relocalisation over the known map: a particle filter started when the pose EKF has lost
the robot (a kidnap, a long slip), run until its particles agree on one pose.

Monte Carlo localisation (Thrun, Burgard and Fox, *Probabilistic Robotics* (2005), table 8.2;
Dellaert et al., ICRA 1999) with the likelihood-field range model (ibid. §6.4) and systematic
resampling (ibid. table 4.4):

* **Start** (:meth:`Relocaliser.start`): ``share_local`` of the particles around the last estimate
  (normal, ``local_sigma_xy_m``, ``local_sigma_theta``), the rest uniform over the map's free
  cells; headings around a given heading with ``heading_sigma`` (the gyro-integrated heading,
  or the compass's; a kidnap that turns the robot is caught by the compass), a share uniform.
  Particles whose body overlaps a wall (the map's clearance < ``body_radius_m``) are redrawn.
* **Motion** (:meth:`Relocaliser.predict`): every particle moves by the odometry increment
  ``(ds, dtheta)`` with Gaussian noise (``sigma_ds``, ``sigma_dtheta`` from the EKF's own motion
  noise, inflated) -- the midpoint unicycle model of the EKF.
* **Weights** (log domain), each a robust mixture ``(1 - eps) N(.) + eps / span`` so one bad
  reading (a wrong landmark id, a sonar late echo) cannot wipe out the right particles:
  ranges -- the end point's distance to the nearest wall (likelihood field); landmarks -- range
  and bearing; heading -- the compass. A particle inside a wall gets ``-inf``.
* **Resampling** when the effective sample size falls below half the particles; when every
  particle has been ruled out (all in walls, or all infinitely unlikely), they are spread again
  as at the start.
* **Converged** (:attr:`Relocaliser.converged`) when the weighted standard deviations of x and y
  are below ``converged_sigma_xy_m`` and of the heading below ``converged_sigma_theta`` (a single
  tight cluster: a two-mode cloud has a large spread): the EKF restarts from the weighted mean and
  covariance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from koala_bridge.core.geometry import wrap_angle
from koala_bridge.estimation.map_model import MapModel
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class RelocaliserParams:
    """Particle count, start spread, noise and the convergence test (module docstring)."""

    particles: int = 2000
    share_local: float = 0.2
    local_sigma_xy_m: float = 0.5
    local_sigma_theta: float = math.radians(20.0)
    heading_sigma: float = math.radians(20.0)
    share_any_heading: float = 0.05
    body_radius_m: float = 0.19
    range_sigma_m: float = 0.05          # end point vs nearest wall (likelihood field)
    range_outlier: float = 0.1           # eps of the range mixture
    landmark_outlier: float = 0.1        # eps of the landmark mixture (wrong ids)
    compass_outlier: float = 0.1
    motion_inflation: float = 2.0        # x the EKF's motion sigmas
    min_sigma_xy_m: float = 0.01         # roughening: never narrower than this per step
    min_sigma_theta: float = math.radians(1.0)
    converged_sigma_xy_m: float = 0.08
    converged_sigma_theta: float = math.radians(8.0)
    min_updates: int = 20               # position weightings (ranges, landmarks) before convergence


class Relocaliser:
    """The particle filter (module docstring). Deterministic for a given ``seed``."""

    def __init__(self, map_model: MapModel, params: RelocaliserParams, seed: int = 0) -> None:
        self.map = map_model
        self.params = params
        self._rng = np.random.default_rng(seed)
        n = params.particles
        self.xy = np.zeros((2, n))
        self.th = np.zeros(n)
        self.logw = np.zeros(n)
        self.active = False
        self.updates = 0
        self.restarts = 0
        self._started: tuple[float, float, float, float | None] = (0.0, 0.0, 0.0, None)
        world = map_model.world
        self._free = np.array(world.free_cells(), dtype=float)  # (F, 2) col, row

    # -- lifecycle ---------------------------------------------------------------------------

    def start(self, x: float, y: float, theta: float, heading: float | None = None) -> None:
        """Spread the particles (module docstring): around ``(x, y, theta)`` and over the map,
        headings around ``heading`` (an absolute heading, the compass's), or uniform when it is
        None."""
        p, rng, n = self.params, self._rng, self.params.particles
        self._started = (x, y, theta, heading)
        n_local = int(round(p.share_local * n))
        self.xy[0, :n_local] = x + p.local_sigma_xy_m * rng.standard_normal(n_local)
        self.xy[1, :n_local] = y + p.local_sigma_xy_m * rng.standard_normal(n_local)
        self.th[:n_local] = theta + p.local_sigma_theta * rng.standard_normal(n_local)
        self._uniform(np.arange(n_local, n), heading)
        self._redraw_inside_walls(heading)
        self.logw[:] = 0.0
        self.active = True
        self.updates = 0

    def stop(self) -> None:
        self.active = False

    def _uniform(self, idx: NDArray[np.intp], heading: float | None) -> None:
        p, rng = self.params, self._rng
        cm = self.map.world.cell_m
        cells = self._free[rng.integers(0, len(self._free), idx.size)]
        self.xy[0, idx] = (cells[:, 0] + rng.random(idx.size)) * cm
        self.xy[1, idx] = (cells[:, 1] + rng.random(idx.size)) * cm
        th = (0.0 if heading is None else heading) + p.heading_sigma * rng.standard_normal(idx.size)
        anyh = rng.random(idx.size) < (1.0 if heading is None else p.share_any_heading)
        th[anyh] = rng.uniform(-math.pi, math.pi, int(anyh.sum()))
        self.th[idx] = th

    def _redraw_inside_walls(self, heading: float | None) -> None:
        for _ in range(20):
            bad = np.nonzero(~self._fits(self.xy[0], self.xy[1]))[0]
            if bad.size == 0:
                return
            self._uniform(bad, heading)

    def _fits(self, x: FloatArray, y: FloatArray) -> NDArray[np.bool_]:
        return self.map.inside(x, y) & (self.map.distance(x, y) >= self.params.body_radius_m)

    # -- motion ------------------------------------------------------------------------------

    def predict(self, ds: float, dtheta: float, sigma_ds: float, sigma_dtheta: float) -> None:
        """Move every particle by the odometry increment with noise (module docstring)."""
        if not self.active:
            return
        p, rng, n = self.params, self._rng, self.params.particles
        k = p.motion_inflation
        s_ds = max(k * sigma_ds, 0.0)
        s_th = max(k * sigma_dtheta, 0.0)
        d = ds + s_ds * rng.standard_normal(n)
        dth = dtheta + s_th * rng.standard_normal(n)
        thm = self.th + 0.5 * dth
        self.xy[0] += d * np.cos(thm)
        self.xy[1] += d * np.sin(thm)
        self.th += dth
        inside = self._fits(self.xy[0], self.xy[1])
        self.logw[~inside] = -np.inf
        if not inside.any():
            self.restarts += 1
            self.start(*self._started)

    # -- weights -----------------------------------------------------------------------------

    def _weigh(self, loglik: FloatArray, counts: bool = True) -> None:
        self.logw += loglik
        top = np.max(self.logw)
        if not np.isfinite(top):  # every particle ruled out: spread them again
            self.restarts += 1
            self.start(*self._started)
            return
        self.logw -= top
        self.updates += int(counts)
        w = np.exp(self.logw)
        w /= w.sum()
        if 1.0 / np.sum(w * w) < 0.5 * self.params.particles:
            self._resample(w)

    def on_ranges(self, body: FloatArray, ranges: FloatArray, sigmas: FloatArray) -> None:
        """Range readings of sensors at body poses ``body`` ``(S, 3)`` ``[x, y, yaw]``; only
        finite ranges are used (the likelihood field, module docstring)."""
        if not self.active:
            return
        ok = np.isfinite(ranges)
        if not ok.any():
            return
        b, r = body[ok], ranges[ok]
        sig = np.hypot(sigmas[ok], self.params.range_sigma_m)
        c, s = np.cos(self.th)[:, None], np.sin(self.th)[:, None]
        ox = self.xy[0][:, None] + c * b[:, 0] - s * b[:, 1]
        oy = self.xy[1][:, None] + s * b[:, 0] + c * b[:, 1]
        phi = self.th[:, None] + b[:, 2]
        ex, ey = ox + r * np.cos(phi), oy + r * np.sin(phi)
        dist = self.map.distance(ex, ey)
        eps = self.params.range_outlier
        gauss = np.exp(-0.5 * (dist / sig) ** 2)
        # the uniform part: a reading anywhere within 1 m of its true value (the span)
        self._weigh(np.sum(np.log((1 - eps) * gauss + eps * 0.05), axis=1))

    def on_landmark(self, lx: float, ly: float, range_m: float, bearing: float,
                    sigma_range: float, sigma_bearing: float) -> None:
        """A landmark's range (m) and bearing (rad), as the EKF takes it, mixed with an outlier
        term for a wrong id."""
        if not self.active:
            return
        dx, dy = lx - self.xy[0], ly - self.xy[1]
        er = (np.hypot(dx, dy) - range_m) / sigma_range
        eb = (wrap_angle_array(np.arctan2(dy, dx) - self.th - bearing)) / sigma_bearing
        eps = self.params.landmark_outlier
        self._weigh(np.log((1 - eps) * np.exp(-0.5 * (er * er + eb * eb)) + eps * 1e-3))

    def on_heading(self, heading: float, sigma: float) -> None:
        """An absolute heading (rad; the compass)."""
        if not self.active:
            return
        e = wrap_angle_array(self.th - heading) / sigma
        eps = self.params.compass_outlier
        self._weigh(np.log((1 - eps) * np.exp(-0.5 * e * e) + eps * 0.05), counts=False)

    def _resample(self, w: FloatArray) -> None:
        p, rng, n = self.params, self._rng, self.params.particles
        positions = (rng.random() + np.arange(n)) / n
        idx = np.minimum(np.searchsorted(np.cumsum(w), positions), n - 1)
        self.xy = self.xy[:, idx]
        self.th = self.th[idx]
        # roughening (Gordon et al. 1993): keeps the cloud from collapsing onto copies
        self.xy += p.min_sigma_xy_m * rng.standard_normal((2, n))
        self.th += p.min_sigma_theta * rng.standard_normal(n)
        self.logw = np.zeros(n)

    # -- read-out ----------------------------------------------------------------------------

    def estimate(self) -> tuple[FloatArray, FloatArray]:
        """Weighted mean ``[x, y, theta]`` (circular mean heading) and its ``(3, 3)``
        covariance."""
        w = np.exp(self.logw - np.max(self.logw))
        w /= w.sum()
        mx, my = float(w @ self.xy[0]), float(w @ self.xy[1])
        mth = math.atan2(float(w @ np.sin(self.th)), float(w @ np.cos(self.th)))
        d = np.vstack([self.xy[0] - mx, self.xy[1] - my, wrap_angle_array(self.th - mth)])
        cov = (d * w) @ d.T
        return np.array([mx, my, wrap_angle(mth)]), cov

    @property
    def converged(self) -> bool:
        """One tight cluster (module docstring)."""
        if not self.active or self.updates < self.params.min_updates:
            return False
        _, cov = self.estimate()
        p = self.params
        return bool(max(cov[0, 0], cov[1, 1]) <= p.converged_sigma_xy_m ** 2
                    and cov[2, 2] <= p.converged_sigma_theta ** 2)


def wrap_angle_array(a: FloatArray) -> FloatArray:
    """Angles wrapped to [-pi, pi)."""
    return (np.asarray(a) + math.pi) % (2 * math.pi) - math.pi
