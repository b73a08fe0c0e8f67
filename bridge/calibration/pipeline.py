"""Calibrate a bundle: build the stream problems, run the residual loop on each, collect results.

Order: compass first (its calibrated heading can be the gyro's reference when the bundle has no
truth heading), then gyro, odometry, range sensors and landmarks.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from bridge.calibration.bundle import Bundle
from bridge.calibration.effects import available_effects
from bridge.calibration.effects.base import EffectInstance
from bridge.calibration.model import DeclaredModel
from bridge.calibration.problem import SecondaryMetric, StreamProblem
from bridge.calibration.selection import MAX_EFFECTS, Selection, parameter_se, select_effects
from bridge.calibration.streams import (
    build_compass,
    build_gyro,
    build_landmarks,
    build_odometry,
    build_ranges,
)
from bridge.calibration.streams.compass import CompassProblem

log = logging.getLogger(__name__)

#: Callback ``(stream, done, total)`` for progress display; the library never prints.
Progress = Callable[[str, int, int], None]


@dataclass(frozen=True)
class Options:
    window_s: float = 5.0
    max_effects: int = MAX_EFFECTS
    effects: Sequence[str] | None = None  # restrict the candidate library (names), None = all


@dataclass
class StreamResult:
    """Everything the report needs about one stream."""

    problem: StreamProblem
    selection: Selection
    before: float
    after: float
    secondary: list[SecondaryMetric] = field(default_factory=list)

    @property
    def effects(self) -> list[EffectInstance]:
        return [inst for inst, _ in self.selection.added]

    def effect_params(self) -> list[tuple[dict[str, float], dict[str, float]]]:
        """Per added effect: its parameters and their standard errors (fixed ones: none)."""
        sel = self.selection
        params = sel.params_of(sel.after)
        se = parameter_se(self.problem, sel.after)
        k0 = len(self.problem.nuisance_x0())
        offsets: dict[str, int] = {}
        k = k0
        for inst in sel.after.insts:
            if not inst.fixed:
                offsets[inst.name] = k
                k += inst.n_free
        out = []
        for inst in self.effects:
            p = params[sel.after.insts.index(inst)]
            entry: dict[str, float] = {
                n: float(f"{v:.6g}") for n, v in zip(inst.param_names, p, strict=True)
            }
            errs: dict[str, float] = {}
            if inst.name in offsets:
                for j, n in enumerate(inst.param_names):
                    errs[n] = float(f"{se[offsets[inst.name] + j]:.3g}")
            out.append((entry, errs))
        return out


def candidates_for(
    problem: StreamProblem, names: Sequence[str] | None = None
) -> list[EffectInstance]:
    """Every registered effect's proposals for ``problem``, optionally restricted by name."""
    out: list[EffectInstance] = []
    for name, effect in available_effects().items():
        if names is not None and name not in names:
            continue
        out.extend(effect.propose(problem))
    return out


def count_work(problems: Sequence[StreamProblem]) -> int:
    return sum(len(candidates_for(p)) for p in problems)


def run_stream(
    problem: StreamProblem, options: Options, progress: Progress | None = None
) -> StreamResult:
    cands = candidates_for(problem, options.effects)
    done = 0

    def tick() -> None:
        nonlocal done
        done += 1
        if progress is not None:
            progress(problem.name, done, len(cands))

    sel = select_effects(problem, cands, options.max_effects, on_trial=tick)
    before = problem.metric_value(sel.before.insts, sel.before.x, "score")
    after = problem.metric_value(sel.after.insts, sel.after.x, "score")
    secondary = problem.secondary_metrics(
        (sel.before.insts, sel.before.x), (sel.after.insts, sel.after.x)
    )
    return StreamResult(problem, sel, before, after, secondary)


def calibrate(
    bundle: Bundle,
    model: DeclaredModel,
    options: Options | None = None,
    progress: Progress | None = None,
) -> list[StreamResult]:
    """Run the loop on every stream the bundle holds; see the module docstring for the order."""
    options = options or Options()
    results: list[StreamResult] = []
    compass = build_compass(bundle, model)
    compass_heading = None
    if compass is not None:
        res = run_stream(compass, options, progress)
        results.append(res)
        compass_heading = compass_heading_of(compass, res.selection)
    gyro = build_gyro(bundle, model, compass_heading)
    others: list[StreamProblem | None] = [gyro, build_odometry(bundle, model, options.window_s)]
    others.extend(build_ranges(bundle, model))
    others.extend(build_landmarks(bundle, model))
    for problem in others:
        if problem is not None:
            results.append(run_stream(problem, options, progress))
    if not results:
        log.warning("%s: no stream with a reference to calibrate against", bundle.path)
    return results


def compass_heading_of(problem: CompassProblem, sel: Selection) -> tuple[Any, Any] | None:
    """The calibrated compass heading over the whole span, for use as a gyro reference."""
    if problem.mode == "magnitude_3d":
        return None
    mc = problem.corrected(sel.after.insts, sel.after.x, "all")
    return problem.t, np.unwrap(problem.heading(mc))
