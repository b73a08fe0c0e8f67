"""Calibrate a bundle: build the stream problems, run the residual loop on each, collect results.

Order: compass first (its calibrated heading can be the gyro's reference when the bundle has no
truth heading), then gyro, odometry, range sensors and landmarks.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from koala_bridge.calibration.bundle import Bundle
from koala_bridge.calibration.effects import available_effects, get_effect
from koala_bridge.calibration.effects.base import EffectInstance
from koala_bridge.calibration.effects.common import (
    MAX_REFERENCE_NOISE_SHARE,
    NOTE_REFERENCE_NOISE_SHARE,
    reference_noise_share,
    stream_share,
)
from koala_bridge.calibration.effects.scale import GROSS_GAIN, gross_gain
from koala_bridge.calibration.effects.time_offset import (
    clock_rival,
    clocks_note,
    correlations,
    search_window,
)
from koala_bridge.calibration.errors import EffectRegistryError
from koala_bridge.calibration.fault_log import set_aside_faulted
from koala_bridge.calibration.metrics import HeldOutStatistics, g4, heldout_statistics
from koala_bridge.calibration.model import META_KEYS, DeclaredModel
from koala_bridge.calibration.noise import StreamNoise, identify_noise
from koala_bridge.calibration.problem import (
    FloatArray,
    SecondaryMetric,
    SkippedStream,
    StreamProblem,
    effective_size,
    split_params,
)
from koala_bridge.calibration.selection import (
    ALPHA,
    MAX_EFFECTS,
    Fit,
    Selection,
    Trial,
    at_values,
    fit_model,
    heldout_score,
    parameter_se,
    select_effects,
)
from koala_bridge.calibration.sim_keys import config_path, is_simulated
from koala_bridge.calibration.streams import (
    beacon_streams,
    build_beacons,
    build_compass,
    build_gyro,
    build_landmarks,
    build_odometry,
    build_ranges,
    bundle_streams,
    to_heading_space,
    unknown_files,
)
from koala_bridge.calibration.streams.compass import CompassProblem
from koala_bridge.calibration.streams.level import build_gyro_level, note_level_bias
from koala_bridge.calibration.streams.scalar import ScalarProblem
from koala_bridge.calibration.units import Misread, misread_units
from koala_bridge.core.distributions import norm_ppf

log = logging.getLogger(__name__)

#: ``z(1 - ALPHA / 2)`` (2.58): the two-sided bar of the turn-on bias test, of the declared
#: turn-on spread "before" may fit, and of writing: ``--write-config`` writes a fitted effect
#: only when it is at least this many standard errors from the declared model (the declared
#: value outside the effect's 99 % interval). A slipping wheel once proposed ticks_per_metre
#: 22 222 -> 70 968 with an SE of 32 500 (1.5 SE), which ``|d| < SE`` alone would have written.
WRITE_Z = norm_ppf(1 - ALPHA / 2)

#: Callback ``(stream, done, total)`` for progress display; the library never prints.
Progress = Callable[[str, int, int], None]


@dataclass(frozen=True)
class Options:
    window_s: float = 5.0
    max_effects: int = MAX_EFFECTS
    effects: Sequence[str] | None = None  # restrict the candidate library (names), None = all
    max_rows: int = 20_000  # longer tables: select on a subset, refit on everything


def _better(value: float, declared: float) -> bool:
    """Whether a held-out metric ``value`` beats the declared model's (by magnitude: a signed
    metric's sign says on which side, not how far)."""
    return bool(abs(value) < abs(declared))


@dataclass(frozen=True)
class WrittenModel:
    """What ``--write-config`` writes of a stream, scored on the held-out part
    (:meth:`StreamResult._written_eval`)."""

    #: held-out metric of the written effects at their final values; None when every effect
    #: is written (then it is *after*)
    value: float | None
    #: the declared model's
    declared: float
    #: effects written only as comments (the simulator has no key for them)
    comments: list[str]
    #: simulated effects left out because the written model beats the declared one only
    #: without them: name -> the written model's metric with it (before it was left out)
    unhelpful: dict[str, float]
    #: no simulated effect is left to write
    none_left: bool


@dataclass
class StreamResult:
    """Everything the report needs about one stream."""

    problem: StreamProblem
    selection: Selection
    before: float
    after: float
    secondary: list[SecondaryMetric] = field(default_factory=list)
    #: Allan-variance noise terms of a rate stream's residual (calibration/noise.py)
    noise: StreamNoise | None = None
    #: the notes the selection added to the stream (an effect not tried, and why): a stream
    #: selected on a decimated subset carries them to the full stream's result
    selection_notes: list[str] = field(default_factory=list)
    #: :meth:`_written_eval`, with the final fit it was computed for
    _written_memo: tuple[Any, WrittenModel] | None = field(
        default=None, init=False, repr=False, compare=False)
    #: :meth:`_params_and_se` of the final fit it was computed for
    _se_memo: tuple[tuple[Any, ...], list[tuple[FloatArray, FloatArray | None]]] | None = field(
        default=None, init=False, repr=False, compare=False)

    @property
    def effects(self) -> list[EffectInstance]:
        return [inst for inst, _ in self.selection.added]

    def metrics(self) -> list[SecondaryMetric]:
        """Every reported metric of the stream: its own first, then the secondary ones."""
        p = self.problem
        return [SecondaryMetric(p.metric, p.unit, self.before, self.after), *self.secondary]

    def _params_and_se(self) -> list[tuple[FloatArray, FloatArray | None]]:
        """Per added effect: its parameter values and their standard errors (None: fixed).
        Kept while the selection's final fit is the same object with the same vector: the
        report asks for them once per table and figure (a sandwich SE of a 1-hour stream
        costs tens of ms)."""
        sel = self.selection
        key = (sel.after, sel.after.x.tobytes(), tuple(self.effects))
        memo = self._se_memo
        if memo is not None and memo[0][0] is key[0] and memo[0][1:] == key[1:]:
            return memo[1]
        out = self._compute_params_and_se()
        self._se_memo = (key, out)
        return out

    def _compute_params_and_se(self) -> list[tuple[FloatArray, FloatArray | None]]:
        sel = self.selection
        params = sel.params_of(sel.after)
        se = parameter_se(self.problem, sel.after)
        offsets: dict[str, int] = {}
        k = len(self.problem.nuisance_x0())
        for inst in sel.after.insts:
            if not inst.fixed:
                offsets[inst.name] = k
                k += inst.n_free
        out: list[tuple[FloatArray, FloatArray | None]] = []
        for inst in self.effects:
            p = params[sel.after.insts.index(inst)]
            k = offsets.get(inst.name, -1)
            out.append((p, None if k < 0 else se[k : k + len(inst.param_names)]))
        return out

    def effect_params(self) -> list[tuple[dict[str, float], dict[str, float]]]:
        """Per added effect: its parameters and their standard errors (fixed ones: none)."""
        out = []
        for inst, (p, se) in zip(self.effects, self._params_and_se(), strict=True):
            entry = {n: float(f"{v:.6g}") for n, v in zip(inst.param_names, p, strict=True)}
            errs = (
                {}
                if se is None
                else {n: float(f"{v:.3g}") for n, v in zip(inst.param_names, se, strict=True)}
            )
            out.append((entry, errs))
        return out

    def not_written(self) -> list[str | None]:
        """Per added effect: why ``--write-config`` must not write it, or None. An effect is
        *uncertain* when its size, ``d = params - absent``, is within ``WRITE_Z`` standard
        errors of nothing: ``sum d^2 < WRITE_Z^2 sum SE^2`` (``|d| < WRITE_Z SE`` for one
        parameter: the declared value lies inside the effect's 99 % interval), or when the
        effect bounds a bias of its estimate beyond ``WRITE_Z`` standard errors
        (:meth:`Effect.estimate_bias`: a gain diluted by a noisy reference). Fixed parameters
        (a glitch value, a quantisation step, a turn-on bias judged against its declared
        spread) have no standard error here. And the simulated effects are not written when,
        at their values, without the effects the written config cannot hold (uncertain ones,
        and those the simulator has no key for: a time offset, a covariate), they leave the
        held-out error no better than the declared model's: they only help beside those (a
        gyro's +2.2 % scale with the time offset it was fitted with, worse than none alone)."""
        out = self._uncertain()
        w = self._written_eval()
        if not w.unhelpful:
            return out
        alone = (f"without {', '.join(w.comments)} (written only as a comment)" if w.comments
                 else "without the uncertain effects")
        besides = (f"{', '.join(w.comments)} written only as a comment" if w.comments
                   else "the uncertain effects left out")
        shown = g4(w.value if w.value is not None else w.declared)
        if w.none_left:
            first = next(iter(w.unhelpful.values()))
            why = {name: (f"alone it does not improve the held-out error: {g4(first)} {alone} "
                          f"against {g4(w.declared)} declared") for name in w.unhelpful}
        else:
            why = {name: (f"the written model does not beat the declared one with it: "
                          f"{g4(with_it)} with it, {shown} without it ({besides}), against "
                          f"{g4(w.declared)} declared") for name, with_it in w.unhelpful.items()}
        return [why.get(inst.name, r) for inst, r in zip(self.effects, out, strict=True)]

    def _uncertain(self) -> list[str | None]:
        out: list[str | None] = []
        pairs = self._params_and_se()
        units = [inst.effect.not_a_sensor_error(inst, np.asarray(p, dtype=float), self.problem)
                 for inst, (p, _) in zip(self.effects, pairs, strict=True)]
        unit_of = next(((inst, u) for inst, u in zip(self.effects, units, strict=True)
                        if u is not None), None)
        for inst, (p, se), unit in zip(self.effects, pairs, units, strict=True):
            if unit is not None:
                out.append(unit)
                continue
            if unit_of is not None:
                # fitted in the bundle's unit beside it: a bias in deg/s read as rad/s
                out.append(f"fitted beside {unit_of[0].name} ({unit_of[1].split('. ')[0]}), "
                           "in the readings' unit, not the sensor model's: fix the bundle first")
                continue
            if se is None:
                out.append(None)
                continue
            d = np.asarray(p, dtype=float) - inst.effect.absent(inst)
            size, err = float(np.sqrt(np.sum(d**2))), float(np.sqrt(np.sum(se**2)))
            if not np.isfinite(err):
                out.append("uncertainty unknown: its standard error could not be computed")
            elif size < WRITE_Z * err:
                what = "|value - declared|" if d.size == 1 else "|values - declared|"
                out.append(
                    f"uncertainty larger than the effect: {what} = {size:.3g} < "
                    f"{WRITE_Z:.3g} SE = {WRITE_Z * err:.3g} (the declared value lies inside "
                    "its 99 % interval)"
                )
            else:
                biased = inst.effect.estimate_bias(inst, np.asarray(p, dtype=float),
                                                   self.problem)
                if biased is not None and biased[0] > WRITE_Z * err:
                    out.append(
                        f"biased beyond its uncertainty: by up to {biased[0]:.3g}, more than "
                        f"{WRITE_Z:.3g} SE = {WRITE_Z * err:.3g}: {biased[1]}"
                    )
                else:
                    out.append(None)
        return out

    def effect_paths(self, inst: EffectInstance) -> list[str]:
        """The dotted config keys ``inst`` writes, simulated or not, at its final values."""
        p, after = self.problem, self.selection.after
        params = split_params(p, after.insts, after.x)[after.insts.index(inst)]
        return [config_path(p.section, key) for key in inst.config(params, p)]

    def is_comment(self, inst: EffectInstance) -> bool:
        """Whether ``--write-config`` can write ``inst`` only as a comment (no simulator key)."""
        return not any(is_simulated(path) for path in self.effect_paths(inst))

    def _written_eval(self) -> WrittenModel:
        """The effects the written config can hold (certain and simulated), at the values the
        final fit gave them -- what a reader who simulates it gets, no refit -- scored on the
        held-out part. When they do not beat the declared model, the simulated effect whose
        removal leaves the best held-out metric is left out, in turn, until they do or none is
        left: a gyro's +2.2 % scale that helps only beside the time offset it was fitted with
        is left out, the bias beside it written. Kept for the same final fit: the report asks
        for it in several places."""
        memo = self._written_memo
        if memo is not None and memo[0] is self.selection.after:
            return memo[1]
        sel, p = self.selection, self.problem
        declared = float(p.metric_value(sel.before.insts, sel.before.x, "score"))
        comment = [self.is_comment(i) for i in self.effects]
        comments = [i.name for i, c in zip(self.effects, comment, strict=True) if c]
        dropped = {id(i) for i, r, c in zip(self.effects, self._uncertain(), comment, strict=True)
                   if r is not None or c}

        def score(keep: list[EffectInstance]) -> float:
            if not keep:
                return declared
            return float(p.metric_value(
                keep, p.initial_vector(keep, sel.after.x, sel.after.insts), "score"))

        value: float | None = None
        unhelpful: dict[str, float] = {}
        found = {id(i) for i in self.effects}  # the rest of the model: nuisance instances
        keep = [i for i in sel.after.insts if id(i) not in dropped]
        if dropped:
            value = score(keep)
            while not _better(value, declared) and any(id(i) in found for i in keep):
                options = [[j for j in keep if j is not i] for i in keep if id(i) in found]
                scores = [score(o) for o in options]
                best = int(np.argmin(np.abs(scores)))
                (gone,) = [i for i in keep if i not in options[best]]
                unhelpful[gone.name] = value
                keep, value = options[best], scores[best]
        result = WrittenModel(value, declared, comments, unhelpful,
                              none_left=not any(id(i) in found for i in keep))
        self._written_memo = (sel.after, result)
        return result

    def after_written(self) -> float | None:
        """The held-out metric of the model ``--write-config`` writes when that leaves an
        effect out (:meth:`not_written`, or written only as a comment), None when it writes
        them all: *after* counts every effect found, and a reader who simulates the written
        config sees this. The written effects at the values the final fit gave them, or the
        declared model when those would not beat it (then none is written)."""
        w = self._written_eval()
        if w.value is None:
            return None
        return w.value if _better(w.value, w.declared) else w.declared

    def heldout_statistics(self, before: FloatArray | None = None) -> HeldOutStatistics:
        """Robust statistics of the held-out errors before and after
        (:func:`koala_bridge.calibration.metrics.heldout_statistics`); ``before`` replaces the
        declared model's errors (a staged run's user-declared model)."""
        p, sel = self.problem, self.selection
        if before is None:
            before = p.heldout_errors(sel.before.insts, sel.before.x)
        return heldout_statistics(before, p.heldout_errors(sel.after.insts, sel.after.x))


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
    noted = len(problem.notes)  # what proposing and selecting note (an effect not tried, why)
    _note_clock_offset(problem)
    cands = candidates_for(problem, options.effects)
    if options.effects is not None:
        _note_unproposed(problem, options.effects, cands, noted)
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
    sel.before = declared_fit(problem, sel.before)
    sel.after = declared_fit(problem, sel.after)
    keep_only_helpful(problem, sel)
    # what was decided here holds for the whole stream (refit_full checks plausibility again)
    selection_notes = list(problem.notes[noted:])
    drop_implausible(problem, sel)
    before = problem.metric_value(sel.before.insts, sel.before.x, "score")
    after = problem.metric_value(sel.after.insts, sel.after.x, "score")
    secondary = problem.secondary_metrics(
        (sel.before.insts, sel.before.x), (sel.after.insts, sel.after.x)
    )
    _note_known_rotation(problem, secondary)
    _note_secondary_worse(problem, sel, before, after, secondary)
    _note_near_misses(problem, sel)
    _note_gross_gain(problem, sel)
    return StreamResult(problem, sel, before, after, secondary, selection_notes=selection_notes)


def _note_clock_offset(problem: StreamProblem) -> None:
    """Say so when a scalar stream or a compass and its reference look stamped on clocks
    seconds apart (:attr:`ScalarProblem.clocks_apart`, :attr:`CompassProblem.clocks_apart`),
    whether or not a time offset can be tried."""
    if isinstance(problem, ScalarProblem):
        if problem.reference is None:
            return
        score = "correlation"
    elif isinstance(problem, CompassProblem):
        score = "match of the declared heading, irons aside,"
    else:
        return
    found = problem.clocks_apart
    if found is None:
        return
    tau, r, r_near = found
    _, span = (search_window(problem) if isinstance(problem, ScalarProblem)
               else problem.latency_window())
    if abs(tau) <= span:
        return  # a latency the window holds (its inner half only centres the search)
    problem.notes.append(clocks_note(tau, r, r_near, score))
    rival = clock_rival(problem, tau) if isinstance(problem, ScalarProblem) else None
    if rival is not None:
        problem.notes.append(
            f"the clocks' offset is ambiguous: the readings match the reference about as well "
            f"{rival[0]:+.4g} s later ({score} {rival[1]:.3f}, against {rival[2]:.3f} at "
            f"{tau:+.3g} s, each refined to half a sample): motion that repeats matches itself "
            "a period on, and the fit part cannot tell which shift is the clocks'. Stamp both "
            "on one clock, or record motion that does not repeat"
        )


def _note_unproposed(
    problem: StreamProblem, names: Sequence[str], cands: Sequence[EffectInstance], noted: int
) -> None:
    """An effect of ``problem``'s kind asked for by name (``--effects``) that proposed nothing
    for it and that no note since ``noted`` explains: say that it was not tried, and why where
    it is plain (a reference computed per reading, which no shift moves), so that an effect
    asked for never vanishes without a word."""
    proposed = {c.name for c in cands} | {c.name.split(":", 1)[0] for c in cands}
    said = " ".join(problem.notes[noted:])
    for name in names:
        if name in proposed or f"{name} not tried" in said:
            continue
        effect = available_effects().get(name.split(":", 1)[0])
        if effect is None or problem.kind not in effect.kinds:
            continue  # an effect of another kind of stream (a compass's, asked for a gyro)
        if name == "time_offset" and getattr(problem, "reference", 1) is None:
            why = ("the reference is computed per reading (a true range), not a series in "
                   "time a shift could move: stamp the readings and the reference on one clock")
        elif ":" in name:
            why = "the stream has no such column, or its column does not vary"
        else:
            why = "it found nothing to fit on this stream (the notes above say what it lacks)"
        problem.notes.append(f"{name} asked for (--effects) but not tried: {why}")


def _note_gross_gain(problem: StreamProblem, sel: Selection) -> None:
    """A scale the fit part shows (its RMS halves) whose gain is beyond :data:`GROSS_GAIN`
    either way (by magnitude) is said with the unit or time base it most likely is, whether or
    not it passed: a car's gyro read with its log's 0.1 s steps as seconds integrated to 9.7
    times the reference's turns, its held-out part too still to confirm a scale, and the report
    said nothing."""
    for rnd in sel.rounds:
        for t in rnd:
            # the fit part shows it: its RMS at least halves (its BIC on a prewhitened residual
            # need not fall: at a lag-1 autocorrelation near 1 a smooth error does not show)
            if t.name != "scale" or t.fit is None or not t.fit.rss_fit <= sel.before.rss_fit / 4:
                continue
            # the final model's gain where it holds the scale (the table's figure: a round's
            # fit on the selection's subset read 55.2 beside the table's 55.8)
            fit = sel.after if any(i.name == "scale" for i in sel.after.insts) else t.fit
            at = [i.name for i in fit.insts].index("scale")
            gain = 1.0 + float(split_params(problem, fit.insts, fit.x)[at][0])
            likely = gross_gain(gain)
            if likely is None:
                continue
            problem.notes.append(
                f"the readings are {gain:.3g} times the reference on the fit part (scale fitted "
                f"{gain - 1:+.4g}, {'passed' if t.passed else 'not passed'}){likely}. A gain "
                f"beyond {GROSS_GAIN:g}:1 is a unit, a time base or a conversion, not a "
                "sensor's error: fix it in the bundle (docs/bundle-format.md: SI units, t in "
                "seconds)"
            )
            return


#: a candidate of the last round that failed only for want of evidence, with at least this
#: held-out gain, is named in the notes (a longer recording could tell)
NEAR_MISS_GAIN = 0.1


def _note_near_misses(problem: StreamProblem, sel: Selection) -> None:
    """Say why the loop stopped where a reader would expect more: the last round's candidates
    that improved the held-out part by :data:`NEAR_MISS_GAIN` or more yet did not pass: not
    the likelihood-ratio test (too few independent units to call it more than chance), or only
    the fit part's BIC (the two parts disagree); and residuals so correlated that the effective
    sample is a handful."""
    if not sel.rounds or any(t.passed for t in sel.rounds[-1]):
        return  # the loop stopped at max_effects: the last round's gains are pre-winner
    large = sorted(
        (t for t in sel.rounds[-1]
         if not t.passed and not t.implausible and np.isfinite(t.lr)
         and np.isfinite(t.relative_gain) and t.relative_gain >= NEAR_MISS_GAIN),
        key=lambda t: -t.relative_gain,
    )
    close = [t for t in large if 0 < t.lr <= t.lr_threshold]
    for t in close[:3]:
        problem.notes.append(
            f"{t.name} not added though it improves the held-out part by "
            f"{100 * t.relative_gain:.0f} %: not significant (held-out likelihood ratio "
            f"{t.lr:.3g} < {t.lr_threshold:.3g}); a longer recording, or more of the motion "
            "that shows it, would tell"
        )
    # significant held out, and large, but the fit part's BIC on its prewhitened residual (at a
    # lag-1 autocorrelation near 1, its changes) got worse: the two parts disagree
    against_fit = [t for t in large if t.lr > t.lr_threshold and t.delta_bic >= 0]
    for t in against_fit[:3]:
        problem.notes.append(
            f"{t.name} not added though it improves the held-out part by "
            f"{100 * t.relative_gain:.0f} % (likelihood ratio {t.lr:.3g} > "
            f"{t.lr_threshold:.3g}): on the fit part it makes the residual's sample-to-sample "
            f"changes worse (BIC {t.delta_bic:+.3g} on the prewhitened residual, lag-1 "
            f"autocorrelation {sel.rho:.3g}). The parts disagree: the fit part holds motion "
            "the effect does not describe (a reference that lags or leads in turns, a "
            "disturbance that changes with the motion), or the held-out part too little of "
            "the motion that would test it"
        )
    units = problem.independent_count("score", sel.after.r_score)
    n = int(sel.after.r_score.size)
    effective = units if units is not None else effective_size(n, sel.rho)
    if close and effective < 10:
        problem.notes.append(
            f"the held-out part holds about {effective:.3g} independent units"
            + (f" (residual lag-1 autocorrelation {sel.rho:.3g} over {n} residuals)"
               if units is None else "")
            + ": few for any effect to pass"
        )


def _note_secondary_worse(
    problem: StreamProblem,
    sel: Selection,
    before: float,
    after: float,
    secondary: Sequence[SecondaryMetric],
) -> None:
    """Effects are chosen on the stream's metric; a further metric of the same stream that the
    chosen model makes worse on held-out data is said in words beside the table's "worse", with
    what it usually means (a gyro whose rate improves while its integrated heading worsens: its
    response to fast motion, a filter, differs from a gain, and a scale fitted on the rate does
    not hold for slow turns)."""
    if not sel.added or not after < before:
        return
    names = ", ".join(i.name for i, _ in sel.added)
    for m in secondary:
        b, a = (abs(m.before), abs(m.after)) if m.signed else (m.before, m.after)
        if not (np.isfinite(a) and np.isfinite(b)) or g4(a) == g4(b) or a < b:
            continue
        hint = ""
        if (m.metric.startswith("heading_error_") and m.metric.endswith("s_window_rms")
                and any(i.name == "scale" for i, _ in sel.added)):
            hint = (
                ": the rate's error fell but the heading it integrates to did not: a sensor "
                "whose response to fast motion (its filter, its timing) differs from a gain "
                "gets a rate-space scale that slow turns do not share; check the written "
                "model against a recording of slow, steady turns"
            )
        problem.notes.append(
            f"{m.metric} worse on the held-out part with {names} ({g4(b)} -> {g4(a)} {m.unit}) "
            f"while {problem.metric} improved ({g4(before)} -> {g4(after)} {problem.unit}); the "
            f"effects were chosen on {problem.metric}{hint}"
        )


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


def declared_fit(problem: StreamProblem, fit: Fit) -> Fit:
    """``fit`` with the declared model's per-run (turn-on) bias held to what it declares
    (:func:`koala_bridge.calibration.selection.at_values`: the other parameters as fitted).

    "Before" is the declared model exactly as declared (issue 16): a turn-on bias declared as
    ``N(mu, sigma^2)`` says the run's bias is unknown *within that spread*, so "before" may fit
    it, but only inside ``mu +- z(1 - alpha/2) sigma`` (2.58 sigma). Fitting it without a bound
    absorbed any bias, however far beyond the declared spread, and before equalled after on a
    gyro whose bias the model lacked. A bias beyond the bound is then a found effect
    (:func:`_turn_on_bias_check`). "After" and every model the backward checks refit are held
    the same way: a nuisance beyond the bound that the z test did not call a bias (its
    standard error large) would otherwise be a fitted parameter that improves the held-out
    error unreported. Other nuisance parameters (magnetic north, the field's magnitude) are
    quantities the declared model itself leaves unknown and stay fitted.
    """
    sigma = float(getattr(problem, "turn_on_bias_sigma", 0.0))
    if sigma <= 0 or not len(fit.x):
        return fit
    bound = WRITE_Z * sigma
    if abs(fit.x[0]) <= bound:
        return fit
    x = fit.x.copy()
    x[0] = float(np.clip(x[0], -bound, bound))
    return at_values(problem, fit, x)


def _declared_refit(problem: StreamProblem, insts: list[EffectInstance], start: Fit) -> Fit:
    """``insts`` refitted from ``start``'s values, the turn-on bias held (:func:`declared_fit`)."""
    return declared_fit(problem, fit_model(
        problem, insts, problem.initial_vector(insts, start.x, start.insts)))


def keep_only_helpful(problem: StreamProblem, sel: Selection) -> None:
    """Backward check on held-out data: an added effect whose removal (the rest refitted) leaves
    the held-out metric no worse is dropped, one at a time, worst first; and a model not better
    than ``sel.before`` on held-out data is no model: "after" is never worse than "before"
    (issue 16: on a still gyro the held-out error once got worse after calibration). Each drop
    is noted in the report."""
    # an outlier effect is judged by the held-out likelihood it was selected by
    likelihood = any(i.effect.mixture for i in sel.after.insts)

    def score(fit: Fit) -> float:
        return heldout_score(problem, fit, likelihood)

    while sel.added:
        current = score(sel.after)
        best: tuple[float, EffectInstance, Fit] | None = None
        for inst, _ in sel.added:
            if inst.name == "bias" and getattr(problem, "turn_on_bias_sigma", 0.0) > 0:
                continue    # judged by its z test against the declared spread (without
                #             it the nuisance takes the same value back)
            fit = _declared_refit(problem, [i for i in sel.after.insts if i is not inst],
                                  sel.after)
            s = score(fit)
            if s <= current and (best is None or s < best[0]):
                best = (s, inst, fit)
        if best is None:
            break
        s, inst, fit = best
        problem.notes.append(
            f"{inst.name} dropped: held-out {problem.metric} {s:.4g} without it, "
            f"{current:.4g} with it (an effect must improve held-out error to be kept)")
        sel.added = [(i, t) for i, t in sel.added if i is not inst]
        sel.after = fit
    base = score(sel.before)
    if sel.added and score(sel.after) >= base:
        problem.notes.append(
            f"{', '.join(i.name for i, _ in sel.added)} dropped: held-out {problem.metric} "
            f"{score(sel.after):.4g} with them, {base:.4g} under the declared model")
        sel.added = []
    if not sel.added:
        # every effect dropped: "after" is the declared model itself, not a refit of it from
        # another start (which can differ from it in the last digits, either way)
        sel.after = sel.before


def drop_implausible(problem: StreamProblem, sel: Selection) -> None:
    """The search rejects a candidate fitted outside its physical range
    (:meth:`Effect.plausible`), but the fits after it move the kept effects again: the backward
    check refits the rest without a dropped one, and a decimated stream's effects are refitted
    on the full stream. A kept effect that such a refit takes out of its range (a gain through
    zero, a singular soft iron) is dropped the same way, the rest refitted, with a note; what is
    left then passes the backward check again (:func:`keep_only_helpful`: each must still
    improve the held-out part, and the whole beat "before"); with none left, "after" is the
    declared model."""
    while _drop_one_implausible(problem, sel):
        while _drop_one_implausible(problem, sel):
            pass
        # what is left must still each improve the held-out part, and the whole beat before
        keep_only_helpful(problem, sel)
    if not sel.added:
        sel.after = sel.before


def _drop_one_implausible(problem: StreamProblem, sel: Selection) -> bool:
    """Drop the first kept effect outside its physical range, the rest refitted, with a note;
    False when there is none."""
    params = split_params(problem, sel.after.insts, sel.after.x)
    by_inst = {id(i): v for i, v in zip(sel.after.insts, params, strict=True)}
    bad = next((i for i, _ in sel.added if not i.effect.plausible(i, by_inst[id(i)])), None)
    if bad is None:
        return False
    problem.notes.append(
        f"{bad.name} dropped: refitted, it left its physical range "
        f"({', '.join(f'{v:.4g}' for v in by_inst[id(bad)])})")
    insts = [i for i in sel.after.insts if i is not bad]
    sel.added = [(i, t) for i, t in sel.added if i is not bad]
    sel.after = _declared_refit(problem, insts, sel.after)
    return True


def _turn_on_bias_check(problem: StreamProblem, sel: Selection) -> None:
    """A declared per-run bias ``N(mu, sigma^2)`` is a nuisance, fitted in every model (its
    deviation from ``mu`` is ``x[0]``). When the fitted deviation is implausible under that
    distribution, ``|b| / sqrt(sigma^2 + SE^2) > z(1 - alpha/2)``, the data hold a bias the
    declared model lacks: ``bias`` is added (its value fixed at ``b``, the nuisance refitted),
    so ``--write-config`` writes ``bias_rad_s = mu + b``; "before" holds the nuisance to the
    declared spread (:func:`declared_fit`), so the bias shows in before -> after."""
    sigma = float(getattr(problem, "turn_on_bias_sigma", 0.0))
    fit = sel.after
    b = float(fit.x[0])
    se = float(parameter_se(problem, fit)[0])
    z = abs(b) / float(np.hypot(sigma, se))
    threshold = WRITE_Z
    held = ""
    if z <= threshold and abs(b) > WRITE_Z * sigma:
        held = (f"; its standard error is too large to call it more, so it is held at the "
                f"declared bound {np.copysign(WRITE_Z * sigma, b):+.4g} in before and after")
    problem.notes.append(
        f"turn-on bias fitted: {b:+.4g} (declared sigma {sigma:g}, SE {se:.2g}, z = {z:.2f}: "
        + ("within the declared spread: this run's turn-on bias, part of the declared model"
           + held + ")"
           if z <= threshold else "beyond the declared spread: a bias the model lacks)"))
    if z <= threshold or len(sel.added) >= MAX_EFFECTS:
        return
    inst = EffectInstance("bias", get_effect("bias"), ("bias",), (b,), fixed=True)
    insts = [*fit.insts, inst]
    new = fit_model(problem, insts, problem.initial_vector(insts, fit.x, fit.insts))
    declared = declared_fit(problem, fit)
    before = problem.metric_value(declared.insts, declared.x, "score")
    gain = 1.0 - problem.metric_value(new.insts, new.x, "score") / before if before else 0.0
    trial = Trial("bias", 1, float("nan"), z * z, threshold**2, gain, True, new,
                  other_test={"turn_on_bias_z": float(f"{z:.4g}"),
                              "turn_on_bias_z_threshold": float(f"{threshold:.4g}"),
                              "turn_on_bias_se": float(f"{se:.3g}"),
                              "declared_sigma": sigma,
                              "heldout_relative_gain": float(f"{gain:.6g}")})
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
    return replace(bundle, tables=tables, whole=bundle)


def _problems(
    bundle: Bundle,
    model: DeclaredModel,
    options: Options,
    compass_heading: Any = None,
    with_compass: bool = True,
    odometry_bundle: Bundle | None = None,
    skipped: list[SkippedStream] | None = None,
    misread: Misread | None = None,
) -> list[StreamProblem]:
    """The streams' problems; none of those ``misread`` sets aside (:mod:`.units`)."""
    out: list[StreamProblem | None] = []
    if with_compass:
        out.append(build_compass(bundle, model, skipped))
    else:
        out.append(build_gyro(bundle, model, compass_heading, skipped))
        out.append(build_gyro_level(bundle, model))
        positions = misread is None or not misread.skip_positions
        if positions:
            out.append(
                build_odometry(odometry_bundle or bundle, model, options.window_s, skipped)
            )
        out.extend(build_ranges(bundle, model, skipped))
        if positions:
            out.extend(build_beacons(bundle, model, skipped))
            out.extend(build_landmarks(bundle, model, skipped))
    aside = set() if misread is None else {s.stream for s in misread.skipped}
    return [p for p in out if p is not None and p.name not in aside]


#: the reference noise share (:func:`koala_bridge.calibration.effects.common.
#: reference_noise_share`) above which a gyro is compared with a dense reference in heading
#: space: a gain fitted rate with rate is pulled towards 0 by up to that share (regression
#: dilution), more than a gyro's scale error usually is (a new user's gyro against a 25 Hz
#: heading with 3 mrad of noise, share 5.8 %: -5.8 % fitted for a true +2 %, and the bias beside
#: it off by 2 SE); the report's note on attenuation starts there too
HEADING_SPACE_SHARE = NOTE_REFERENCE_NOISE_SHARE
#: a share a latency explains: read at the latency grid's best, at most this part of it is left
#: (the simulator's gyro 7 ms late: 1.2 % -> 0). A noisy reference read between its samples is
#: smoothed, and its share falls too: half a sample over, white heading noise keeps exactly a
#: quarter of its differenced variance, ``1 - 3f + 3f^2`` at a fraction ``f`` (a new user's
#: gyro against a tracker sampled as densely: 0.72 -> 0.18 %, ratio 0.249, rate space on 4 of 9
#: seeds at 0.25 and a half-sample latency "found"); half that floor is a latency's
LATENCY_SHARE_LEFT = 0.125


#: the share of the rate residual (variance, fit part) that the reference's own differenced
#: noise may be before a gyro is compared in heading space: beyond it that noise is a large
#: part of the rate residual, and a shift of a fraction of a sample "improves" it by smoothing
#: the noise (a gyro late by a whole number of a tracker's samples read 0.45 of its residual,
#: a tracker's own noise nearly all of it). An independent study's clean gyros against a
#: 50 Hz tracker with 0.3 mrad of heading noise, its share of the reference's variance only 0.16 %:
#: ``time_offset`` 9-15 ms, "better by 16-39 %", on 4 of 28, the heading 8 times worse
RESIDUAL_NOISE_SHARE = 0.25
#: consecutive rows of the fit part that residual is measured on
RESIDUAL_ROWS = 2000


def _reference_noise(problem: ScalarProblem, share: float) -> tuple[float, float]:
    """``(of_residual, aligned)``: the reference's own noise over the variance of the rate
    residual on the fit part, and the noise share with the reference read at the readings'
    latency (the best of the latency grid, about the clocks' offset).

    Both on a block of :data:`RESIDUAL_ROWS` consecutive rows from the middle of the fit part
    (the latency grid's correlations on a whole hour of 100 Hz readings took 7 s). ``aligned``:
    readings late by a fraction of a sample share the reference's fast variation smoothed,
    which reads as unshared at no lag (a simulated gyro 7 ms late: 1.2 %), where the
    reference's own noise stays unshared at any lag. ``of_residual``: the noise, the larger of
    ``share`` and ``aligned`` (motion read a latency apart looks partly unshared, and the
    estimate shrinks: a gyro 0.148 s late, a quarter), in the readings' unit (times the slope
    of the line ``a + b u(t - tau)`` through the readings: a gyro of gain 2, or in deg/s,
    stayed in rate space by the gain squared), over the least of the declared model's residual
    variance and that line's (a gyro late by 0.15 s, or 5 % off in scale, has a residual that
    is mostly that error, and once the effect is in the model, mostly the reference's noise)."""
    p = problem.part("fit")
    pred = problem.base_gain * p.u
    ok = np.isfinite(pred) & np.isfinite(p.y)
    if ok.sum() < 3:
        return 0.0, share
    var_r = float(np.var(p.y[ok] - pred[ok]))
    var_p = float(np.var(pred[ok]))
    aligned = share
    if problem.reference is not None:
        rows = np.flatnonzero(ok)
        if rows.size > RESIDUAL_ROWS:
            start = (rows.size - RESIDUAL_ROWS) // 2
            rows = rows[start:start + RESIDUAL_ROWS]
        t, y = p.t[rows], p.y[rows]
        step, span = search_window(problem)
        clocks = problem.clocks_apart
        around = 0.0 if clocks is None else clocks[0]
        taus = around + (np.arange(-span, span + step / 2, step) if span else np.zeros(1))
        r = correlations(t, y, problem.reference, taus)
        if np.isfinite(r).any():
            best = int(np.nanargmax(r))
            tau = float(taus[best])
            u = problem._u_at(t, tau)
            var_u = float(np.var(u))
            if tau:
                aligned = reference_noise_share(problem, u=problem._u_at(problem.t, tau))
            if var_u > 0:
                slope = float(np.cov(y, u, bias=True)[0, 1]) / var_u
                # the least squares line's residual variance is var(y) (1 - r^2)
                line = float(np.var(y)) * (1.0 - float(r[best]) ** 2)
                if line > 0:
                    noise = max(share, aligned)
                    of_declared = noise * var_p / var_r if var_r > 0 else 0.0
                    return max(noise * var_u * slope**2 / line, of_declared), aligned
    return (share * var_p / var_r if var_r > 0 else 0.0), aligned


def _heading_space_if_noisy(small: StreamProblem, full: StreamProblem | None) -> None:
    """A gyro compared rate with rate against a dense reference that proves mostly its own
    noise (:func:`koala_bridge.calibration.effects.common.reference_noise_share` of the whole
    stream's consecutive samples above ``MAX_REFERENCE_NOISE_SHARE``) is compared in heading
    space instead (:func:`koala_bridge.calibration.streams.to_heading_space`), the subset it is
    selected on and the whole stream alike."""
    if small.name not in ("gyro", "gyro:level") or not isinstance(small, ScalarProblem):
        return
    if small.integrate_window_s is not None:  # already in heading space (a compass reference)
        return
    whole = full if isinstance(full, ScalarProblem) else small
    share = stream_share(small)  # the whole stream's: calibrate sets it for a subset
    if not np.isfinite(share):
        return  # a constant reference (a still gyro: its noise, by Allan)
    residual, aligned = _reference_noise(whole, share)
    if share <= MAX_REFERENCE_NOISE_SHARE and (
        (share <= HEADING_SPACE_SHARE and residual <= RESIDUAL_NOISE_SHARE)
        # a share beyond 1 % that a latency explains; below 1 % the residual decides alone (a
        # noisy reference read at a sub-sample shift can look noiseless: 0.075 % -> 0)
        or (share > HEADING_SPACE_SHARE and aligned <= LATENCY_SHARE_LEFT * share)
    ):
        return  # a clean reference, or a latency the readings' share is
    for q in [small] if whole is small else [small, whole]:
        # the residual's share is the reason where the share alone was below the note's 1 %
        to_heading_space(q, share, residual if share <= HEADING_SPACE_SHARE else 0.0)
    # the heading's noise share in heading space, on consecutive samples: on a random subset
    # the readings' trapezoid over its gaps is no integral of the motion
    small.heading_share = whole.heading_share = whole.heading_noise_share()


def _rows(problem: StreamProblem) -> int:
    """The stream's samples (an odometry stream's: its odometry rows)."""
    t = getattr(problem, "t_odo", None)
    t = getattr(problem, "t", None) if t is None else t
    return 0 if t is None else int(np.size(t))


def refit_full(full: StreamProblem, small: StreamResult) -> StreamResult:
    """Refit the effects selected on a decimated stream on the full stream; metrics on it."""
    sel = small.selection
    # what the selection noted on the subset (an effect not tried, and why) holds for the
    # stream; what the builder noted, the full stream's builder noted itself
    full.notes.extend(n for n in small.selection_notes if n not in full.notes)
    n_small, n_full = _rows(small.problem), _rows(full)
    if 0 < n_small < n_full:
        full.notes.append(
            f"effects selected on {n_small} of the stream's {n_full} rows (a subset, for "
            "speed): the candidates' evidence (dBIC, held-out LR and gain) is the subset's; "
            "before, after and the parameters are the whole stream's"
        )
    before = declared_fit(full, fit_model(full, [], full.nuisance_x0()))
    insts = list(sel.after.insts)
    after = declared_fit(full, fit_model(
        full,
        insts,
        full.initial_vector(insts, sel.after.x, insts) if len(sel.after.x) else full.nuisance_x0(),
    ))
    added = list(sel.added)
    result = Selection(full, before, after, added, sel.rounds, sel.rho, (
        full.independent_count("fit", after.r_fit), full.independent_count("score", after.r_score)
    ))
    drop_implausible(full, result)
    after = result.after
    b = full.metric_value(before.insts, before.x, "score")
    a = full.metric_value(after.insts, after.x, "score")
    secondary = full.secondary_metrics((before.insts, before.x), (after.insts, after.x))
    _note_known_rotation(full, secondary)
    _note_secondary_worse(full, result, b, a, secondary)
    _note_near_misses(full, result)
    _note_gross_gain(full, result)
    return StreamResult(full, result, b, a, secondary, selection_notes=small.selection_notes)


def calibrate(
    bundle: Bundle,
    model: DeclaredModel,
    options: Options | None = None,
    progress: Progress | None = None,
    skipped: list[SkippedStream] | None = None,
) -> list[StreamResult]:
    """Run the loop on every stream the bundle holds; see the module docstring for the order.

    Streams longer than ``options.max_rows`` samples are selected on a random subset of that
    size (estimates from 20 000 samples are far more precise than any tolerance, and the test
    is then only more conservative); the selected effects are refitted on the full stream and
    before/after are measured on the full held-out part.

    Every stream of the bundle (:func:`koala_bridge.calibration.streams.bundle_streams`) ends
    either among the results or in ``skipped``, with what it lacks and how to add it.
    """
    found: list[SkippedStream] = []
    options = options or Options()
    bundle, fault_notes = set_aside_faulted(bundle)
    streams = bundle_streams(bundle)  # a column misread_units sets aside is no stream's
    misread = misread_units(bundle, streams, beacon_streams(bundle))
    bundle = misread.bundle
    small = decimate_bundle(bundle, options.max_rows)
    small_odometry = decimate_bundle(bundle, options.max_rows, references=True)

    def run(
        problems_small: list[StreamProblem], problems_full: list[StreamProblem]
    ) -> list[StreamResult]:
        out = []
        full_by_name = {p.name: p for p in problems_full}
        for p in problems_small:
            full = full_by_name.get(p.name)  # a stream the subset alone has keeps its result
            if isinstance(p, ScalarProblem) and isinstance(full, ScalarProblem) and full is not p:
                # measured on the stream's consecutive samples, not the subset's random rows
                p.reference_share = reference_noise_share(full)
                p.full = full
            _heading_space_if_noisy(p, full)
            res = run_stream(p, options, progress)
            out.append(res if small is bundle or full is None else refit_full(full, res))
        return out

    results = run(
        _problems(small, model, options, skipped=found),
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
            skipped=found,
            misread=misread,
        ),
        _problems(bundle, model, options, compass_heading, with_compass=False, misread=misread)
        if small is not bundle
        else [],
    )
    # a stream set aside for its unit is said so, not why a builder would also have skipped it
    aside = {s.stream for s in misread.skipped}
    found = [misread.explained(s) for s in found if s.stream not in aside] + misread.skipped
    named = {r.problem.name for r in results} | {s.stream for s in found}
    for stream in streams:
        if stream not in named:  # a builder that dropped a stream without saying why
            found.append(
                SkippedStream(
                    stream,
                    "not calibrated, for no reason the tool recorded",
                    "please report this with the bundle (docs/calibration.md)",
                )
            )
    found += unknown_files(bundle)
    for res in results:
        res.problem.notes.extend(fault_notes.get(res.problem.name, []))
        res.problem.notes.extend(misread.notes_for(res.problem.name))
        unread = _unread_meta(bundle.meta, res.problem.name)
        if unread:
            res.problem.notes.append(unread)
        res.noise = identify_noise(res.problem, res.selection.after)
    note_level_bias(results)
    if skipped is not None:
        skipped.extend(found)
    return results  # empty: no stream with a reference (the caller says so, from skipped)


def _unread_meta(meta: Mapping[str, Any], stream: str) -> str | None:
    """A note when ``meta.json``'s ``sensor`` section has numbers for ``stream``'s kind of
    sensor (``sensor.<kind>``: ``uwb`` for ``range:uwb``) that the declared model does not read
    (:data:`koala_bridge.calibration.model.META_KEYS`): a user's declared UWB scale was ignored
    without a word, and the tool then "found" the scale the user had declared."""
    kind = stream.split(":", 1)[1] if stream.startswith(("range:", "landmark_range:")) else stream
    section = meta.get("sensor")
    declared = section.get(kind) if isinstance(section, Mapping) else None
    if not isinstance(declared, Mapping):
        return None
    read = {path[-1] for path in META_KEYS if path[:2] == ("sensor", kind)}
    numbers = {k: v for k, v in declared.items()
               if k not in read and isinstance(v, int | float) and not isinstance(v, bool)}
    if not numbers:
        return None
    listed = ", ".join(f"{k} = {v:g}" for k, v in list(numbers.items())[:5])
    return (
        f"meta.json's sensor.{kind} ({listed}) is not read: the declared model takes from "
        f"meta.json only {', '.join(sorted(dotted for dotted in META_KEYS.values()))}; a "
        "found effect is measured against the model without them (declare what the simulator "
        "has keys for with --config)"
    )


def compass_heading_of(problem: CompassProblem, sel: Selection) -> tuple[Any, Any] | None:
    """The calibrated compass heading over the whole span, for use as a gyro reference."""
    if problem.mode == "magnitude_3d":
        return None
    mc = problem.corrected(sel.after.insts, sel.after.x, "all")
    return problem.t, np.unwrap(problem.heading(mc))
