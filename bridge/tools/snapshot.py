"""A picture of the robot's world from what Zenoh publishes (matplotlib, no pyplot state).

:func:`collect_scene` asks ``<prefix>/world`` for the world and listens for a while to
``truth/pose``, ``estimate/pose``, ``estimate/cell``, ``estimate/grid`` (belief) and
``map/occupancy``; :func:`render_scene` draws walls, blocked cells, landmarks, magnetic sources,
magnetic north, the truth (ring) and estimated (dot) trails and poses, and the belief / occupancy
grid when one was published.

Every payload is read with its typed message of :mod:`koala_bridge.core.topics`: the world
(``WorldMessage``), the belief (``EstimateGrid``, base64 float32 probabilities) and the occupancy
map (``OccupancyMap``, int8 log-odds, drawn as P(occupied) at its own ``resolution_m`` from its
``origin``; docs/localisation.md). A grid payload of another shape is left out of the picture; a
world of another shape is an error (:class:`~koala_bridge.core.topics.TopicError`).
"""

from __future__ import annotations

import json
import math
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
from koala_bridge.core.topics import (
    EstimateCell,
    EstimateGrid,
    EstimatePose,
    OccupancyMap,
    TopicError,
    TruthPose,
    WorldMessage,
    pose_of,
)
from koala_bridge.tools.monitor import ZenohWatch
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

PoseT = tuple[float, float, float, float]  # t, x, y, theta
G = TypeVar("G", EstimateGrid, OccupancyMap)


@dataclass
class Scene:
    """What a snapshot shows; every part optional except the world (the ``world`` queryable's
    JSON answer, read as a :class:`WorldMessage` when drawn)."""

    world: dict[str, Any] | None = None
    truth: list[PoseT] = field(default_factory=list)
    estimate: list[PoseT] = field(default_factory=list)
    belief: EstimateGrid | None = None
    occupancy: OccupancyMap | None = None
    cell: Any = None
    prefix: str = ""


def _pose(v: Any) -> PoseT | None:
    """``(t, x, y, theta)`` of a ``truth/pose`` or ``estimate/pose`` payload (core.topics)."""
    p = pose_of(v)
    return None if p is None else (float(p.t), float(p.x), float(p.y), float(p.theta))


class SceneCollector:
    """Thread-safe sink for :class:`tools.monitor.ZenohWatch` messages, building a Scene."""

    def __init__(self, max_trail: int = 5000) -> None:
        self._lock = threading.Lock()
        self.scene = Scene()
        self._max_trail = max_trail

    def on_message(self, suffix: str, payload: bytes) -> None:
        msg = json.loads(payload)
        with self._lock:
            s = self.scene
            if suffix in (TruthPose.TOPIC, EstimatePose.TOPIC):
                p = _pose(msg)
                trail = s.truth if suffix == TruthPose.TOPIC else s.estimate
                if p is not None:
                    trail.append(p)
                    del trail[: -self._max_trail]
            elif suffix == EstimateGrid.TOPIC:
                s.belief = _parsed(EstimateGrid, msg, s.belief)
            elif suffix == OccupancyMap.TOPIC:
                s.occupancy = _parsed(OccupancyMap, msg, s.occupancy)
            elif suffix == EstimateCell.TOPIC:
                s.cell = msg


def collect_scene(
    connect: Sequence[str], prefix: str, duration_s: float = 1.0, timeout_s: float = 5.0
) -> Scene:
    """Query the world and listen ``duration_s`` seconds (longer, up to ``timeout_s``, until a
    truth pose has arrived)."""
    collector = SceneCollector()
    with ZenohWatch(connect, prefix, collector.on_message) as watch:
        t0 = time.monotonic()
        world = watch.query_json("world", timeout_s=timeout_s)
        remaining = duration_s - (time.monotonic() - t0)
        if remaining > 0:
            time.sleep(remaining)
        deadline = t0 + timeout_s
        while not collector.scene.truth and time.monotonic() < deadline:
            time.sleep(0.05)
    collector.scene.world = world
    collector.scene.prefix = prefix.strip("/")
    return collector.scene


def _parsed(cls: type[G], msg: Any, previous: G | None) -> G | None:
    """``msg`` as a ``cls`` message, or the previous one when it has another shape."""
    try:
        return cls.from_json(msg)
    except TopicError:
        return previous


def grid_array(msg: EstimateGrid | OccupancyMap | None) -> np.ndarray | None:
    """The ``(rows, cols)`` float array of a grid message, row 0 south: the belief's
    probabilities, or the occupancy map's P(occupied) (0.5 where unknown); None without a
    message or when its ``data`` does not hold ``rows * cols`` cells."""
    try:
        if isinstance(msg, EstimateGrid):
            return msg.probabilities()
        if isinstance(msg, OccupancyMap):
            return msg.p_occupied()
    except TopicError:
        pass
    return None


def _grid_extent(
    msg: EstimateGrid | OccupancyMap, grid: np.ndarray,
    world_extent: tuple[float, float, float, float],
) -> tuple[float, float, float, float]:
    """Where a grid lies: the occupancy map's own ``resolution_m``/``origin``, the belief on the
    world's cells."""
    if not isinstance(msg, OccupancyMap) or not msg.resolution_m > 0:
        return world_extent
    ox, oy = (tuple(msg.origin) + (0.0, 0.0))[:2]
    rows, cols = grid.shape
    res = msg.resolution_m
    return (float(ox), float(ox) + cols * res, float(oy), float(oy) + rows * res)


@dataclass(frozen=True)
class PoseStyle:
    """How one pose stream is drawn: its trail, its latest pose and that pose's heading arrow."""

    colour: str
    trail: str          # matplotlib line style of the trail
    markersize: float   # points
    filled: bool
    arrow: float        # heading arrow length, in cells
    arrow_lw: float
    zorder: float       # of the marker; the arrow goes just below it


# Truth and estimate usually overlap (a good estimate), so neither may hide the other: the truth
# is a large ring whose long, wide arrow lies under everything, the estimate a small filled dot
# with a short, thin arrow inside the ring, and the ring on top of all.
TRUTH = PoseStyle("tab:green", "-", 15.0, False, 0.7, 3.5, zorder=8)
ESTIMATE = PoseStyle("tab:red", "--", 6.0, True, 0.45, 1.5, zorder=7)
_Z_TRAIL, _Z_TRUTH_ARROW, _Z_LABEL = 4, 5, 9


def _draw_pose_stream(
    ax: Axes, trail: Sequence[PoseT], style: PoseStyle, label: str, cell: float, gid: str
) -> None:
    """The trail and the latest pose (marker and heading arrow) of one pose stream."""
    ax.plot([p[1] for p in trail], [p[2] for p in trail], style.trail, color=style.colour,
            lw=1.2, alpha=0.8, zorder=_Z_TRAIL)
    _, x, y, th = trail[-1]
    marker: dict[str, Any] = {
        "marker": "o",
        "markersize": style.markersize,
        "color": style.colour,
        "mfc": style.colour if style.filled else "none",
        "mew": 1.0 if style.filled else 2.5,
    }
    ax.plot([x], [y], linestyle="none", zorder=style.zorder, gid=gid, **marker)
    length = style.arrow * cell
    ax.annotate(
        "",
        xy=(x + length * math.cos(th), y + length * math.sin(th)),
        xytext=(x, y),
        arrowprops={"arrowstyle": "-|>", "color": style.colour, "lw": style.arrow_lw,
                    "shrinkA": 0, "shrinkB": 0},
        zorder=style.zorder if style.filled else _Z_TRUTH_ARROW,
    )
    # The legend entry shows the marker on the trail's line style, as drawn.
    ax.plot([], [], linestyle=style.trail, label=label, **marker)


def _draw_world(ax: Axes, world: WorldMessage) -> tuple[float, float, float]:
    """Walls, blocked cells, landmarks, magnetic sources, north; returns (width, height, cell)."""
    cell = world.cell_m
    w, h = world.cols * cell, world.rows * cell
    for c, r in world.blocked:
        ax.add_patch(Rectangle((c * cell, r * cell), cell, cell, color="0.35", zorder=1))
    for i, (x0, y0, x1, y1) in enumerate(world.segments):
        ax.plot([x0, x1], [y0, y1], color="black", lw=2.5, solid_capstyle="round", zorder=3,
                label="wall" if i == 0 else None)
    for i, lm in enumerate(world.landmarks):
        x, y = lm.x, lm.y
        star: dict[str, Any] = {"markersize": 16, "mec": "black", "zorder": 4,
                "label": "landmark Ln" if i == 0 else None}
        try:
            ax.plot([x], [y], "*", color=lm.colour or "magenta", **star)
        except ValueError:  # a colour name matplotlib does not know
            ax.plot([x], [y], "*", color="magenta", **star)
        # The label goes towards the middle of the world: landmarks sit by the walls and in the
        # corners, where a label outside would cross a wall or leave the axes.
        right, above = x < w / 2, y < h / 2
        ax.annotate(
            f"L{lm.id}",
            (x, y),
            textcoords="offset points",
            xytext=(9 if right else -9, 9 if above else -9),
            ha="left" if right else "right",
            va="bottom" if above else "top",
            fontsize=8,
            bbox={"boxstyle": "round,pad=0.15", "fc": "white", "ec": "none", "alpha": 0.8},
            zorder=_Z_LABEL,
            gid=f"landmark-label-{lm.id}",
        )
    for i, m in enumerate(world.magnetic_sources):
        s = m.strength_uT
        ax.plot(
            [m.x],
            [m.y],
            "X",
            color="tab:purple",
            markersize=6 + 3 * min(abs(s), 5),
            zorder=4,
            label="magnetic source" if i == 0 else None,
        )
    if w > 0:
        # In the right margin at mid-height, clear of the corners where landmarks usually are.
        a = math.radians(world.earth_field.north_deg)
        cx, cy, half = w + 0.45 * cell, h / 2, 0.3 * cell
        ax.annotate(
            "",
            xy=(cx + half * math.cos(a), cy + half * math.sin(a)),
            xytext=(cx - half * math.cos(a), cy - half * math.sin(a)),
            arrowprops={"arrowstyle": "-|>", "color": "tab:purple", "lw": 1.5},
            gid="north",
        )
        ax.text(cx + 1.6 * half * math.cos(a), cy + 1.6 * half * math.sin(a), "N",
                color="tab:purple", ha="center", va="center", fontsize=9, gid="north")
    return w, h, cell


def draw_scene(scene: Scene, dpi: int = 120) -> Figure:
    """The figure of ``scene`` (an Agg canvas attached; no pyplot state).

    Artists a reader may want to find carry a ``gid``: ``north`` (the arrow and its "N"),
    ``landmark-label-<id>``, ``truth-pose`` and ``estimate-pose`` (the latest pose markers).
    """
    fig = Figure(figsize=(7.5, 7.0), dpi=dpi)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    world = WorldMessage.from_json(scene.world, "world") if scene.world else None
    w, h, cell = _draw_world(ax, world) if world else (0.0, 0.0, 0.5)
    extent = (0.0, w, 0.0, h)
    occupancy = grid_array(scene.occupancy)
    if scene.occupancy is not None and occupancy is not None and w > 0:
        im = ax.imshow(
            occupancy,
            origin="lower",
            extent=_grid_extent(scene.occupancy, occupancy, extent),
            cmap="Greys",
            vmin=0,
            vmax=1,
            alpha=0.6,
            zorder=0,
        )
        fig.colorbar(im, ax=ax, fraction=0.04, label="P(occupied)")
    belief = grid_array(scene.belief)
    if belief is not None and w > 0:
        im = ax.imshow(belief, origin="lower", extent=extent, cmap="Blues", alpha=0.55, zorder=0)
        fig.colorbar(im, ax=ax, fraction=0.04, label="belief")
    if scene.truth:
        _draw_pose_stream(ax, scene.truth, TRUTH, "truth (ring, solid trail)", cell, "truth-pose")
    if scene.estimate:
        _draw_pose_stream(
            ax, scene.estimate, ESTIMATE, "estimate (dot, dashed trail)", cell, "estimate-pose"
        )
    if w > 0:
        ax.set_xlim(-0.1 * cell, w + 0.9 * cell)  # the right margin holds the north arrow
        ax.set_ylim(-0.1 * cell, h + 0.1 * cell)
    ax.set_aspect("equal")
    ax.set_xlabel("x east (m)")
    ax.set_ylabel("y north (m)")
    t = scene.truth[-1][0] if scene.truth else None
    title = f"{scene.prefix or 'koala'} — world {world.name if world else '?'}"
    if t is not None:
        title += f", t = {t:.2f} s"
    ax.set_title(title)
    if scene.cell is not None:
        ax.text(
            0.01,
            0.01,
            f"estimate/cell: {json.dumps(scene.cell)[:80]}",
            transform=ax.transAxes,
            fontsize=7,
        )
    handles, labels = ax.get_legend_handles_labels()
    if handles:
        # Below the axes, clear of the tick labels and the x label (the pad is in font sizes):
        # inside, it would hide the corner landmarks.
        ax.legend(handles, labels, loc="upper center", bbox_to_anchor=(0.5, 0.0),
                  borderaxespad=4.0, ncol=3, fontsize=8)
    ax.grid(True, color="0.85", lw=0.5)
    return fig


def render_scene(scene: Scene, out: str | Path, dpi: int = 120) -> Path:
    """Draw ``scene`` and write it as a PNG to ``out``; returns the path."""
    fig = draw_scene(scene, dpi)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, format="png", bbox_inches="tight")
    return out
