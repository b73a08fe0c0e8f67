"""Staged calibration: several recordings of the same robot, each calibrated on the model the
ones before it produced.

Some effects show only in a recording made for them. A gyro's bias is plain in a recording
lying still and lost under the motion of a hand-turned one; a compass's hard iron needs the
turns. Calibration tools work in the same order (Kalibr and imu_utils fit IMU noise and bias on a
static log before the dynamic calibration; ArduPilot's compass calibration assumes a calibrated
gyro). ``koala-bridge calibrate STILL TURNS ...`` does the same:

* stage 1 calibrates ``INPUT 1`` against ``--config`` (the user's declared model);
* stage *k* calibrates ``INPUT k`` against the model stage *k-1* wrote: the declared model plus
  every effect found so far that the simulator has a key for (``config_update.SIMULATED_KEYS``;
  the others are reported but cannot be carried, the model has no place for them);
* ``--write-config`` writes the model after the last stage.

The report keeps the meaning of *before* and *after* of a single run: *before* is the metric
under the **user's declared model** (stage *k* is therefore run once more against it, for its
*before* values), *after* under the model with the carried and the newly found effects. The
carried effects are listed with each stream of their config section, their evidence naming the
stage that found them; ``before_with_carried`` gives the stage's own starting point.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from koala_bridge.calibration.bundle import load_input
from koala_bridge.calibration.config_update import (
    found_keys,
    noise_keys,
    updated_config,
)
from koala_bridge.calibration.errors import BundleError
from koala_bridge.calibration.model import (
    config_value,
    declared_model,
    meta_declared,
    stated_key,
    without_declared,
)
from koala_bridge.calibration.pipeline import Options, Progress, StreamResult, calibrate
from koala_bridge.calibration.problem import FloatArray, SkippedStream
from koala_bridge.calibration.sim_keys import is_simulated

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CarriedEffect:
    """An effect found in an earlier stage and carried, through its config keys, into a later
    stage's declared model."""

    name: str
    section: str
    params: Mapping[str, float]
    keys: Mapping[str, Any]
    source: str
    stage: int


@dataclass
class Stage:
    """One input's calibration within a staged run (a single input is a run of one stage)."""

    number: int
    source: str
    results: list[StreamResult]
    #: config section -> effects found in earlier stages that this stage's model holds
    carried: dict[str, list[CarriedEffect]] = field(default_factory=dict)
    #: (stream, metric) -> the metric under the user's declared model (stages after the first)
    declared_before: dict[tuple[str, str], float] = field(default_factory=dict)
    #: stream -> its held-out errors under the user's declared model (stages after the first)
    declared_errors: dict[str, FloatArray] = field(default_factory=dict)
    #: streams of the input that could not be calibrated, with what they lack
    skipped: list[SkippedStream] = field(default_factory=list)
    #: the config this input was calibrated against: the user's, with the geometry its
    #: meta.json declares and what earlier stages found set (:func:`_with_meta`)
    config: Mapping[str, Any] = field(default_factory=dict)


def _effect_keys(res: StreamResult) -> list[tuple[str, dict[str, float], dict[str, Any]]]:
    """``(name, params, simulated config keys with their written values)`` of each effect
    added to ``res``'s stream."""
    written = found_keys([res])
    out = []
    for inst, (named, _) in zip(res.effects, res.effect_params(), strict=True):
        paths = res.effect_paths(inst)
        keys = {p: written[p] for p in paths if is_simulated(p) and p in written}
        out.append((inst.name, named, keys))
    return out


def carried_from(stage: Stage) -> list[CarriedEffect]:
    """The effects of ``stage`` that its written config holds (simulated keys)."""
    out = []
    for res in stage.results:
        for name, params, keys in _effect_keys(res):
            if keys:
                out.append(
                    CarriedEffect(
                        name, res.problem.section, params, keys, stage.source, stage.number
                    )
                )
    return out


def _befores(results: Sequence[StreamResult]) -> dict[tuple[str, str], float]:
    return {(r.problem.name, m.metric): m.before for r in results for m in r.metrics()}


@contextmanager
def _quiet() -> Iterator[None]:
    """The second pass over a stage (for its *before* values) logs nothing new."""
    logger = logging.getLogger("koala_bridge.calibration")
    level = logger.level
    logger.setLevel(logging.WARNING)
    try:
        yield
    finally:
        logger.setLevel(level)


def calibrate_stages(
    inputs: Sequence[Path],
    config: Mapping[str, Any],
    options: Options,
    tmp: Path,
    progress: Progress | None = None,
    with_noise: bool = False,
    on_stage: Callable[[int, Path], None] | None = None,
) -> tuple[list[Stage], dict[str, Any]]:
    """Calibrate ``inputs`` in order (module docstring); returns the stages and the final
    config (``config`` with every stage's simulated keys set)."""
    stages: list[Stage] = []
    current: dict[str, Any] = dict(config)
    carried: list[CarriedEffect] = []
    found: set[str] = set()  # config keys an earlier stage found
    uncarried: dict[str, list[str]] = {}  # stream -> earlier stages' effects with no key
    for number, path in enumerate(inputs, 1):
        if on_stage is not None:
            on_stage(number, path)
        work = tmp / f"stage-{number}"
        work.mkdir(parents=True, exist_ok=True)
        bundle = load_input(path, work)
        current = _with_meta(current, bundle.meta, found, path, stated=number > 1 or bool(config))
        skipped: list[SkippedStream] = []
        # what earlier stages found a later bundle's meta.json (the nominal values) must not undo
        meta = without_declared(bundle.meta, found)
        results = calibrate(bundle, declared_model(current, meta), options, progress, skipped)
        if not results:
            raise BundleError(_nothing_to_calibrate(path, skipped))
        stage = Stage(number, str(path), results, skipped=skipped, config=current)
        if carried:
            sections = {res.problem.section for res in results}
            for effect in carried:
                if effect.section in sections:
                    stage.carried.setdefault(effect.section, []).append(effect)
            with _quiet():
                declared = calibrate(bundle, declared_model(config, bundle.meta), options)
            stage.declared_before = _befores(declared)
            stage.declared_errors = {
                r.problem.name: r.problem.heldout_errors(
                    r.selection.before.insts, r.selection.before.x
                )
                for r in declared
            }
        for res in results:  # stream names are unique in a stage: earlier stages' only
            if res.problem.name in uncarried:
                res.problem.notes.append(
                    f"not carried from earlier stages: {'; '.join(uncarried[res.problem.name])} "
                    "(the simulator has no key for them, so the declared model cannot hold "
                    "them: they are in the written config's comment); this stage is against "
                    "the declared model without them"
                )
            names = [i.name for i, why in zip(res.effects, res.not_written(), strict=True)
                     if why is None and res.is_comment(i)]
            if names:
                uncarried.setdefault(res.problem.name, []).append(
                    f"{', '.join(names)} (stage {number})")
        stages.append(stage)
        keys = found_keys(results)
        if with_noise:
            keys.update(noise_keys(results))
        current = updated_config(current, keys)
        found |= set(keys)
        carried += carried_from(stage)
    return stages, current


def _with_meta(
    config: dict[str, Any], meta: Mapping[str, Any], found: set[str], path: Path, stated: bool
) -> dict[str, Any]:
    """``config`` with the robot geometry ``meta.json`` declares (tick size, wheel base, wheel
    ratio; meta.json wins, :func:`declared_model`) set, except keys an earlier stage found:
    the written config then holds the robot the data were calibrated against, not the config's
    robot with the bundle's found wheel base (a LEGO robot's wheel base over a Koala's tick
    size). A --config is completed by the simulator's defaults, so the keys it does not state
    are set too, which would otherwise be the default Koala's; without one the written file
    still holds the geometry meta.json declared beside what was found: a new user's file held
    ``wheel_base_m`` alone, which its header's advice to copy into ``config/default.toml`` put
    on the Koala's ticks per metre (22 222 against the robot's 10 598). Where a value already
    set (``stated``: by the --config, or by an earlier input's meta.json) differs, a warning
    says so."""
    laid = {}
    for key, value in meta_declared(meta).items():
        if not key.startswith("robot.") or key in found:
            continue
        if not stated_key(config, key):
            laid[key] = value
            continue
        before = config_value(config, key)
        if before != value:
            if stated:
                log.warning("%s: meta.json declares %s = %g, over %s from the config or an "
                            "earlier input's meta.json; the calibration, and the written config, "
                            "take this meta.json's", path, key, value, before)
            laid[key] = value
    return updated_config(config, laid) if laid else config


def _nothing_to_calibrate(path: Path, skipped: Sequence[SkippedStream]) -> str:
    """The one line for an input none of whose streams can be calibrated: each stream, what it
    lacks and how to add it."""
    if not skipped:
        return (
            f"{path}: holds no measured stream (gyro.csv, compass.csv, odometry.csv, range.csv "
            "or landmarks.csv), only references; see docs/bundle-format.md"
        )
    return f"{path}: no stream can be calibrated: " + " | ".join(s.line() for s in skipped)


def all_keys(stages: Sequence[Stage], with_noise: bool = False) -> dict[str, Any]:
    """Every stage's found keys, later stages overriding earlier ones."""
    out: dict[str, Any] = {}
    for stage in stages:
        out.update(found_keys(stage.results))
        if with_noise:
            out.update(noise_keys(stage.results))
    return out
