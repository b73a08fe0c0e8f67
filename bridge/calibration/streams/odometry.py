"""Odometry stream: dead reckoning against a reference trajectory, re-anchored in windows.

Wheel odometry (UMBmark's kinematics, Borenstein & Feng 1996, eq. 2-5), per step k::

    s_l = dL / tpm * 2 rho / (1 + rho)     s_r = dR / tpm * 2 / (1 + rho)
    ds  = (s_l + s_r) / 2                  dtheta = (s_r - s_l) / b
    theta_k = theta_{k-1} + dtheta         p_k = p_{k-1} + ds [cos, sin](theta_{k-1} + dtheta / 2)

with ``tpm`` ticks per metre, ``b`` the wheel base and ``rho`` the left/right wheel diameter ratio.
Odometry given as body speeds (``v, omega``) or as a dead-reckoned pose (``x, y, theta``) is turned
into ``ds, dtheta`` directly; then ``tick_scale`` scales ``ds`` and ``wheel_base`` scales
``dtheta`` (the parameters are reported as factors). In every form ``heading_drift`` takes
``d dt`` off each ``dtheta`` (a dead-reckoned heading that turns at ``d`` rad/s relative to the
truth).

Residual: the reference is cut into windows of ``window_s`` seconds; each window starts at the
reference pose of its first sample (re-anchored) and the dead-reckoned path is compared with the
reference positions in it. Without a reference heading, the window's start heading is the one
that best aligns the window (closed-form 2-D Procrustes rotation), so only the shape of the path
counts. The metric is the RMS position error over the score part's windows (m).

Set aside: stalls and wheel slip (:func:`find_stalls`). Where the wheels turn and the robot
does not follow -- pushing into a wall, spinning on a slippery floor -- the encoders count motion
that did not happen, and no effect of the declared model explains it (a recording of the
simulator pushing into walls proposed ``ticks_per_metre`` 22 222 -> 49 662 against the config it
ran with, ``tests/integration/test_calibration_wall_slip.py``). The span is cut into intervals of
:data:`STALL_INTERVAL_S`; on each, the motion the declared odometry gives is held against the
reference's. An interval is *stalled* when the odometry says the robot travelled at least
:data:`STALL_MIN_TRAVEL_M` (or turned at least :data:`STALL_MIN_TURN_RAD`, with a reference
heading) and the reference moved (turned) less than :data:`STALL_FRACTION` of what the
recording's typical ratio makes of it: the median of reference over odometry motion on the
intervals where both moved that much. The median takes out any global error of the declared
geometry (a wrong tick size or wheel base scales every interval alike), and a robot that spent
most of a recording against a wall still has its ratio from where it moved; so only intervals far
off the recording's own ratio are set aside, with one interval more on each side (the contact's
onset and end). The reference is first shifted by the lag that best aligns the two motion
profiles (:func:`speed_lag`, within +-:data:`STALL_MAX_LAG_S`): a reference that shows the motion
late would otherwise make every start look like a stall (the LEGO log's tracker lags its encoders
by ~0.2 s). Reference samples in a set-aside span are dropped, the windows restart after it
(pieces shorter than half a window are dropped too), and the counts inside it are not
dead-reckoned. How much was set aside, and why, is in the stream's notes and ``describe()``.
Not detected: a twist the encoders do not count (the reference turns, the odometry does not), and
slip that keeps more than :data:`STALL_FRACTION` of the motion.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from koala_bridge.calibration.effects.base import EffectInstance
from koala_bridge.calibration.effects.time_offset import (
    CLOCK_ROWS,
    CLOCK_SPAN_SHARE,
    MAX_CLOCK_OFFSET_S,
)
from koala_bridge.calibration.problem import (
    FloatArray,
    LastResult,
    Part,
    StreamProblem,
    apply_all,
)
from numpy.typing import NDArray


def metres_per_tick(tpm: float, ratio: float) -> tuple[float, float]:
    """``(k_l, k_r)``: metres per tick of the left and right wheel for ``tpm`` ticks per metre
    (their mean) and the diameter ratio ``ratio`` = D_l / D_r (module docstring)."""
    return 2 * ratio / (1 + ratio) / tpm, 2 / (1 + ratio) / tpm


@dataclass
class OdometryState:
    """What the effects change: ticks per metre, wheel base, diameter ratio, time offset,
    heading drift."""

    tpm: float
    wheel_base: float
    ratio: float = 1.0
    tau: float = 0.0
    distance_scale: float = 1.0
    yaw_scale: float = 1.0
    heading_drift: float = 0.0  # rad/s the dead-reckoned heading turns relative to the truth


#: Length of the intervals on which the odometry's motion is held against the reference's (s);
#: at least two sample intervals of either series.
STALL_INTERVAL_S = 0.5
#: Least motion by the declared odometry on an interval for it to be judged (m, rad).
STALL_MIN_TRAVEL_M = 0.01
STALL_MIN_TURN_RAD = 0.1
#: Largest time offset between the odometry and the reference taken out before judging (s).
STALL_MAX_LAG_S = 0.5
#: Finest step of the speed profiles it is found on (s): finer ones hold the drive's per-step
#: jitter and the ticks' rounding rather than the motion.
STALL_LAG_STEP_S = 0.05
#: The clocks' coarse offset (:meth:`OdometryProblem.coarse_clock_offset`): searched in steps
#: of CLOCK_STEP_S over the reach a scalar stream's clocks are searched in
#: (``effects.time_offset``: +-min(MAX_CLOCK_OFFSET_S, CLOCK_SPAN_SHARE of the fit part), on at
#: most CLOCK_ROWS samples); taken when the windows' RMS there is below CLOCK_GAIN of the best
#: within +-STALL_MAX_LAG_S.
CLOCK_STEP_S = 0.25
CLOCK_GAIN = 0.5
#: Stalled: the reference moved less than this fraction of the recording's typical ratio
#: times the odometry's motion.
STALL_FRACTION = 0.5


@dataclass(frozen=True)
class SetAside:
    """Spans of the recording where the wheels stalled or slipped (:func:`find_stalls`)."""

    spans: tuple[tuple[float, float], ...] = ()
    #: travel (m) the declared odometry counted over the spans, and the reference's
    odometry_m: float = 0.0
    reference_m: float = 0.0

    @property
    def seconds(self) -> float:
        return float(sum(b - a for a, b in self.spans))

    def contains(self, t: FloatArray) -> NDArray[np.bool_]:
        """Which of the times ``t`` lie in a span."""
        out = np.zeros(np.shape(t), dtype=bool)
        for a, b in self.spans:
            out |= (t >= a) & (t <= b)
        return out


def _typical_ratio(ref: FloatArray, odo: FloatArray, least: float) -> float | None:
    """The reference's motion per unit of the odometry's: the median ratio over the intervals
    where both moved by ``least`` (a robot that spent most of a recording against a wall still
    has its ratio from where it moved); None when too few did, or the ratio is not positive."""
    both = (np.abs(odo) >= least) & (np.abs(ref) >= least)
    if both.sum() < 3:
        return None
    typical = float(np.median(ref[both] / odo[both]))
    return typical if typical > 0 else None


def _stalled(
    ref: FloatArray, odo: FloatArray, typical: float | None, least: float
) -> NDArray[np.bool_]:
    """Intervals where the reference motion ``ref`` is below :data:`STALL_FRACTION` of the
    ``typical`` ratio (:func:`_typical_ratio`) times the odometry motion ``odo`` (signed: a turn
    the other way is a stall too), judged where ``|odo| >= least``."""
    out = np.zeros(odo.shape, dtype=bool)
    if typical is None:
        return out
    judged = np.abs(odo) >= least
    out[judged] = ref[judged] / odo[judged] < STALL_FRACTION * typical
    return out


def _lost(ref: FloatArray, odo: FloatArray, core: NDArray[np.bool_], typical: float | None,
          least: float) -> bool:
    """Whether a span (its intervals ``ref``, ``odo``; ``core`` the ones :func:`_stalled`
    flagged) lost motion: over the whole span the reference fell behind what the typical ratio
    makes of the odometry by at least half the odometry's motion on the flagged intervals. The
    reference's motion counts along the odometry's (signed per interval): a turn the other way
    is lost too, and odometry wiggling while the body is held does not cancel itself out. A
    reference that runs late for an interval and catches up inside the span lost nothing."""
    if typical is None:
        return False
    moved = float(np.sum(np.abs(odo[core])))
    if moved < least:
        return False
    behind = typical * float(np.sum(np.abs(odo))) - float(np.sum(np.sign(odo) * ref))
    return behind >= STALL_FRACTION * typical * moved


def speed_lag(
    t0: float,
    t1: float,
    t_odo: FloatArray,
    pose_odo: tuple[FloatArray, FloatArray, FloatArray],
    t_ref: FloatArray,
    p_ref: FloatArray,
    theta_ref: FloatArray | None = None,
    around: float = 0.0,
) -> float:
    """How late the reference shows the odometry's motion (s, within +-:data:`STALL_MAX_LAG_S`
    of ``around``, the clocks' coarse offset :meth:`OdometryProblem.coarse_clock_offset`):
    the shift of the reference's speed profile -- and turn-rate profile, with a reference
    heading -- that correlates best with the odometry's (the profiles' correlation coefficients,
    each weighted by its own unshifted one), on a grid of half the finer sample interval (at least
    :data:`STALL_LAG_STEP_S`) over ``[t0, t1]``. The turn rate makes it well defined on a drive
    at constant speed (the weave of the simulator tests); without any profile that varies, 0."""
    step = max(
        STALL_LAG_STEP_S,
        0.5 * min(float(np.median(np.diff(t_odo))), float(np.median(np.diff(t_ref)))),
    )
    k = int(STALL_MAX_LAG_S / step)
    centre = int(round(around / step))
    grid = np.arange(t0, t1, step)
    if grid.size < 4 * (k + abs(centre)) + 10:
        return around
    odo = [np.hypot(*(np.diff(np.interp(grid, t_odo, c)) for c in pose_odo[:2]))]
    ref = [np.hypot(*(np.diff(np.interp(grid, t_ref, p_ref[:, j])) for j in (0, 1)))]
    if theta_ref is not None:
        odo.append(np.diff(np.interp(grid, t_odo, pose_odo[2])))
        ref.append(np.diff(np.interp(grid, t_ref, theta_ref)))
    n = odo[0].size

    def corr(v_o: FloatArray, v_r: FloatArray, j: int) -> float:
        a = v_o[max(0, -j) : n - max(0, j)]
        b = v_r[max(0, j) : n - max(0, -j)]  # the reference j steps later
        a, b = a - a.mean(), b - b.mean()
        den = float(np.sqrt(np.dot(a, a) * np.dot(b, b)))
        return float(np.dot(a, b)) / den if den > 0 else 0.0

    # A profile counts by how well it agrees unshifted: the speed of a drive at constant speed
    # is the drive's jitter (correlation ~0), its turn rate the motion (~1); one that does not
    # vary (by 1 % of its RMS) holds no timing at all.
    weight = [
        max(corr(v_o, v_r, 0), 0.0) if np.std(v_o) > 0.01 * np.sqrt(np.mean(v_o**2)) else 0.0
        for v_o, v_r in zip(odo, ref, strict=True)
    ]
    if not any(weight):
        return around
    best, best_r = centre, -np.inf
    for j in range(centre - k, centre + k + 1):
        r = sum(w * corr(v_o, v_r, j) for w, v_o, v_r in zip(weight, odo, ref, strict=True) if w)
        if r > best_r:
            best, best_r = j, r
    return best * step


#: A wheel counts backwards when the declared odometry covers less than this share of the
#: reference's travel and the same counts with one wheel negated cover within this factor of it.
BACKWARD_SHARE = 0.5


def backward_wheel(
    t_odo: FloatArray,
    left: FloatArray,
    right: FloatArray,
    k: tuple[float, float],
    t_ref: FloatArray,
    p_ref: FloatArray,
    wheel_base: float | None = None,
    theta_ref: FloatArray | None = None,
) -> tuple[str, str] | None:
    """What is wrong when one wheel's counts fall as the robot drives forward, or None.

    The bundle format counts forward as up on both wheels. A log whose left (or right) encoder
    counts the other way dead-reckons driving forward as turning on the spot: the declared
    odometry's travel, in chords over :data:`STALL_INTERVAL_S` intervals (as :func:`find_stalls`
    measures it), falls far short of the reference's, while the same counts with one wheel
    negated travel about as far. ``left``/``right`` are the cumulative counts at ``t_odo``,
    ``k`` the declared metres per tick of each wheel. A wrong tick size scales both travels
    alike, so it is told apart: the negated counts must come within 1 / :data:`BACKWARD_SHARE`
    of the reference while the declared ones cover less than :data:`BACKWARD_SHARE` of it.
    With a reference heading (``theta_ref`` at ``t_ref``, and the ``wheel_base``) the turns
    must say the same: the negated counts' turning within a factor 2 of the reference's, and
    closer to it by that factor than the declared counts'. A robot spinning on the spot with its
    tracker's marker ahead of the axle moves the marker in circles, which the travel alone
    took for a wheel counting backwards. Returns what was found and the column to negate (the
    one whose counts fell overall).
    """
    t0, t1 = max(t_odo[0], t_ref[0]), min(t_odo[-1], t_ref[-1])
    n = int((t1 - t0) // STALL_INTERVAL_S)
    if n < 3:
        return None
    edges = t0 + STALL_INTERVAL_S * np.arange(n + 1)
    s_l = k[0] * np.diff(np.interp(edges, t_odo, left))
    s_r = k[1] * np.diff(np.interp(edges, t_odo, right))
    ref = float(np.sum(np.hypot(*(np.diff(np.interp(edges, t_ref, p_ref[:, j])) for j in (0, 1)))))
    # along a chord of an interval the travel is |s_l + s_r| / 2 to first order in the turn
    declared = float(np.sum(np.abs(s_l + s_r))) / 2
    negated = float(np.sum(np.abs(s_r - s_l))) / 2
    if ref < n * STALL_MIN_TRAVEL_M or declared >= BACKWARD_SHARE * ref:
        return None
    if not BACKWARD_SHARE * ref <= negated <= ref / BACKWARD_SHARE:
        return None
    if theta_ref is not None and wheel_base:
        turn_ref = float(np.sum(np.abs(np.diff(np.interp(edges, t_ref, theta_ref)))))
        turn_decl = float(np.sum(np.abs(s_r - s_l))) / abs(wheel_base)
        turn_neg = float(np.sum(np.abs(s_r + s_l))) / abs(wheel_base)
        if turn_ref <= 0 or turn_neg <= 0:
            return None
        off_neg = abs(np.log(turn_neg / turn_ref))
        off_decl = abs(np.log(max(turn_decl, 1e-300) / turn_ref))
        if off_neg > np.log(2) or off_neg > off_decl - np.log(2):
            return None
    net = {"left_ticks": float(left[-1] - left[0]), "right_ticks": float(right[-1] - right[0])}
    falls = [c for c, v in net.items() if v < 0]
    which = falls[0] if len(falls) == 1 else "left_ticks or right_ticks"
    return (
        f"a wheel counts backwards: under the declared geometry the ticks travel "
        f"{declared:.3g} m where the reference moved {ref:.3g} m, and {negated:.3g} m with one "
        f"wheel's counts negated (left_ticks {net['left_ticks']:+.0f}, right_ticks "
        f"{net['right_ticks']:+.0f} over the recording)"
    ), which


#: A reference step is a jump when its speed is above JUMP_FACTOR times the recording's
#: JUMP_QUANTILE of step speeds (the robot's top speed, which a few glitches leave alone).
JUMP_FACTOR = 5.0
JUMP_QUANTILE = 0.98


def reference_jumps(
    t: FloatArray, p: FloatArray, explained: tuple[tuple[float, float], ...] = ()
) -> str | None:
    """A note when the reference positions ``p`` (N, 2) at ``t`` jump: steps faster than
    :data:`JUMP_FACTOR` times the :data:`JUMP_QUANTILE` quantile of all steps' speeds (a
    tracker that loses its markers for a sample, a mocap frame swap). Nothing is taken out: a
    jump counts in its window's error (and may be set aside as a stall), so the note says
    where, and how to remove them. Steps inside ``explained`` (spans the fault log sets
    aside: a kidnap) are none. A reference still in more than
    ``1 - JUMP_QUANTILE`` of its steps (a simulated robot that never drove) jumps at any step
    that moves."""
    dt = np.diff(t)
    ok = dt > 0
    if ok.sum() < 10:
        return None
    speed = np.hypot(*np.diff(p, axis=0)[ok].T) / dt[ok]
    top = float(np.quantile(speed, JUMP_QUANTILE))
    fast = np.flatnonzero(speed > JUMP_FACTOR * top)
    at = t[1:][ok][fast]
    for a, b in explained:
        keep = (at < a) | (at > b)
        fast, at = fast[keep], at[keep]
    if fast.size == 0:
        return None
    than = (f"faster than {JUMP_FACTOR:g}x the robot's {100 * JUMP_QUANTILE:g}th-percentile "
            f"speed {top:.3g} m/s" if top > 0 else
            f"at all, where it is still in at least {100 * JUMP_QUANTILE:g} % of them")
    return (
        f"the reference jumps: {fast.size} of {speed.size} truth_pose steps move {than} "
        f"(up to {float(speed[fast].max()):.3g} m/s; first at t = "
        f"{', '.join(f'{v:.6g}' for v in at[:3])}{', ...' if at.size > 3 else ''} s): "
        "a tracker's glitches? They count in their windows' errors; remove those rows from "
        "truth_pose.csv to leave them out"
    )


def _with_spans(stalls: SetAside, more: tuple[tuple[float, float], ...]) -> SetAside:
    """``stalls`` with the spans ``more`` too (sorted, overlapping ones merged: the windows
    restart after each), its travel totals the stalls' own."""
    if not more:
        return stalls
    merged: list[list[float]] = []
    for a, b in sorted([*stalls.spans, *more]):
        if merged and a <= merged[-1][1]:
            merged[-1][1] = max(merged[-1][1], b)
        else:
            merged.append([a, b])
    return SetAside(tuple((a, b) for a, b in merged), stalls.odometry_m, stalls.reference_m)


def _runs(flag: NDArray[np.bool_]) -> list[tuple[int, int]]:
    """``(start, end)`` (end exclusive) of each run of true values."""
    padded = np.r_[False, flag, False].astype(np.int8)
    starts, ends = np.flatnonzero(np.diff(padded) == 1), np.flatnonzero(np.diff(padded) == -1)
    return list(zip(starts.tolist(), ends.tolist(), strict=True))


def find_stalls(
    t_odo: FloatArray,
    pose_odo: tuple[FloatArray, FloatArray, FloatArray],
    t_ref: FloatArray,
    p_ref: FloatArray,
    theta_ref: FloatArray | None,
    around: float = 0.0,
) -> SetAside:
    """Spans where the declared odometry moves and the reference does not (module docstring).

    ``pose_odo``: the dead-reckoned ``(x, y, theta)`` at ``t_odo`` under the declared model;
    ``p_ref`` (N, 2) and ``theta_ref`` (N,, unwrapped, or None) at ``t_ref``. The odometry's
    travel on an interval is its chord (the distance between its end points, in the robot's own
    frame: no heading needed), as is the reference's, taken :func:`speed_lag` later (searched
    around ``around`` s, the clocks' coarse offset as a lag of the reference).
    """
    t0, t1 = max(t_odo[0], t_ref[0]), min(t_odo[-1], t_ref[-1])
    h = max(
        STALL_INTERVAL_S, 2 * float(np.median(np.diff(t_ref))), 2 * float(np.median(np.diff(t_odo)))
    )
    n = int((t1 - t0) // h)
    if n < 3:
        return SetAside()
    lag = speed_lag(t0, t1, t_odo, pose_odo, t_ref, p_ref, theta_ref, around)
    # Intervals where both series are, the reference shifted.
    t0, t1 = max(t0, t_ref[0] - lag), min(t1, t_ref[-1] - lag)
    n = int((t1 - t0) // h)
    if n < 3:
        return SetAside()
    edges = t0 + h * np.arange(n + 1)
    x, y, th = (np.interp(edges, t_odo, v) for v in pose_odo)
    travel_odo = np.hypot(np.diff(x), np.diff(y))
    px, py = (np.interp(edges + lag, t_ref, p_ref[:, j]) for j in (0, 1))
    travel_ref = np.hypot(np.diff(px), np.diff(py))
    turn_odo = np.diff(th)
    turn_ref = np.diff(np.interp(edges + lag, t_ref, theta_ref)) if theta_ref is not None else None
    move = _typical_ratio(travel_ref, travel_odo, STALL_MIN_TRAVEL_M)
    turn = _typical_ratio(turn_ref, turn_odo, STALL_MIN_TURN_RAD) if turn_ref is not None else None
    moving = _stalled(travel_ref, travel_odo, move, STALL_MIN_TRAVEL_M)
    turning = (_stalled(turn_ref, turn_odo, turn, STALL_MIN_TURN_RAD) if turn_ref is not None
               else np.zeros_like(moving))
    core = moving | turning
    # One interval more on each side: the contact's onset and end fall inside neither.
    flag = core | np.r_[core[1:], False] | np.r_[False, core[:-1]]
    if not flag.any():
        return SetAside()
    # A span is motion lost only if its totals still show it: where the reference merely
    # runs late for an interval (a commanded speed the robot reaches a moment later) and
    # catches up inside the span, nothing was lost and the span is kept.
    runs = []
    # the totals reach a catch-up up to the largest lag taken out later than the span's padding
    ext = int(np.ceil(STALL_MAX_LAG_S / h))
    for a, b in _runs(flag):
        w = slice(max(a - ext, 0), min(b + ext, n))
        lost = _lost(travel_ref[w], travel_odo[w], moving[w], move, STALL_MIN_TRAVEL_M)
        if turn_ref is not None:
            lost |= _lost(turn_ref[w], turn_odo[w], turning[w], turn, STALL_MIN_TURN_RAD)
        if lost:
            runs.append((a, b))
        else:
            flag[a:b] = False
    if not runs:
        return SetAside()
    spans = tuple((float(edges[a]), float(edges[b])) for a, b in runs)
    return SetAside(spans, float(travel_odo[flag].sum()), float(travel_ref[flag].sum()))


@dataclass
class _Windows:
    ref_idx: NDArray[np.intp]  # reference samples scored
    label: NDArray[np.intp]  # window label per sample (0..n_windows-1)
    n: int
    # What the model does not change, gathered once per part (each is a gather of every scored
    # sample; on a 1-hour stream they cost more than the dead reckoning):
    t: FloatArray = field(default_factory=lambda: np.empty(0))  # reference times scored
    t_starts: FloatArray = field(default_factory=lambda: np.empty(0))  # the anchors' times
    q: FloatArray = field(default_factory=lambda: np.empty((2, 0)))  # reference travel (2, N)
    phi: FloatArray | None = None  # the reference heading at each window's anchor (n,)


@dataclass
class OdometryProblem(StreamProblem):
    t_odo: FloatArray = field(default_factory=lambda: np.empty(0))
    d_left: FloatArray | None = None  # tick increments (N-1,)
    d_right: FloatArray | None = None
    ds: FloatArray | None = None  # or distance / heading increments (N-1,)
    dtheta: FloatArray | None = None
    t_ref: FloatArray = field(default_factory=lambda: np.empty(0))
    p_ref: FloatArray = field(default_factory=lambda: np.empty((0, 2)))
    theta_ref: FloatArray | None = None
    tpm: float = 1.0
    wheel_base: float = 1.0
    ratio: float = 1.0  # declared left/right wheel diameter ratio
    window_s: float = 10.0
    form: str = "ticks"
    start_pose: tuple[float, float, float] | None = None  # (t, theta) known at the start
    #: spans set aside because a fault was injected there (``Bundle.odometry_faulted``:
    #: a kidnap, a wheel slip, stuck encoders; :mod:`koala_bridge.calibration.fault_log`)
    faulted: tuple[tuple[float, float], ...] = ()

    def __post_init__(self) -> None:
        self._last = LastResult()
        self._track = LastResult()  # the dead reckoning, shared by the parts (one per model)
        self._counted: NDArray[np.bool_] | None = None  # odometry steps dead-reckoned
        self.set_aside = SetAside()
        declared = self.dead_reckon(self.state())
        self.clock_offset, clock_note = self.coarse_clock_offset(declared)
        if clock_note:
            self.notes.append(clock_note)
        self.stalls = find_stalls(
            self.t_odo, declared, self.t_ref, self.p_ref, self.theta_ref, -self.clock_offset
        )
        self.set_aside = _with_spans(self.stalls, self.faulted)
        if self.set_aside.spans:
            mid = 0.5 * (self.t_odo[1:] + self.t_odo[:-1])
            self._counted = ~self.set_aside.contains(mid)
        inside = (self.t_ref >= self.t_odo[0]) & (self.t_ref <= self.t_odo[-1])
        self._short_s = 0.0  # pieces between set-aside spans too short for a window
        keep = inside & ~self.set_aside.contains(self.t_ref)
        self._windows = {
            p: self._make_windows(keep & self.split.mask(self.t_ref, p), p)
            for p in ("fit", "score")
        }
        self._windows["all"] = self._make_windows(keep, "all")
        if self.stalls.spans:
            self._note_set_aside(inside)

    def coarse_clock_offset(
        self, pose: tuple[FloatArray, FloatArray, FloatArray]
    ) -> tuple[float, str | None]:
        """The odometry's clock against the reference's, when they are seconds apart (a log
        aligned by hand): ``(tau, note)``, ``tau`` as :mod:`.time_offset`'s (the pose stamped
        ``t + tau`` is the reference's at ``t``), else ``(0, None)``.

        The declared dead reckoning ``pose`` is scored in the metric's windows on the fit part
        (at most :data:`CLOCK_ROWS` of its reference samples, those with the whole search inside
        the odometry's span) at shifts ``tau`` in steps of :data:`CLOCK_STEP_S` over
        +-min(:data:`MAX_CLOCK_OFFSET_S`, :data:`CLOCK_SPAN_SHARE` of the fit part). Least
        squares from 0 reaches a local minimum within a fraction of a second, and the stall
        detector aligns within +-:data:`STALL_MAX_LAG_S`: a clock 2 s off read as 21 % of a
        recording stalled, and no time offset. The shift is taken only beyond that reach and
        where its RMS is below :data:`CLOCK_GAIN` of the best within it: motion that repeats
        (a weave, circles) scores about alike one period on, and then nothing is taken. It is
        where the stall detector searches and where ``time_offset`` starts; it changes no
        declared value (the held-out test judges ``time_offset`` as any effect)."""
        fit = self.split.mask(self.t_ref, "fit")
        t_fit = self.t_ref[fit]
        if t_fit.size < 10 or not np.all(np.isfinite(pose[0])):
            return 0.0, None
        reach = min(MAX_CLOCK_OFFSET_S, CLOCK_SPAN_SHARE * float(t_fit[-1] - t_fit[0]))
        k = int(reach / CLOCK_STEP_S)
        if k * CLOCK_STEP_S <= STALL_MAX_LAG_S:
            return 0.0, None
        reach = k * CLOCK_STEP_S
        idx = np.flatnonzero(
            fit & (self.t_ref >= self.t_odo[0] + reach) & (self.t_ref <= self.t_odo[-1] - reach)
        )
        idx = idx[:: max(1, idx.size // CLOCK_ROWS)]
        if idx.size < 10:
            return 0.0, None
        rows = np.zeros(self.t_ref.size, dtype=bool)
        rows[idx] = True
        w = self._make_windows(rows, "fit")  # nothing is set aside yet
        taus = CLOCK_STEP_S * np.arange(-k, k + 1)
        rms = np.array([np.sqrt(np.mean(np.sum(self._window_errors(w, pose, tau) ** 2, axis=0)))
                        for tau in taus])
        near = np.abs(taus) <= STALL_MAX_LAG_S
        best = int(np.argmin(rms))
        if near[best] or not rms[best] < CLOCK_GAIN * rms[near].min():
            return 0.0, None
        tau = float(taus[best])
        return tau, (
            f"the odometry's clock is about {tau:+.2f} s off the reference's (the declared "
            f"model's windows on the fit part: {rms[best]:.3g} m RMS there, "
            f"{rms[near].min():.3g} m at best within +-{STALL_MAX_LAG_S:g} s); wheel stalls "
            "are looked for, and time_offset fitted, from there. Stamp both on one clock, or "
            "shift one, to compare them as recorded"
        )

    def _note_set_aside(self, inside: NDArray[np.bool_]) -> None:
        s = self.stalls
        span = float(np.ptp(self.t_ref[inside])) if inside.any() else 0.0
        share = f"{s.seconds:.1f} s of {span:.1f} s ({100 * s.seconds / max(span, 1e-9):.0f} %)"
        if s.reference_m < STALL_FRACTION * s.odometry_m:
            why = (
                f"set aside {len(s.spans)} span(s) where the wheels stalled or slipped, {share}: "
                f"the odometry (declared model) gave {s.odometry_m:.2f} m while the reference "
                f"moved {s.reference_m:.2f} m (e.g. wheels pushing into a wall, or a commanded "
                "speed the robot did not reach)"
            )
        else:  # the travel agreed over the spans: the turns did not (or a part of them)
            why = (
                f"set aside {len(s.spans)} span(s) where the reference did not follow the "
                f"odometry's motion, {share}: over them the odometry (declared model) gave "
                f"{s.odometry_m:.2f} m and the reference {s.reference_m:.2f} m, so it is the "
                "turn, or a part of the spans, that disagreed (a wheel slipping, or the "
                "reference's heading or position jumping)"
            )
        self.notes.append(
            why + "; windows restart after each span"
            + (
                f", and {self._short_s:.1f} s between spans too short for half a window "
                "were dropped"
                if self._short_s > 0
                else ""
            )
        )

    def _make_windows(self, m: NDArray[np.bool_], part: str) -> _Windows:
        idx = np.flatnonzero(m)
        if idx.size and self.set_aside.spans:
            # Windows restart after every set-aside span; a piece shorter than half a window
            # between two spans holds too little to judge anything and is dropped.
            starts = np.array([a for a, _ in self.set_aside.spans])
            piece = np.searchsorted(starts, self.t_ref[idx], side="right")
            keep = np.ones(idx.size, dtype=bool)
            for k in np.unique(piece):
                sel = piece == k
                t_k = self.t_ref[idx[sel]]
                if t_k[-1] - t_k[0] < 0.5 * self.window_s:
                    keep[sel] = False
                    if part == "all":
                        self._short_s += float(t_k[-1] - t_k[0])
            idx, piece = idx[keep], piece[keep]
        else:
            piece = np.zeros(idx.size, dtype=np.intp)
        if idx.size == 0:
            e = np.empty(0, dtype=np.intp)
            return _Windows(e, e, 0)
        t = self.t_ref[idx]
        first_of_piece = np.r_[0, np.flatnonzero(np.diff(piece)) + 1]
        t_start = t[first_of_piece][np.cumsum(np.r_[0, np.diff(piece) != 0])]
        label = np.floor((t - t_start) / self.window_s).astype(np.intp)
        # (piece, window) pairs are non-decreasing in time: a new label at every change (what
        # np.unique(..., axis=0) gave, without its sort)
        label = np.cumsum(np.r_[True, (np.diff(piece) != 0) | (np.diff(label) != 0)]) - 1
        first = np.r_[0, np.flatnonzero(np.diff(label)) + 1]
        starts = idx[first]  # each window's anchor
        return _Windows(
            idx, label, int(label.max()) + 1,
            t=self.t_ref[idx],
            t_starts=self.t_ref[starts],
            q=np.ascontiguousarray((self.p_ref[idx] - self.p_ref[starts[label]]).T),
            phi=None if self.theta_ref is None else self.theta_ref[starts],
        )

    def state(self) -> OdometryState:
        return OdometryState(self.tpm, self.wheel_base, self.ratio)

    def dead_reckon(self, st: OdometryState) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Cumulative pose (x, y, theta) at the odometry times, from (0, 0, 0).

        Every fit evaluates it on the whole stream (a 1-hour one's 360 000 steps), so it works
        in place: the same arithmetic as ``ds = (s_l + s_r) / 2``, ``dth = (s_r - s_l) / b``,
        ``mid = th + dth / 2``, ``x = cumsum(ds cos mid)``, bit for bit."""
        if self.d_left is not None and self.d_right is not None:
            if not (st.tpm > 0 and st.ratio > 0 and st.wheel_base != 0):
                # No wheel geometry (a fit stepping through a singular one, e.g. the diameter
                # ratio towards -1 where a wheel counts backwards): no dead reckoning, and
                # least squares takes the step back.
                nan = np.full(self.d_left.size + 1, np.nan)
                return nan, nan.copy(), nan.copy()
            k_l, k_r = metres_per_tick(st.tpm, st.ratio)
            s_l, s_r = self.d_left * k_l, self.d_right * k_r
            ds = s_l + s_r
            ds *= 0.5
            dth = np.subtract(s_r, s_l, out=s_r)
            dth /= st.wheel_base
        else:
            assert self.ds is not None and self.dtheta is not None
            ds = self.ds * st.distance_scale
            dth = self.dtheta * st.yaw_scale
        if self._counted is not None:
            # Counts over a stall are not motion (set aside, module docstring).
            ds *= self._counted
            dth *= self._counted
        if st.heading_drift:
            dth -= st.heading_drift * np.diff(self.t_odo)
        th, x, y = (np.empty(dth.size + 1) for _ in range(3))
        th[0] = x[0] = y[0] = 0.0
        np.cumsum(dth, out=th[1:])
        mid = dth * 0.5
        mid += th[:-1]
        step = np.cos(mid)
        step *= ds
        np.cumsum(step, out=x[1:])
        np.sin(mid, out=step)
        step *= ds
        np.cumsum(step, out=y[1:])
        return x, y, th

    def _errors(
        self, insts: Sequence[EffectInstance], x: FloatArray, part: str
    ) -> tuple[FloatArray, _Windows]:
        hit = self._last.get(insts, x, part)
        if hit is not None:
            return hit  # type: ignore[no-any-return]
        return self._last.put(insts, x, part, self._compute_errors(insts, x, part))

    def _compute_errors(
        self, insts: Sequence[EffectInstance], x: FloatArray, part: str
    ) -> tuple[FloatArray, _Windows]:
        w = self._windows[part]
        if w.ref_idx.size == 0:
            return np.empty((2, 0)), w
        track = self._track.get(insts, x, "track")
        if track is None:
            # The fit part, the held-out part and the whole stream are scored on one dead
            # reckoning of the same model (a 1-hour stream's is 360 000 samples).
            st = self.state()
            apply_all(st, self, insts, x)
            track = self._track.put(insts, x, "track", (st, *self.dead_reckon(st)))
        st, X, Y, TH = track
        return self._window_errors(w, (X, Y, TH), st.tau), w

    def _window_errors(
        self, w: _Windows, pose: tuple[FloatArray, FloatArray, FloatArray], tau: float
    ) -> FloatArray:
        """(2, N): the reference's travel from each window's start minus the dead-reckoned
        ``pose``'s (at the odometry times), stamped ``t + tau``, turned onto it."""
        X, Y, TH = pose
        # Dead-reckoned pose at the scored samples and at the windows' anchors only (the other
        # part's samples are not needed: interpolating every reference sample cost twice this).
        tq, tq_a = (w.t, w.t_starts) if tau == 0 else (w.t + tau, w.t_starts + tau)
        dx = np.interp(tq, self.t_odo, X)
        dx -= np.interp(tq_a, self.t_odo, X)[w.label]
        dy = np.interp(tq, self.t_odo, Y)
        dy -= np.interp(tq_a, self.t_odo, Y)[w.label]
        # Each window's dead-reckoned travel (dx, dy), in the odometry's frame, is turned onto
        # the reference's by one angle a per window: the anchor's reference heading phi minus
        # its dead-reckoned one (travel in the anchor's body frame, then in the reference's).
        if w.phi is not None:
            a = w.phi - np.interp(tq_a, self.t_odo, TH)
        elif self.start_pose is not None:
            # Heading is not re-anchored: dead-reckoned from the declared start heading.
            t_s, th_s, _ = self.start_pose
            a = np.full(w.n, th_s - float(np.interp(t_s + tau, self.t_odo, TH)))
        else:
            # No reference heading: the angle that best turns the travel onto the
            # reference's, per window (least squares: atan2 of the summed cross and dot).
            qx, qy = w.q
            cross = np.bincount(w.label, dx * qy - dy * qx, w.n)
            dot = np.bincount(w.label, dx * qx + dy * qy, w.n)
            a = np.arctan2(cross, dot)
        ca, sa = np.cos(a)[w.label], np.sin(a)[w.label]
        e = np.empty((2, tq.size))
        np.subtract(w.q[0], ca * dx - sa * dy, out=e[0])
        np.subtract(w.q[1], sa * dx + ca * dy, out=e[1])
        return e

    def residuals(
        self, insts: Sequence[EffectInstance], x: FloatArray, part: Part, for_fit: bool = False
    ) -> FloatArray:
        e, _ = self._errors(insts, x, part)
        return e.reshape(-1).copy()  # x errors, then y; a copy: a robust loss scales it in place

    def metric_value(self, insts: Sequence[EffectInstance], x: FloatArray, part: Part) -> float:
        e, _ = self._errors(insts, x, part)
        return float(np.sqrt(np.mean(np.sum(e**2, axis=0)))) if e.size else float("nan")

    def heldout_errors(self, insts: Sequence[EffectInstance], x: FloatArray) -> FloatArray:
        """The held-out position error per reference sample (m): its RMS is the metric."""
        e, _ = self._errors(insts, x, "score")
        return np.asarray(np.linalg.norm(e, axis=0), dtype=float)

    def independent_count(self, part: Part, r: FloatArray | None = None) -> float | None:
        # Dead-reckoning errors integrate the noise twice (slip -> heading -> position), so
        # residuals inside a window are not independent whatever their lag-1 correlation says;
        # windows are (each starts from the reference), two coordinates each.
        return 2 * self._windows[part].n

    def clusters(self, part: Part) -> NDArray[np.intp] | None:
        # a window's x errors, then its y errors (residuals()): one cluster, its heading's
        label = self._windows[part].label
        return np.r_[label, label]

    def residual_series(
        self, insts: Sequence[EffectInstance], x: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        e, w = self._errors(insts, x, "all")
        return w.t, np.linalg.norm(e, axis=0)

    def reference_travel(self) -> tuple[float, float]:
        """``(travel, jitter)`` on the fit part: the RMS distance of the reference from its
        windows' starts, and the white noise of its positions (their second differences, over
        ``sqrt(12)`` for two coordinates; a long stream's reference is cut by a regular stride,
        so these stay differences of neighbours, with the motion's share small beside the
        travel). A distance scale shows only where the first is far beyond the second: a robot
        turning on the spot with its tracker on the axle travels nowhere, and a tick size
        fitted there only shrank the slip its counts carry (9.5e6 ticks/m, declared 1e4)."""
        w = self._windows["fit"]
        if w.t.size < 4:
            return 0.0, 0.0
        travel = float(np.sqrt(np.mean(np.sum(w.q**2, axis=0))))
        second = np.diff(self.p_ref[w.ref_idx], n=2, axis=0)
        jitter = float(np.sqrt(np.mean(np.sum(second**2, axis=1)) / 12))
        return travel, jitter

    def describe(self) -> dict[str, Any]:
        return {
            "odometry_samples": int(self.t_odo.size),
            "reference_samples": int(self.t_ref.size),
            "form": self.form,
            "window_s": self.window_s,
            "reference_heading": self.theta_ref is not None,
            "windows": {"fit": self._windows["fit"].n, "score": self._windows["score"].n},
            "set_aside": {
                "reason": "stall or wheel slip: the encoders counted, the reference did not move",
                "spans_s": [[round(a, 3), round(b, 3)] for a, b in self.stalls.spans],
                "seconds": round(self.stalls.seconds, 3),
                "odometry_m": round(self.stalls.odometry_m, 4),
                "reference_m": round(self.stalls.reference_m, 4),
                "short_pieces_s": round(self._short_s, 3),
            },
            **({"faulted_spans_s": [[round(a, 3), round(b, 3)] for a, b in self.faulted]}
               if self.faulted else {}),
        }
