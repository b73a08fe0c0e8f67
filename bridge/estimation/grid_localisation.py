"""Grid (histogram) localisation from wall observations (seeds/003 "Key functions" A-G).

The belief is one number per cell: the log-probability that the robot is in that cell,
normalised after every step (log-sum-exp, seeds/003 F). Arrays are indexed
``[row, col]`` with row 0 the southern-most row (docs/architecture.md), so a flat index is
row-major from the south-west corner. Blocked cells hold ``-inf``.

Two steps, as in any Bayes filter:

* :func:`predict` -- the motion model. The robot commands a move to the neighbour on one side
  (``N``/``E``/``S``/``W``). From every cell whose move is open (``Grid.can_move``) the mass goes
  to the neighbour with ``p_move`` (the lab's 0.8) and stays with ``1 - p_move``; from a cell whose
  move is blocked by a wall, the grid edge or a blocked cell, all the mass stays. This is a
  convolution of the whole belief with a kernel conditioned on the command and the map -- the
  lab's ``move_probably`` instead added log-probabilities to the current and next cell of the
  *guessed* position only, which is not a prediction and made the belief oscillate.
* :func:`update` -- the wall-observation model. For each side the sensor reports wall / no wall;
  ``P(report wall | wall) = p_hit`` (0.9) and ``P(report no wall | no wall) = p_clear`` (0.7).
  Every cell gets the product of the four per-side likelihoods of *its own* walls (seeds/003 D),
  added in the log domain (seeds/003 B), then the belief is normalised (F). A side reported as
  ``None`` (no sensor looks that way) contributes nothing.

:class:`GridLocaliser` is the thin stateful wrapper the bridge and the firmware use.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from koala_bridge.core.grid import SIDES, Grid
from koala_bridge.estimation.errors import EstimationError
from koala_bridge.estimation.probability import log_normalise
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
WallObservation = Sequence[bool | None]  # N, E, S, W

SIDE_INDEX = {s: i for i, s in enumerate(SIDES)}


@dataclass(frozen=True)
class GridModel:
    """The map facts the filter needs, as arrays precomputed once from a :class:`Grid`.

    Attributes:
        rows, cols: grid size in cells.
        free: ``(rows, cols)`` True where the cell is not blocked.
        walls: ``(4, rows, cols)`` True where side ``N, E, S, W`` of the cell is a wall
            (``Grid.wall_signature``).
        movable: ``(4, rows, cols)`` True where the robot can move out through that side
            (``Grid.can_move``).
    """

    rows: int
    cols: int
    free: BoolArray
    walls: BoolArray
    movable: BoolArray

    @classmethod
    def from_world(cls, world: Grid) -> GridModel:
        rows, cols = world.rows, world.cols
        free = np.zeros((rows, cols), dtype=bool)
        walls = np.zeros((4, rows, cols), dtype=bool)
        movable = np.zeros((4, rows, cols), dtype=bool)
        for r in range(rows):
            for c in range(cols):
                free[r, c] = (c, r) not in world.blocked
                walls[:, r, c] = world.wall_signature(c, r)
                movable[:, r, c] = [world.can_move(c, r, s) for s in SIDES]
        for a in (free, walls, movable):
            a.flags.writeable = False
        return cls(rows, cols, free, walls, movable)


@dataclass(frozen=True)
class GridParams:
    """Probabilities of the lab's motion and wall models (seeds/003 "Key functions" C, D).

    Attributes:
        p_move: probability that a commanded, unobstructed move reaches the neighbour (0.8 in the
            lab). Set it to the robot's measured success rate (docs/localisation.md).
        p_hit: ``P(wall reported | wall)`` (the lab's 90 % confidence in a detected wall).
        p_clear: ``P(no wall reported | no wall)`` (the lab's 70 % confidence in no wall).
    """

    p_move: float = 0.8
    p_hit: float = 0.9
    p_clear: float = 0.7

    def __post_init__(self) -> None:
        for name in ("p_move", "p_hit", "p_clear"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise EstimationError(f"GridParams.{name} must be in [0, 1], got {v}")


def uniform_prior(model: GridModel) -> FloatArray:
    """Log-belief with equal probability on every free cell (no known start)."""
    lb = np.where(model.free, 0.0, -np.inf)
    return log_normalise(lb)


def known_start_prior(model: GridModel, cell: tuple[int, int], p: float = 1.0) -> FloatArray:
    """Log-belief with probability ``p`` on ``cell = (col, row)`` and the rest spread uniformly
    over the other free cells (the lab's "force" of seeds/003 B, asserting a start)."""
    col, row = cell
    if not (0 <= row < model.rows and 0 <= col < model.cols) or not model.free[row, col]:
        raise EstimationError(f"start cell {cell} is outside the grid or blocked")
    n_other = int(model.free.sum()) - 1
    prob = np.zeros((model.rows, model.cols))
    if n_other > 0:
        prob[model.free] = (1.0 - p) / n_other
    prob[row, col] = p if n_other > 0 else 1.0
    with np.errstate(divide="ignore"):
        return log_normalise(np.log(prob))


def predict(log_belief: FloatArray, model: GridModel, side: str, p_move: float) -> FloatArray:
    """Motion update for a commanded one-cell move towards ``side`` (see module docstring).

    Args:
        log_belief: ``(rows, cols)`` log-probabilities.
        model: the map arrays.
        side: ``"N"``, ``"E"``, ``"S"`` or ``"W"``.
        p_move: probability that an unobstructed move succeeds.

    Returns:
        The normalised predicted log-belief, ``(rows, cols)``.
    """
    k = SIDE_INDEX[side]
    m = float(np.max(log_belief))
    b = np.exp(log_belief - m)
    mov = model.movable[k]
    go = np.where(mov, p_move * b, 0.0)
    out = b - go
    # Grid.can_move is False at the grid's edge, so nothing is shifted off the array.
    if side == "N":
        out[1:, :] += go[:-1, :]
    elif side == "S":
        out[:-1, :] += go[1:, :]
    elif side == "E":
        out[:, 1:] += go[:, :-1]
    else:
        out[:, :-1] += go[:, 1:]
    total = float(out.sum())  # > 0: the mass is conserved
    with np.errstate(divide="ignore"):
        return np.log(out) - math.log(total)


def wall_log_likelihood(
    model: GridModel, observed: WallObservation, p_hit: float, p_clear: float
) -> FloatArray:
    """``log P(observed walls | robot in cell)`` for every cell, ``(rows, cols)`` (seeds/003 D).

    ``observed`` lists ``N, E, S, W``: True = wall reported, False = no wall, None = not seen.
    """
    if len(observed) != 4:
        raise EstimationError(f"a wall observation has 4 sides (N, E, S, W), got {observed!r}")
    with np.errstate(divide="ignore"):
        l_hit, l_miss = float(np.log(p_hit)), float(np.log1p(-p_hit))
        l_clear, l_false = float(np.log(p_clear)), float(np.log1p(-p_clear))
    ll = np.zeros((model.rows, model.cols))
    for k, z in enumerate(observed):
        if z is None:
            continue
        if z:
            ll += np.where(model.walls[k], l_hit, l_false)
        else:
            ll += np.where(model.walls[k], l_miss, l_clear)
    return ll


def update(
    log_belief: FloatArray,
    model: GridModel,
    observed: WallObservation,
    p_hit: float,
    p_clear: float,
) -> FloatArray:
    """Measurement update with one wall observation; returns the normalised log-belief.

    Raises :class:`EstimationError` when the observation is impossible in every cell (only when
    ``p_hit`` or ``p_clear`` is exactly 1).
    """
    return log_normalise(log_belief + wall_log_likelihood(model, observed, p_hit, p_clear))


def guess_cell(log_belief: FloatArray) -> tuple[int, int]:
    """The most probable cell ``(col, row)`` (seeds/003 G); ties go to the first in row-major
    order from the south-west corner (lowest row, then lowest column)."""
    idx = int(np.argmax(log_belief))
    row, col = divmod(idx, log_belief.shape[1])
    return (col, row)


def belief_probabilities(log_belief: FloatArray) -> FloatArray:
    """The belief as probabilities summing to 1, ``(rows, cols)``."""
    return np.exp(log_normalise(log_belief))


class GridLocaliser:
    """Stateful histogram filter over a world's cells (thin wrapper over the pure functions).

    Call :meth:`observe` when the robot is stopped at a cell centre and :meth:`move` after each
    commanded one-cell move (whether or not the robot thinks it succeeded: the model accounts
    for failure and for walls).
    """

    def __init__(
        self,
        world: Grid,
        params: GridParams,
        start: tuple[int, int] | None = None,
    ) -> None:
        self.world = world
        self.params = params
        self.model = GridModel.from_world(world)
        self.log_belief = self._prior(start)

    def _prior(self, start: tuple[int, int] | None) -> FloatArray:
        if start is None:
            return uniform_prior(self.model)
        return known_start_prior(self.model, start)

    def reset(self, start: tuple[int, int] | None = None) -> None:
        """Back to a uniform prior, or to certainty at ``start = (col, row)``."""
        self.log_belief = self._prior(start)

    def move(self, side: str) -> None:
        """Prediction for a commanded move towards ``side``."""
        self.log_belief = predict(self.log_belief, self.model, side, self.params.p_move)

    def observe(self, walls: WallObservation) -> None:
        """Correction with the walls seen on ``N, E, S, W`` (None: side not observed)."""
        self.log_belief = update(
            self.log_belief, self.model, walls, self.params.p_hit, self.params.p_clear
        )

    def guess(self) -> tuple[int, int]:
        """The most probable cell ``(col, row)``."""
        return guess_cell(self.log_belief)

    def probability(self, cell: tuple[int, int]) -> float:
        """The belief's probability of ``cell = (col, row)``."""
        col, row = cell
        return float(math.exp(self.log_belief[row, col]))

    def probabilities(self) -> FloatArray:
        """The belief as probabilities, ``(rows, cols)``, row 0 south."""
        return belief_probabilities(self.log_belief)
