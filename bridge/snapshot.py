"""A picture of the robot's world from what Zenoh publishes (matplotlib, no pyplot state).

:func:`collect_scene` asks ``<prefix>/world`` for the world and listens for a while to
``truth/pose``, ``estimate/pose``, ``estimate/cell``, ``estimate/grid`` (belief) and
``map/occupancy``; :func:`render_scene` draws walls, blocked cells, landmarks, magnetic sources,
magnetic north, the truth and estimated trails and poses, and the belief / occupancy grid when
one was published.

Grids are accepted as ``[row][col]`` nested lists (row 0 the southern-most row,
docs/architecture.md) or flat row-major lists with ``rows``/``cols`` members, under one of the
keys of :data:`GRID_KEYS`, or in the bridge's own encodings (``encoding`` ``float32-le`` for the
belief, ``int8-logodds`` for the occupancy map, drawn as P(occupied); docs/localisation.md). A
grid with ``resolution_m`` (the occupancy map) is drawn at that resolution from ``origin``.
"""

from __future__ import annotations

import json
import math
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from bridge.monitor import ZenohWatch

GRID_KEYS = ("belief", "probabilities", "p", "occupancy", "grid", "cells", "values", "data")
PoseT = tuple[float, float, float, float]  # t, x, y, theta


@dataclass
class Scene:
    """What a snapshot shows; every part optional except the world."""

    world: dict[str, Any] | None = None
    truth: list[PoseT] = field(default_factory=list)
    estimate: list[PoseT] = field(default_factory=list)
    belief: Any = None
    occupancy: Any = None
    cell: Any = None
    prefix: str = ""


def _pose(v: Any) -> PoseT | None:
    try:
        return float(v.get("t", 0.0)), float(v["x"]), float(v["y"]), float(v["theta"])
    except (AttributeError, KeyError, TypeError, ValueError):
        return None


class SceneCollector:
    """Thread-safe sink for :class:`~bridge.monitor.ZenohWatch` messages, building a Scene."""

    def __init__(self, max_trail: int = 5000) -> None:
        self._lock = threading.Lock()
        self.scene = Scene()
        self._max_trail = max_trail

    def on_message(self, suffix: str, payload: bytes) -> None:
        msg = json.loads(payload)
        with self._lock:
            s = self.scene
            if suffix in ("truth/pose", "estimate/pose"):
                p = _pose(msg)
                trail = s.truth if suffix == "truth/pose" else s.estimate
                if p is not None:
                    trail.append(p)
                    del trail[: -self._max_trail]
            elif suffix == "estimate/grid":
                s.belief = msg
            elif suffix == "map/occupancy":
                s.occupancy = msg
            elif suffix == "estimate/cell":
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


def grid_array(msg: Any, rows: int | None = None, cols: int | None = None) -> np.ndarray | None:
    """A ``(rows, cols)`` float array from a grid message (see module docstring), or None."""
    if not isinstance(msg, dict):
        return None
    encoded = _decode_encoded(msg)
    if encoded is not None:
        return encoded
    rows = int(msg.get("rows", rows or 0)) or rows
    cols = int(msg.get("cols", cols or 0)) or cols
    for key in GRID_KEYS:
        v = msg.get(key)
        if not isinstance(v, list) or not v:
            continue
        try:
            a = np.array(v, dtype=float)  # None -> nan
        except (TypeError, ValueError):
            continue
        if a.ndim == 2:
            return a
        if a.ndim == 1 and rows and cols and a.size == rows * cols:
            return a.reshape(rows, cols)
    return None


def _decode_encoded(msg: dict[str, Any]) -> np.ndarray | None:
    """The bridge's base64 grids (bridge/estimation/messages.py): belief probabilities, or the
    occupancy log-odds as P(occupied) (0.5 where unknown); None for other messages."""
    encoding = msg.get("encoding")
    if encoding not in ("float32-le", "int8-logodds"):
        return None
    # Imported here: the estimation package loads scipy, which a plain snapshot does not need.
    from bridge.estimation import EstimationError, decode_grid, decode_occupancy

    try:
        if encoding == "float32-le":
            return decode_grid(msg)
        return 1.0 / (1.0 + np.exp(-decode_occupancy(msg)))
    except (EstimationError, KeyError, TypeError, ValueError):
        return None


def _grid_extent(
    msg: Any, grid: np.ndarray, world_extent: tuple[float, float, float, float]
) -> tuple[float, float, float, float]:
    """Where a grid lies: its own ``resolution_m``/``origin`` if it has them, else the world's."""
    res = msg.get("resolution_m") if isinstance(msg, dict) else None
    if not isinstance(res, int | float) or not res > 0:
        return world_extent
    ox, oy = (msg.get("origin") or [0.0, 0.0])[:2]
    rows, cols = grid.shape
    return (float(ox), float(ox) + cols * res, float(oy), float(oy) + rows * res)


def _draw_pose(ax: Axes, p: PoseT, colour: str, label: str, size: float) -> None:
    _, x, y, th = p
    ax.plot([x], [y], "o", color=colour, markersize=6, label=label, zorder=5)
    ax.annotate(
        "",
        xy=(x + size * math.cos(th), y + size * math.sin(th)),
        xytext=(x, y),
        arrowprops={"arrowstyle": "-|>", "color": colour, "lw": 2},
        zorder=6,
    )


def _draw_world(ax: Axes, world: dict[str, Any]) -> tuple[float, float, float]:
    """Walls, blocked cells, landmarks, magnetic sources, north; returns (width, height, cell)."""
    cell = float(world.get("cell_m", 0.5))
    cols, rows = int(world.get("cols", 0)), int(world.get("rows", 0))
    for c, r in world.get("blocked", []):
        ax.add_patch(Rectangle((c * cell, r * cell), cell, cell, color="0.35", zorder=1))
    for x0, y0, x1, y1 in world.get("segments", []):
        ax.plot([x0, x1], [y0, y1], color="black", lw=2.5, solid_capstyle="round", zorder=3)
    for lm in world.get("landmarks", []):
        colour = lm.get("colour") or "magenta"
        try:
            ax.plot([lm["x"]], [lm["y"]], "*", color=colour, markersize=16, mec="black", zorder=4)
        except ValueError:  # a colour name matplotlib does not know
            ax.plot([lm["x"]], [lm["y"]], "*", color="magenta", markersize=16, zorder=4)
        ax.annotate(
            f"L{lm.get('id')}",
            (lm["x"], lm["y"]),
            textcoords="offset points",
            xytext=(6, -12),
            fontsize=8,
        )
    for i, m in enumerate(world.get("magnetic_sources", [])):
        s = float(m.get("strength_uT", 1.0))
        ax.plot(
            [m["x"]],
            [m["y"]],
            "X",
            color="tab:purple",
            markersize=6 + 3 * min(abs(s), 5),
            zorder=4,
            label="magnetic source" if i == 0 else None,
        )
    w, h = cols * cell, rows * cell
    north = (world.get("earth_field") or {}).get("north_deg")
    if north is not None and w > 0:
        a = math.radians(float(north))
        x, y, L = w + 0.15 * cell, h - 0.6 * cell, 0.4 * cell
        ax.annotate(
            "N",
            xy=(x + L * math.cos(a), y + L * math.sin(a)),
            xytext=(x, y),
            arrowprops={"arrowstyle": "-|>", "color": "tab:purple"},
            color="tab:purple",
            ha="center",
            va="center",
            fontsize=9,
        )
    return w, h, cell


def render_scene(scene: Scene, out: str | Path, dpi: int = 120) -> Path:
    """Draw ``scene`` and write it as a PNG to ``out``; returns the path."""
    fig = Figure(figsize=(7.5, 7.0), dpi=dpi)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    world = scene.world or {}
    w, h, cell = _draw_world(ax, world) if world else (0.0, 0.0, 0.5)
    rows, cols = int(world.get("rows", 0)) or None, int(world.get("cols", 0)) or None
    extent = (0.0, w, 0.0, h)
    occupancy = grid_array(scene.occupancy, rows, cols)
    if occupancy is not None and w > 0:
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
    belief = grid_array(scene.belief, rows, cols)
    if belief is not None and w > 0:
        im = ax.imshow(belief, origin="lower", extent=extent, cmap="Blues", alpha=0.55, zorder=0)
        fig.colorbar(im, ax=ax, fraction=0.04, label="belief")
    size = 0.6 * cell
    if scene.truth:
        xs, ys = [p[1] for p in scene.truth], [p[2] for p in scene.truth]
        ax.plot(xs, ys, "-", color="tab:green", lw=1, alpha=0.7, zorder=4)
        _draw_pose(ax, scene.truth[-1], "tab:green", "truth", size)
    if scene.estimate:
        xs, ys = [p[1] for p in scene.estimate], [p[2] for p in scene.estimate]
        ax.plot(xs, ys, "--", color="tab:red", lw=1, alpha=0.7, zorder=4)
        _draw_pose(ax, scene.estimate[-1], "tab:red", "estimate", size)
    if w > 0:
        ax.set_xlim(-0.1 * cell, w + 0.5 * cell)
        ax.set_ylim(-0.1 * cell, h + 0.1 * cell)
    ax.set_aspect("equal")
    ax.set_xlabel("x east (m)")
    ax.set_ylabel("y north (m)")
    t = scene.truth[-1][0] if scene.truth else None
    title = f"{scene.prefix or 'koala'} — world {world.get('name', '?')}"
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
    if ax.get_legend_handles_labels()[0]:
        # Below the axes: inside, it would hide the corner landmarks.
        ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.09), ncol=4, fontsize=8)
    ax.grid(True, color="0.85", lw=0.5)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, format="png", bbox_inches="tight")
    return out
