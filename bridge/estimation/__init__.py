"""Localisation and mapping from decoded bus data: pure algorithms, no I/O, no threads, no clock.

The bridge service (and the example firmware) call these; docs/localisation.md explains them.

* :mod:`.trilateration` -- closed-form three-landmark fix (seeds/003) and weighted least squares.
* :mod:`.grid_localisation` -- histogram filter over the world's cells from wall observations.
* :mod:`.wall_detection` -- N/E/S/W walls from the IR counts at a cell centre.
* :mod:`.pose_filter` -- EKF over ``[x, y, theta, gyro_bias]`` (odometry, gyro, compass, landmarks).
* :mod:`.occupancy` -- log-odds occupancy grid along beam arcs (seeds/004).
* :mod:`.messages` -- JSON-ready payloads of ``estimate/*`` and ``map/occupancy``.
"""

from koala_bridge.estimation.errors import DegenerateGeometryError, EstimationError
from koala_bridge.estimation.grid_localisation import (
    GridLocaliser,
    GridModel,
    GridParams,
    guess_cell,
    known_start_prior,
    predict,
    uniform_prior,
    update,
)
from koala_bridge.estimation.messages import (
    cell_message,
    decode_grid,
    decode_occupancy,
    grid_message,
    occupancy_message,
    pose_message,
)
from koala_bridge.estimation.occupancy import BeamModel, OccupancyGrid, OccupancyParams, beam_cells
from koala_bridge.estimation.pose_filter import PoseTracker, PoseTrackerParams, heading_from_field
from koala_bridge.estimation.probability import log_normalise, log_odds, prob_from_log_odds
from koala_bridge.estimation.trilateration import LandmarkFix, trilaterate3, wls_fix
from koala_bridge.estimation.wall_detection import sensor_sides, walls_from_ir

__all__ = [
    "BeamModel",
    "DegenerateGeometryError",
    "EstimationError",
    "GridLocaliser",
    "GridModel",
    "GridParams",
    "LandmarkFix",
    "OccupancyGrid",
    "OccupancyParams",
    "PoseTracker",
    "PoseTrackerParams",
    "beam_cells",
    "cell_message",
    "decode_grid",
    "decode_occupancy",
    "grid_message",
    "guess_cell",
    "heading_from_field",
    "known_start_prior",
    "log_normalise",
    "log_odds",
    "occupancy_message",
    "pose_message",
    "predict",
    "prob_from_log_odds",
    "sensor_sides",
    "trilaterate3",
    "uniform_prior",
    "update",
    "walls_from_ir",
    "wls_fix",
]
