"""``Grid.reachable``: the cells a robot can drive to, through open sides only."""

from __future__ import annotations

from koala_bridge.core.grid import Grid

# Two rooms: the west column is walled off from the rest along its whole length, and the
# east room holds one blocked cell.
WORLD = {
    "name": "two_rooms",
    "cell_m": 0.5,
    "map": """
+---+---+---+
|   |       |
+   +   +   +
|   |       |
+---+---+---+
""",
}


def test_only_cells_behind_open_sides_are_reachable() -> None:
    world = Grid.from_dict(WORLD)
    assert world.reachable((0, 0)) == {(0, 0), (0, 1)}
    assert world.reachable((2, 1)) == {(1, 0), (1, 1), (2, 0), (2, 1)}


def test_a_blocked_cell_is_not_reachable() -> None:
    world = Grid.from_dict({**WORLD, "blocked": [[2, 0]]})
    assert world.reachable((1, 0)) == {(1, 0), (1, 1), (2, 1)}
