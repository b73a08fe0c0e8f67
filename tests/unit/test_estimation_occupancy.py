"""Occupancy grid along beam arcs (seeds/004) and its int8 encoding."""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

import numpy as np
import pytest
from koala_bridge.core.grid import Grid
from koala_bridge.core.raycast import SegmentSet, cast_rays
from koala_bridge.estimation import BeamModel, OccupancyGrid, OccupancyParams, beam_cells
from koala_bridge.estimation.occupancy import decode_log_odds, encode_log_odds

ROOT = Path(__file__).resolve().parents[2]
RES = 0.05
# seeds/004: Khepera III IR aperture 1.72 deg, +-3 %; ultrasonic 22.9 deg, +-6.6 %.
IR_BEAM = BeamModel(math.radians(1.72), 0.03, max_range_m=0.25)
SONAR_BEAM = BeamModel(math.radians(22.9), 0.066, max_range_m=2.5, min_range_m=0.25)


def load_world(name: str) -> Grid:
    text = (ROOT / "config" / "worlds" / f"{name}.toml").read_text()
    return Grid.from_dict(tomllib.loads(text)["world"])


def sensor_poses(kind: str) -> np.ndarray:
    sec = tomllib.loads((ROOT / "config" / "default.toml").read_text())["sensors"][kind]
    poses = np.array(sec["poses"], dtype=float)
    poses[:, 2] = np.radians(poses[:, 2])
    return poses


def true_occupancy(world: Grid, grid: OccupancyGrid) -> np.ndarray:
    """A cell is occupied when a wall segment touches its closed square."""
    occ = np.zeros((grid.rows, grid.cols), dtype=bool)
    tol = 1e-9
    for x0, y0, x1, y1 in world.segments:
        c0 = max(math.floor((min(x0, x1) - tol) / RES), 0)
        c1 = min(math.floor((max(x0, x1) + tol) / RES), grid.cols - 1)
        r0 = max(math.floor((min(y0, y1) - tol) / RES), 0)
        r1 = min(math.floor((max(y0, y1) + tol) / RES), grid.rows - 1)
        occ[r0 : r1 + 1, c0 : c1 + 1] = True
    return occ


def ideal_ranges(
    walls: SegmentSet, pose: tuple[float, float, float], poses: np.ndarray, beam: BeamModel,
    rays: int,
) -> np.ndarray:
    """Noise-free readings: the nearest hit over ``rays`` rays across the aperture (Webots)."""
    x, y, th = pose
    c, s = math.cos(th), math.sin(th)
    offs = np.linspace(-beam.beam_width_rad / 2, beam.beam_width_rad / 2, rays)
    out = np.empty(len(poses))
    for i, (bx, by, yaw) in enumerate(poses):
        ox, oy = x + c * bx - s * by, y + s * bx + c * by
        phi = th + yaw + offs
        hits = cast_rays(walls, np.full(rays, ox), np.full(rays, oy), np.cos(phi), np.sin(phi))
        out[i] = float(np.min(hits.range))
    return out


def map_world(world: Grid, kind: str, beam: BeamModel, rays: int) -> OccupancyGrid:
    grid = OccupancyGrid.for_world(world, RES, OccupancyParams())
    walls = SegmentSet.from_segments(world.segments)
    poses = sensor_poses(kind)
    for col, row in world.free_cells():
        cx, cy = world.cell_centre(col, row)
        for heading_deg in range(0, 360, 30):
            pose = (cx, cy, math.radians(heading_deg))
            grid.integrate_scan(pose, poses, ideal_ranges(walls, pose, poses, beam, rays), beam)
    return grid


@pytest.mark.parametrize("name", ["lab_walls_1", "lab_walls_3"])
@pytest.mark.parametrize(("kind", "beam", "rays"), [("ir", IR_BEAM, 3), ("sonar", SONAR_BEAM, 5)])
def test_known_map_is_recovered_from_ideal_ranges(
    name: str, kind: str, beam: BeamModel, rays: int
) -> None:
    world = load_world(name)
    grid = map_world(world, kind, beam, rays)
    cls = grid.classify()
    truth = true_occupancy(world, grid)
    seen = cls >= 0
    correct = float(np.mean((cls[seen] == 1) == truth[seen]))
    assert seen.sum() > 100
    assert correct >= 0.95, (correct, int(seen.sum()))


def test_one_reading_marks_its_arc_band_occupied_and_the_cone_before_it_free() -> None:
    beam = BeamModel(math.radians(20.0), 0.05, max_range_m=3.0)
    occ, free = beam_cells((40, 40), RES, (1.0, 1.0), 0.0, 0.6, beam)
    assert occ.size and free.size and np.intersect1d(occ, free).size == 0
    rows, cols = np.divmod(occ, 40)
    centres = np.column_stack([(cols + 0.5) * RES - 1.0, (rows + 0.5) * RES - 1.0])
    d = np.hypot(centres[:, 0], centres[:, 1])
    assert np.all(np.abs(d - 0.6) < 0.03 + RES)  # within the +-eps band, up to a cell
    assert np.all(np.abs(np.arctan2(centres[:, 1], centres[:, 0])) < math.radians(10) + 0.1)
    rows, cols = np.divmod(free, 40)
    d = np.hypot((cols + 0.5) * RES - 1.0, (rows + 0.5) * RES - 1.0)
    assert np.all(d < 0.6 * 0.95 + RES)


def test_no_echo_and_too_close_readings() -> None:
    occ, free = beam_cells((40, 40), RES, (1.0, 1.0), 0.0, math.inf, SONAR_BEAM)
    assert occ.size == 0 and free.size == 0
    occ, free = beam_cells((40, 40), RES, (1.0, 1.0), 0.0, 0.1, SONAR_BEAM)
    assert occ.size == 0 and free.size == 0
    occ, free = beam_cells((40, 40), RES, (1.0, 1.0), 0.0, math.nan, SONAR_BEAM, True)
    assert occ.size == 0 and free.size > 0


def test_log_odds_accumulate_and_clamp() -> None:
    params = OccupancyParams(l_occ=1.0, l_free=-0.5, l_min=-2.0, l_max=3.0)
    grid = OccupancyGrid(40, 40, RES, params)
    for _ in range(10):
        grid.integrate((1.0, 1.0), 0.0, 0.5, BeamModel(0.0, 0.0, 2.0))
    assert grid.log_odds.max() == pytest.approx(3.0) and grid.log_odds.min() == pytest.approx(-2.0)
    assert grid.probabilities().max() == pytest.approx(1 / (1 + math.exp(-3.0)))


def test_int8_encoding_round_trips_within_half_a_step() -> None:
    rng = np.random.default_rng(5)
    lo = rng.uniform(-4.0, 4.0, size=(7, 9))
    data, scale = encode_log_odds(lo, 4.0)
    back = decode_log_odds(data, 7, 9, scale)
    assert np.max(np.abs(back - lo)) <= scale / 2 + 1e-12
    assert np.all(decode_log_odds(encode_log_odds(np.zeros((2, 3)), 4.0)[0], 2, 3, scale) == 0)


def test_free_margin_stops_the_cone_short_of_the_band() -> None:
    beam = BeamModel(0.0, 0.0, max_range_m=3.0)
    _, free0 = beam_cells((40, 40), RES, (0.025, 1.025), 0.0, 1.0, beam)
    _, free1 = beam_cells((40, 40), RES, (0.025, 1.025), 0.0, 1.0, beam, free_margin_m=RES)
    assert np.max(free0 % 40) == 19 and np.max(free1 % 40) == 18
