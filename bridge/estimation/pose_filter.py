"""Continuous pose tracking: an extended Kalman filter over ``[x, y, theta, gyro_bias]``.

Why an EKF (docs/localisation.md has the long form): once the grid filter or a landmark fix has
said where the robot is, the pose belief is unimodal; the motion and measurement models (unicycle,
range/bearing, heading) are smooth and only mildly non-linear at the centimetre/degree
uncertainties involved; and an EKF step costs tens of microseconds, so it keeps up with 200 Hz
odometry in pure numpy. Global ambiguity (no known start, a kidnapped robot) is the job of the
histogram filter (:mod:`estimation.grid_localisation`) and :func:`wls_fix`, whose output
re-initialises this filter.

State ``x = [x, y, theta, b]``: position (m, world frame), heading (rad CCW from east, wrapped to
(-pi, pi]) and the gyro's yaw-rate bias ``b`` (rad/s; a real MEMS gyro's bias is of order
0.02 rad/s, tests/data/real/PROVENANCE.md, "mpu6050_gyro_static").

Motion (prediction) -- "gyrodometry": the distance travelled ``ds`` comes from the wheel
encoders; the heading change comes from the gyro, ``dtheta = integral(omega) - b * T``, whenever
gyro samples arrive, otherwise from the encoders, ``(d_right - d_left) / wheel_base``. The
midpoint unicycle model propagates the pose (Thrun et al., *Probabilistic Robotics*, 2005,
§5.4 odometry motion model, linearised as in §7.4 table 7.3)::

    theta_m = theta + dtheta / 2
    x' = x + ds cos(theta_m);  y' = y + ds sin(theta_m);  theta' = theta + dtheta;  b' = b

Measurements: compass heading ``theta``; landmark range ``|L - p|`` and bearing
``atan2(L - p) - theta``; a position fix ``[x, y]`` (from :func:`wls_fix`). Each is gated by its
normalised innovation squared (NIS) against a chi-square quantile, so a misrecognised landmark
(seeds/000 eq. 9) or a compass near a radiator is rejected and counted, not fused.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from koala_bridge.core.distributions import chi2_ppf
from koala_bridge.core.geometry import wrap_angle
from koala_bridge.estimation.errors import EstimationError
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

STATE_DIM = 4  # x, y, theta, gyro bias


# --------------------------------------------------------------------------- pure functions


def odometry_increment(
    d_left_m: float, d_right_m: float, wheel_base_m: float
) -> tuple[float, float]:
    """Distance travelled by the axle centre and heading change from the two wheels' distances.

    Returns ``(ds, dtheta)``: metres, rad CCW.
    """
    return 0.5 * (d_left_m + d_right_m), (d_right_m - d_left_m) / wheel_base_m


def predict(
    x: FloatArray,
    P: FloatArray,
    ds: float,
    dtheta: float,
    cov_u: FloatArray,
    bias_time: float = 0.0,
    bias_var: float = 0.0,
) -> tuple[FloatArray, FloatArray]:
    """EKF prediction with the midpoint unicycle model (module docstring).

    Args:
        x: ``(4,)`` state ``[x, y, theta, b]``.
        P: ``(4, 4)`` covariance.
        ds: distance travelled, m.
        dtheta: measured heading change, rad (gyro integral, or encoder difference / wheel base).
        cov_u: ``(2, 2)`` covariance of ``(ds, dtheta)``.
        bias_time: seconds over which ``dtheta`` integrated the gyro (the bias is subtracted for
            that long); 0 when ``dtheta`` came from the encoders.
        bias_var: variance added to the bias over this step, (rad/s)^2 (bias random walk).

    Returns:
        ``(x', P')``.
    """
    th = x[2]
    dth = dtheta - x[3] * bias_time
    thm = th + 0.5 * dth
    c, s = math.cos(thm), math.sin(thm)
    xn = np.array([x[0] + ds * c, x[1] + ds * s, wrap_angle(th + dth), x[3]])
    F = np.eye(STATE_DIM)
    F[0, 2] = -ds * s
    F[1, 2] = ds * c
    F[0, 3] = 0.5 * ds * s * bias_time
    F[1, 3] = -0.5 * ds * c * bias_time
    F[2, 3] = -bias_time
    G = np.array([[c, -0.5 * ds * s], [s, 0.5 * ds * c], [0.0, 1.0], [0.0, 0.0]])
    Pn = F @ P @ F.T + G @ cov_u @ G.T
    Pn[3, 3] += bias_var
    return xn, 0.5 * (Pn + Pn.T)


def innovation(
    x: FloatArray,
    P: FloatArray,
    z: ArrayLike,
    R: ArrayLike,
    H: FloatArray,
    hx: ArrayLike | None = None,
    angle_rows: tuple[int, ...] = (),
) -> tuple[FloatArray, FloatArray]:
    """Innovation ``y = z - h(x)`` (angles wrapped) and its covariance ``S = H P H^T + R``."""
    za = np.atleast_1d(np.asarray(z, dtype=float))
    h = H @ x if hx is None else np.atleast_1d(np.asarray(hx, dtype=float))
    y = za - h
    for i in angle_rows:
        y[i] = wrap_angle(y[i])
    S = H @ P @ H.T + np.atleast_2d(np.asarray(R, dtype=float))
    return y, S


def update(
    x: FloatArray,
    P: FloatArray,
    z: ArrayLike,
    R: ArrayLike,
    H: FloatArray,
    hx: ArrayLike | None = None,
    angle_rows: tuple[int, ...] = (),
) -> tuple[FloatArray, FloatArray]:
    """EKF measurement update (Joseph form, so ``P`` stays symmetric positive semi-definite).

    Args:
        x: ``(n,)`` state; P: ``(n, n)`` covariance.
        z: ``(m,)`` measurement; R: ``(m, m)`` its covariance.
        H: ``(m, n)`` Jacobian of the measurement model at ``x``.
        hx: ``(m,)`` predicted measurement ``h(x)``; ``H @ x`` when omitted (linear model).
        angle_rows: indices of ``z`` that are angles (their innovation is wrapped).

    Returns:
        ``(x', P')``; the heading (index 2) of a pose state is wrapped.
    """
    y, S = innovation(x, P, z, R, H, hx, angle_rows)
    return _correct(x, P, y, S, np.atleast_2d(np.asarray(R, dtype=float)), H)


def _correct(
    x: FloatArray, P: FloatArray, y: FloatArray, S: FloatArray, R: FloatArray, H: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Kalman gain and Joseph-form correction from an innovation ``y`` with covariance ``S``."""
    K = np.linalg.solve(S, H @ P).T  # = P H^T S^-1 (S and P symmetric)
    xn = x + K @ y
    if xn.size > 2:
        xn[2] = wrap_angle(xn[2])
    ikh = np.eye(x.size) - K @ H
    Pn = ikh @ P @ ikh.T + K @ R @ K.T
    return xn, 0.5 * (Pn + Pn.T)


def landmark_model(x: FloatArray, landmark_xy: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Predicted ``[range, bearing]`` of a landmark and its ``(2, 4)`` Jacobian."""
    lx, ly = np.asarray(landmark_xy, dtype=float)
    dx, dy = lx - x[0], ly - x[1]
    q = dx * dx + dy * dy
    if q == 0.0:
        raise EstimationError("the estimate coincides with the landmark")
    r = math.sqrt(q)
    hx = np.array([r, wrap_angle(math.atan2(dy, dx) - x[2])])
    H = np.array([[-dx / r, -dy / r, 0.0, 0.0], [dy / q, -dx / q, -1.0, 0.0]])
    return hx, H


HEADING_H = np.array([[0.0, 0.0, 1.0, 0.0]])
POSITION_H = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]])


def heading_from_field(
    field_body_uT: ArrayLike,
    north_rad: float,
    hard_iron_uT: ArrayLike | None = None,
) -> float:
    """Robot heading from a magnetometer on a level robot.

    The horizontal Earth field points at ``north_rad`` (CCW from east, ``World.earth_field``);
    seen from the body frame (FLU) it points at ``north_rad - theta``, hence
    ``theta = north_rad - atan2(m_y, m_x)``. ``hard_iron_uT`` (body frame) is subtracted first.

    Args:
        field_body_uT: ``(3,)`` field in the body frame, x forward, y left, z up, microtesla.
        north_rad: direction of magnetic north in the world frame, rad.
        hard_iron_uT: optional ``(3,)`` offset to remove.

    Returns:
        Heading, rad, wrapped to (-pi, pi].
    """
    m = np.asarray(field_body_uT, dtype=float)
    if hard_iron_uT is not None:
        m = m - np.asarray(hard_iron_uT, dtype=float)
    return wrap_angle(north_rad - math.atan2(m[1], m[0]))


# --------------------------------------------------------------------------- stateful wrapper


@dataclass(frozen=True)
class PoseTrackerParams:
    """Noise model of the pose tracker (docs/localisation.md lists these as a TOML table).

    Attributes:
        wheel_base_m: distance between the wheels' contact points, m.
        ticks_per_metre: encoder counts per metre of wheel travel.
        odo_distance_var_per_m: variance of the encoder distance per metre travelled, m^2/m.
        odo_heading_var_per_m: variance of the encoder heading change per metre, rad^2/m.
        odo_heading_var_per_rad: variance of the encoder heading change per radian, rad^2/rad.
        gyroscope_noise_density: gyro white noise, rad/s/sqrt(Hz) (Kalibr's name; the integrated
            heading has variance ``density^2 * T``).
        gyroscope_random_walk: gyro bias random walk, rad/s^2/sqrt(Hz) (Kalibr's name).
        gyro_bias_sigma0: prior standard deviation of the gyro bias, rad/s.
        gyro_timeout_s: after this long without a gyro sample, heading comes from the encoders.
        compass_sigma_rad: standard deviation of a compass heading, rad.
        gate_probability: NIS gate; a measurement beyond this chi-square quantile is rejected.
        process_noise_xy: random walk of x and y per metre the wheels travel, m^2/m
            (unmodelled effects; a wheel's travel is ``|ds| + wheel_base / 2 * |dtheta|``).
        process_noise_theta: random walk of the heading per metre the wheels travel, rad^2/m.
    """

    wheel_base_m: float
    ticks_per_metre: float
    odo_distance_var_per_m: float = 1e-4
    odo_heading_var_per_m: float = 4e-3
    odo_heading_var_per_rad: float = 2e-3
    gyroscope_noise_density: float = 2e-3
    gyroscope_random_walk: float = 1e-4
    gyro_bias_sigma0: float = 0.05
    gyro_timeout_s: float = 0.5
    compass_sigma_rad: float = math.radians(5.0)
    gate_probability: float = 0.999
    process_noise_xy: float = 0.0
    process_noise_theta: float = 0.0

    def __post_init__(self) -> None:
        if not (self.wheel_base_m > 0 and self.ticks_per_metre > 0):
            raise EstimationError("wheel_base_m and ticks_per_metre must be > 0")
        if not 0.0 < self.gate_probability < 1.0:
            raise EstimationError("gate_probability must be in (0, 1)")


@dataclass
class GateCounters:
    """Accepted and rejected (gated-out) measurements per kind."""

    accepted: dict[str, int] = field(default_factory=dict)
    rejected: dict[str, int] = field(default_factory=dict)

    def count(self, kind: str, ok: bool) -> None:
        d = self.accepted if ok else self.rejected
        d[kind] = d.get(kind, 0) + 1


class PoseTracker:
    """EKF pose tracker fed with decoded bus data (thin wrapper over the pure functions).

    Feed it in arrival order: :meth:`on_gyro` and :meth:`on_odometry` predict, the ``on_*``
    measurement methods correct and return whether the measurement passed the gate.
    """

    def __init__(self, params: PoseTrackerParams) -> None:
        self.params = params
        self.x = np.zeros(STATE_DIM)
        self.P = np.diag([1e6, 1e6, math.pi**2, params.gyro_bias_sigma0**2])
        self.t = 0.0
        self.counters = GateCounters()
        self._gates = {m: chi2_ppf(params.gate_probability, m) for m in (1, 2)}
        self._ticks: tuple[int, int] | None = None
        self._gyro_t: float | None = None
        self._gyro_angle = 0.0
        self._gyro_time = 0.0
        self._gyro_last_seen = -math.inf
        self.last_increment = (0.0, 0.0, 0.0, 0.0)
        self.odometry_increments = 0
        self.last_nis: dict[str, float] = {}

    def reset(
        self,
        x: float,
        y: float,
        theta: float,
        cov: ArrayLike,
        t: float = 0.0,
        gyro_bias: float = 0.0,
        keep_bias_cov: bool = False,
    ) -> None:
        """Set the pose and its ``(3, 3)`` covariance; the bias takes its prior variance, or
        keeps the current one (``keep_bias_cov``: a relocalisation, which moves the robot but
        tells nothing new about its gyro)."""
        bias_var = self.P[3, 3] if keep_bias_cov else self.params.gyro_bias_sigma0**2
        self.x = np.array([x, y, wrap_angle(theta), gyro_bias])
        P = np.zeros((STATE_DIM, STATE_DIM))
        P[:3, :3] = np.asarray(cov, dtype=float)
        P[3, 3] = bias_var
        self.P = P
        self.t = t

    # -- prediction ------------------------------------------------------------------------
    def pending_gyro(self, t: float) -> tuple[float, float] | None:
        """The bias-corrected heading change the gyro has integrated since the last odometry
        sample, and over how long; None when the gyro is silent (encoders carry the heading)."""
        if t - self._gyro_last_seen > self.params.gyro_timeout_s:
            return None
        return self._gyro_angle - float(self.x[3]) * self._gyro_time, self._gyro_time

    def on_gyro(self, t: float, yaw_rate: float) -> None:
        """A gyro yaw rate (rad/s, CCW) sampled at ``t``; integrated until the next odometry."""
        # After a gap longer than the timeout the encoders carried the heading: start afresh.
        if self._gyro_t is not None and 0.0 < t - self._gyro_t <= self.params.gyro_timeout_s:
            dt = t - self._gyro_t
            self._gyro_angle += yaw_rate * dt
            self._gyro_time += dt
        self._gyro_t = t
        self._gyro_last_seen = t

    def on_odometry(self, t: float, left_ticks: int, right_ticks: int,
                    slip_sigma_rel: float = 0.0, slip_distance_scale: float = 1.0) -> None:
        """Cumulative encoder counts at ``t``; predicts over the interval since the last ones.

        ``slip_sigma_rel``: the wheels may be slipping (a wall, a slippery floor: the node's
        slip detector), so the distance the encoders report is only an upper bound of the real
        one; its standard deviation becomes ``slip_sigma_rel * |ds|`` on top of the normal
        noise, and its mean ``slip_distance_scale`` times the encoders' (a slipping wheel
        realises only part of its turn). The heading still comes from the gyro, which slip does
        not fool.
        :attr:`last_increment` keeps ``(ds, dtheta, sigma_ds, sigma_dtheta)`` of the step."""
        p = self.params
        if self._ticks is None:
            self._ticks = (left_ticks, right_ticks)
            self.t = t
            return
        dl = (left_ticks - self._ticks[0]) / p.ticks_per_metre
        dr = (right_ticks - self._ticks[1]) / p.ticks_per_metre
        self._ticks = (left_ticks, right_ticks)
        ds, dth_odo = odometry_increment(dl, dr, p.wheel_base_m)
        var_ds = p.odo_distance_var_per_m * abs(ds)
        dt = max(t - self.t, 0.0)
        if t - self._gyro_last_seen <= p.gyro_timeout_s:
            dth, bias_time = self._gyro_angle, self._gyro_time
            var_th = p.gyroscope_noise_density**2 * bias_time
        else:
            dth, bias_time = dth_odo, 0.0
            var_th = p.odo_heading_var_per_m * abs(ds) + p.odo_heading_var_per_rad * abs(dth_odo)
        # The gyro integral restarts at every odometry sample, used or not.
        self._gyro_angle = 0.0
        self._gyro_time = 0.0
        var_ds += (slip_sigma_rel * ds) ** 2
        ds *= slip_distance_scale
        self.last_increment = (ds, dth - self.x[3] * bias_time, math.sqrt(var_ds),
                               math.sqrt(var_th))
        self.odometry_increments += 1
        cov_u = np.diag([var_ds, var_th])
        self.x, self.P = predict(
            self.x, self.P, ds, dth, cov_u, bias_time, p.gyroscope_random_walk**2 * dt
        )
        # Unmodelled effects (map and range-model errors that are not white, soft iron, floor
        # unevenness): a random walk of the pose with the wheels' travel, so that errors that
        # stay the same while the geometry does, averaged as if independent, cannot shrink the
        # covariance below what the data support. (Per metre, not per second: a robot at rest
        # sees the same scene, and its estimate does not get worse by waiting.)
        if p.process_noise_xy or p.process_noise_theta:
            travel = abs(ds) + 0.5 * p.wheel_base_m * abs(dth)
            self.P[0, 0] += p.process_noise_xy * travel
            self.P[1, 1] += p.process_noise_xy * travel
            self.P[2, 2] += p.process_noise_theta * travel
        self.t = t

    # -- correction ------------------------------------------------------------------------
    def _gated_update(
        self,
        kind: str,
        z: ArrayLike,
        R: FloatArray,
        H: FloatArray,
        hx: ArrayLike | None = None,
        angle_rows: tuple[int, ...] = (),
    ) -> bool:
        y, S = innovation(self.x, self.P, z, R, H, hx, angle_rows)
        nis = float(y @ np.linalg.solve(S, y))
        ok = nis <= self._gates[y.size]
        self.last_nis[kind] = nis
        self.counters.count(kind, ok)
        if ok:
            self.x, self.P = _correct(self.x, self.P, y, S, R, H)
        return ok

    def on_compass(self, t: float, heading: float, sigma: float | None = None) -> bool:
        """A compass heading (rad; see :func:`heading_from_field`)."""
        s = self.params.compass_sigma_rad if sigma is None else sigma
        return self._gated_update(
            "compass", [heading], np.array([[s * s]]), HEADING_H, [self.x[2]], (0,)
        )

    def on_landmark(
        self,
        t: float,
        landmark_xy: ArrayLike,
        range_m: float,
        bearing: float,
        sigma_range: float,
        sigma_bearing: float,
    ) -> bool:
        """A camera landmark observation: range (m) and bearing (rad CCW from heading)."""
        hx, H = landmark_model(self.x, landmark_xy)
        R = np.diag([sigma_range**2, sigma_bearing**2])
        return self._gated_update("landmark", [range_m, bearing], R, H, hx, (1,))

    def on_coordinate(self, t: float, axis: int, value: float, sigma: float) -> bool:
        """One world coordinate of the robot's centre (``axis`` 0: x, 1: y), metres -- e.g. from
        a range sensor facing a known wall, which fixes the coordinate across the wall only."""
        H = POSITION_H[axis : axis + 1]
        return self._gated_update("coordinate", [value], np.array([[sigma * sigma]]), H)

    def on_ranges(self, t: float, kind: str, z: ArrayLike, hz: ArrayLike, H3: ArrayLike,
                  sigma: ArrayLike) -> NDArray[np.bool_]:
        """Ranges of sensors against the known map, each gated on its own and the accepted ones
        fused in one update (independent errors, so one joint update equals the sequential
        ones; one ``m x m`` solve instead of ``m``).

        Args:
            kind: counter label (``"ir"``, ``"sonar"``).
            z: ``(m,)`` measured ranges, m.
            hz: ``(m,)`` expected ranges at the current estimate
                (:meth:`koala_bridge.estimation.map_model.MapModel.expected`).
            H3: ``(m, 3)`` their Jacobians with respect to ``(x, y, theta)``.
            sigma: ``(m,)`` standard deviations of the readings, m.

        Returns:
            ``(m,)`` which readings passed the gate.
        """
        za, ha = np.asarray(z, dtype=float), np.asarray(hz, dtype=float)
        m = za.size
        if m == 0:
            return np.zeros(0, dtype=bool)
        H = np.zeros((m, STATE_DIM))
        H[:, :3] = np.asarray(H3, dtype=float).reshape(m, 3)
        var = np.asarray(sigma, dtype=float) ** 2
        y = za - ha
        s_diag = np.einsum("ij,jk,ik->i", H, self.P, H) + var
        nis = y * y / s_diag
        ok = nis <= self._gates[1]
        n_ok = int(ok.sum())
        self.counters.accepted[kind] = self.counters.accepted.get(kind, 0) + n_ok
        self.counters.rejected[kind] = self.counters.rejected.get(kind, 0) + m - n_ok
        if n_ok:
            Ha, ya = H[ok], y[ok]
            R = np.diag(var[ok])
            S = Ha @ self.P @ Ha.T + R
            self.x, self.P = _correct(self.x, self.P, ya, S, R, Ha)
        return ok

    def on_position(self, t: float, xy: ArrayLike, cov: ArrayLike) -> bool:
        """A position fix ``[x, y]`` with its ``(2, 2)`` covariance (e.g. from ``wls_fix``)."""
        return self._gated_update("position", xy, np.asarray(cov, dtype=float), POSITION_H)

    # -- read-out --------------------------------------------------------------------------
    @property
    def pose(self) -> tuple[float, float, float]:
        """``(x, y, theta)``, m and rad."""
        return (float(self.x[0]), float(self.x[1]), float(self.x[2]))

    @property
    def pose_cov(self) -> FloatArray:
        """``(3, 3)`` covariance of ``(x, y, theta)``."""
        return self.P[:3, :3].copy()

    @property
    def gyro_bias(self) -> float:
        """Estimated gyro bias, rad/s."""
        return float(self.x[3])
