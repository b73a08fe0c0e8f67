"""The estimator node: localisation and mapping from what the robot's buses carry.

:class:`LocalisationNode` owns the estimators of :mod:`koala_bridge.estimation` -- the pose EKF
(:class:`estimation.PoseTracker`), the grid (histogram) localiser and the occupancy grid
-- and feeds them with **decoded bus frames**: it is handed the raw bytes the robot put on its
buses (:meth:`LocalisationNode.on_frame`, the same call shape as a recorder's
``record_frame``) and decodes them with the project's codecs:

=======================  ======================================  ============================
bus                      codec (``drivers``)                     estimator input
=======================  ======================================  ============================
``can``                  ``can_codec.KoalaCanCodec`` (the DBC)   ``WheelOdometry``, ``Gyro``
``mavlink``              ``mavlink_codec.CompassDecoder``        ``SCALED_IMU`` field
``serial/rangefinders``  ``rangeframes.RangeFrameDecoder``       IR counts, sonar mm
``serial/kteam``         the dialect's ``parse_reply``,          koala1 ``n`` IR, ``h`` ticks;
                         ``real_kteam.KteamReplyDecoder``        koala25 ``p`` ticks, ``n`` gyro,
                                                                 ``@`` field, ``g`` sonar
=======================  ======================================  ============================

So it runs the same against the simulator (``runtime/sim_source.py`` hands it every frame it sends)
and against a real Koala (``runtime/real_source.py`` hands it every frame it reads). The camera
has no bus: in simulation the service passes the simulator's *measured* landmark observations
(:meth:`LocalisationNode.on_camera`); a real robot has none. The node never sees the truth.

One source per quantity, as in ``real_source``: K-Team ``n``/``h`` replies (answers to whoever
polls the robot) are used only until a streaming source (range frames, CAN ``WheelOdometry``)
has been seen; so are a Koala 2.5's ``p``, ``n``, ``@`` and ``g`` lines (``kteam_dialect``,
converted by :class:`runtime.real_kteam.KteamReplyDecoder`) until CAN ``WheelOdometry`` or
``Gyro``, MAVLink compass or sonar range frames have been seen.

What it does with them (docs/localisation.md, "In the bridge"):

* **pose** -- ``WheelOdometry`` frames predict (at ``predict_rate_hz``: the counters are
  cumulative, so the frames in between are skipped undecoded), every ``Gyro`` frame supplies the
  heading change; the compass (at ``compass_rate_hz``, after hard-iron removal: configured, or
  fitted online to the circle the horizontal field draws once the robot has turned through most
  headings) and camera landmarks correct; near a cell centre, IR sensors facing a known wall of
  the cell fix the coordinate across that wall (``PoseTracker.on_coordinate``).
* **grid** -- moves come from the pose: when the estimated position enters a neighbouring cell
  (by ``move_hysteresis_m`` past the boundary) the grid filter predicts a move to that side; a
  wall observation is made once per cell visit, from the first IR frame taken within
  ``observe_radius_m`` of the cell centre (the lab's model assumes a cell-centred robot).
* **occupancy** -- IR (and optionally sonar) ranges are integrated at the estimated pose, at
  most ``update_hz`` scans per second (the heavy step).

Outputs go through the ``publish(suffix, payload)`` callback the owner gives (Zenoh + recorder)
at the configured rates, in the frames' time (simulation seconds in simulation):
``estimate/pose``, ``estimate/cell``, ``estimate/grid``, ``map/occupancy``
(:mod:`koala_bridge.estimation.messages`).

Configuration: ``[localisation]`` with ``[localisation.pose]``, ``[localisation.grid]``,
``[localisation.occupancy]`` (``config/default.toml`` shows every key); no section = off.
"""

from __future__ import annotations

import collections
import logging
import math
import threading
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Annotated, Any

import numpy as np
from koala_bridge.core.geometry import circle_centre
from koala_bridge.core.schema import (
    Bool,
    ConfigError,
    Finite,
    FloatTuple,
    NonNegative,
    Positive,
    Probability,
    Str,
    field_names,
    one_of,
    reject_unknown,
    section,
    validate,
)
from koala_bridge.core.topics import (
    CompassMessage,
    GyroMessage,
    IrMessage,
    OdometryMessage,
    SonarMessage,
)
from koala_bridge.drivers.can_codec import KoalaCanCodec, wrap_int32
from koala_bridge.drivers.dialects import dialect
from koala_bridge.drivers.kteam import LineSplitter
from koala_bridge.drivers.mavlink_codec import CompassDecoder
from koala_bridge.drivers.messages import (
    CompassSample,
    GyroFrame,
    KteamReply,
    RangeKind,
    WheelOdometryFrame,
)
from koala_bridge.drivers.rangeframes import NO_ECHO, RangeFrameDecoder
from koala_bridge.estimation import (
    BeamModel,
    GridLocaliser,
    GridParams,
    OccupancyGrid,
    OccupancyParams,
    PoseTracker,
    PoseTrackerParams,
    heading_from_field,
    walls_from_ir,
)
from koala_bridge.estimation.health import (
    LOST,
    RELOCALISING,
    TRACKING,
    HealthMonitor,
    HealthParams,
)
from koala_bridge.estimation.map_model import MapModel, RangeHit
from koala_bridge.estimation.messages import (
    KEY_CELL,
    KEY_GRID,
    KEY_HEALTH,
    KEY_OCCUPANCY,
    KEY_POSE,
    cell_message,
    grid_message,
    health_message,
    occupancy_message,
    pose_message,
)
from koala_bridge.estimation.relocaliser import Relocaliser, RelocaliserParams
from koala_bridge.runtime.real_kteam import KteamReplyDecoder
from koala_bridge.sim.config import SimConfig
from koala_bridge.sim.world import SIDE_STEP, World
from pydantic import AfterValidator, Field

log = logging.getLogger(__name__)

SECTION = "localisation"
FROM_ROBOT = "from_robot"
GRID_PRIORS = ("start", "uniform")
HARD_IRON_BINS = 12          # heading bins (30 deg) the online hard-iron fit wants filled ...
HARD_IRON_MIN_BINS = 10      # ... at least this many of them
HARD_IRON_PER_BIN = 20       # samples kept per bin
#: A robot whose estimated centre is closer than its body radius minus this (or minus 3 sigma of
#: its position, if more) to a wall is "in the wall" (the margin absorbs the estimate's normal
#: error in wall contact).
IN_WALL_MARGIN_M = 0.05
#: An IR sensor counts as facing the direction of travel when cos(its yaw) has the sign of the
#: motion and at least this size (within ~70 deg of straight ahead / behind).
CONTACT_FACING_COS = 0.35
#: The map says "contact" when the estimated body is within this of a wall (touching, not merely
#: passing close: a robot passing a wall's end at 1 cm is not blocked) ...
MAP_CONTACT_GAP_M = 0.005
#: ... and the motion points into the nearest wall by at least this cosine (~6 deg off parallel).
MAP_CONTACT_COS = 0.1
#: ... and it pushes into the wall (a stall: ``push_distance_scale``) when that cosine is at least
#: this (within 60 deg of the wall's normal); at a shallower angle a body slides along or grazes
#: past (a robot backing past a wall's end touches it and moves on).
MAP_PUSH_COS = 0.5
#: Simulated seconds between consistency checks (estimate in a wall, evidence against it, the
#: relocaliser's convergence): the evidence arrives at the range sensors' rates, 5-20 Hz.
CHECK_PERIOD_S = 0.1
Publish = Callable[[str, dict[str, Any]], None]


# --------------------------------------------------------------------------- settings


def _sized(*sizes: int) -> Any:
    def check(value: tuple[float, ...]) -> tuple[float, ...]:
        if len(value) not in sizes:
            raise ValueError(f"must be a list of {' or '.join(map(str, sizes))} numbers, "
                             f"got {list(value)!r}")
        return value

    return AfterValidator(check)



#: More occupancy cells than this is a configuration mistake (the default world has 3 600).
MAX_OCCUPANCY_CELLS = 4_000_000
#: The camera range sigma's doublings are capped here: 2**60 already makes an observation
#: carry no information, and 2**far overflows past 1023 (a tiny landmark_far_doubling_m).
MAX_DOUBLINGS = 60.0

#: A probability that is not 0 (a likelihood that may not vanish) nor above 1.
_Likelihood = Annotated[Positive, Field(le=1)]


@section
class PoseSettings:
    """``[localisation.pose]``: the EKF's noise model and its measurement options."""

    odo_distance_var_per_m: NonNegative
    odo_heading_var_per_m: NonNegative
    odo_heading_var_per_rad: NonNegative
    gyroscope_noise_density: NonNegative
    gyroscope_random_walk: NonNegative
    gyro_bias_sigma0: NonNegative
    gyro_timeout_s: Positive
    predict_rate_hz: Positive
    compass_rate_hz: Positive
    compass_sigma_deg: Positive
    compass_hard_iron_uT: Annotated[FloatTuple, _sized(0, 2, 3)]   # () = estimate online
    compass_field_tolerance: Annotated[Positive, Field(le=1)]
    gate_probability: Annotated[Positive, Field(lt=1)]
    landmark_range_sigma_m: Positive
    landmark_range_sigma_rel: NonNegative
    landmark_far_from_m: NonNegative
    landmark_far_doubling_m: Positive
    landmark_bearing_sigma_deg: Positive
    process_noise_xy_m: NonNegative
    process_noise_theta_deg: NonNegative


@section
class GridSettings:
    """``[localisation.grid]``: the histogram filter and when it moves and observes."""

    p_move: Probability
    p_hit: Probability
    p_clear: Probability
    ir_wall_threshold_counts: NonNegative
    observe_radius_m: NonNegative
    move_hysteresis_m: NonNegative


@section
class OccupancySettings:
    """``[localisation.occupancy]``: the log-odds grid and which readings go into it."""

    resolution_m: Positive
    update_hz: Positive
    l_occ: NonNegative
    l_free: Finite
    occ_share_cells: Positive
    l_min: Finite
    l_max: Positive
    mark_free_on_no_echo: Bool
    ir: Bool
    ir_no_echo_counts: NonNegative
    ir_range_error: NonNegative
    sonar: Bool
    sonar_range_error: NonNegative

    def __post_init__(self) -> None:
        if not self.l_min < 0 < self.l_max:
            raise ConfigError(f"[{SECTION}.occupancy] needs l_min < 0 < l_max")


@section
class RobustSettings:
    """``[localisation.robust]``: range sensors against the map, slip and contact, health and
    global relocalisation (docs/localisation.md "Robustness")."""

    ir_ranges: Bool
    ir_range_sigma_m: Positive
    ir_range_sigma_rel: NonNegative
    ir_usable_counts: Annotated[FloatTuple, _sized(2)]
    sonar_ranges: Bool
    sonar_range_sigma_m: Positive
    sonar_range_sigma_rel: NonNegative
    sonar_beam_rays: Annotated[int, Field(ge=1, le=15)]
    sonar_critical_incidence_deg: Annotated[Positive, Field(le=90)]
    corner_margin_m: NonNegative
    contact_range_m: NonNegative
    slip_window_s: Positive
    slip_gate_sigmas: Positive
    slip_sigma_rel: NonNegative
    slip_distance_scale: Annotated[NonNegative, Field(le=1)]
    push_distance_scale: Annotated[NonNegative, Field(le=1)]
    slip_hold_s: NonNegative
    health_rate_hz: Positive
    lost_window_s: Positive
    lost_min_rejections: Annotated[int, Field(ge=1)]
    lost_reject_ratio: Probability
    disputed_ratio: Probability
    in_wall_s: Positive
    absolute_window_s: Positive
    absolute_min_rejections: Annotated[int, Field(ge=1)]
    uncertain_sigma_xy_m: Positive
    uncertain_sigma_theta_deg: Positive
    no_fix_timeout_s: Positive
    relocalise: Bool
    particles: Annotated[int, Field(ge=10, le=200_000)]
    converged_sigma_xy_m: Positive
    converged_sigma_theta_deg: Positive

    def __post_init__(self) -> None:
        lo, hi = self.ir_usable_counts
        if not 0 <= lo < hi:
            raise ConfigError(f"[{SECTION}.robust] 'ir_usable_counts' needs 0 <= low < high, "
                              f"got {[lo, hi]}")


#: The sub-tables of ``[localisation]``, each its own section.
_TABLES: dict[str, Any] = {
    "pose": PoseSettings, "grid": GridSettings, "occupancy": OccupancySettings,
    "robust": RobustSettings,
}


@section
class LocalisationSettings:
    """``[localisation]``: on/off, publication rates (simulation time), the prior."""

    enabled: Bool
    pose_rate_hz: Positive
    cell_rate_hz: Positive
    grid_rate_hz: Positive
    occupancy_rate_hz: Positive
    # () = the world's start; else (x_m, y_m, theta_deg)
    initial_pose: Annotated[FloatTuple, _sized(0, 3)]
    initial_sigma_xy_m: Positive
    initial_sigma_theta_deg: Positive
    grid_prior: Annotated[Str, one_of(GRID_PRIORS)]     # "start" | "uniform"
    use_landmarks: Bool
    pose: PoseSettings
    grid: GridSettings
    occupancy: OccupancySettings
    robust: RobustSettings

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> LocalisationSettings:
        s = SECTION
        if not isinstance(d, Mapping):
            raise ConfigError(f"[{s}] must be a table, got {d!r}")
        reject_unknown(d, field_names(cls), s)
        tables = {}
        for key, table_cls in _TABLES.items():
            if not isinstance(d.get(key), Mapping):
                raise ConfigError(f"[{s}.{key}] missing or not a table")
            tables[key] = validate(table_cls, d[key], f"{s}.{key}")
        return validate(cls, {**d, **tables}, s)

    @classmethod
    def from_config(cls, config: Mapping[str, Any]) -> LocalisationSettings | None:
        """The typed ``[localisation]`` section, or None when it is absent or disabled."""
        d = config.get(SECTION)
        if d is None:
            return None
        if not isinstance(d, Mapping):
            raise ConfigError(f"[{SECTION}] must be a table")
        settings = cls.from_dict(d)
        return settings if settings.enabled else None


# --------------------------------------------------------------------------- the node


@dataclass
class NodeCounters:
    """What the node took in and what it made of it (``status`` carries a copy)."""

    frames: dict[str, int] = field(default_factory=dict)       # decoded, per input kind
    rejected: dict[str, int] = field(default_factory=dict)     # undecodable, per bus
    odometry_resets: int = 0       # encoder counters set by a client (K-Team G) or a jump
    grid_moves: int = 0
    grid_observations: int = 0
    relocalisations: int = 0
    slip_steps: int = 0           # odometry steps predicted with the slip noise
    compass_disturbed: int = 0    # compass samples whose field strength says "not the Earth's"
    occupancy_scans: int = 0
    clock_restarts: int = 0
    hard_iron_uT: list[float] | None = None

    def took(self, kind: str) -> None:
        self.frames[kind] = self.frames.get(kind, 0) + 1

    def bad(self, bus: str, n: int = 1) -> None:
        if n:
            self.rejected[bus] = self.rejected.get(bus, 0) + n


class _HardIron:
    """Online hard-iron estimate: the horizontal field, binned by the EKF's heading, draws a circle
    centred on the offset (Kasa least-squares fit, as the coverage firmware's calibration turn)."""

    def __init__(self) -> None:
        self.bins: list[list[tuple[float, float]]] = [[] for _ in range(HARD_IRON_BINS)]

    def add(self, heading: float, mx: float, my: float) -> np.ndarray | None:
        k = int((heading + math.pi) / (2 * math.pi) * HARD_IRON_BINS) % HARD_IRON_BINS
        if len(self.bins[k]) < HARD_IRON_PER_BIN:
            self.bins[k].append((mx, my))
        if sum(1 for b in self.bins if b) < HARD_IRON_MIN_BINS:
            return None
        xy = np.array([p for b in self.bins for p in b])
        return np.array([*circle_centre(xy), 0.0])


class LocalisationNode:
    """Estimators fed with decoded bus frames; publishes ``estimate/*`` and ``map/occupancy``.

    Thread-safe: frames may come from several reader threads (a real robot's ports).

    Args:
        settings: the ``[localisation]`` section, typed.
        robot: the robot and its known map (``koala_bridge.sim.config.load_sim_config`` of the run's
            configuration: wheel base, ticks per metre, IR poses and response curve, sonar poses,
            the world's grid, walls, landmarks and magnetic north).
        publish: called with ``(key suffix, JSON-ready payload)`` for each output message.
        can_codec: decodes the CAN frames (the owner's, from ``[buses.can] dbc``); default: a
            codec of the shipped DBC.
        kteam_dialect: the dialect of the K-Team frames (the real robot's ``[real]
            kteam_dialect``); default: the classic Koala's.
    """

    def __init__(self, settings: LocalisationSettings, robot: SimConfig, publish: Publish,
                 can_codec: KoalaCanCodec | None = None, kteam_dialect: str = "koala1") -> None:
        self.settings = settings
        self.world: World = robot.world
        self._publish = publish
        self._lock = threading.Lock()
        self.counters = NodeCounters()
        r, ir, sonar = robot.robot, robot.sensors.ir, robot.sensors.sonar
        ps = settings.pose
        self.tracker = PoseTracker(PoseTrackerParams(
            wheel_base_m=r.wheel_base_m,
            ticks_per_metre=r.ticks_per_metre,
            odo_distance_var_per_m=ps.odo_distance_var_per_m,
            odo_heading_var_per_m=ps.odo_heading_var_per_m,
            odo_heading_var_per_rad=ps.odo_heading_var_per_rad,
            gyroscope_noise_density=ps.gyroscope_noise_density,
            gyroscope_random_walk=ps.gyroscope_random_walk,
            gyro_bias_sigma0=ps.gyro_bias_sigma0,
            gyro_timeout_s=ps.gyro_timeout_s,
            compass_sigma_rad=math.radians(ps.compass_sigma_deg),
            gate_probability=ps.gate_probability,
            process_noise_xy=ps.process_noise_xy_m ** 2,
            process_noise_theta=math.radians(ps.process_noise_theta_deg) ** 2,
        ))
        self._ticks_per_metre = r.ticks_per_metre
        self._max_wheel_speed = r.max_wheel_speed_mps
        x0, y0, th0 = self._initial_pose()
        sxy, sth = settings.initial_sigma_xy_m, math.radians(settings.initial_sigma_theta_deg)
        self.tracker.reset(x0, y0, th0, np.diag([sxy**2, sxy**2, sth**2]))
        g = settings.grid
        start = self._cell_at(x0, y0)
        self.grid = GridLocaliser(
            self.world, GridParams(g.p_move, g.p_hit, g.p_clear),
            start if settings.grid_prior == "start" else None,
        )
        self._cell = start            # the pose's cell the grid filter last moved to
        self._observed_visit = False  # a wall observation made since entering self._cell
        o = settings.occupancy
        cells = math.ceil(self.world.width_m / o.resolution_m) * math.ceil(
            self.world.height_m / o.resolution_m)
        if cells > MAX_OCCUPANCY_CELLS:  # a typo (1e-9) must not allocate the machine away
            raise ConfigError(
                f"[{SECTION}.occupancy] 'resolution_m' {o.resolution_m:g} makes {cells:.3g} cells "
                f"for this {self.world.width_m:g} x {self.world.height_m:g} m world; at most "
                f"{MAX_OCCUPANCY_CELLS} (use a coarser resolution)"
            )
        self.occupancy = OccupancyGrid.for_world(self.world, o.resolution_m, OccupancyParams(
            l_occ=o.l_occ, l_free=o.l_free, occ_share_cells=o.occ_share_cells, l_min=o.l_min,
            l_max=o.l_max, mark_free_on_no_echo=o.mark_free_on_no_echo,
        ))
        self._ir_poses = np.asarray(ir.poses, dtype=float)
        self._ir_curve = (np.asarray(ir.response_counts, dtype=float)[::-1],
                          np.asarray(ir.response_range_m, dtype=float)[::-1])
        self._ir_beam = BeamModel(math.radians(ir.aperture_deg), o.ir_range_error, ir.max_range_m)
        self._sonar_poses = np.asarray(sonar.poses, dtype=float)
        self._sonar_beam = BeamModel(math.radians(sonar.aperture_deg), o.sonar_range_error,
                                     sonar.max_range_m, sonar.min_range_m)
        self._landmarks = {lm.id: (lm.x, lm.y) for lm in self.world.landmarks}
        self._north = math.radians(self.world.earth_field.north_deg)
        self._earth_horizontal = abs(self.world.earth_field.horizontal_uT)
        hard = ps.compass_hard_iron_uT
        self._hard_iron: np.ndarray | None = (
            np.array([*hard, 0.0][:3]) if hard else None)
        self._hard_iron_fit = _HardIron() if not hard else None
        self._init_robust(settings.robust, robot)
        # decoders, one per bus (streams keep their partial frames)
        self._can = can_codec if can_codec is not None else KoalaCanCodec()
        self._mavlink = CompassDecoder()
        self._ranges = RangeFrameDecoder()
        self._kteam = LineSplitter()
        # its replies as the topic messages they are published as (koala1 n = IR counts, h =
        # counters; koala25 p = counters, n = gyro samples, @ = field, g = sonar)
        self._kteam_decoder = KteamReplyDecoder(dialect(kteam_dialect))
        # "ir", "odometry", "gyro", "compass", "sonar": a streaming source of it was seen
        self._streamed: set[str] = set()
        self._raw_ticks: tuple[int, int] | None = None
        self._ticks = (0, 0)                   # counters fed to the EKF (resets removed)
        self._odo_t: float | None = None
        self._odometry_id = self._can.frame_ids["WheelOdometry"]
        self._predict_period = 1.0 / ps.predict_rate_hz
        self._compass_period = 1.0 / ps.compass_rate_hz
        self._compass_t = -math.inf
        self._last_occupancy = -math.inf
        periods = {KEY_POSE: settings.pose_rate_hz, KEY_HEALTH: settings.robust.health_rate_hz,
                   KEY_CELL: settings.cell_rate_hz,
                   KEY_GRID: settings.grid_rate_hz, KEY_OCCUPANCY: settings.occupancy_rate_hz}
        self._period = {k: 1.0 / hz for k, hz in periods.items()}
        self._next = {k: -math.inf for k in periods}
        self._next_due = -math.inf
        self._last_t = -math.inf

    def _init_robust(self, rb: RobustSettings, robot: SimConfig) -> None:
        """Map ranges, slip and contact detection, health, relocalisation
        (docs/localisation.md "Robustness")."""
        self._rb = rb
        self.map_model = MapModel(self.world, corner_margin_m=rb.corner_margin_m)
        self._wheel_base = robot.robot.wheel_base_m
        ir, sonar = robot.sensors.ir, robot.sensors.sonar
        yaw = self._ir_poses[:, 2]               # SimConfig poses: radians
        self._ir_yaw_cos = np.cos(yaw)
        self._ir_rays = np.ascontiguousarray(np.vstack([self._ir_poses[:, 0], self._ir_poses[:, 1],
                                                        yaw]))
        self._ir_max = np.full(yaw.size, float(ir.max_range_m))
        self._contact_counts = float(np.interp(rb.contact_range_m, ir.response_range_m,
                                               ir.response_counts))
        k = rb.sonar_beam_rays
        half = 0.5 * math.radians(sonar.aperture_deg)
        offsets = np.linspace(-half, half, k) if k > 1 else np.zeros(1)
        syaw = self._sonar_poses[:, 2]
        self._sonar_rays = np.ascontiguousarray(np.vstack([
            np.repeat(self._sonar_poses[:, 0], k), np.repeat(self._sonar_poses[:, 1], k),
            (syaw[:, None] + offsets[None, :]).ravel()]))
        self._sonar_max = np.full(self._sonar_rays.shape[1], float(sonar.max_range_m))
        self._sonar_min = float(sonar.min_range_m)
        self._sonar_critical = math.radians(rb.sonar_critical_incidence_deg)
        self.health = HealthMonitor(HealthParams(
            window_s=rb.lost_window_s, lost_min_rejections=rb.lost_min_rejections,
            lost_reject_ratio=rb.lost_reject_ratio, disputed_ratio=rb.disputed_ratio,
            in_wall_s=rb.in_wall_s,
            absolute_window_s=rb.absolute_window_s,
            absolute_min_rejections=rb.absolute_min_rejections,
            uncertain_sigma_xy_m=rb.uncertain_sigma_xy_m,
            uncertain_sigma_theta=math.radians(rb.uncertain_sigma_theta_deg),
            no_fix_timeout_s=rb.no_fix_timeout_s))
        self.relocaliser = Relocaliser(self.map_model, RelocaliserParams(
            particles=rb.particles, body_radius_m=robot.robot.body_radius_m,
            converged_sigma_xy_m=rb.converged_sigma_xy_m,
            converged_sigma_theta=math.radians(rb.converged_sigma_theta_deg),
        )) if rb.relocalise else None
        self._body_radius = robot.robot.body_radius_m
        self._slip_terms: collections.deque[tuple[float, float, float]] = collections.deque()
        self._slip_until = -math.inf
        self._contact_until = -math.inf
        self._contact_sign = 0.0
        self._pushing_until = -math.inf
        self._last_ds = 0.0
        self._state: str = TRACKING
        self._reasons: list[str] = []
        self._compass_heading: float | None = None
        self._next_check = -math.inf

    def _restart_clock(self, t: float) -> None:
        """Time went backwards (the simulator was reset, e.g. a second ``run``, which puts the
        robot back at its start): restart every schedule from ``t``, the pose estimate from the
        initial pose and its prior (a relocalisation in progress is dropped, the health evidence
        forgotten), the grid from its prior. The occupancy map and the hard-iron offset carry
        on (same world, same robot); the encoder counters' jump back to 0 is taken as a client
        reset (:meth:`_odometry`)."""
        log.info("localisation: time went back from %.3f to %.3f s; schedules restarted",
                 self._last_t, t)
        self._next = dict.fromkeys(self._next, -math.inf)
        self._next_check = -math.inf
        self._next_due = -math.inf
        self._odo_t = None
        self._compass_t = -math.inf
        self._last_occupancy = -math.inf
        self._reset_pose(t)
        self.counters.clock_restarts += 1

    def _reset_pose(self, t: float) -> None:
        """The pose estimate, grid and health as at the start (``_restart_clock``)."""
        s = self.settings
        x0, y0, th0 = self._initial_pose()
        sxy, sth = s.initial_sigma_xy_m, math.radians(s.initial_sigma_theta_deg)
        self.tracker.reset(x0, y0, th0, np.diag([sxy**2, sxy**2, sth**2]), t=t)
        start = self._cell_at(x0, y0)
        g = s.grid
        self.grid = GridLocaliser(self.world, GridParams(g.p_move, g.p_hit, g.p_clear),
                                  start if s.grid_prior == "start" else None)
        self._cell = start
        self._observed_visit = False
        if self.relocaliser is not None:
            self.relocaliser.stop()
        self.health.reset(t)
        self._slip_terms.clear()
        self._slip_until = self._contact_until = self._pushing_until = -math.inf
        self._last_ds = 0.0
        self._state, self._reasons = TRACKING, []

    def _now(self, t: float) -> None:
        if t < self._last_t - 0.5:
            self._restart_clock(t)
        self._last_t = t

    @classmethod
    def from_config(cls, config: Mapping[str, Any], robot: SimConfig, publish: Publish,
                    can_codec: KoalaCanCodec | None = None,
                    kteam_dialect: str = "koala1") -> LocalisationNode | None:
        """A node for ``config``'s ``[localisation]`` section, or None when it is off.
        ``can_codec``: the owner's (its ``[buses.can] dbc``); default: the shipped DBC.
        ``kteam_dialect``: what the K-Team serial link speaks (its replies are read by it)."""
        settings = LocalisationSettings.from_config(config)
        if settings is None:
            return None
        return cls(settings, robot, publish, can_codec, kteam_dialect=kteam_dialect)

    def _initial_pose(self) -> tuple[float, float, float]:
        p = self.settings.initial_pose
        if p:
            return p[0], p[1], math.radians(p[2])
        start = self.world.start
        if start is None:
            raise ConfigError(f"[{SECTION}] 'initial_pose' = [] needs a world with a start pose")
        return start.x, start.y, start.theta

    def _cell_at(self, x: float, y: float) -> tuple[int, int]:
        col, row = self.world.cell_of(x, y)
        return (min(max(col, 0), self.world.cols - 1), min(max(row, 0), self.world.rows - 1))

    # -- input ---------------------------------------------------------------------------

    def on_frame(self, bus: str, direction: str, t: float, data: bytes, **fields: object) -> None:
        """One raw frame seen on ``bus`` (a recorder's ``record_frame`` shape). Only what the
        robot sends (``from_robot``) is used; CAN frames carry ``can_id``/``extended``."""
        if direction != FROM_ROBOT:
            return
        with self._lock:
            self._now(t)
            if bus == "can":
                self._on_can(t, data, fields)
            elif bus == "mavlink":
                self._on_mavlink(t, data)
            elif bus == "serial/rangefinders":
                self._on_ranges(t, data)
            elif bus == "serial/kteam":
                self._on_kteam(t, data)
            self._maybe_publish(t)

    def on_camera(self, t: float, observations: Sequence[Any]) -> None:
        """Landmark observations (objects with ``id``, ``range`` m, ``bearing`` rad CCW from the
        heading): the simulator's measured camera reading, which has no bus."""
        if not self.settings.use_landmarks:
            return
        ps = self.settings.pose
        with self._lock:
            self._now(t)
            for ob in observations:
                xy = self._landmarks.get(int(ob.id))
                if xy is None or not (math.isfinite(ob.range) and math.isfinite(ob.bearing)):
                    continue
                bias, sr = self._landmark_range_error(ob.range)
                r = ob.range - bias
                sb = math.radians(ps.landmark_bearing_sigma_deg)
                ok = self.tracker.on_landmark(t, xy, r, ob.bearing, sr, sb)
                self.health.evidence(t, int(ok), int(not ok))
                self.health.absolute(t, ok)
                if self.relocaliser is not None and self.relocaliser.active:
                    self.relocaliser.on_landmark(xy[0], xy[1], r, ob.bearing, sr, sb)
                self.counters.took("landmark")
            self._maybe_publish(t)

    def _landmark_range_error(self, d: float) -> tuple[float, float]:
        """Mean and standard deviation of a camera range error at distance ``d`` (m).

        seeds/000 eq. 10-12 as docs/models.md reads them: ``d_est = d + eps_near N(0,1) +
        eps_far |N(0,1)|`` with ``eps_near = rel d`` and ``eps_far = rel d_mid 2^((d - d_mid) /
        doubling)`` -- the far term is one-sided (stereo over-estimates far ranges), so its mean
        ``eps_far sqrt(2/pi)`` is a bias the estimator removes, and the rest is the variance
        ``eps_near^2 + eps_far^2 (1 - 2/pi)``; ``landmark_range_sigma_m`` adds in quadrature
        (``rel`` = ``landmark_range_sigma_rel``, ``d_mid`` = ``landmark_far_from_m``, ``doubling``
        = ``landmark_far_doubling_m``: the camera's dist, d_mid_m and far_doubling_m)."""
        ps = self.settings.pose
        doublings = min((d - ps.landmark_far_from_m) / ps.landmark_far_doubling_m, MAX_DOUBLINGS)
        far = ps.landmark_range_sigma_rel * ps.landmark_far_from_m * 2.0 ** doublings
        near = ps.landmark_range_sigma_rel * d
        sigma = math.sqrt(ps.landmark_range_sigma_m ** 2 + near * near
                          + far * far * (1.0 - 2.0 / math.pi))
        return far * math.sqrt(2.0 / math.pi), sigma

    def _on_can(self, t: float, data: bytes, fields: Mapping[str, object]) -> None:
        can_id = fields.get("can_id")
        if not isinstance(can_id, int):
            self.counters.bad("can")
            return
        # The counters are cumulative: a frame between two predictions carries nothing the next
        # one does not, so it is not even decoded (predict_rate_hz; the heavy part is cantools).
        if can_id == self._odometry_id and self._odo_t is not None \
                and t - self._odo_t < self._predict_period - 1e-9:
            return
        frame = self._can.decode_data(can_id, bytes(data), bool(fields.get("extended", False)))
        if isinstance(frame, WheelOdometryFrame):
            self._streamed.add("odometry")
            self._odometry(t, frame.left_ticks, frame.right_ticks)
        elif isinstance(frame, GyroFrame):
            self._streamed.add("gyro")
            self.counters.took("gyro")
            self.tracker.on_gyro(t, frame.yaw_rate)
        else:  # a Reject, or a MotorCommand (not the robot's)
            self.counters.bad("can")

    def _on_mavlink(self, t: float, data: bytes) -> None:
        before = self._mavlink.rejected
        for m in self._mavlink.feed(data):
            if isinstance(m, CompassSample):
                self._streamed.add("compass")
                self._compass(t, m.x_ut, m.y_ut, m.z_ut)
        self.counters.bad("mavlink", self._mavlink.rejected - before)

    def _on_ranges(self, t: float, data: bytes) -> None:
        before = self._ranges.rejected
        for f in self._ranges.feed(data):
            if f.kind == RangeKind.IR:
                self._streamed.add("ir")
                self._ir(t, np.asarray(f.readings, dtype=float))
            else:
                self._streamed.add("sonar")
                self._sonar(t, f.readings)
        self.counters.bad("serial/rangefinders", self._ranges.rejected - before)

    def _on_kteam(self, t: float, data: bytes) -> None:
        for line in self._kteam.feed(data):
            reply = (self._kteam_decoder.dialect.parse_reply(line) if isinstance(line, bytes)
                     else None)
            if not isinstance(reply, KteamReply):
                continue
            for m in self._kteam_decoder.messages(t, reply):
                if isinstance(m, IrMessage) and "ir" not in self._streamed \
                        and len(m.counts) == len(self._ir_poses):
                    self._ir(t, np.asarray(m.counts, dtype=float))
                elif isinstance(m, OdometryMessage) and "odometry" not in self._streamed:
                    self._odometry(t, m.left_ticks, m.right_ticks)
                elif isinstance(m, GyroMessage) and "gyro" not in self._streamed:
                    self.counters.took("gyro")
                    self.tracker.on_gyro(m.t, m.yaw_rate)
                elif isinstance(m, CompassMessage) and "compass" not in self._streamed:
                    self._compass(t, m.mx, m.my, m.mz)
                elif isinstance(m, SonarMessage) and "sonar" not in self._streamed:
                    # as the range frames carry them: mm, NO_ECHO for none
                    self._sonar(t, [NO_ECHO if r is None else round(r * 1000.0)
                                    for r in m.ranges])

    # -- estimators ----------------------------------------------------------------------

    def _odometry(self, t: float, left: int, right: int) -> None:
        """Cumulative counters -> the EKF, with client resets (K-Team ``G``) and int32 wraps
        removed: a step the wheels cannot have made in the time is a reset, not a motion."""
        self.counters.took("odometry")
        if self._raw_ticks is None:
            self._raw_ticks = (left, right)
            self._odo_t = t
            self.tracker.on_odometry(t, *self._ticks)
            return
        dl = wrap_int32(left - self._raw_ticks[0])
        dr = wrap_int32(right - self._raw_ticks[1])
        dt = max(t - (self._odo_t if self._odo_t is not None else t), 0.01)
        # (after a clock restart _odo_t is None: the first step is judged over one 10 ms step)
        limit = (2.0 * self._max_wheel_speed * dt + 0.01) * self._ticks_per_metre
        self._raw_ticks = (left, right)
        self._odo_t = t
        if abs(dl) > limit or abs(dr) > limit:
            self.counters.odometry_resets += 1
            dl = dr = 0
        self._ticks = (self._ticks[0] + dl, self._ticks[1] + dr)
        slipping = self._slip_check(t, dl / self._ticks_per_metre, dr / self._ticks_per_metre)
        rb = self._rb
        self._map_contact(t, 0.5 * (dl + dr))
        # contact holds while the wheels keep driving the same way (backing off a wall is free)
        contact = t < self._contact_until and (dl + dr) * self._contact_sign > 0
        widen = slipping or contact
        if widen:
            self.counters.slip_steps += 1
        # Slip or contact: the encoders' distance is uncertain. In contact the robot may be
        # pushing against a wall, so it realises only part of it (the mean is scaled): an IR
        # sensor near a wall says "perhaps blocked" (a robot backing past a wall's end reads it
        # and moves on), the map with a sure estimate says "pushing into it": a stall, whose
        # wheels spin in place. A slip seen by the gyro alone (one wheel) says nothing about
        # the mean.
        scale = 1.0
        if contact:
            scale = (rb.push_distance_scale if t < self._pushing_until
                     else rb.slip_distance_scale)
        self.tracker.on_odometry(t, *self._ticks,
                                 slip_sigma_rel=rb.slip_sigma_rel if widen else 0.0,
                                 slip_distance_scale=scale)
        if widen:
            self._out_of_walls()
        ds, dth, sds, sdth = self.tracker.last_increment
        self._last_ds = ds
        if self.relocaliser is not None and self.relocaliser.active:
            self.relocaliser.predict(ds, dth, sds, sdth)
        self._check_consistency(t)
        self._follow_cells()

    def _map_contact(self, t: float, ds: float) -> None:
        """Wall contact from the map: the estimated body touches a wall (within
        ``MAP_CONTACT_GAP_M``), the position is known to better than ``contact_range_m``, and
        the encoders drive it towards that wall (even at a glancing angle, where no
        IR sensor faces the motion) -- the robot cannot be moving as the encoders say."""
        if ds == 0.0:
            return
        x, y, th = self.tracker.pose
        P = self.tracker.P
        reach = self._rb.contact_range_m
        # (only when the estimate is sure to within that range: dead reckoning that merely
        # believes itself near a wall is no evidence of contact)
        if max(P[0, 0], P[1, 1]) > reach * reach:
            return
        # the raster field first (a lookup; its error is under two cells): the exact distance to
        # every segment only when the body may touch
        near = self._body_radius + MAP_CONTACT_GAP_M + 2 * self.map_model.resolution_m
        if self.map_model.clearance(x, y) > near:
            return
        clearance, gx, gy = self.map_model.nearest_wall(x, y)
        if clearance > self._body_radius + MAP_CONTACT_GAP_M:
            return
        direction = math.copysign(1.0, ds)
        into = -direction * (math.cos(th) * gx + math.sin(th) * gy)
        if into > MAP_CONTACT_COS:
            self._contact_until = t + self._rb.slip_hold_s
            self._contact_sign = direction
            if into > MAP_PUSH_COS:
                self._pushing_until = self._contact_until

    def _out_of_walls(self) -> None:
        """In contact the robot touches a wall and cannot be inside it: an estimate whose body
        overlaps the wall (the encoders drove it there) is moved straight out, to touching (the
        map as a constraint, exact distances; the covariance is left as the prediction made
        it)."""
        x = self.tracker.x
        clearance, gx, gy = self.map_model.nearest_wall(float(x[0]), float(x[1]))
        overlap = self._body_radius - clearance
        if 0.0 < overlap < self._body_radius:
            x[0] += overlap * gx
            x[1] += overlap * gy

    def _slip_check(self, t: float, d_left: float, d_right: float) -> bool:
        """Wheel slip: over ``slip_window_s`` the heading change the encoders report differs from
        the gyro's by more than ``slip_gate_sigmas`` of their joint noise (the EKF's own
        variances: encoder heading per metre and per radian, gyro white noise over the time).
        Held for ``slip_hold_s``. A slip that turns both wheels alike (pushing straight into a
        wall) does not show here; the IR contact test catches that."""
        rb, ps = self._rb, self.settings.pose
        pending = self.tracker.pending_gyro(t)
        if pending is not None:
            gyro_dth, span = pending
            ds = 0.5 * (d_left + d_right)
            enc_dth = (d_right - d_left) / self._wheel_base
            var = (ps.odo_heading_var_per_m * abs(ds) + ps.odo_heading_var_per_rad * abs(enc_dth)
                   + ps.gyroscope_noise_density ** 2 * span)
            self._slip_terms.append((t, enc_dth - gyro_dth, var))
        terms = self._slip_terms
        while terms and terms[0][0] <= t - rb.slip_window_s:
            terms.popleft()
        if terms:
            d = sum(e for _, e, _ in terms)
            v = sum(w for _, _, w in terms)
            if d * d > rb.slip_gate_sigmas ** 2 * v:
                self._slip_until = t + rb.slip_hold_s
        return t < self._slip_until

    def _check_consistency(self, t: float) -> None:
        """After a prediction, every ``CHECK_PERIOD_S``: is the estimated body in a wall, does
        the evidence contradict the estimate (start relocalising), has the relocaliser converged
        (restart the EKF)?"""
        if t < self._next_check - 1e-9:
            return
        self._next_check = t + CHECK_PERIOD_S
        x, y, _ = self.tracker.pose
        P = self.tracker.P
        margin = max(IN_WALL_MARGIN_M, 3.0 * math.sqrt(max(P[0, 0], P[1, 1])))
        self.health.body_in_wall(t, self.map_model.clearance(x, y) < self._body_radius - margin)
        reloc = self.relocaliser
        if reloc is not None and reloc.active:
            if reloc.converged:
                mean, cov = reloc.estimate()
                self.tracker.reset(float(mean[0]), float(mean[1]), float(mean[2]), cov, t=t,
                                   gyro_bias=self.tracker.gyro_bias, keep_bias_cov=True)
                reloc.stop()
                self.health.reset(t)
                self.counters.relocalisations += 1
                log.info("localisation: relocalised at t=%.2f s to (%.2f, %.2f, %.0f deg)", t,
                         mean[0], mean[1], math.degrees(mean[2]))
                self._set_state(t, TRACKING, [])
            return
        reasons = self.health.inconsistent(t)
        if not reasons:
            return
        if reloc is None:
            self._set_state(t, LOST, reasons)
            return
        # Headings: around the compass's (a kidnap may turn the robot), or any heading while the
        # compass has no hard-iron offset yet.
        self._set_state(t, LOST, reasons)
        reloc.start(x, y, self.tracker.pose[2], self._compass_heading)
        self._set_state(t, RELOCALISING, reasons)

    def _set_state(self, t: float, state: str, reasons: list[str]) -> None:
        changed = state != self._state
        self._state, self._reasons = state, list(reasons)
        if changed:
            if state in (LOST, RELOCALISING):
                log.warning("localisation: %s at t=%.2f s (%s)", state, t, ", ".join(reasons))
            self._publish(KEY_HEALTH, self._health_message(t))

    def _compass(self, t: float, mx: float, my: float, mz: float) -> None:
        self.counters.took("compass")
        if self._hard_iron is None:
            # every sample goes to the online fit (the EKF gets the compass at compass_rate_hz,
            # which would leave a turn on the spot with too few samples to fill the bins)
            assert self._hard_iron_fit is not None
            self._hard_iron = self._hard_iron_fit.add(self.tracker.pose[2], mx, my)
            if self._hard_iron is None:
                return
            self.counters.hard_iron_uT = [round(float(v), 3) for v in self._hard_iron]
            log.info("localisation: hard-iron offset %s uT (online fit)", self._hard_iron[:2])
        # A local magnetic disturbance (a radiator, steel in the floor) bends the heading and
        # changes the field's strength: a horizontal field off the Earth's by more than
        # compass_field_tolerance is not a heading (the standard magnetic-disturbance test).
        hx, hy = mx - float(self._hard_iron[0]), my - float(self._hard_iron[1])
        if abs(math.hypot(hx, hy) - self._earth_horizontal) \
                > self.settings.pose.compass_field_tolerance * self._earth_horizontal:
            self.counters.compass_disturbed += 1
            self._compass_heading = None
            return
        # Every sample: the latest heading starts a relocalisation (a turning robot's heading of
        # a second ago is no prior), and while relocalising it is what tells mirror-image places
        # of a symmetric map apart (sigma widened: its errors are correlated).
        heading = heading_from_field((mx, my, mz), self._north, self._hard_iron)
        self._compass_heading = heading
        reloc = self.relocaliser
        if reloc is not None and reloc.active:
            reloc.on_heading(heading, 3.0 * self.tracker.params.compass_sigma_rad)
        if t - self._compass_t < self._compass_period - 1e-9:
            return
        self._compass_t = t
        self.health.absolute(t, self.tracker.on_compass(t, heading))

    def _ir(self, t: float, counts: np.ndarray) -> None:
        self.counters.took("ir")
        rb = self._rb
        # Wall contact: a sensor facing the direction of travel reads a wall within
        # contact_range_m (seeds/003: the Koala's IR is its bumper).
        if self._last_ds != 0.0:
            facing = self._ir_yaw_cos * math.copysign(1.0, self._last_ds) > CONTACT_FACING_COS
            if np.any(facing & (counts >= self._contact_counts)):
                self._contact_until = t + rb.slip_hold_s
                self._contact_sign = math.copysign(1.0, self._last_ds)
        if rb.ir_ranges:
            lo, hi = rb.ir_usable_counts
            usable = (counts >= lo) & (counts < hi)
            if usable.any():
                r = np.interp(counts, *self._ir_curve)
                sigma = rb.ir_range_sigma_m + rb.ir_range_sigma_rel * r
                self._map_ranges("ir", t, usable, r, sigma, self._ir_rays, self._ir_max, 1,
                                 math.pi / 2)
        x, y, th = self.tracker.pose
        cx, cy = self.world.cell_centre(*self._cell)
        g = self.settings.grid
        if not self._observed_visit and math.hypot(x - cx, y - cy) <= g.observe_radius_m:
            self._observed_visit = True
            walls = walls_from_ir(counts, th, self._ir_poses, g.ir_wall_threshold_counts,
                                  cell_m=self.world.cell_m)
            self.grid.observe(walls)
            self.counters.grid_observations += 1
        o = self.settings.occupancy
        if o.ir and t - self._last_occupancy >= 1.0 / o.update_hz:
            self._last_occupancy = t
            ranges = np.where(counts < o.ir_no_echo_counts, np.inf,
                              np.interp(counts, *self._ir_curve))
            self.occupancy.integrate_scan(self.tracker.pose, self._ir_poses, ranges,
                                          self._ir_beam)
            self.counters.occupancy_scans += 1

    def _map_ranges(self, kind: str, t: float, usable: np.ndarray, z: np.ndarray,
                    sigma: np.ndarray, rays: np.ndarray, max_range: np.ndarray, beams: int,
                    critical: float) -> None:
        """Readings of one ring against the map: the EKF update of the readings whose expected
        range is usable, each gated; the evidence to the health monitor (a reading of a wall
        where the map has none within the sensor's range counts as rejected); the readings to
        the relocaliser when it runs."""
        reloc = self.relocaliser
        if reloc is not None and reloc.active:
            axis = rays[:, beams // 2::beams]     # each sensor's middle ray: its axis
            reloc.on_ranges(np.ascontiguousarray(axis.T)[usable], z[usable], sigma[usable])
        hits = self.map_model.expected(self.tracker.pose, rays, max_range, beams, critical)
        idx: list[int] = []
        expected: list[RangeHit] = []
        unexplained = 0
        for i in np.flatnonzero(usable):
            h = hits[i]
            if h is None:
                continue
            if not math.isfinite(h.r):
                unexplained += 1
                continue
            idx.append(int(i))
            expected.append(h)
        accepted = 0
        if idx:
            ok = self.tracker.on_ranges(t, kind, z[idx], [h.r for h in expected],
                                        [h.H for h in expected], sigma[idx])
            accepted = int(ok.sum())
        self.health.evidence(t, accepted, len(idx) - accepted + unexplained)

    def _sonar(self, t: float, readings: Sequence[int]) -> None:
        self.counters.took("sonar")
        ranges = np.array([np.inf if v == NO_ECHO else v / 1000.0 for v in readings])
        if ranges.size != len(self._sonar_poses):
            return
        rb = self._rb
        if rb.sonar_ranges:
            usable = np.isfinite(ranges) & (ranges >= self._sonar_min) \
                & (ranges < self._sonar_max[0])
            if usable.any():
                sigma = rb.sonar_range_sigma_m + rb.sonar_range_sigma_rel * np.where(
                    usable, ranges, 0.0)
                self._map_ranges("sonar", t, usable, np.where(usable, ranges, 0.0), sigma,
                                 self._sonar_rays, self._sonar_max, rb.sonar_beam_rays,
                                 self._sonar_critical)
        if self.settings.occupancy.sonar:
            self.occupancy.integrate_scan(self.tracker.pose, self._sonar_poses, ranges,
                                          self._sonar_beam)

    def _follow_cells(self) -> None:
        """Grid moves from the pose: entering a neighbouring cell by ``move_hysteresis_m`` past
        the boundary is a move to that side (a jump of several cells, several moves)."""
        x, y, _ = self.tracker.pose
        w = self.world
        col, row = self._cell
        h = self.settings.grid.move_hysteresis_m
        x0, y0 = col * w.cell_m, row * w.cell_m
        side = None
        if x >= x0 + w.cell_m + h and col + 1 < w.cols:
            side = "E"
        elif x <= x0 - h and col > 0:
            side = "W"
        elif y >= y0 + w.cell_m + h and row + 1 < w.rows:
            side = "N"
        elif y <= y0 - h and row > 0:
            side = "S"
        if side is None:
            return
        self.grid.move(side)
        self.counters.grid_moves += 1
        dc, dr = SIDE_STEP[side]
        self._cell = (col + dc, row + dr)
        self._observed_visit = False
        self._follow_cells()  # the other axis, or a jump of more than one cell

    # -- output --------------------------------------------------------------------------

    def _maybe_publish(self, t: float) -> None:
        # On a fixed schedule in the frames' time (no drift from frame spacing; no catch-up
        # burst after a gap).
        if t < self._next_due - 1e-9:  # the common case: nothing due (every frame asks)
            return
        due = [k for k, nxt in self._next.items() if t >= nxt - 1e-9]
        for key in due:
            nxt = self._next[key] + self._period[key]
            self._next[key] = nxt if nxt > t else t + self._period[key]
            self._publish(key, self._message(key, t))
        self._next_due = min(self._next.values())

    def _health_message(self, t: float) -> dict[str, Any]:
        x, cov = self._estimate()
        state, reasons = self._state, self._reasons
        if state == TRACKING:  # the EKF runs: tracking or uncertain (or lost, seen first here)
            state, reasons = self.health.assess(
                t, math.sqrt(max(cov[0, 0], cov[1, 1])), math.sqrt(cov[2, 2]),
                t < self._slip_until, t < self._contact_until)
        accepted, rejected = self.health.counts()
        return health_message(t, state, reasons, math.sqrt(max(cov[0, 0], cov[1, 1])),
                              math.degrees(math.sqrt(cov[2, 2])), accepted, rejected,
                              self.counters.relocalisations)

    def _estimate(self) -> tuple[np.ndarray, np.ndarray]:
        """The published pose and covariance: the relocaliser's while it runs, else the EKF's."""
        if self.relocaliser is not None and self.relocaliser.active:
            return self.relocaliser.estimate()
        return np.array(self.tracker.pose), self.tracker.pose_cov

    def _message(self, key: str, t: float) -> dict[str, Any]:
        if key == KEY_POSE:
            x, cov = self._estimate()
            return pose_message(t, float(x[0]), float(x[1]), float(x[2]), cov)
        if key == KEY_HEALTH:
            return self._health_message(t)
        if key == KEY_CELL:
            cell = self.grid.guess()
            return cell_message(t, cell, self.grid.probability(cell))
        if key == KEY_GRID:
            return grid_message(t, self.grid.probabilities(), self.world.cell_m)
        o = self.settings.occupancy
        return occupancy_message(t, self.occupancy.log_odds, self.occupancy.resolution_m, o.l_max)

    def snapshot(self) -> dict[str, Any]:
        """Counters for ``status`` (JSON-ready)."""
        with self._lock:
            c = self.counters
            return {
                "frames": dict(c.frames),
                "rejected": dict(c.rejected),
                "gated_out": dict(self.tracker.counters.rejected),
                "odometry_resets": c.odometry_resets,
                "grid_moves": c.grid_moves,
                "grid_observations": c.grid_observations,
                "relocalisations": c.relocalisations,
                "slip_steps": c.slip_steps,
                "compass_disturbed": c.compass_disturbed,
                "health": {"state": self._state, "reasons": list(self._reasons)},
                "occupancy_scans": c.occupancy_scans,
                "clock_restarts": c.clock_restarts,
                "hard_iron_uT": c.hard_iron_uT,
            }
