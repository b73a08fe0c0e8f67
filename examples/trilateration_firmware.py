#!/usr/bin/env python3
"""Lab 4 Task 1 over the buses: a full turn, the first three landmarks, trilaterate, cover.

The trilateration task of seeds/003 (Lab 4, "Task 1 - Trilateration", "Find Landmarks",
"Landmark localization", "Coordinate to Cell", "Full grid navigation"), as a firmware that talks
to the robot exactly as :mod:`coverage_firmware` (beside this file) does -- K-Team serial ``D``
for the wheels (and ``N`` for the IR ring), CAN (socketcand, the DBC) for ``WheelOdometry`` and
``Gyro``, MAVLink for the compass -- plus the one sensor that has no bus: the camera's landmark
observations, which the bridge publishes on Zenoh under ``<prefix>/sensors/camera``
(docs/protocols.md §5, ``CameraMessage`` in ``koala_bridge.core.topics``). Nothing else is read
from Zenoh; the truth is never looked at.

What the robot knows, as the lab's robot does ("Key values" A-C): the grid and the landmark map
(id and position of each landmark) from the ``--world`` file, its own build (wheel base, ticks
per metre, IR poses, rates, the control period) and its camera's range calibration from the
``--config`` file: ``[sensors.camera]`` ``dist``, ``d_mid_m``, ``far_doubling_m``,
``bearing_sigma_deg`` and ``rate_hz`` -- the mean and spread of the range error versus distance,
seeds/000 eq. 10-12 (a real team measures these once per camera; the simulator draws from them).

What it does:

1. *Find landmarks* (seeds/003 "Find Landmarks": "performs a full rotation, storing all landmarks
   which were visible at any point during the rotation"): the coverage firmware's calibration
   turn on the spot (gyro; the compass's hard iron and absolute heading come out of it too), with
   every camera sighting kept as ``(id, range, direction)``, the direction being the
   start-relative heading (gyro) plus the bearing. Turning in place, a landmark stays at one
   direction and one range, so its sightings form one cluster; a sighting that carries a wrong
   id (seeds/000 eq. 9) lies in another landmark's cluster. For each id, the largest set of its
   sightings that agree in direction (``--cluster-deg``) and range (4 sigma) is kept, the rest
   are dropped as misrecognitions; an id needs ``--min-sightings`` agreeing sightings. When an
   id's largest group sits where another id's larger group is (a far landmark mostly missed,
   its id mostly given to a nearer one), it loses that group and is grouped from the rest.
2. *Trilaterate*: the landmarks in the order they were first seen; the *first three* give the
   lab's closed form (:func:`koala_bridge.estimation.trilaterate3`) and the weighted
   least-squares fix (:func:`koala_bridge.estimation.wls_fix`, ranges only) -- each range the
   mean of its cluster minus the camera's mean far-range error, with sigma the camera's
   per-sighting spread over the square root of the count. Before it is trusted the set is
   checked: a fit with the cluster directions as bearings (heading free) must pass a chi-square
   gate (``--gate-probability``); if the first three fail it (a wrong id that survived, a
   degenerate triangle), every landmark found is used, then every subset of at least three, in
   the order seen, and the first consistent one is taken. Without a consistent set (or with
   fewer than three landmarks) the robot turns again, at most ``--extra-turns`` times, and
   starts over with that turn's sightings; then the best set is taken (``"consistent": false``
   in the report).
3. *Report the cell* (seeds/003 "Coordinate to Cell"; the world frame has y north and row 0
   south, so the cell is ``(floor(x / l), floor(y / l))``), logged and in the JSON report.
4. *Cover*: the EKF pose is set to the fix, the grid filter to certainty at the cell, and the
   coverage firmware's :meth:`~coverage_firmware.CoverageFirmware.cover` runs (the lab's left, up,
   down, right, else back). While it drives, camera landmarks correct the EKF too
   (``PoseTracker.on_landmark``; its innovation gate rejects a wrong id).

*Time.* The control cycle is the coverage firmware's (read its docstring): one ``D`` per
``[lockstep] period_s``, every stream read up to the cycle's end by its samples' own time
stamps. The camera is a fourth stream, sampled at multiples of ``1 / rate_hz``, stamped with its
``t``; a cycle waits for it like for the others (in lockstep the bridge has put it on Zenoh before
it answers ``d``; Zenoh delivers it a moment later). Camera samples at or before ``T_0`` are not
used: Zenoh does not repeat the t = 0 sample to a late subscriber, so whether it arrived would
depend on the wall clock. Before the first ``D`` the firmware asks the bridge's ``world``
queryable once and waits for its answer: the query travels behind the subscription on the same
session, so when it is answered the bridge knows the subscriber and no camera sample is lost.

Command line as the coverage firmware's (``--endpoints-file``, ``--config``, ``--world``,
``--seed``, ``--report``, ``--timeout-s``, ...). It prints a JSON report -- the coverage
firmware's, plus ``trilateration`` (the fix, its covariance, the cell, the landmarks used, the
closed form, the sightings kept and dropped, the turns taken), ``landmark_updates`` and
``landmark_rejects`` -- and exits 0 when every reachable
cell was visited, 1 otherwise.

example::

    koala-bridge run --clock lockstep --endpoints-file /tmp/koala.json --config my.toml &
    python examples/trilateration_firmware.py --endpoints-file /tmp/koala.json --config my.toml \\
        --world config/worlds/lab_trilateration.toml
"""

from __future__ import annotations

import argparse
import itertools
import json
import logging
import math
import os
import select
import threading
from collections import defaultdict, deque
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import zenoh
from coverage_firmware import (
    STREAM_NAMES,
    CoverageFirmware,
    Links,
    RobotClock,
    RobotParams,
    Sample,
    argument_parser,
    run_firmware,
)
from koala_bridge.core.geometry import wrap_angle as wrap
from koala_bridge.core.grid import Grid
from koala_bridge.core.topics import CameraMessage, parse
from koala_bridge.estimation import (
    DegenerateGeometryError,
    EstimationError,
    trilaterate3,
    wls_fix,
)
from scipy.stats import chi2

log = logging.getLogger("trilateration_firmware")

#: the fourth stream, after coverage_firmware's GYRO, ODOMETRY, COMPASS
CAMERA = len(STREAM_NAMES)
#: a range sigma never below this (an ideal camera: only float rounding), m
RANGE_SIGMA_FLOOR_M = 1e-3
#: a bearing sigma never below this, rad
BEARING_SIGMA_FLOOR_RAD = 1e-3
#: the start-relative heading (gyro) drifts a little over the turn: added to each direction's
#: sigma in the consistency check, rad
DIRECTION_DRIFT_RAD = math.radians(3.0)


# --------------------------------------------------------------------------- the camera


@dataclass(frozen=True)
class CameraParams:
    """The camera's range and bearing calibration, from the robot's config ``[sensors.camera]``.

    Range error (seeds/000 eq. 10-12, docs/models.md "Camera"): ``d_est = d + eps_near N(0,1) +
    eps_far |N(0,1)|`` with ``eps_near = dist d`` and ``eps_far = dist d_mid 2^((d - d_mid) /
    far_doubling)``; so ``E[d_est - d] = eps_far sqrt(2/pi)`` and ``Var = eps_near^2 +
    eps_far^2 (1 - 2/pi)``. Bearing: Gaussian, ``bearing_sigma_deg`` (eq. 14). ``ideal``: exact.
    """

    rate_hz: float
    ideal: bool
    dist: float
    d_mid_m: float
    far_doubling_m: float
    bearing_sigma_rad: float

    @classmethod
    def from_config(cls, d: Mapping[str, Any]) -> CameraParams:
        cam = d["sensors"]["camera"]
        return cls(
            rate_hz=float(cam["rate_hz"]),
            ideal=bool(cam["ideal"]),
            dist=float(cam["dist"]),
            d_mid_m=float(cam["d_mid_m"]),
            far_doubling_m=float(cam["far_doubling_m"]),
            bearing_sigma_rad=math.radians(float(cam["bearing_sigma_deg"])),
        )

    def _far(self, d: float) -> float:
        doublings = min((d - self.d_mid_m) / self.far_doubling_m, 60.0)  # 2**x overflows > 1023
        return self.dist * self.d_mid_m * 2.0**doublings

    def range_bias(self, d: float) -> float:
        """Mean range error at distance ``d`` (m): ``eps_far sqrt(2/pi)``."""
        return 0.0 if self.ideal else self._far(d) * math.sqrt(2.0 / math.pi)

    def range_sigma(self, d: float) -> float:
        """Standard deviation of one range at distance ``d`` (m)."""
        if self.ideal:
            return RANGE_SIGMA_FLOOR_M
        near = self.dist * d
        return max(RANGE_SIGMA_FLOOR_M,
                   math.sqrt(near**2 + self._far(d) ** 2 * (1.0 - 2.0 / math.pi)))

    def bearing_sigma(self) -> float:
        return max(BEARING_SIGMA_FLOOR_RAD, 0.0 if self.ideal else self.bearing_sigma_rad)


# --------------------------------------------------------------------------- find landmarks


@dataclass(frozen=True, slots=True)
class Sighting:
    """One landmark in one camera sample during the turn."""

    t: float            # robot time, s
    id: int             # the id the camera reported (possibly wrong)
    range_m: float
    direction: float    # start-relative heading + bearing, rad


@dataclass(frozen=True)
class FoundLandmark:
    """A landmark found in the turn: its sightings that agree, averaged."""

    id: int
    range_m: float      # mean range minus the camera's mean error, m
    sigma_m: float      # sigma of that mean, m
    direction: float    # circular mean direction, start-relative, rad
    sigma_dir: float    # sigma of that mean (with the heading drift), rad
    sightings: int      # agreeing sightings
    dropped: int        # sightings with this id that did not agree (misrecognitions)
    first_t: float      # robot time of the first agreeing sighting, s


def _largest_agreeing(ss: Sequence[Sighting], camera: CameraParams, cluster_rad: float
                      ) -> list[Sighting]:
    """The largest subset of ``ss`` within ``cluster_rad`` in direction and 4 sigma in range of
    one of its members (ties: the earliest member)."""
    best: list[Sighting] = []
    for centre in ss:
        agree = [s for s in ss if _agree(s, centre, camera, cluster_rad)]
        if len(agree) > len(best):
            best = agree
    return best


def _agree(a: Sighting, b: Sighting, camera: CameraParams, cluster_rad: float) -> bool:
    """Same direction and range: the same landmark, as seen from the spin centre."""
    return (abs(wrap(a.direction - b.direction)) <= cluster_rad
            and abs(a.range_m - b.range_m) <= 4.0 * camera.range_sigma(b.range_m))


def _centre(group: Sequence[Sighting]) -> Sighting:
    """A group's mean range and circular-mean direction (at its first sighting's time)."""
    d = np.array([s.direction for s in group])
    return Sighting(group[0].t, group[0].id, float(np.mean([s.range_m for s in group])),
                    math.atan2(float(np.mean(np.sin(d))), float(np.mean(np.cos(d)))))


def find_landmarks(
    sightings: Iterable[Sighting], camera: CameraParams, cluster_rad: float, min_sightings: int
) -> list[FoundLandmark]:
    """Group the turn's sightings by id and keep, per id, the largest set that agrees in
    direction (within ``cluster_rad`` of one of them) and range (within 4 sigma); returns the
    landmarks found, in the order first seen (seeds/003 "first three" = the first three of them).

    A wrong id (seeds/000 eq. 9) copies another landmark's range and direction, so a minority of
    an id's sightings sits elsewhere: dropped. When the wrong ones are the majority of an id (a
    far landmark mostly missed), its group sits where another id's group is: two ids at one
    place. The id with fewer sightings there loses them and is grouped again from the rest.
    Deterministic: ties go to the earliest sighting, then the larger id loses.
    """
    by_id: dict[int, list[Sighting]] = defaultdict(list)
    for s in sorted(sightings, key=lambda s: (s.t, s.id, s.range_m)):
        by_id[s.id].append(s)
    left = {lid: list(ss) for lid, ss in by_id.items()}
    while True:
        groups = {lid: _largest_agreeing(ss, camera, cluster_rad) for lid, ss in left.items()}
        groups = {lid: g for lid, g in groups.items() if len(g) >= min_sightings}
        centres = {lid: _centre(g) for lid, g in groups.items()}
        clash = next(((a, b) for a, b in itertools.combinations(sorted(groups), 2)
                      if _agree(centres[a], centres[b], camera, cluster_rad)), None)
        if clash is None:
            break
        a, b = clash
        loser = b if (len(groups[a]), -groups[a][0].t) >= (len(groups[b]), -groups[b][0].t) \
            else a
        lost = {id(s) for s in groups[loser]}
        left[loser] = [s for s in left[loser] if id(s) not in lost]
    found = []
    for lid, best in groups.items():
        n = len(best)
        c = centres[lid]
        r = c.range_m
        found.append(FoundLandmark(
            id=lid,
            range_m=r - camera.range_bias(r),
            sigma_m=camera.range_sigma(r) / math.sqrt(n),
            direction=c.direction,
            sigma_dir=math.hypot(camera.bearing_sigma() / math.sqrt(n), DIRECTION_DRIFT_RAD),
            sightings=n,
            dropped=len(by_id[lid]) - n,
            first_t=best[0].t,
        ))
    found.sort(key=lambda f: (f.first_t, f.id))
    return found


@dataclass(frozen=True)
class Trilateration:
    """The accepted fix (``wls_fix`` on ranges), the lab's closed form on the same first three,
    and the consistency check that chose the landmark set."""

    xy: tuple[float, float]
    cov: tuple[tuple[float, float], tuple[float, float]]
    closed_form: tuple[float, float] | None  # trilaterate3 on the first three of the set
    ids: tuple[int, ...]                     # the landmarks used, in the order seen
    check_chi2: float                        # ranges + directions (heading free)
    check_dof: int
    consistent: bool
    frame_heading: float                     # world heading of the directions' frame (check)
    sets_tried: int


def candidate_sets(n: int) -> list[tuple[int, ...]]:
    """Index sets to try, in order: the first three, all, then every subset of at least three
    (larger first, earlier landmarks first)."""
    out: list[tuple[int, ...]] = []
    for s in [tuple(range(min(3, n))), tuple(range(n))] + [
        c for k in range(n - 1, 2, -1) for c in itertools.combinations(range(n), k)
    ]:
        if len(s) >= 3 and s not in out:
            out.append(s)
    return out


def trilaterate(
    found: Sequence[FoundLandmark], landmark_map: Mapping[int, tuple[float, float]],
    gate_probability: float,
) -> Trilateration:
    """The fix from the landmarks found (see the module docstring, step 2).

    Raises:
        EstimationError: fewer than three known landmarks found, or no set determines a fix.
    """
    known = [f for f in found if f.id in landmark_map]
    if len(known) < 3:
        raise EstimationError(f"need three known landmarks, found {[f.id for f in found]}")
    best: tuple[float, Trilateration] | None = None
    sets = candidate_sets(len(known))
    for tried, idx in enumerate(sets, start=1):
        use = [known[i] for i in idx]
        lm = np.array([landmark_map[f.id] for f in use])
        ranges = np.array([f.range_m for f in use])
        try:
            check = wls_fix(lm, ranges, [f.sigma_m for f in use],
                            bearings=[f.direction for f in use],
                            sigma_bearing=[f.sigma_dir for f in use])
            fix = wls_fix(lm, ranges, [f.sigma_m for f in use])
        except DegenerateGeometryError:
            continue
        closed: tuple[float, float] | None = None
        try:
            cx, cy = trilaterate3(lm[:3], ranges[:3])
            closed = (float(cx), float(cy))
        except DegenerateGeometryError:
            pass
        gate = float(chi2.ppf(gate_probability, check.dof))
        result = Trilateration(
            xy=(float(fix.x[0]), float(fix.x[1])),
            cov=tuple(tuple(float(v) for v in row) for row in fix.cov),  # type: ignore[arg-type]
            closed_form=closed,
            ids=tuple(f.id for f in use),
            check_chi2=check.chi2,
            check_dof=check.dof,
            consistent=check.chi2 <= gate,
            frame_heading=float(check.x[2]),
            sets_tried=tried,
        )
        if result.consistent:
            return result
        log.warning("landmarks %s disagree (chi2 %.1f > %.1f, dof %d): trying others",
                    result.ids, check.chi2, gate, check.dof)
        score = chi2.sf(check.chi2, check.dof)
        if best is None or score > best[0]:
            best = (score, result)
    if best is None:
        raise EstimationError(f"no set of the landmarks {[f.id for f in known]} fixes a position")
    return best[1]


# --------------------------------------------------------------------------- the links


class CameraLinks(Links):
    """The coverage firmware's three links plus a Zenoh session subscribed to the camera."""

    def __init__(self, endpoints: Mapping[str, Any], watchdog_s: float) -> None:
        super().__init__(endpoints, watchdog_s)
        self._camera: deque[CameraMessage] = deque()
        self._lock = threading.Lock()
        self._wake_r, self._wake_w = os.pipe()  # readable when a camera sample has come
        os.set_blocking(self._wake_r, False)
        os.set_blocking(self._wake_w, False)
        self.session: zenoh.Session | None = None
        try:
            z = endpoints["zenoh"]
            self.prefix = str(z["prefix"]).strip("/")
            conf = zenoh.Config()
            conf.insert_json5("mode", '"peer"')
            conf.insert_json5("scouting/multicast/enabled", "false")
            conf.insert_json5("connect/endpoints", json.dumps(list(z["endpoints"])))
            self.session = zenoh.open(conf)
            self._sub = self.session.declare_subscriber(
                f"{self.prefix}/{CameraMessage.TOPIC}", self._on_camera)
            self._barrier()
        except BaseException:
            self.close()
            raise

    def _on_camera(self, sample: zenoh.Sample) -> None:
        """Zenoh's thread: queue the message, wake the control loop."""
        try:
            msg = parse(CameraMessage.TOPIC, sample.payload.to_bytes())
        except Exception:  # a bad payload is counted out, never kills Zenoh's thread
            log.exception("cannot read a camera message")
            return
        assert isinstance(msg, CameraMessage)
        with self._lock:
            self._camera.append(msg)
        try:
            os.write(self._wake_w, b"\0")
        except BlockingIOError:
            pass  # the pipe is full: the loop is awake anyway

    def _barrier(self) -> None:
        """Ask the bridge's ``world`` queryable until it answers: the query follows the
        subscription on the session, so once answered the bridge routes the camera to us."""
        assert self.session is not None
        while True:
            self.check_watchdog()
            for reply in self.session.get(f"{self.prefix}/world", timeout=1.0):
                if reply.ok is not None:
                    return

    def samples(self, wait_s: float = 0.0) -> list[Sample]:
        out = super().samples(wait_s)
        try:
            while os.read(self._wake_r, 4096):
                pass
        except BlockingIOError:
            pass
        with self._lock:
            msgs = list(self._camera)
            self._camera.clear()
        out += [Sample(m.t, CAMERA, m) for m in msgs]  # type: ignore[arg-type]
        return out

    def wait_compass(self, timeout_s: float) -> None:
        """Sleep until MAVLink or the camera has data, or ``timeout_s`` passed."""
        select.select([self.mav.fileno(), self._wake_r], [], [], timeout_s)

    def close(self) -> None:
        try:
            if self.session is not None:
                self.session.close()
                self.session = None
        finally:
            for fd in (self._wake_r, self._wake_w):
                try:
                    os.close(fd)
                except OSError:
                    pass
            super().close()


# --------------------------------------------------------------------------- the firmware


class TrilaterationFirmware(CoverageFirmware):
    """Find landmarks in the calibration turn, trilaterate, then the coverage firmware's tour."""

    stream_names = (*STREAM_NAMES, "camera")

    def __init__(self, links: CameraLinks, robot: RobotParams, world: Grid,
                 camera: CameraParams, args: argparse.Namespace) -> None:
        super().__init__(links, robot, world, args)
        self.camera = camera
        self.clock = RobotClock(robot.period_s, (*robot.stream_rates_hz(), camera.rate_hz))
        self.landmark_map = {lm.id: (lm.x, lm.y) for lm in world.landmarks}
        self.collect_landmarks = False
        self.sightings: list[Sighting] = []
        self.found: list[FoundLandmark] = []
        self.fix: Trilateration | None = None
        self.fix_t: float | None = None
        self.turns = 0
        self.landmark_updates = 0
        self.landmark_rejects = 0

    def start(self) -> None:
        """As the coverage firmware, then: no camera sample at or before ``T_0`` (one that came
        while the bridge held at t = 0 may or may not have arrived: not used)."""
        super().start()
        clock = self.clock
        assert clock.origin is not None
        clock.newest[CAMERA] = max(clock.newest[CAMERA], clock.origin)
        clock.pending = [s for s in clock.pending
                         if not (s.stream == CAMERA and s.t <= clock.origin)]

    def on_sample(self, s: Sample) -> None:
        if s.stream != CAMERA:
            super().on_sample(s)
            return
        msg = s.value
        assert isinstance(msg, CameraMessage)
        for ob in msg.observations:
            if ob.range is None or ob.bearing is None:
                continue
            if self.collect_landmarks:
                self.sightings.append(Sighting(s.t, int(ob.id), float(ob.range),
                                               float(wrap(self.tracker.pose[2] + ob.bearing))))
            elif self.localised is not None and ob.id in self.landmark_map:
                r = float(ob.range)
                ok = self.tracker.on_landmark(
                    s.t, self.landmark_map[ob.id], r - self.camera.range_bias(r),
                    float(ob.bearing), self.camera.range_sigma(r), self.camera.bearing_sigma())
                self.landmark_updates += int(ok)
                self.landmark_rejects += int(not ok)

    def spin(self, rate: float = 0.6) -> None:
        """One more full turn on the spot at ``rate`` rad/s (gyro-tracked), then stop."""
        turned, last = 0.0, self.tracker.pose[2]
        end = self.t + 2 * math.pi / rate + 20.0
        while turned < 2 * math.pi and self.t < end:
            self.drive(0.0, rate)
            self.cycle()
            th = self.tracker.pose[2]
            turned += abs(wrap(th - last))
            last = th
        self.stop()

    def calibrate(self) -> None:
        """The coverage firmware's turn, keeping every camera sighting (seeds/003 "Find
        Landmarks"). Every sighting is in the start-relative heading frame: the compass heading
        replaces it only at the very end of the turn."""
        self.collect_landmarks = True
        try:
            super().calibrate()
        finally:
            self.collect_landmarks = False

    def localise(self) -> tuple[tuple[int, int], int]:
        """Trilaterate from the turn's landmarks; the cell; the EKF and the grid filter set to
        them. No move is needed: returns ``(cell, 0)``. When the turn did not give a consistent
        fix (fewer than three landmarks found, or no consistent set), the robot turns again, up
        to ``--extra-turns`` times, each turn's sightings on their own (after the first turn the
        heading is the compass's: another frame)."""
        fix: Trilateration | None = None
        found: list[FoundLandmark] = []
        for turn in range(self.args.extra_turns + 1):
            if turn:
                self.sightings = []
                self.collect_landmarks = True
                try:
                    self.spin()
                finally:
                    self.collect_landmarks = False
            self.found = find_landmarks(self.sightings, self.camera,
                                        math.radians(self.args.cluster_deg),
                                        self.args.min_sightings)
            log.info("turn %d: landmarks found, in the order seen: %s", turn + 1, ", ".join(
                f"{f.id} ({f.range_m:.3f} m, {f.sightings} kept, {f.dropped} dropped)"
                for f in self.found))
            try:
                fix = trilaterate(self.found, self.landmark_map, self.args.gate_probability)
            except EstimationError as e:
                log.warning("turn %d: %s", turn + 1, e)
                continue
            found, self.turns = self.found, turn + 1
            if fix.consistent:
                break
        if fix is None:
            raise RuntimeError(f"no trilateration after {self.args.extra_turns + 1} turns")
        self.fix, self.fix_t, self.found = fix, self.t, found
        cell = self.world.cell_of(*fix.xy)
        log.info("trilaterated (%.3f, %.3f) m from landmarks %s: cell %s", *fix.xy, fix.ids, cell)
        if not self.world.in_bounds(*cell):
            raise RuntimeError(f"the fix {fix.xy} is outside the world")
        # The fix is the spin centre; the robot has stood there since the turn.
        x, y, th = self.tracker.pose
        cov = self.tracker.pose_cov
        cov[:2, :] = cov[:, :2] = 0.0
        cov[:2, :2] = np.array(fix.cov)
        self.tracker.reset(fix.xy[0], fix.xy[1], th, cov, t=self.t,
                           gyro_bias=self.tracker.gyro_bias)
        self.grid.reset(cell)
        return cell, 0

    def run(self) -> dict[str, Any]:
        report = super().run()
        fix = self.fix
        report["trilateration"] = None if fix is None else {
            **asdict(fix),
            "cell": list(self.world.cell_of(*fix.xy)),
            "t": self.fix_t,
            "landmarks": [asdict(f) for f in self.found],
            "sightings": len(self.sightings),
            "turns": self.turns,
        }
        report["landmark_updates"] = self.landmark_updates
        report["landmark_rejects"] = self.landmark_rejects
        return report


def main(argv: list[str] | None = None) -> int:
    ap = argument_parser(
        description=__doc__.split("\n\n")[0],
        epilog="example:\n  python examples/trilateration_firmware.py --endpoints-file "
               "/tmp/koala.json --config config/default.toml --world "
               "config/worlds/lab_trilateration.toml",
    )
    ap.add_argument("--cluster-deg", type=float, default=12.0,
                    help="sightings of one id within this direction agree (default 12)")
    ap.add_argument("--min-sightings", type=int, default=2,
                    help="agreeing sightings a landmark needs (default 2)")
    ap.add_argument("--gate-probability", type=float, default=0.999,
                    help="chi-square gate of the landmark set's consistency (default 0.999)")
    ap.add_argument("--extra-turns", type=int, default=2,
                    help="turns again, at most this often, without a consistent fix (default 2)")
    return run_firmware(
        ap.parse_args(argv), make_links=CameraLinks,
        make_firmware=lambda links, robot, world, config, args: TrilaterationFirmware(
            links, robot, world, CameraParams.from_config(config), args),
    )


if __name__ == "__main__":
    raise SystemExit(main())
