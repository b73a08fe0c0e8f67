"""JSON-ready payloads of the estimation keys on Zenoh (the bridge publishes them).

The payloads are the typed messages of :mod:`koala_bridge.core.topics` (``EstimatePose``,
``EstimateCell``, ``EstimateGrid``, ``OccupancyMap``: one definition for the JSON, the
recording's schema and the parsers); this module turns the estimators' arrays into them and back.

Keys are relative to the bridge's key prefix. Every payload is a plain ``dict`` of ``str``,
``int``, ``float``, ``list`` and ``None`` (``json.dumps`` takes it as is); ``t`` is simulation
seconds. Arrays of cells are row-major from the south-west corner (row 0 south, column fastest),
the grid convention of docs/architecture.md, and travel as base64 so a 100 x 100 grid stays small:

* ``estimate/pose``  ``{t, x, y, theta, cov}`` -- m, m, rad; ``cov`` the 3 x 3 covariance of
  ``(x, y, theta)`` as nested lists.
* ``estimate/health`` ``{t, state, reasons, sigma_xy_m, sigma_theta_deg, accepted, rejected,
  relocalisations}`` -- ``state`` one of tracking / uncertain / lost / relocalising
  (:mod:`koala_bridge.estimation.health`).
* ``estimate/cell``  ``{t, cell: [col, row], p}`` -- the grid filter's guess and its probability.
* ``estimate/grid``  ``{t, cols, rows, cell_m, encoding: "float32-le", data, cell, p}`` -- the
  whole belief, ``rows * cols`` little-endian float32 probabilities in base64.
* ``map/occupancy``  ``{t, cols, rows, resolution_m, origin: [x, y], encoding: "int8-logodds",
  scale, data}`` -- log-odds quantised as ``q = round(l / scale)`` to int8 in base64;
  ``P(occupied) = 1 / (1 + exp(-q * scale))``, ``q = 0`` unknown.
"""

from __future__ import annotations

import base64
from typing import Any

import numpy as np
from koala_bridge.core.topics import (
    GRID_ENCODING,
    OCCUPANCY_ENCODING,
    EstimateCell,
    EstimateGrid,
    EstimateHealth,
    EstimatePose,
    OccupancyMap,
    TopicError,
)
from koala_bridge.estimation.errors import EstimationError
from koala_bridge.estimation.occupancy import encode_log_odds
from numpy.typing import ArrayLike, NDArray

KEY_POSE = EstimatePose.TOPIC
KEY_CELL = EstimateCell.TOPIC
KEY_HEALTH = EstimateHealth.TOPIC
KEY_GRID = EstimateGrid.TOPIC
KEY_OCCUPANCY = OccupancyMap.TOPIC

__all__ = [
    "GRID_ENCODING",
    "KEY_CELL",
    "KEY_GRID",
    "KEY_HEALTH",
    "KEY_OCCUPANCY",
    "KEY_POSE",
    "OCCUPANCY_ENCODING",
    "cell_message",
    "decode_grid",
    "decode_occupancy",
    "grid_message",
    "health_message",
    "occupancy_message",
    "pose_message",
]


def pose_message(t: float, x: float, y: float, theta: float, cov: ArrayLike) -> dict[str, Any]:
    """``estimate/pose``: pose (m, m, rad) and the ``(3, 3)`` covariance of ``(x, y, theta)``."""
    c = np.asarray(cov, dtype=float)
    if c.shape != (3, 3):
        raise EstimationError(f"pose covariance must be (3, 3), got {c.shape}")
    cov_rows = tuple(tuple(float(v) for v in row) for row in c)
    return EstimatePose(float(t), float(x), float(y), float(theta), cov_rows).to_json()


def cell_message(t: float, cell: tuple[int, int], p: float) -> dict[str, Any]:
    """``estimate/cell``: the most probable cell ``(col, row)`` and its probability."""
    return EstimateCell(float(t), (int(cell[0]), int(cell[1])), float(p)).to_json()


def grid_message(t: float, probabilities: ArrayLike, cell_m: float) -> dict[str, Any]:
    """``estimate/grid``: the belief ``(rows, cols)`` (row 0 south) as base64 float32."""
    p = np.asarray(probabilities, dtype=float)
    if p.ndim != 2:
        raise EstimationError(f"belief must be (rows, cols), got {p.shape}")
    rows, cols = p.shape
    idx = int(np.argmax(p))
    row, col = divmod(idx, cols)
    data = base64.b64encode(p.astype("<f4").tobytes(order="C")).decode("ascii")
    return EstimateGrid(
        float(t), cols, rows, float(cell_m), GRID_ENCODING, data, (col, row), float(p[row, col])
    ).to_json()


def decode_grid(msg: dict[str, Any]) -> NDArray[np.float64]:
    """The ``(rows, cols)`` probabilities of an ``estimate/grid`` payload."""
    if msg.get("encoding") != GRID_ENCODING:
        raise EstimationError(f"unknown grid encoding {msg.get('encoding')!r}")
    try:
        return EstimateGrid.from_json(msg).probabilities()
    except TopicError as e:
        raise EstimationError(str(e)) from e


def occupancy_message(
    t: float, log_odds: ArrayLike, resolution_m: float, l_max: float
) -> dict[str, Any]:
    """``map/occupancy``: log-odds ``(rows, cols)`` (row 0 south, origin at world (0, 0))."""
    lo = np.asarray(log_odds, dtype=float)
    if lo.ndim != 2:
        raise EstimationError(f"occupancy must be (rows, cols), got {lo.shape}")
    data, scale = encode_log_odds(lo, l_max)
    return OccupancyMap(
        float(t),
        int(lo.shape[1]),
        int(lo.shape[0]),
        float(resolution_m),
        (0.0, 0.0),
        OCCUPANCY_ENCODING,
        float(scale),
        data,
    ).to_json()


def decode_occupancy(msg: dict[str, Any]) -> NDArray[np.float64]:
    """The ``(rows, cols)`` log-odds of a ``map/occupancy`` payload."""
    if msg.get("encoding") != OCCUPANCY_ENCODING:
        raise EstimationError(f"unknown occupancy encoding {msg.get('encoding')!r}")
    try:
        return OccupancyMap.from_json(msg).log_odds()
    except TopicError as e:
        raise EstimationError(str(e)) from e


def health_message(t: float, state: str, reasons: list[str], sigma_xy_m: float,
                   sigma_theta_deg: float, accepted: int, rejected: int,
                   relocalisations: int) -> dict[str, Any]:
    """``estimate/health`` payload (:class:`koala_bridge.core.topics.EstimateHealth`)."""
    return EstimateHealth(float(t), state, tuple(reasons), float(sigma_xy_m),  # type: ignore[arg-type]
                          float(sigma_theta_deg), int(accepted), int(rejected),
                          int(relocalisations)).to_json()
