"""JSON-ready payloads of the estimation keys on Zenoh (the bridge publishes them).

Keys are relative to the bridge's key prefix. Every payload is a plain ``dict`` of ``str``,
``int``, ``float``, ``list`` and ``None`` (``json.dumps`` takes it as is); ``t`` is simulation
seconds. Arrays of cells are row-major from the south-west corner (row 0 south, column fastest),
the grid convention of docs/architecture.md, and travel as base64 so a 100 x 100 grid stays small:

* ``estimate/pose``  ``{t, x, y, theta, cov}`` -- m, m, rad; ``cov`` the 3 x 3 covariance of
  ``(x, y, theta)`` as nested lists.
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
from koala_bridge.estimation.errors import EstimationError
from koala_bridge.estimation.occupancy import decode_log_odds, encode_log_odds
from numpy.typing import ArrayLike, NDArray

KEY_POSE = "estimate/pose"
KEY_CELL = "estimate/cell"
KEY_GRID = "estimate/grid"
KEY_OCCUPANCY = "map/occupancy"

GRID_ENCODING = "float32-le"
OCCUPANCY_ENCODING = "int8-logodds"


def pose_message(t: float, x: float, y: float, theta: float, cov: ArrayLike) -> dict[str, Any]:
    """``estimate/pose``: pose (m, m, rad) and the ``(3, 3)`` covariance of ``(x, y, theta)``."""
    c = np.asarray(cov, dtype=float)
    if c.shape != (3, 3):
        raise EstimationError(f"pose covariance must be (3, 3), got {c.shape}")
    return {
        "t": float(t),
        "x": float(x),
        "y": float(y),
        "theta": float(theta),
        "cov": [[float(v) for v in row] for row in c],
    }


def cell_message(t: float, cell: tuple[int, int], p: float) -> dict[str, Any]:
    """``estimate/cell``: the most probable cell ``(col, row)`` and its probability."""
    return {"t": float(t), "cell": [int(cell[0]), int(cell[1])], "p": float(p)}


def grid_message(t: float, probabilities: ArrayLike, cell_m: float) -> dict[str, Any]:
    """``estimate/grid``: the belief ``(rows, cols)`` (row 0 south) as base64 float32."""
    p = np.asarray(probabilities, dtype=float)
    if p.ndim != 2:
        raise EstimationError(f"belief must be (rows, cols), got {p.shape}")
    rows, cols = p.shape
    idx = int(np.argmax(p))
    row, col = divmod(idx, cols)
    data = base64.b64encode(p.astype("<f4").tobytes(order="C")).decode("ascii")
    return {
        "t": float(t),
        "cols": cols,
        "rows": rows,
        "cell_m": float(cell_m),
        "encoding": GRID_ENCODING,
        "data": data,
        "cell": [col, row],
        "p": float(p[row, col]),
    }


def decode_grid(msg: dict[str, Any]) -> NDArray[np.float64]:
    """The ``(rows, cols)`` probabilities of an ``estimate/grid`` payload."""
    if msg.get("encoding") != GRID_ENCODING:
        raise EstimationError(f"unknown grid encoding {msg.get('encoding')!r}")
    a = np.frombuffer(base64.b64decode(msg["data"]), dtype="<f4")
    rows, cols = int(msg["rows"]), int(msg["cols"])
    if a.size != rows * cols:
        raise EstimationError(f"grid data holds {a.size} cells, expected {rows}x{cols}")
    return a.reshape(rows, cols).astype(float)


def occupancy_message(
    t: float, log_odds: ArrayLike, resolution_m: float, l_max: float
) -> dict[str, Any]:
    """``map/occupancy``: log-odds ``(rows, cols)`` (row 0 south, origin at world (0, 0))."""
    lo = np.asarray(log_odds, dtype=float)
    if lo.ndim != 2:
        raise EstimationError(f"occupancy must be (rows, cols), got {lo.shape}")
    data, scale = encode_log_odds(lo, l_max)
    return {
        "t": float(t),
        "cols": int(lo.shape[1]),
        "rows": int(lo.shape[0]),
        "resolution_m": float(resolution_m),
        "origin": [0.0, 0.0],
        "encoding": OCCUPANCY_ENCODING,
        "scale": float(scale),
        "data": data,
    }


def decode_occupancy(msg: dict[str, Any]) -> NDArray[np.float64]:
    """The ``(rows, cols)`` log-odds of a ``map/occupancy`` payload."""
    if msg.get("encoding") != OCCUPANCY_ENCODING:
        raise EstimationError(f"unknown occupancy encoding {msg.get('encoding')!r}")
    return decode_log_odds(msg["data"], int(msg["rows"]), int(msg["cols"]), float(msg["scale"]))
