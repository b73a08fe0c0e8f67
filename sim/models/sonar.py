"""Ultrasonic range sensors: beam of rays, distance error table, specular reflection, crosstalk,
glitches (seeds/004 "Sensor Models").

Sources
- seeds/004_38ad9834df6871a1.txt: Webots ``Khepera3_USSensor`` ``aperture 0.4`` rad (22.9°),
  ``numberOfRays 5``; "Ultrasonic Sensors have a distance error of +-6.6 %" with the range table
  0–5 cm +-0.0, 5 cm +-0.03 cm, 10 cm +-0.1 cm, 30 cm +-0.7 cm, 60 cm +-2.5 cm, 100 cm +-6.6 cm
  (each "+-" read as one Gaussian standard deviation, interpolated linearly, held beyond 1 m);
  "3. Reflection Errors": beyond a critical angle specular reflection makes the echo "never
  return to the sensor" ("maximum distance reading") or "return to the sensor too late"
  ("distance returned represents total round-trip delay"); "crosstalk: echoes emitted from one
  sensor are detected by others".
- Webots reference, DistanceSensor "sonar": the reading is the nearest collision of any ray,
  and a ray whose angle of incidence exceeds pi/8 (22.5°) is lost: our ``critical_angle_deg``.

Model, per sensor (rays ``k``; incidence = angle between ray and surface normal)::

    truth      = min_k d_k                       (nearest surface in the beam; nan if none)
    echo       = min { d_k : incidence_k <= critical }           (direct echoes)
    if no direct echo and some ray hit: with probability late_echo_probability, a late echo of
               length (d_k + second_leg_k) / 2 from the nearest hit ray whose specular reflection
               reaches a second surface (second_leg_k = |p1 p2| + |p2 sensor|), else no echo (nan)
    crosstalk: for each other sensor j fired in the same cycle, each of j's direct-echo hit
               points p inside this sensor's cone gives an echo (d_jk + |p - s_i|) / 2; it is
               heard (per pair and cycle) with probability crosstalk_probability; the first echo
               to arrive (the smallest) is the reading
    range      = echo + sigma(echo) * z          (seed-004 table; clipped at 0)
    glitch:    with probability glitch_probability the reading is U(min_range_m, max_range_m)
    beyond max range: nan (no echo)
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from sim.models._params import check_nonnegative, check_probability, params_from_dict
from sim.noise import LookupTable
from sim.schema import ConfigError


def _seed004_us_table() -> LookupTable:
    # seeds/004 "Ultrasonic Sensors have a distance error of +-6.6%": [range m, sigma m].
    return LookupTable.from_rows(
        [[0.0, 0.0], [0.05, 0.0003], [0.10, 0.001], [0.30, 0.007], [0.60, 0.025], [1.00, 0.066]]
    )


@dataclass(frozen=True)
class SonarErrorParams:
    """``[sensors.sonar]`` error-model keys."""

    ideal: bool = False
    distance_error: LookupTable = field(default_factory=_seed004_us_table)
    critical_angle_deg: float = 22.5     # Webots sonar: rays beyond pi/8 incidence are lost
    late_echo_probability: float = 0.0   # lost echo returns via a second surface
    crosstalk_probability: float = 0.0   # per pair of sensors fired together, per cycle
    glitch_probability: float = 0.0      # per reading
    min_range_m: float = 0.0             # lower end of a glitch's uniform value
    firing_groups: tuple[tuple[float, ...], ...] = ()   # () = all sonars fired together

    def __post_init__(self) -> None:
        if not 0.0 <= self.critical_angle_deg <= 90.0:
            raise ConfigError("'critical_angle_deg' must be in [0, 90]")
        for name in ("late_echo_probability", "crosstalk_probability", "glitch_probability"):
            check_probability(getattr(self, name), name)
        check_nonnegative(self.min_range_m, "min_range_m")
        for g in self.firing_groups:
            if any(int(i) != i or i < 0 for i in g):
                raise ConfigError("'firing_groups' must be lists of sensor indices")

    @classmethod
    def from_dict(cls, d: dict[str, Any], section: str = "sensors.sonar") -> SonarErrorParams:
        return params_from_dict(cls, d, section)


def same_cycle(n: int, firing_groups: tuple[tuple[float, ...], ...]) -> np.ndarray:
    """(n, n) bool: sensors i and j (i != j) are fired in the same cycle."""
    if not firing_groups:
        m = np.ones((n, n), dtype=bool)
    else:
        group = np.full(n, -1)
        for gi, g in enumerate(firing_groups):
            for i in g:
                if int(i) < n:
                    group[int(i)] = gi
        m = (group[:, None] == group[None, :]) & (group[:, None] >= 0)
    np.fill_diagonal(m, False)
    return m


@dataclass(frozen=True)
class SonarMeasurement:
    ranges: np.ndarray        # (n,) m, nan = no echo
    truth_ranges: np.ndarray  # (n,) m, nearest surface in the beam, nan = none within range
    incidence: np.ndarray     # (n,) rad, incidence of the ray giving truth_ranges, nan = none
    kind: np.ndarray          # (n,) int8: 0 none, 1 direct, 2 late, 3 crosstalk, 4 glitch


def measure(
    ray_dists_m: np.ndarray,
    incidence_rad: np.ndarray,
    max_range_m: float,
    params: SonarErrorParams,
    rng: np.random.Generator,
    *,
    second_leg_m: np.ndarray | None = None,
    sensor_xy: np.ndarray | None = None,
    sensor_heading: np.ndarray | None = None,
    hit_xy: np.ndarray | None = None,
    half_aperture_rad: float = math.radians(22.9) / 2,
) -> SonarMeasurement:
    """Sonar ring reading from per-ray geometry.

    ``ray_dists_m`` (n, r): distance to the first surface along each ray, ``inf`` if none within
    ``max_range_m``; ``incidence_rad`` (n, r) angle between the ray and that surface's normal.
    Optional geometry: ``second_leg_m`` (n, r) length of the specular continuation back to the
    sensor (``inf``: none) for late echoes; ``sensor_xy`` (n, 2), ``sensor_heading`` (n,) and
    ``hit_xy`` (n, r, 2), world frame, for crosstalk. Draws ``4 n`` variates per call, plus
    ``n^2`` when crosstalk is modelled.
    """
    d = np.asarray(ray_dists_m, dtype=float)
    inc = np.asarray(incidence_rad, dtype=float)
    n, r = d.shape
    hit = np.isfinite(d) & (d <= max_range_m)
    d_hit = np.where(hit, d, np.inf)
    k_near = np.argmin(d_hit, axis=1)
    rows = np.arange(n)
    truth = d_hit[rows, k_near]
    has = np.isfinite(truth)
    truth_r = np.where(has, truth, np.nan)
    truth_inc = np.where(has, inc[rows, k_near], np.nan)
    kind = np.zeros(n, dtype=np.int8)
    if params.ideal:
        kind[has] = 1
        return SonarMeasurement(truth_r.copy(), truth_r, truth_inc, kind)

    # Fixed draws first (4 n); the crosstalk draws (n^2) come last and only when crosstalk is
    # modelled, so switching crosstalk on does not shift the other draws of the sonar's stream.
    u_late = rng.random(n)
    z = rng.standard_normal(n)
    u_glitch = rng.random(n)
    u_gval = rng.random(n)

    crit = math.radians(params.critical_angle_deg)
    direct = hit & (np.abs(inc) <= crit)
    d_direct = np.where(direct, d, np.inf)
    echo = d_direct.min(axis=1)
    kind[np.isfinite(echo)] = 1

    if second_leg_m is not None and params.late_echo_probability > 0:
        leg = np.asarray(second_leg_m, dtype=float)
        late_len = np.where(hit & np.isfinite(leg), 0.5 * (d + leg), np.inf).min(axis=1)
        late = ((~np.isfinite(echo)) & np.isfinite(late_len)
                & (u_late < params.late_echo_probability))
        echo = np.where(late, late_len, echo)
        kind[late] = 2

    if (hit_xy is not None and sensor_xy is not None and sensor_heading is not None
            and params.crosstalk_probability > 0 and n > 1):
        v = hit_xy[None, :, :, :] - sensor_xy[:, None, None, :]          # (i, j, k, 2)
        dist_back = np.hypot(v[..., 0], v[..., 1])
        ang = np.arctan2(v[..., 1], v[..., 0]) - sensor_heading[:, None, None]
        in_cone = np.abs(np.arctan2(np.sin(ang), np.cos(ang))) <= half_aperture_rad
        path = np.where(direct[None, :, :] & in_cone, 0.5 * (d[None, :, :] + dist_back), np.inf)
        u_cross = rng.random((n, n))
        heard = same_cycle(n, params.firing_groups) & (u_cross < params.crosstalk_probability)
        cross = np.where(heard[:, :, None], path, np.inf).min(axis=(1, 2))
        take = cross < echo
        echo = np.where(take, cross, echo)
        kind[take] = 3

    has_echo = np.isfinite(echo)
    e0 = np.where(has_echo, echo, 0.0)
    ranges = np.where(has_echo, np.maximum(e0 + params.distance_error.value(e0) * z, 0.0), np.nan)
    glitch = u_glitch < params.glitch_probability
    gval = params.min_range_m + (max_range_m - params.min_range_m) * u_gval
    ranges = np.where(glitch, gval, ranges)
    kind[glitch] = 4
    beyond = ranges > max_range_m
    ranges = np.where(beyond, np.nan, ranges)
    kind[beyond] = 0
    return SonarMeasurement(ranges, truth_r, truth_inc, kind)


def reflect(directions: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Specular reflection of unit ``directions`` (..., 2) off surfaces with unit ``normals``."""
    dot = (directions * normals).sum(axis=-1, keepdims=True)
    return directions - 2.0 * dot * normals
