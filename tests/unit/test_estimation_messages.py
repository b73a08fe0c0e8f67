"""JSON payloads of estimate/pose, estimate/cell, estimate/grid and map/occupancy."""

from __future__ import annotations

import json

import numpy as np
import pytest
from koala_bridge.estimation import (
    EstimationError,
    cell_message,
    decode_grid,
    decode_occupancy,
    grid_message,
    occupancy_message,
    pose_message,
)


def test_pose_and_cell_payloads_are_plain_json() -> None:
    cov = np.diag([1e-4, 2e-4, 3e-3])
    msg = pose_message(np.float64(1.5), np.float64(0.25), 0.75, -1.0, cov)
    back = json.loads(json.dumps(msg))
    assert back == {"t": 1.5, "x": 0.25, "y": 0.75, "theta": -1.0, "cov": cov.tolist()}
    assert json.loads(json.dumps(cell_message(2.0, (np.int64(3), 1), np.float32(0.5)))) == {
        "t": 2.0, "cell": [3, 1], "p": 0.5,
    }
    with pytest.raises(EstimationError):
        pose_message(0.0, 0.0, 0.0, 0.0, np.eye(4))


def test_grid_payload_round_trips_row_major_from_south_west() -> None:
    p = np.zeros((4, 5))
    p[0, 1] = 0.7  # row 0 = south, column 1
    p[3, 4] = 0.3
    msg = json.loads(json.dumps(grid_message(3.0, p, 0.5)))
    assert (msg["rows"], msg["cols"], msg["cell"], msg["encoding"]) == (4, 5, [1, 0], "float32-le")
    assert msg["p"] == pytest.approx(0.7)
    np.testing.assert_allclose(decode_grid(msg), p, atol=1e-7)
    # the first float of the payload is the south-west cell
    assert decode_grid(msg).reshape(-1)[1] == pytest.approx(0.7)


def test_occupancy_payload_round_trips() -> None:
    lo = np.linspace(-4, 4, 12).reshape(3, 4)
    msg = json.loads(json.dumps(occupancy_message(4.0, lo, 0.05, 4.0)))
    assert msg["encoding"] == "int8-logodds" and msg["origin"] == [0.0, 0.0]
    assert len(msg["data"]) == 16  # 12 bytes of base64
    np.testing.assert_allclose(decode_occupancy(msg), lo, atol=msg["scale"] / 2 + 1e-12)
    with pytest.raises(EstimationError):
        decode_occupancy({**msg, "encoding": "png"})
