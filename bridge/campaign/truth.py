"""What really happened in a run, read from its recording's truth: the track, how close the body
came to the walls, which cells the robot visited, how far the firmware's estimates were from the
truth, and a digest of the run's outcome.

Shared by the campaign checks (``campaign/checks.py``) and the firmware test teams copy
(``examples/test_firmware_lockstep.py``). Pure functions of a recording and arrays.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, TypeAlias

import numpy as np
from koala_bridge.core.geometry import wall_clearance
from koala_bridge.core.grid import Grid
from koala_bridge.recording.mcap_file import Recording, open_recording, outcome_messages

#: "Visited a cell" = the true centre passed this close to the cell's centre, m.
CENTRE_TOLERANCE_M = 0.1

#: A recording, or the path of its MCAP file.
RecordingLike: TypeAlias = Recording | str | Path  # noqa: UP040 - Python 3.11


def _recording(rec: RecordingLike) -> Recording:
    return rec if isinstance(rec, Recording) else open_recording(rec)


def truth_track(rec: RecordingLike) -> np.ndarray:
    """The recorded true pose, ``(n, 4)`` rows ``t, x, y, theta`` (s, m, m, rad), in time
    order."""
    poses = [m.json() for m in _recording(rec).topic("/truth/pose")]
    return np.array([(p["t"], p["x"], p["y"], p["theta"]) for p in poses]).reshape(-1, 4)


def wall_segments(rec: RecordingLike) -> np.ndarray:
    """The walls the bridge simulated, ``(k, 4)`` rows ``x0, y0, x1, y1`` (the recording's world
    metadata)."""
    world = _recording(rec).world
    if world is None:
        raise ValueError("the recording carries no world")
    return np.asarray(world["segments"], dtype=float).reshape(-1, 4)


def body_clearance_bound(track: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """A lower bound of the centre's distance to the walls between consecutive truth samples,
    ``(n - 1,)``: between two samples the centre moves along a path of length ~``L`` and the
    distance to the nearest wall is 1-Lipschitz, so along the path it stays above
    ``(d_i + d_i+1 - L) / 2``. The body touched a wall where this is below its radius."""
    if len(track) < 2:
        return wall_clearance(track[:, 1:3], segments)
    d = wall_clearance(track[:, 1:3], segments)
    step = np.linalg.norm(np.diff(track[:, 1:3], axis=0), axis=1)
    return np.asarray((d[:-1] + d[1:] - step) / 2)


def reachable_cells(world: Grid, start: tuple[int, int]) -> set[tuple[int, int]]:
    """Every cell the robot can drive to from ``start`` (:meth:`Grid.reachable`)."""
    return world.reachable(start)


def first_visits(track: np.ndarray, world: Grid,
                 tolerance_m: float = CENTRE_TOLERANCE_M) -> dict[tuple[int, int], float]:
    """For each cell whose centre the truth passed within ``tolerance_m``: the first time it
    did, s."""
    out: dict[tuple[int, int], float] = {}
    for t, x, y, _ in track:
        cell = world.cell_of(x, y)
        cx, cy = world.cell_centre(*cell)
        if cell not in out and math.hypot(x - cx, y - cy) < tolerance_m:
            out[cell] = float(t)
    return out


def estimate_errors(report: Mapping[str, Any], track: np.ndarray) -> np.ndarray:
    """The firmware's position estimates against the truth, ``(m, 2)`` rows ``t, error_m``.

    The estimates are the report's ``estimates`` (``[[t, x, y], ...]``, robot time) or, without
    them, its final ``estimate`` (``{"t", "x", "y"}``); the truth is the sample nearest in time.
    Empty when the report holds neither or the track is empty."""
    rows: list[Sequence[float]] = [tuple(map(float, e[:3])) for e in report.get("estimates") or ()]
    final = report.get("estimate")
    if not rows and isinstance(final, Mapping) and {"t", "x", "y"} <= set(final):
        rows = [(float(final["t"]), float(final["x"]), float(final["y"]))]
    if not rows or len(track) == 0:
        return np.empty((0, 2))
    est = np.asarray(rows, dtype=float)
    i = np.clip(np.searchsorted(track[:, 0], est[:, 0]), 0, len(track) - 1)
    j = np.clip(i - 1, 0, len(track) - 1)
    nearest = np.where(np.abs(track[j, 0] - est[:, 0]) <= np.abs(track[i, 0] - est[:, 0]), j, i)
    err = np.hypot(est[:, 1] - track[nearest, 1], est[:, 2] - track[nearest, 2])
    return np.column_stack([est[:, 0], err])


def firmware_bus_rejections(rec: RecordingLike) -> dict[str, int]:
    """Frames from the firmware that the robot rejected, per bus (the last ``/status``
    counters; Zenoh left out: it is not a bus of the robot)."""
    statuses = _recording(rec).topic("/status")
    if not statuses:
        return {}
    buses = statuses[-1].json().get("buses", {})
    return {name: int(c.get("rejected", 0)) for name, c in sorted(buses.items())
            if name != "zenoh"}


def outcome_digest(rec: RecordingLike) -> str:
    """SHA-256 over every channel a run's outcome depends on, message by message with its time
    stamp (:func:`recording.mcap_file.outcome_messages`: what the lockstep determinism test
    compares too). Two lockstep runs of one case have the same digest."""
    h = hashlib.sha256()
    for m in outcome_messages(_recording(rec)):
        h.update(m.topic.encode())
        h.update(m.log_time_ns.to_bytes(8, "little", signed=True))
        h.update(len(m.data).to_bytes(8, "little"))
        h.update(m.data)
    return h.hexdigest()
