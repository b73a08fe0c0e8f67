"""The bridge's messages as Foxglove standard-schema messages: what the 3D, map, plot and log
panels of Foxglove draw with no set-up (docs/foxglove.md).

A :class:`SceneTranslator` is a pure function of the ``world`` answer (the world and the robot's
description, :class:`core.topics.WorldMessage`) and of each published message (the Zenoh key
below the prefix, its simulation time and its JSON payload): it holds no clock, no socket and no
state that a message changes. The live server and the recording (:mod:`runtime.foxglove_io`) are
fed by the same translator, so a recording opened in Foxglove shows what the live view showed.

Frames (Foxglove's frame tree; FLU body frame, world x east / y north, z up):

- ``world`` -- the map's frame, origin at the grid's south-west corner;
- ``<robot>/base_link`` -- the robot where it truly is (``truth/pose``);
- ``<robot>/estimate`` -- where the localisation node thinks it is (``estimate/pose``).

Topics: the world's (shared by every robot) under ``/world``, each robot's under
``/<robot name>`` (:class:`SceneTopics`; a robot of ``[[robots]]``: ``/<robot name>/scene``),
so that several robots share one server and one recording:

=================================  ==================  ===========================================
topic                              schema              from
=================================  ==================  ===========================================
``/world/map``                     SceneUpdate         walls, blocked cells, landmarks, magnets
``/world/grid``                    Grid                the world's blocked cells (1) and free (0)
``/<r>/body``                      SceneUpdate         the robot's body, in ``<r>/base_link``
``/<r>/truth/tf``                  FrameTransform      ``truth/pose``: world -> ``<r>/base_link``
``/<r>/truth/pose``                PoseInFrame         ``truth/pose``
``/<r>/estimate/tf``               FrameTransform      ``estimate/pose``: world -> ``<r>/estimate``
``/<r>/estimate/pose``             PoseInFrame         ``estimate/pose``
``/<r>/estimate/odometry``         Odometry            ``estimate/pose`` with its covariance
``/<r>/estimate/uncertainty``      SceneUpdate         the 2-sigma ellipse of ``estimate/pose``
``/<r>/estimate/grid``             Grid                ``estimate/grid``: the grid belief ``p``
``/<r>/map/occupancy``             Grid                ``map/occupancy``: ``p_occupied``
``/<r>/sensors/ir``                SceneUpdate         IR beams coloured by their counts
``/<r>/sensors/sonar``             SceneUpdate         sonar cones as long as their echo
``/<r>/sensors/sonar/scan``        PointCloud          sonar echoes, ``x y z range`` float32
``/<r>/sensors/camera``            SceneUpdate         a line to each landmark detection
``/<r>/sensors/compass``           SceneUpdate         the horizontal field, 1 cm per uT
``/<r>/log``                       Log                 ``status`` (bus counters), ``events/fault``
=================================  ==================  ===========================================

Every message's ``timestamp`` and log time is the simulation time (s -> ns, as the recording's).
"""

from __future__ import annotations

import base64
import math
import struct
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from foxglove.messages import (
    ArrowPrimitive,
    Color,
    CubePrimitive,
    CylinderPrimitive,
    FrameTransform,
    Grid,
    LinePrimitive,
    LinePrimitiveLineType,
    Log,
    LogLevel,
    Odometry,
    PackedElementField,
    PackedElementFieldNumericType,
    Point3,
    PointCloud,
    Pose,
    PoseInFrame,
    Quaternion,
    SceneEntity,
    SceneUpdate,
    SpherePrimitive,
    TextPrimitive,
    Timestamp,
    TriangleListPrimitive,
    Vector2,
    Vector3,
)

__all__ = ["WORLD_FRAME", "Output", "SceneTopics", "SceneTranslator", "quaternion_yaw"]

WORLD_FRAME = "world"
MAP_TOPIC = "/world/map"
GRID_TOPIC = "/world/grid"
WALL_HEIGHT_M = 0.15          # drawn height of a wall (the world is 2-D)
WALL_THICKNESS_M = 0.02
COMPASS_M_PER_UT = 0.01       # the compass arrow's length per microtesla of horizontal field
SIGMAS = 2.0                  # the uncertainty ellipse's half-axes in standard deviations

#: A Foxglove message of :mod:`foxglove.messages` (each has ``encode()`` and ``get_schema()``).
FoxgloveMessage = Any
#: ``build(t, payload)``: the message for one published payload, or None (nothing to draw).
Build = Callable[[float, Mapping[str, Any]], FoxgloveMessage | None]

_FLOAT32 = PackedElementFieldNumericType.Float32
_UINT8 = PackedElementFieldNumericType.Uint8


@dataclass(frozen=True)
class Output:
    """One Foxglove topic made from one of the bridge's keys."""

    topic: str
    schema: type  # a foxglove.messages class
    build: Build


@dataclass(frozen=True)
class SceneTopics:
    """The topic and frame names of one robot (``robot``: its ``[robot] name``). Its topics are
    under ``namespace``, by default ``/<robot>``; a robot of ``[[robots]]`` has its scene under
    ``/<robot>/scene`` (its recording's JSON channels are ``/<robot>/<key>`` already)."""

    robot: str
    namespace: str = ""

    def topic(self, suffix: str) -> str:
        return f"{self.namespace or '/' + self.robot}/{suffix}"

    @property
    def base_frame(self) -> str:
        return f"{self.robot}/base_link"

    @property
    def estimate_frame(self) -> str:
        return f"{self.robot}/estimate"


# -- small builders ----------------------------------------------------------------------------

def timestamp(t: float) -> Timestamp:
    """Simulation seconds as a Foxglove timestamp (never negative)."""
    ns = max(0, round(t * 1e9))
    return Timestamp(ns // 1_000_000_000, ns % 1_000_000_000)


def quaternion_yaw(theta: float) -> Quaternion:
    """A rotation of ``theta`` rad about +z (CCW seen from above)."""
    return Quaternion(x=0.0, y=0.0, z=math.sin(theta / 2.0), w=math.cos(theta / 2.0))


def pose2d(x: float, y: float, theta: float = 0.0, z: float = 0.0) -> Pose:
    return Pose(position=Vector3(x=x, y=y, z=z), orientation=quaternion_yaw(theta))


def _rgba(r: float, g: float, b: float, a: float = 1.0) -> Color:
    return Color(r=r, g=g, b=b, a=a)


_COLOURS = {
    "red": (0.9, 0.1, 0.1), "green": (0.1, 0.75, 0.2), "blue": (0.15, 0.3, 0.95),
    "yellow": (0.95, 0.85, 0.1), "white": (1.0, 1.0, 1.0), "black": (0.1, 0.1, 0.1),
    "orange": (1.0, 0.55, 0.0), "magenta": (0.9, 0.1, 0.9), "cyan": (0.1, 0.85, 0.9),
}
WALL_COLOUR = _rgba(0.55, 0.55, 0.6)
BLOCKED_COLOUR = _rgba(0.35, 0.35, 0.4)


def _named_colour(name: str, a: float = 1.0) -> Color:
    return _rgba(*_COLOURS.get(name.lower(), (0.8, 0.8, 0.8)), a)


def _entity(t: float, frame: str, ident: str, **primitives: Any) -> SceneEntity:
    return SceneEntity(timestamp=timestamp(t), frame_id=frame, id=ident, **primitives)


def _pose_xytheta(payload: Mapping[str, Any]) -> tuple[float, float, float] | None:
    x, y, th = payload.get("x"), payload.get("y"), payload.get("theta")
    if x is None or y is None or th is None:
        return None
    return float(x), float(y), float(th)


def _sensor_poses(robot: Mapping[str, Any], sensor: str) -> list[tuple[float, float, float]]:
    s = (robot.get("sensors") or {}).get(sensor) or {}
    return [(float(p["x"]), float(p["y"]), float(p["theta"])) for p in s.get("poses", ())]


# -- the translator ----------------------------------------------------------------------------

class SceneTranslator:
    """The Foxglove messages of one robot's published messages (see the module table).

    Args:
        world: the ``world`` answer (:class:`core.topics.WorldMessage` as JSON), with ``robot``.
        robot: the robot's name (its frames' prefix, and its topics' unless ``namespace``); by
            default the description's ``name``.
        namespace: the robot's topics' prefix (``/alpha/scene``); by default ``/<robot>``.
        world_topics: whether it draws the world's topics (``/world/map``, ``/world/grid``):
            several robots on one server or in one recording share them, drawn by one robot.
    """

    def __init__(self, world: Mapping[str, Any], robot: str | None = None, *,
                 namespace: str = "", world_topics: bool = True) -> None:
        self.world = world
        self.robot_description: Mapping[str, Any] = world.get("robot") or {}
        self.names = SceneTopics(robot or str(self.robot_description.get("name") or "koala"),
                                 namespace)
        self.world_topics = world_topics
        sensors = self.robot_description.get("sensors") or {}
        self._ir = _sensor_poses(self.robot_description, "ir")
        self._ir_range = float((sensors.get("ir") or {}).get("max_range_m", 0.25))
        self._sonar = _sensor_poses(self.robot_description, "sonar")
        sonar = sensors.get("sonar") or {}
        self._sonar_range = float(sonar.get("max_range_m", 2.5))
        self._sonar_half = 0.5 * float(sonar.get("aperture_rad", 0.4))
        # the beams do not move in the body frame: their ends and 64 shades, made once
        self._ir_points = [
            p for x, y, th in self._ir
            for p in (Point3(x=x, y=y, z=0.12),
                      Point3(x=x + self._ir_range * math.cos(th),
                             y=y + self._ir_range * math.sin(th), z=0.12))]
        self._ir_colours = [_rgba(k / 63, 1.0 - k / 63, 0.1, 0.9) for k in range(64)]
        camera = (sensors.get("camera") or {}).get("pose") or {}
        self._camera = (float(camera.get("x", 0.0)), float(camera.get("y", 0.0)),
                        float(camera.get("theta", 0.0)))
        n = self.names
        self._outputs: dict[str, tuple[Output, ...]] = {
            "truth/pose": (
                Output(n.topic("truth/tf"), FrameTransform, self.truth_transform),
                Output(n.topic("truth/pose"), PoseInFrame, self.truth_pose),
            ),
            "estimate/pose": (
                Output(n.topic("estimate/tf"), FrameTransform, self.estimate_transform),
                Output(n.topic("estimate/pose"), PoseInFrame, self.estimate_pose),
                Output(n.topic("estimate/odometry"), Odometry, self.estimate_odometry),
                Output(n.topic("estimate/uncertainty"), SceneUpdate, self.estimate_ellipse),
            ),
            "estimate/grid": (Output(n.topic("estimate/grid"), Grid, self.belief_grid),),
            "map/occupancy": (Output(n.topic("map/occupancy"), Grid, self.occupancy_grid),),
            "sensors/ir": (Output(n.topic("sensors/ir"), SceneUpdate, self.ir_beams),),
            "sensors/sonar": (
                Output(n.topic("sensors/sonar"), SceneUpdate, self.sonar_cones),
                Output(n.topic("sensors/sonar/scan"), PointCloud, self.sonar_scan),
            ),
            "sensors/camera": (Output(n.topic("sensors/camera"), SceneUpdate, self.camera),),
            "sensors/compass": (Output(n.topic("sensors/compass"), SceneUpdate, self.compass),),
            "status": (Output(n.topic("log"), Log, self.status_log),),
            "events/fault": (Output(n.topic("log"), Log, self.fault_log),),
        }

    # -- what there is -----------------------------------------------------------------------

    def outputs(self, key: str) -> tuple[Output, ...]:
        """The Foxglove topics made from the bridge key ``key`` (none for a key not drawn)."""
        return self._outputs.get(key, ())

    def channels(self) -> dict[str, type]:
        """Every topic this translator writes -> its schema class (static ones included)."""
        out: dict[str, type] = ({MAP_TOPIC: SceneUpdate, GRID_TOPIC: Grid}
                                if self.world_topics else {})
        out[self.names.topic("body")] = SceneUpdate
        for outputs in self._outputs.values():
            out.update({o.topic: o.schema for o in outputs})
        return out

    def static(self, t: float = 0.0) -> list[tuple[str, FoxgloveMessage]]:
        """The messages that do not change: the map and the world's grid (if it draws the
        world's topics) and the robot's body."""
        world = ([(MAP_TOPIC, self.world_map(t)), (GRID_TOPIC, self.world_grid(t))]
                 if self.world_topics else [])
        return [*world, (self.names.topic("body"), self.body(t))]

    # -- the world ---------------------------------------------------------------------------

    def world_map(self, t: float = 0.0) -> SceneUpdate:
        """Walls (a thin box per segment), blocked cells, landmarks and magnetic sources."""
        w = self.world
        walls = []
        for x0, y0, x1, y1 in w.get("segments", ()):
            length = math.hypot(x1 - x0, y1 - y0)
            walls.append(CubePrimitive(
                pose=pose2d((x0 + x1) / 2, (y0 + y1) / 2, math.atan2(y1 - y0, x1 - x0),
                            WALL_HEIGHT_M / 2),
                size=Vector3(x=length + WALL_THICKNESS_M, y=WALL_THICKNESS_M, z=WALL_HEIGHT_M),
                color=WALL_COLOUR))
        cell = float(w.get("cell_m", 1.0))
        blocked = [CubePrimitive(
            pose=pose2d((c + 0.5) * cell, (r + 0.5) * cell, 0.0, WALL_HEIGHT_M / 2),
            size=Vector3(x=cell, y=cell, z=WALL_HEIGHT_M), color=BLOCKED_COLOUR)
            for c, r in w.get("blocked", ())]
        landmarks, labels = [], []
        for lm in w.get("landmarks", ()):
            landmarks.append(CylinderPrimitive(
                pose=pose2d(lm["x"], lm["y"], 0.0, 0.15), size=Vector3(x=0.06, y=0.06, z=0.3),
                bottom_scale=1.0, top_scale=1.0, color=_named_colour(str(lm["colour"]))))
            labels.append(TextPrimitive(
                pose=pose2d(lm["x"], lm["y"], 0.0, 0.36), billboard=True, font_size=14.0,
                scale_invariant=True, color=_rgba(1, 1, 1), text=f"landmark {lm['id']}"))
        magnets = [SpherePrimitive(
            pose=pose2d(m["x"], m["y"], 0.0, 0.02), size=Vector3(x=0.08, y=0.08, z=0.04),
            color=_rgba(0.8, 0.2, 0.8, 0.8)) for m in w.get("magnetic_sources", ())]
        return SceneUpdate(entities=[
            _entity(t, WORLD_FRAME, "walls", cubes=walls),
            _entity(t, WORLD_FRAME, "blocked", cubes=blocked),
            _entity(t, WORLD_FRAME, "landmarks", cylinders=landmarks, texts=labels),
            _entity(t, WORLD_FRAME, "magnetic_sources", spheres=magnets),
        ])

    def world_grid(self, t: float = 0.0) -> Grid:
        """The world's cells as a Grid: ``occupied`` uint8, 1 blocked, 0 free (row 0 south)."""
        w = self.world
        cols, rows = int(w.get("cols", 0)), int(w.get("rows", 0))
        cells = np.zeros((rows, cols), dtype=np.uint8)
        for c, r in w.get("blocked", ()):
            cells[int(r), int(c)] = 1
        return self._grid(t, cols, float(w.get("cell_m", 1.0)), (0.0, 0.0), "occupied", _UINT8,
                          1, cells.tobytes())

    def body(self, t: float = 0.0) -> SceneUpdate:
        """The robot's body (a disc of ``body_radius_m``) and a heading arrow, locked to its
        frame."""
        radius = float(self.robot_description.get("body_radius_m", 0.19))
        entity = SceneEntity(
            timestamp=timestamp(t), frame_id=self.names.base_frame, id="body",
            frame_locked=True,
            cylinders=[CylinderPrimitive(
                pose=pose2d(0.0, 0.0, 0.0, 0.05), size=Vector3(x=2 * radius, y=2 * radius, z=0.1),
                bottom_scale=1.0, top_scale=1.0, color=_rgba(0.2, 0.6, 1.0, 0.6))],
            arrows=[ArrowPrimitive(pose=pose2d(0.0, 0.0, 0.0, 0.11), shaft_length=radius,
                                   shaft_diameter=0.02, head_length=0.06, head_diameter=0.05,
                                   color=_rgba(1, 1, 1))])
        return SceneUpdate(entities=[entity])

    # -- poses -------------------------------------------------------------------------------

    def _transform(self, t: float, payload: Mapping[str, Any], child: str) -> FrameTransform | None:
        p = _pose_xytheta(payload)
        if p is None:
            return None
        return FrameTransform(timestamp=timestamp(t), parent_frame_id=WORLD_FRAME,
                              child_frame_id=child, translation=Vector3(x=p[0], y=p[1], z=0.0),
                              rotation=quaternion_yaw(p[2]))

    def _pose(self, t: float, payload: Mapping[str, Any]) -> PoseInFrame | None:
        p = _pose_xytheta(payload)
        if p is None:
            return None
        return PoseInFrame(timestamp=timestamp(t), frame_id=WORLD_FRAME, pose=pose2d(*p))

    def truth_transform(self, t: float, payload: Mapping[str, Any]) -> FrameTransform | None:
        return self._transform(t, payload, self.names.base_frame)

    def truth_pose(self, t: float, payload: Mapping[str, Any]) -> PoseInFrame | None:
        return self._pose(t, payload)

    def estimate_transform(self, t: float, payload: Mapping[str, Any]) -> FrameTransform | None:
        return self._transform(t, payload, self.names.estimate_frame)

    def estimate_pose(self, t: float, payload: Mapping[str, Any]) -> PoseInFrame | None:
        return self._pose(t, payload)

    def estimate_odometry(self, t: float, payload: Mapping[str, Any]) -> Odometry | None:
        """The estimate with its covariance: ``pose_covariance`` is the 6 x 6 row-major
        covariance of (x, y, z, roll, pitch, yaw), the filter's (x, y, theta) block in place and
        the axes it does not estimate 0."""
        p = _pose_xytheta(payload)
        cov = payload.get("cov")
        if p is None or cov is None:
            return None
        six = [0.0] * 36
        for i, a in enumerate((0, 1, 5)):
            for j, b in enumerate((0, 1, 5)):
                six[6 * a + b] = float(cov[i][j])
        return Odometry(timestamp=timestamp(t), frame_id=WORLD_FRAME,
                        body_frame_id=self.names.estimate_frame, pose=pose2d(*p),
                        pose_covariance=six)

    def estimate_ellipse(self, t: float, payload: Mapping[str, Any]) -> SceneUpdate | None:
        """The position's ``SIGMAS``-sigma ellipse (eigen-decomposition of the x, y block) and a
        heading wedge of +-``SIGMAS`` sigma of theta, in ``world``."""
        p = _pose_xytheta(payload)
        cov = payload.get("cov")
        if p is None or cov is None:
            return None
        c = np.asarray(cov, dtype=float)
        if c.shape != (3, 3) or not np.isfinite(c).all():
            return None
        # eigen-decomposition of the symmetric 2 x 2 block, closed form
        a, b, d = float(c[0, 0]), float(c[0, 1]), float(c[1, 1])
        mid, half = (a + d) / 2, math.hypot((a - d) / 2, b)
        major = SIGMAS * math.sqrt(max(mid + half, 0.0))
        minor = SIGMAS * math.sqrt(max(mid - half, 0.0))
        angle = 0.5 * math.atan2(2 * b, a - d)              # the major axis's direction
        x, y, th = p
        spread = SIGMAS * math.sqrt(max(c[2, 2], 0.0))
        reach = 0.3
        wedge = [Point3(x=x, y=y, z=0.01)]
        for a in (th - spread, th + spread):
            wedge.append(Point3(x=x + reach * math.cos(a), y=y + reach * math.sin(a), z=0.01))
        return SceneUpdate(entities=[_entity(
            t, WORLD_FRAME, "estimate",
            spheres=[SpherePrimitive(pose=pose2d(x, y, angle, 0.005),
                                     size=Vector3(x=2 * major, y=2 * minor, z=0.01),
                                     color=_rgba(1.0, 0.6, 0.0, 0.35))],
            triangles=[TriangleListPrimitive(points=wedge, color=_rgba(1.0, 0.6, 0.0, 0.25))],
        )])

    # -- grids -------------------------------------------------------------------------------

    def _grid(self, t: float, cols: int, cell_m: float, origin: tuple[float, float], field: str,
              kind: PackedElementFieldNumericType, size: int, data: bytes) -> Grid:
        return Grid(timestamp=timestamp(t), frame_id=WORLD_FRAME,
                    pose=pose2d(origin[0], origin[1]), column_count=cols,
                    cell_size=Vector2(x=cell_m, y=cell_m), row_stride=cols * size,
                    cell_stride=size, fields=[PackedElementField(name=field, offset=0, type=kind)],
                    data=data)

    def belief_grid(self, t: float, payload: Mapping[str, Any]) -> Grid | None:
        """``estimate/grid``: its float32-le probabilities as they are (field ``p``)."""
        if payload.get("encoding") != "float32-le":
            return None
        data = base64.b64decode(payload["data"])
        return self._grid(t, int(payload["cols"]), float(payload["cell_m"]), (0.0, 0.0), "p",
                          _FLOAT32, 4, data)

    def occupancy_grid(self, t: float, payload: Mapping[str, Any]) -> Grid | None:
        """``map/occupancy``: ``P(occupied) = 1 / (1 + exp(-q * scale))`` as float32
        (field ``p_occupied``; 0.5 where unknown)."""
        if payload.get("encoding") != "int8-logodds":
            return None
        q = np.frombuffer(base64.b64decode(payload["data"]), dtype=np.int8)
        p = (1.0 / (1.0 + np.exp(-q.astype(np.float32) * float(payload["scale"])))).astype("<f4")
        origin = payload.get("origin") or (0.0, 0.0)
        return self._grid(t, int(payload["cols"]), float(payload["resolution_m"]),
                          (float(origin[0]), float(origin[1])), "p_occupied", _FLOAT32, 4,
                          p.tobytes())

    # -- sensors (drawn in the robot's true frame: what the robot saw, where it was) ---------

    def ir_beams(self, t: float, payload: Mapping[str, Any]) -> SceneUpdate | None:
        """One line per IR sensor along its axis to its maximum range, from green (0 counts:
        nothing near) to red (1023: touching): one line list, coloured per vertex."""
        counts = payload.get("counts") or ()
        n = min(len(counts), len(self._ir))
        colours = []
        for c in counts[:n]:
            colour = self._ir_colours[min(max(int(c), 0), 1023) >> 4]
            colours += [colour, colour]
        return SceneUpdate(entities=[_entity(t, self.names.base_frame, "ir", lines=[
            LinePrimitive(type=LinePrimitiveLineType.LineList, thickness=0.012,
                          points=self._ir_points[: 2 * n], colors=colours)])])

    def sonar_cones(self, t: float, payload: Mapping[str, Any]) -> SceneUpdate | None:
        """One cone (a triangle of the beam's aperture) per sonar, as long as its echo; to the
        maximum range and faint where there is none."""
        ranges: Sequence[float | None] = payload.get("ranges") or ()
        points, colours = [], []
        for (x, y, th), r in zip(self._sonar, ranges, strict=False):
            reach = self._sonar_range if r is None else float(r)
            colour = _rgba(0.6, 0.6, 0.6, 0.08) if r is None else _rgba(0.2, 0.8, 1.0, 0.35)
            points += [Point3(x=x, y=y, z=0.1),
                       Point3(x=x + reach * math.cos(th - self._sonar_half),
                              y=y + reach * math.sin(th - self._sonar_half), z=0.1),
                       Point3(x=x + reach * math.cos(th + self._sonar_half),
                              y=y + reach * math.sin(th + self._sonar_half), z=0.1)]
            colours += [colour, colour, colour]
        return SceneUpdate(entities=[_entity(
            t, self.names.base_frame, "sonar",
            triangles=[TriangleListPrimitive(points=points, colors=colours)])])

    def sonar_scan(self, t: float, payload: Mapping[str, Any]) -> PointCloud | None:
        """Each sonar echo as a point at its range along the sensor's axis, in the body frame:
        fields ``x y z range`` float32 (no point where there is no echo)."""
        ranges: Sequence[float | None] = payload.get("ranges") or ()
        data = bytearray()
        for (x, y, th), r in zip(self._sonar, ranges, strict=False):
            if r is None:
                continue
            data += struct.pack("<4f", x + r * math.cos(th), y + r * math.sin(th), 0.1, r)
        fields = [PackedElementField(name=name, offset=4 * i, type=_FLOAT32)
                  for i, name in enumerate(("x", "y", "z", "range"))]
        return PointCloud(timestamp=timestamp(t), frame_id=self.names.base_frame,
                          pose=pose2d(0.0, 0.0), point_stride=16, fields=fields,
                          data=bytes(data))

    def camera(self, t: float, payload: Mapping[str, Any]) -> SceneUpdate | None:
        """A line from the camera to each detected landmark (range, bearing) and its id."""
        cx, cy, cth = self._camera
        lines, texts = [], []
        for o in payload.get("observations") or ():
            r, b = o.get("range"), o.get("bearing")
            if r is None or b is None:
                continue
            a = cth + float(b)
            ex, ey = cx + r * math.cos(a), cy + r * math.sin(a)
            lines.append(LinePrimitive(type=LinePrimitiveLineType.LineList, thickness=0.01,
                                       points=[Point3(x=cx, y=cy, z=0.15),
                                               Point3(x=ex, y=ey, z=0.15)],
                                       color=_rgba(1.0, 1.0, 0.3, 0.9)))
            texts.append(TextPrimitive(pose=Pose(position=Vector3(x=ex, y=ey, z=0.25)),
                                       billboard=True, font_size=12.0, scale_invariant=True,
                                       color=_rgba(1.0, 1.0, 0.3), text=f"id {o.get('id')}"))
        return SceneUpdate(entities=[_entity(t, self.names.base_frame, "camera", lines=lines,
                                             texts=texts)])

    def compass(self, t: float, payload: Mapping[str, Any]) -> SceneUpdate | None:
        """The measured horizontal field as an arrow in the body frame,
        ``COMPASS_M_PER_UT`` m per microtesla."""
        mx, my = payload.get("mx"), payload.get("my")
        if mx is None or my is None:
            return None
        length = COMPASS_M_PER_UT * math.hypot(mx, my)
        return SceneUpdate(entities=[_entity(t, self.names.base_frame, "compass", arrows=[
            ArrowPrimitive(pose=pose2d(0.0, 0.0, math.atan2(my, mx), 0.2),
                           shaft_length=max(length - 0.04, 0.0), shaft_diameter=0.01,
                           head_length=0.04, head_diameter=0.03, color=_rgba(0.9, 0.2, 0.9)),
        ])])

    # -- logs --------------------------------------------------------------------------------

    def status_log(self, t: float, payload: Mapping[str, Any]) -> Log:
        """``status``: the real-time factor and each bus's counters, one line."""
        parts = [f"rtf {float(payload.get('real_time_factor') or 0.0):.1f}"]
        for bus, c in sorted((payload.get("buses") or {}).items()):
            parts.append(f"{bus} sent {c.get('sent', 0)} received {c.get('received', 0)} "
                         f"rejected {c.get('rejected', 0)} dropped {c.get('dropped', 0)}")
        return Log(timestamp=timestamp(t), level=LogLevel.Info, message="; ".join(parts),
                   name=f"{self.names.robot}/status")

    def fault_log(self, t: float, payload: Mapping[str, Any]) -> Log:
        """``events/fault``: one injected fault, a warning."""
        detail = ", ".join(f"{k}={v}" for k, v in sorted((payload.get("detail") or {}).items()))
        return Log(timestamp=timestamp(t), level=LogLevel.Warning,
                   message=f"{payload.get('kind')} on {payload.get('target')} "
                           f"({payload.get('name')}){': ' + detail if detail else ''}",
                   name=f"{self.names.robot}/faults")
