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
from koala_bridge.calibration.bundle import Bundle
from koala_bridge.calibration.effects import available_effects, get_effect
from koala_bridge.calibration.effects.base import EffectInstance
from koala_bridge.calibration.errors import EffectRegistryError
from koala_bridge.calibration.model import DeclaredModel
from koala_bridge.calibration.problem import SecondaryMetric, StreamProblem
from koala_bridge.calibration.selection import (
    ALPHA,
    MAX_EFFECTS,
    Selection,
    Trial,
    fit_model,
    parameter_se,
    select_effects,
)
from koala_bridge.calibration.streams import (
    build_compass,
    build_gyro,
    build_landmarks,
    build_odometry,
    build_ranges,
)
from koala_bridge.calibration.streams.compass import CompassProblem
from scipy import stats

log = logging.getLogger(__name__)

#: Callback ``(stream, done, total)`` for progress display; the library never prints.
Progress = Callable[[str, int, int], None]


@dataclass(frozen=True)
class Options:
    window_s: float = 5.0
    max_effects: int = MAX_EFFECTS
    effects: Sequence[str] | None = None  # restrict the candidate library (names), None = all
    max_rows: int = 20_000  # longer tables: select on a subset, refit on everything


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

    def metrics(self) -> list[SecondaryMetric]:
        """Every reported metric of the stream: its own first, then the secondary ones."""
        p = self.problem
        return [SecondaryMetric(p.metric, p.unit, self.before, self.after), *self.secondary]

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
    """Every registered effect's proposals for ``problem``, optionally restricted by name: an
    effect's name (``offset_per``) takes all its proposals, a proposal's own name as the report
    prints it (``offset_per:sensor``, ``covariate:temperature_c``) just that one."""
    out: list[EffectInstance] = []
    for name, effect in available_effects().items():
        if names is not None and name not in names:
            out.extend(i for i in effect.propose(problem) if i.name in names)
            continue
        out.extend(effect.propose(problem))
    return out


def check_effect_names(names: Sequence[str]) -> None:
    """Raise :class:`EffectRegistryError` for a name that is neither a registered effect nor
    ``<effect>:<column>`` of one."""
    known = available_effects()
    unknown = [n for n in names if n.split(":", 1)[0] not in known]
    if unknown:
        raise EffectRegistryError(
            f"unknown effect {', '.join(map(repr, unknown))}; registered: {', '.join(known)} "
            "(per-column ones as covariate:<column>, offset_per:<column>)"
        )


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
    if getattr(problem, "turn_on_bias_sigma", 0.0) > 0 and (
        options.effects is None or "bias" in options.effects
    ):
        _turn_on_bias_check(problem, sel)
    before = problem.metric_value(sel.before.insts, sel.before.x, "score")
    after = problem.metric_value(sel.after.insts, sel.after.x, "score")
    secondary = problem.secondary_metrics(
        (sel.before.insts, sel.before.x), (sel.after.insts, sel.after.x)
    )
    _note_known_rotation(problem, secondary)
    return StreamResult(problem, sel, before, after, secondary)


def _note_known_rotation(problem: StreamProblem, secondary: Sequence[SecondaryMetric]) -> None:
    """A known net rotation (meta.json) is one number: it cannot be split into fit and score
    parts, so it only ever *checks* a model. What it implies is noted for the reader: the scale
    error ``s = e / K`` that would close the remaining error ``e`` of the total ``K``, not
    added, as nothing held out could test it (the hand that turned the sensor, or the bias, may
    account for it as well)."""
    known = getattr(problem, "known_rotation", None)
    for m in secondary:
        if m.metric == "known_rotation_error" and known is not None and known[2] != 0:
            problem.notes.append(
                f"known total rotation {known[2]:.4g} rad: the model leaves {m.after:+.3g} rad; "
                f"a further gyro scale error of {100 * m.after / known[2]:+.2g} % would close "
                "it (one number, not testable on held-out data: not added)"
            )


def _turn_on_bias_check(problem: StreamProblem, sel: Selection) -> None:
    """A declared per-run bias ``N(mu, sigma^2)`` is a nuisance, fitted in every model (its
    deviation from ``mu`` is ``x[0]``). When the fitted deviation is implausible under that
    distribution, ``|b| / sqrt(sigma^2 + SE^2) > z(1 - alpha/2)``, the data hold a bias the
    declared model lacks: ``bias`` is added (its value fixed at ``b``, the nuisance refitted),
    so ``--write-config`` writes ``bias_rad_s = mu + b``."""
    sigma = float(getattr(problem, "turn_on_bias_sigma", 0.0))
    fit = sel.after
    b = float(fit.x[0])
    se = float(parameter_se(problem, fit)[0])
    z = abs(b) / float(np.hypot(sigma, se))
    threshold = float(stats.norm.ppf(1 - ALPHA / 2))
    problem.notes.append(
        f"turn-on bias fitted: {b:+.4g} (declared sigma {sigma:g}, SE {se:.2g}, z = {z:.2f})"
    )
    if z <= threshold or len(sel.added) >= MAX_EFFECTS:
        return
    inst = EffectInstance("bias", get_effect("bias"), ("bias",), (b,), fixed=True)
    insts = [*fit.insts, inst]
    new = fit_model(problem, insts, problem.initial_vector(insts, fit.x, fit.insts))
    trial = Trial("bias", 1, float("nan"), z * z, threshold**2, 0.0, True, new)
    sel.added.append((inst, trial))
    sel.after = new


def decimate_bundle(bundle: Bundle, max_rows: int, references: bool = False) -> Bundle:
    """The bundle with long measurement tables cut to about ``max_rows`` rows (rows kept in
    order): a random subset for independent readings, a regular stride for odometry, whose
    cumulative counts stay valid on any subset. ``truth_pose`` is cut (by stride) only when
    ``references`` is true: a gyro's reference rate needs it at full resolution."""
    if all(len(t) <= max_rows for t in bundle.tables.values()):
        return bundle
    rng = np.random.default_rng(0)
    tables = {}
    for name, table in bundle.tables.items():
        n = len(table)
        if n > max_rows and (name != "truth_pose" or references):
            keep = np.zeros(n, dtype=bool)
            if name in ("odometry", "truth_pose"):
                keep[:: -(-n // max_rows)] = True
            else:
                keep[rng.choice(n, max_rows, replace=False)] = True
            keep[[0, -1]] = True  # keep the span, so the split is the same
            table = table.select(keep)
        tables[name] = table
    return Bundle(bundle.path, tables, bundle.meta)


def _problems(
    bundle: Bundle,
    model: DeclaredModel,
    options: Options,
    compass_heading: Any = None,
    with_compass: bool = True,
    odometry_bundle: Bundle | None = None,
) -> list[StreamProblem]:
    out: list[StreamProblem | None] = []
    if with_compass:
        out.append(build_compass(bundle, model))
    else:
        out.append(build_gyro(bundle, model, compass_heading))
        out.append(build_odometry(odometry_bundle or bundle, model, options.window_s))
        out.extend(build_ranges(bundle, model))
        out.extend(build_landmarks(bundle, model))
    return [p for p in out if p is not None]


def refit_full(full: StreamProblem, small: StreamResult) -> StreamResult:
    """Refit the effects selected on a decimated stream on the full stream; metrics on it."""
    sel = small.selection
    before = fit_model(full, [], full.nuisance_x0())
    insts = list(sel.after.insts)
    after = fit_model(
        full,
        insts,
        full.initial_vector(insts, sel.after.x, insts) if len(sel.after.x) else full.nuisance_x0(),
    )
    added = list(sel.added)
    result = Selection(full, before, after, added, sel.rounds, sel.rho)
    b = full.metric_value(before.insts, before.x, "score")
    a = full.metric_value(after.insts, after.x, "score")
    secondary = full.secondary_metrics((before.insts, before.x), (after.insts, after.x))
    _note_known_rotation(full, secondary)
    return StreamResult(full, result, b, a, secondary)


def calibrate(
    bundle: Bundle,
    model: DeclaredModel,
    options: Options | None = None,
    progress: Progress | None = None,
) -> list[StreamResult]:
    """Run the loop on every stream the bundle holds; see the module docstring for the order.

    Streams longer than ``options.max_rows`` samples are selected on a random subset of that
    size (estimates from 20 000 samples are far more precise than any tolerance, and the test
    is then only more conservative); the selected effects are refitted on the full stream and
    before/after are measured on the full held-out part.
    """
    options = options or Options()
    small = decimate_bundle(bundle, options.max_rows)
    small_odometry = decimate_bundle(bundle, options.max_rows, references=True)

    def run(
        problems_small: list[StreamProblem], problems_full: list[StreamProblem]
    ) -> list[StreamResult]:
        out = []
        full_by_name = {p.name: p for p in problems_full}
        for p in problems_small:
            res = run_stream(p, options, progress)
            out.append(res if small is bundle else refit_full(full_by_name[p.name], res))
        return out

    results = run(
        _problems(small, model, options),
        _problems(bundle, model, options) if small is not bundle else [],
    )
    compass_heading = None
    for res in results:
        if isinstance(res.problem, CompassProblem):
            compass_heading = compass_heading_of(res.problem, res.selection)
    # The decimated gyro gets the full compass heading too (it is a reference series).
    results += run(
        _problems(
            small,
            model,
            options,
            compass_heading,
            with_compass=False,
            odometry_bundle=small_odometry,
        ),
        _problems(bundle, model, options, compass_heading, with_compass=False)
        if small is not bundle
        else [],
    )
    return results  # empty: no stream with a reference (the caller says so)


def compass_heading_of(problem: CompassProblem, sel: Selection) -> tuple[Any, Any] | None:
    """The calibrated compass heading over the whole span, for use as a gyro reference."""
    if problem.mode == "magnitude_3d":
        return None
    mc = problem.corrected(sel.after.insts, sel.after.x, "all")
    return problem.t, np.unwrap(problem.heading(mc))
