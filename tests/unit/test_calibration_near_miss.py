"""When the loop stops, the report says what nearly passed and why it did not.

A new-user trial (OptiOdom) saw wheel-base, heading-drift and wheel-ratio candidates improve the
held-out part by 19-24 % on short runs and not pass; only the candidate table showed it. The
notes now name such a candidate with its statistics, and say when the held-out part holds too
few independent units for anything to pass.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from koala_bridge.calibration.pipeline import NEAR_MISS_GAIN, _note_near_misses
from koala_bridge.calibration.selection import Trial


def _problem(units: int | None) -> SimpleNamespace:
    return SimpleNamespace(notes=[], independent_count=lambda part, r=None: units)


def _selection(*trials: Trial, rho: float = 0.0, n: int = 100) -> SimpleNamespace:
    return SimpleNamespace(rounds=[list(trials)], rho=rho,
                           after=SimpleNamespace(r_score=np.zeros(n)))


def test_a_large_gain_that_is_not_significant_is_named() -> None:
    problem = _problem(units=3)
    sel = _selection(
        Trial("wheel_base", 1, -2.0, 8.59, 9.55, 0.19, False),
        Trial("tick_scale", 1, 1.0, 0.4, 9.55, 0.02, False),  # small gain: not named
        Trial("time_offset", 1, 1.0, -3.0, 9.55, -0.1, False),
    )
    _note_near_misses(problem, sel)  # type: ignore[arg-type]
    assert len(problem.notes) == 2
    assert problem.notes[0].startswith("wheel_base not added though it improves the held-out "
                                       "part by 19 %: not significant (held-out likelihood "
                                       "ratio 8.59 < 9.55)")
    assert "about 3 independent units" in problem.notes[1]


def test_nothing_is_said_when_nothing_came_close() -> None:
    problem = _problem(units=None)
    sel = _selection(Trial("bias", 1, 1.0, 0.1, 6.6, NEAR_MISS_GAIN / 2, False), rho=0.999)
    _note_near_misses(problem, sel)  # type: ignore[arg-type]
    assert problem.notes == []
