"""Walls on the N, E, S, W sides of the robot's cell from its IR proximity counts
(seeds/003 "Key functions" D, "Detect Wall (Cardinal)").

The robot stops at a cell centre facing (roughly) a cardinal direction. Each IR sensor's ray is
followed from its mounting pose, rotated by the robot's heading, to the side of the cell square
through which it leaves the cell: that sensor reports on that side. A sensor whose ray leaves at
more than ``max_off_normal`` from the side's outward normal (towards a corner, where it could see
the neighbouring cell's walls) reports on no side. A side is a wall when any of its sensors reads
at least ``threshold`` counts (K-Team counts grow as the obstacle gets closer); a side that no
sensor covers is ``None`` (not observed), which the grid filter ignores.
"""

from __future__ import annotations

import math

import numpy as np
from koala_bridge.core.grid import SIDES
from koala_bridge.estimation.errors import EstimationError
from numpy.typing import ArrayLike

# Outward normal of each side of a cell, in SIDES order (N, E, S, W).
_NORMALS = np.array([[0.0, 1.0], [1.0, 0.0], [0.0, -1.0], [-1.0, 0.0]])


def sensor_sides(
    heading: float,
    sensor_poses: ArrayLike,
    cell_m: float,
    max_off_normal: float = math.radians(40.0),
) -> list[int | None]:
    """For each sensor, the index into ``SIDES`` (N, E, S, W) of the cell side its ray reports on.

    Args:
        heading: robot heading, rad CCW from +x (east), world frame.
        sensor_poses: ``(n, 3)`` sensor poses in the body frame (x forward, y left, metres;
            yaw CCW from forward, rad).
        cell_m: cell side length, metres; the robot is assumed at the cell centre.
        max_off_normal: largest angle between the ray and the side's outward normal, rad.

    Returns:
        ``n`` entries, each a side index or None (ray towards a corner).
    """
    poses = np.asarray(sensor_poses, dtype=float)
    if poses.ndim != 2 or poses.shape[1] != 3:
        raise EstimationError(f"sensor_poses must be (n, 3) [x, y, yaw], got {poses.shape}")
    c, s = math.cos(heading), math.sin(heading)
    px = c * poses[:, 0] - s * poses[:, 1]
    py = s * poses[:, 0] + c * poses[:, 1]
    phi = heading + poses[:, 2]
    ux, uy = np.cos(phi), np.sin(phi)
    h = 0.5 * cell_m
    cos_limit = math.cos(max_off_normal)
    out: list[int | None] = []
    for i in range(poses.shape[0]):
        # Ray parameter at which it meets each side's line (inf when moving away from it).
        t = np.full(4, np.inf)
        if uy[i] > 0:
            t[0] = (h - py[i]) / uy[i]
        if ux[i] > 0:
            t[1] = (h - px[i]) / ux[i]
        if uy[i] < 0:
            t[2] = (-h - py[i]) / uy[i]
        if ux[i] < 0:
            t[3] = (-h - px[i]) / ux[i]
        k = int(np.argmin(t))
        along = float(_NORMALS[k] @ np.array([ux[i], uy[i]]))
        out.append(k if along >= cos_limit else None)
    return out


def walls_from_ir(
    counts: ArrayLike,
    heading: float,
    sensor_poses: ArrayLike,
    threshold: ArrayLike,
    *,
    cell_m: float,
    max_off_normal: float = math.radians(40.0),
) -> tuple[bool | None, bool | None, bool | None, bool | None]:
    """Wall / no wall / not observed on the N, E, S, W sides of the robot's cell.

    Args:
        counts: ``(n,)`` IR proximity counts (K-Team 0..1023, larger = closer), e.g. the 16 of
            the Koala, in the order of ``sensor_poses``.
        heading: robot heading, rad CCW from east (from the pose filter or the compass).
        sensor_poses: ``(n, 3)`` body-frame sensor poses ``[x, y, yaw]`` (metres, rad).
        threshold: counts at or above which a sensor sees a wall (scalar or ``(n,)``): the
            count the sensor reads at the distance from a cell-centred robot to a wall.
        cell_m: cell side length, metres.
        max_off_normal: see :func:`sensor_sides`.

    Returns:
        ``(N, E, S, W)``: True = wall, False = no wall, None = no sensor looks that way.
    """
    cnt = np.asarray(counts, dtype=float)
    sides = sensor_sides(heading, sensor_poses, cell_m, max_off_normal)
    if cnt.shape != (len(sides),):
        raise EstimationError(f"counts must have shape ({len(sides)},), got {cnt.shape}")
    thr = np.broadcast_to(np.asarray(threshold, dtype=float), cnt.shape)
    seen: list[bool | None] = [None] * len(SIDES)
    for i, k in enumerate(sides):
        if k is None:
            continue
        hit = bool(cnt[i] >= thr[i])
        seen[k] = hit or bool(seen[k])
    return (seen[0], seen[1], seen[2], seen[3])
