"""Whether the pose estimate can be trusted: the state published on ``estimate/health``.

States, worst first (the published ``state``), with the ``reasons`` that led to it:

* ``relocalising`` -- the particle filter (:mod:`.relocaliser`) is searching the map; the
  published pose is its weighted mean and covariance. Reason ``kidnap_suspected`` (or whatever
  made the estimate ``lost``).
* ``lost`` -- the evidence contradicts the estimate and no relocalisation runs (it is off, or the
  moment it is detected). Reasons: ``innovations_rejected`` -- in the last ``window_s`` at least
  ``lost_min_rejections`` informative readings (landmarks, map ranges) were gated out and they
  were at least ``lost_reject_ratio`` of all; ``absolute_references_rejected`` -- the same test
  over the longer ``absolute_window_s`` on the absolute references alone (landmarks and the
  compass, which no symmetry of the map can fool: a relocalisation onto a look-alike place that
  the walls confirm is caught by them), with ``absolute_min_rejections``;
  ``estimate_in_wall`` -- the estimated body has overlapped a wall for ``in_wall_s`` (the robot
  cannot be there).
* ``uncertain`` -- the estimate is consistent but not tight, or the robot is in a situation its
  model handles by widening the covariance. Reasons: ``wheel_slip`` (encoders disagree with the
  gyro), ``wall_contact`` (an IR sensor facing the direction of travel touches a wall),
  ``covariance_large`` (position sigma above ``uncertain_sigma_xy_m`` or heading sigma above
  ``uncertain_sigma_theta``), ``no_absolute_fix`` (no landmark or map range accepted for
  ``no_fix_timeout_s``: dead reckoning only), ``evidence_disputed`` (in the window at least
  ``lost_min_rejections`` readings and ``disputed_ratio`` of all were gated out: not
  enough to call the estimate lost, too many to call it tracking).
* ``tracking`` -- none of the above.
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass

TRACKING, UNCERTAIN, LOST, RELOCALISING = "tracking", "uncertain", "lost", "relocalising"
STATES = (TRACKING, UNCERTAIN, LOST, RELOCALISING)


@dataclass(frozen=True)
class HealthParams:
    """Thresholds of the states (module docstring)."""

    window_s: float = 2.0
    lost_min_rejections: int = 8
    lost_reject_ratio: float = 0.7
    in_wall_s: float = 0.5
    absolute_window_s: float = 10.0
    absolute_min_rejections: int = 4
    disputed_ratio: float = 0.3
    uncertain_sigma_xy_m: float = 0.1
    uncertain_sigma_theta: float = math.radians(10.0)
    no_fix_timeout_s: float = 10.0


class HealthMonitor:
    """Keeps the evidence window and decides the state (module docstring)."""

    def __init__(self, params: HealthParams) -> None:
        self.params = params
        self._window: collections.deque[tuple[float, int, int]] = collections.deque()
        self._accepted = 0
        self._rejected = 0
        self.last_fix_t = 0.0
        self._in_wall_since: float | None = None
        self._absolute: collections.deque[tuple[float, bool]] = collections.deque()

    def reset(self, t: float) -> None:
        """Forget the evidence (after a relocalisation: the old rejections are explained)."""
        self._window.clear()
        self._absolute.clear()
        self._accepted = self._rejected = 0
        self.last_fix_t = t
        self._in_wall_since = None

    def evidence(self, t: float, accepted: int, rejected: int) -> None:
        """``accepted`` and ``rejected`` informative readings at ``t``."""
        if accepted:
            self.last_fix_t = t
        if accepted or rejected:
            self._window.append((t, accepted, rejected))
            self._accepted += accepted
            self._rejected += rejected
        self._expire(t)

    def absolute(self, t: float, accepted: bool) -> None:
        """One absolute reference (a landmark, a compass heading) accepted or gated out."""
        self._absolute.append((t, accepted))
        self._expire(t)

    def body_in_wall(self, t: float, inside: bool) -> None:
        """Whether the estimated body overlaps a wall at ``t``."""
        if not inside:
            self._in_wall_since = None
        elif self._in_wall_since is None:
            self._in_wall_since = t

    def _expire(self, t: float) -> None:
        w = self._window
        while w and w[0][0] < t - self.params.window_s:
            _, a, r = w.popleft()
            self._accepted -= a
            self._rejected -= r
        ab = self._absolute
        while ab and ab[0][0] < t - self.params.absolute_window_s:
            ab.popleft()

    def inconsistent(self, t: float) -> list[str]:
        """Reasons the evidence contradicts the estimate (empty: it does not)."""
        self._expire(t)
        p, out = self.params, []
        total = self._accepted + self._rejected
        if self._rejected >= p.lost_min_rejections \
                and self._rejected >= p.lost_reject_ratio * total:
            out.append("innovations_rejected")
        bad = sum(1 for _, ok in self._absolute if not ok)
        if bad >= p.absolute_min_rejections and bad >= p.lost_reject_ratio * len(self._absolute):
            out.append("absolute_references_rejected")
        if self._in_wall_since is not None and t - self._in_wall_since >= p.in_wall_s:
            out.append("estimate_in_wall")
        return out

    def assess(self, t: float, sigma_xy: float, sigma_theta: float, slipping: bool,
               contact: bool) -> tuple[str, list[str]]:
        """``(state, reasons)`` of a tracking EKF (the node reports ``lost`` and
        ``relocalising`` itself, from :meth:`inconsistent` and the relocaliser)."""
        p = self.params
        reasons = self.inconsistent(t)
        if reasons:
            return LOST, reasons
        if slipping:
            reasons.append("wheel_slip")
        if contact:
            reasons.append("wall_contact")
        if sigma_xy > p.uncertain_sigma_xy_m or sigma_theta > p.uncertain_sigma_theta:
            reasons.append("covariance_large")
        if t - self.last_fix_t > p.no_fix_timeout_s:
            reasons.append("no_absolute_fix")
        if self._rejected >= p.lost_min_rejections \
                and self._rejected >= p.disputed_ratio * (self._accepted + self._rejected):
            reasons.append("evidence_disputed")
        return (UNCERTAIN if reasons else TRACKING), reasons

    def counts(self) -> tuple[int, int]:
        """Accepted and rejected readings in the window."""
        return self._accepted, self._rejected
