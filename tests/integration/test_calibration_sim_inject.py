"""Undeclared effects injected into a simulator recording: named, recovered, held-out error halved.

The simulator is recorded once (``config/default.toml``, every model on, seed 3, 60 s of
``tools.sim_recording.weave_command``) and exported to a bundle; each case copies the bundle,
injects into the exported measurements an effect ``config/default.toml`` does not declare (each
effect, and four pairs; ``tests/_sim_inject.py``), and calibrates against the config the run was
recorded with. A case passes when on the injected stream exactly the injected effects are named,
each parameter is within its tolerance, and the held-out metric at least halves, and no other
stream gets an effect. The one exception to halving is a gyro ``bias`` alone: the declared per-run
turn-on bias is fitted in every model, *before* included, so a constant leaves the held-out error
as it was (it is named because its value is implausible under the declared spread). The clean
recording adds no effect anywhere -- so no case's effect is found without its injection.

Not tested here, with the reasons and measured numbers below ``CASES``: quantisation (the
simulated sonar's noise is far too large against any step), and one wheel's tick error alone
(two effects at once, neither passing alone).

The truth pose is recorded at the gyro's 100 Hz (a motion tracker at the sensor rate): at the
default 50 Hz the reference misses half of each 10 ms step's drive-error jitter, and that, not
the gyro, is the gyro stream's residual (0.056 rad/s held out, against 0.0068 at 100 Hz).

Magnitudes, from the clean fit of this recording (held-out metric sigma_0, standard errors SE):
each is at least 20 SE of its estimate and large enough that the held-out metric *can* halve --
with the effect fully removed that needs its held-out RMS >= sqrt(3) sigma_0; we take 3 sigma_0
(before ~ 3.2 sigma_0, so `after` may keep up to 1.6 sigma_0 of misfit). Whichever bound is
larger sets the magnitude, rounded up. Tolerances are 10 % of the injected magnitude (>= 2 SE,
as in ``koala_bridge.calibration.synthetic``; checked below against the tool's own SE) unless a case
says why not.
"""

from __future__ import annotations

import copy
import shutil
import tomllib
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from _sim_inject import (
    STREAMS,
    glitch,
    gyro_bias,
    gyro_bias_drift,
    gyro_covariate,
    gyro_scale,
    gyro_time_offset,
    hard_iron,
    heading_drift,
    range_dependent,
    soft_iron,
    tick_scale,
    undeclare_robot_key,
    wheel_ratio,
)
from koala_bridge.calibration.bundle import load_bundle
from koala_bridge.calibration.model import declared_model
from koala_bridge.calibration.pipeline import StreamResult, calibrate
from koala_bridge.recording.export import export_bundle
from koala_bridge.tools.sim_recording import record_simulator

ROOT = Path(__file__).parents[2]
SEED = 3
DURATION_S = 60.0
POSE_RATE_HZ = 100.0

Config = dict[str, Any]
#: Edits the bundle in place; returns the config to calibrate against (None: the recorded one).
Injection = Callable[[Path, Config], Config | None]


@dataclass(frozen=True)
class Expect:
    """A parameter the tool must find: ``value``, within ``tol`` (default 10 % of ``size``, the
    injected magnitude: its distance from the declared value)."""

    value: float
    size: float
    tol: float | None = None
    #: the value is relative to the run's turn-on bias (a nuisance fitted in every model)
    plus_turn_on: bool = False
    #: a fraction of readings: tolerance 3 binomial SE of the fit part's count
    binomial: bool = False


@dataclass(frozen=True)
class SimCase:
    inject: Injection
    expect: Mapping[str, Mapping[str, Mapping[str, Expect]]]


TPM = 22222.222  # [robot] ticks_per_metre of config/default.toml
WHEEL_BASE = 0.285  # [robot] wheel_base_m
SONAR_MAX = 2.5  # [sensors.sonar] max_range_m

# gyro: sigma_0 = 0.0068 rad/s (rms_rate_error). The nuisance turn-on bias absorbs the mean of
# any additive effect on the fit part, so what is left held out is: for scale, the weave's
# turn-rate sine, rms 0.354 rad/s -> s >= 3 sigma_0 / 0.354 = 0.058; for a drift about the
# middle of the fit part, rms(t - 18 s) over 36..60 s = 30.8 s -> d >= 6.6e-4; for the
# temperature column (+-4 degC, 42 s period), rms 2.96 degC -> c >= 6.9e-3. SEs: 3e-4, 1e-5,
# 4e-5, far below. The time offset: a 3 ms lag already gives 0.034 rad/s, 5 sigma_0.
BIAS = 0.02
SCALE = 0.06
DRIFT = 7e-4
TEMP_COEFF = 0.007
TAU = 0.007
TAU_LONG = 0.05  # five gyro samples
# compass: sigma_0 = 0.0156 rad (rms_heading_error) in a 20 uT horizontal field. A hard iron h
# moves the heading by |h|/B sin(.), rms |h|/(B sqrt 2) -> |h| >= 3 sigma_0 20 sqrt 2 = 1.32 uT;
# a soft iron |e| sin 2(.), rms |e|/sqrt 2 -> |e| >= 0.066. SEs 0.011 uT and 6e-4.
HARD = (1.2, -0.8)  # |h| = 1.44 uT
SOFT = (0.06, 0.03)  # |e| = 0.067
# odometry: sigma_0 = 0.0015 m (window_position_rms); the SEs set these (the odometry has 2
# independent units per 5 s window, so its SEs are large): ticks per metre 114, in the pair
# with the ratio 129 -> 0.13 x 22222 = 2889 = 22 SE; wheel ratio 0.0081, in the pair 0.0090
# -> 0.20 = 22 SE; wheel base 0.0015 m -> 0.035 m = 23 SE.
TICKS = 0.13
RATIO = 1.20
# heading drift: SE 0.0029 rad/s -> 20 SE = 0.058 (3 sigma_0 needs only 0.009: a drift d gives
# a window error of ~v d t^2 / 2, 0.0057 m at 0.01 rad/s).
DRIFT_ODO = 0.06
WRONG_BASE = 0.25  # declared; the recorded robot's is 0.285 (0.035 m = 23 SE)
# sonar: sigma_0 = 0.076 m (rms_error); k r^2 has held-out rms 1.65 k (r up to 2.2 m) ->
# k >= 3 sigma_0 / 1.65 = 0.139 (SE 9e-4). A glitch of probability p adds (2.5 m - r) on a
# fraction p: any p >= 0.023 gives 3 sigma_0.
K_R2 = 0.14
GLITCH_P = 0.05


def _wheel_base_declared(bundle: Path, config: Config) -> Config:
    """The wheel base error as a wrong declaration (equivalent to scaling the tick difference):
    meta.json's robot geometry wins over MODEL.toml, so it is dropped there first."""
    undeclare_robot_key(bundle, "wheel_base_m")
    wrong = copy.deepcopy(config)
    wrong["robot"]["wheel_base_m"] = WRONG_BASE
    return wrong


def _scale_and_bias(bundle: Path, config: Config) -> None:
    # The scale also multiplies the run's turn-on draw (-0.0009 rad/s): 5e-5 off, 2 % of the
    # tolerance.
    gyro_scale(bundle, SCALE)
    gyro_bias(bundle, BIAS)


def _soft_then_hard(bundle: Path, config: Config) -> None:
    # Soft iron first: a hard iron added after it is not rotated by it, so dh = HARD exactly.
    soft_iron(bundle, SOFT, config["sensors"]["compass"])
    hard_iron(bundle, HARD)


def _ticks_and_ratio(bundle: Path, config: Config) -> None:
    tick_scale(bundle, TICKS)
    wheel_ratio(bundle, RATIO)


#: The glitch of the pair: max range as this sensor reads it. With k r^2 the far readings pass
#: 2.5 m (2.9 m at 2.2 m), and a glitch is a repeated *extreme* reading (the effect looks at the
#: largest and smallest): stuck at 2.5 m it would sit among them, and is not proposed (measured:
#: only ``scale`` 0.25 named, held out 0.41 -> 0.32).
GLITCH_K_VALUE = SONAR_MAX + K_R2 * SONAR_MAX**2


def _range_dependent_and_glitch(bundle: Path, config: Config) -> None:
    range_dependent(bundle, K_R2)
    glitch(bundle, GLITCH_P, GLITCH_K_VALUE)


_H = float(np.hypot(*HARD))
_E = float(np.hypot(*SOFT))
E_BIAS = {
    # The turn-on bias is declared N(0, 0.002^2) and fitted in every model, *before* included:
    # ``bias`` is named when the fitted value is implausible under it (> 2.58 x 0.002), and its
    # value is the injection plus this run's draw (the clean fit's nuisance). 0.02 = 10 declared
    # sigma; the held-out error cannot change (see _check).
    "bias": {"bias": Expect(BIAS, BIAS, plus_turn_on=True)}
}
E_SCALE = {"scale": {"scale_error": Expect(SCALE, SCALE)}}
# Both components to 10 % of |h|.
E_HARD = {"hard_iron": {"dh_x": Expect(HARD[0], _H), "dh_y": Expect(HARD[1], _H)}}
# E = -F (tests/_sim_inject.soft_iron); both entries to 10 % of |e|.
E_SOFT = {"soft_iron": {"e_xx": Expect(-SOFT[0], _E), "e_xy": Expect(-SOFT[1], _E)}}
E_TICKS = {"tick_scale": {"ticks_per_metre": Expect(TPM * (1 + TICKS), TPM * TICKS)}}
E_RATIO = {"wheel_ratio": {"ratio_left_right": Expect(RATIO, RATIO - 1)}}
E_K = {"range_dependent": {"k_per_m2": Expect(K_R2, K_R2)}}
E_GLITCH = {
    "glitch": {
        # A fraction of the fit part's readings, not a fitted parameter: its scatter is the
        # binomial one, sqrt(p (1 - p) / n) = 0.0068 for n ~ 1000 -- 10 % of p would be 0.7 SE.
        "probability": Expect(GLITCH_P, GLITCH_P, binomial=True),
        "value": Expect(SONAR_MAX, SONAR_MAX, tol=1e-9),
    }
}


def _lag_case(tau: float) -> SimCase:
    return SimCase(
        lambda b, c: gyro_time_offset(b, tau),
        {"gyro": {"time_offset": {"tau_s": Expect(tau, tau)}}},
    )


CASES: Mapping[str, SimCase] = {
    "bias": SimCase(lambda b, c: gyro_bias(b, BIAS), {"gyro": E_BIAS}),
    "scale": SimCase(lambda b, c: gyro_scale(b, SCALE), {"gyro": E_SCALE}),
    "bias_drift": SimCase(
        lambda b, c: gyro_bias_drift(b, DRIFT),
        {"gyro": {"bias_drift": {"rate_per_s": Expect(DRIFT, DRIFT)}}},
    ),
    "covariate": SimCase(
        lambda b, c: gyro_covariate(b, TEMP_COEFF),
        {"gyro": {"covariate:temperature_c": {"coefficient": Expect(TEMP_COEFF, TEMP_COEFF)}}},
    ),
    # The reference rate is white at the 10 ms step (the drive error's per-step jitter), so
    # the residual has a local minimum near every half sample: least squares from tau = 0 fitted
    # 0.02 and 0.1 s as 0.0049 s. The effect now starts from the cross-correlation peak on a
    # half-sample grid (effects/time_offset.py), and lags beyond one sample are recovered
    # (measured, seeds 3 and 5: 0.02, 0.05, 0.1, -0.03 s to within 3e-6 s).
    "time_offset": _lag_case(TAU),
    "time_offset_long": _lag_case(TAU_LONG),
    "hard_iron": SimCase(lambda b, c: hard_iron(b, HARD), {"compass": E_HARD}),
    "soft_iron": SimCase(
        lambda b, c: soft_iron(b, SOFT, c["sensors"]["compass"]), {"compass": E_SOFT}
    ),
    "tick_scale": SimCase(lambda b, c: tick_scale(b, TICKS), {"odometry": E_TICKS}),
    "wheel_ratio": SimCase(lambda b, c: wheel_ratio(b, RATIO), {"odometry": E_RATIO}),
    "wheel_base": SimCase(
        _wheel_base_declared,
        {
            "odometry": {
                "wheel_base": {
                    "wheel_base_m": Expect(WHEEL_BASE, WHEEL_BASE - WRONG_BASE),
                }
            }
        },
    ),
    "heading_drift": SimCase(
        lambda b, c: heading_drift(b, DRIFT_ODO, WHEEL_BASE, TPM),
        {"odometry": {"heading_drift": {"rate_rad_s": Expect(DRIFT_ODO, DRIFT_ODO)}}},
    ),
    "range_dependent": SimCase(lambda b, c: range_dependent(b, K_R2), {"range:sonar": E_K}),
    "glitch": SimCase(lambda b, c: glitch(b, GLITCH_P, SONAR_MAX), {"range:sonar": E_GLITCH}),
    "bias+scale": SimCase(_scale_and_bias, {"gyro": {**E_BIAS, **E_SCALE}}),
    "hard+soft_iron": SimCase(_soft_then_hard, {"compass": {**E_HARD, **E_SOFT}}),
    "tick_scale+wheel_ratio": SimCase(_ticks_and_ratio, {"odometry": {**E_TICKS, **E_RATIO}}),
    "glitch+range_dependent": SimCase(
        _range_dependent_and_glitch,
        {
            "range:sonar": {
                **E_K,
                "glitch": {
                    "probability": E_GLITCH["glitch"]["probability"],
                    "value": Expect(GLITCH_K_VALUE, GLITCH_K_VALUE, tol=1e-9),
                },
            }
        },
    ),
}
# Left out, and why:
# - quantisation: rounding explains the error only when the noise before it is small against
#   the step (synthetic.py's note). The simulated sonar's noise is 6.6 % of the range (0.066 m
#   at 1 m); for the rounded model to halve the held-out error the step must be about 38 sigma
#   (the chance that noise moves a reading across a step boundary must be small), 2.5 m: the
#   whole range. Measured: sonar rounded to 5 cm or 25 cm, quantisation is proposed and
#   rejected (held-out RMS 0.7 % and 5 % worse than without it).
# - one wheel's ticks alone (left x 0.96 or x 0.85): in the effects' terms that is wheel_ratio
#   1/c *and* tick_scale 2c/(1 + c) at once, and neither alone passes, so forward selection
#   names nothing (measured at x 0.85: held out 0.022 m, 14 sigma_0; wheel_ratio alone gains
#   15 % but LR 3.2 < 9.1, tick_scale 0.2 %). The pair below is injected by the effects' own
#   definitions instead.


def _by_name(results: list[StreamResult]) -> dict[str, StreamResult]:
    return {r.problem.name: r for r in results}


def _calibrate(path: Path, config: Config) -> dict[str, StreamResult]:
    bundle = load_bundle(path)
    return _by_name(calibrate(bundle, declared_model(config, bundle.meta)))


@pytest.fixture(scope="module")
def default_config() -> Config:
    with (ROOT / "config" / "default.toml").open("rb") as fh:
        return tomllib.load(fh)


@pytest.fixture(scope="module")
def recording(default_config: Config, tmp_path_factory: pytest.TempPathFactory) -> Path:
    tmp = tmp_path_factory.mktemp("sim_inject")
    mcap = record_simulator(
        default_config, tmp / "run.mcap", DURATION_S, seed=SEED, pose_rate_hz=POSE_RATE_HZ
    )
    return export_bundle(mcap, tmp / "clean")


@pytest.fixture(scope="module")
def clean(recording: Path, default_config: Config) -> dict[str, StreamResult]:
    return _calibrate(recording, default_config)


def _check(case: SimCase, results: Mapping[str, StreamResult], turn_on: float) -> list[str]:
    """Problems with the calibration of ``case``'s bundle (empty: passed); see the docstring."""
    problems = []
    for name, res in results.items():
        found = {
            inst.name: (params, se)
            for inst, (params, se) in zip(res.effects, res.effect_params(), strict=True)
        }
        expected = case.expect.get(name, {})
        if set(found) != set(expected):
            problems.append(f"{name}: found {sorted(found)}, expected {sorted(expected)}")
            continue
        for eff, params in expected.items():
            values, errors = found[eff]
            for p, e in params.items():
                value = e.value + (turn_on if e.plus_turn_on else 0.0)
                tol = 0.1 * e.size if e.tol is None else e.tol
                if e.binomial:
                    n = res.problem.part("fit").y.size  # type: ignore[attr-defined]
                    tol = 3 * np.sqrt(e.value * (1 - e.value) / n)
                if abs(values[p] - value) > tol:
                    problems.append(
                        f"{name}: {eff}.{p} = {values[p]:.6g}, expected {value:.6g} +- {tol:.3g}"
                    )
                if p in errors and not e.size >= 20 * errors[p]:
                    problems.append(f"{name}: {eff}.{p} injected {e.size:.3g} < 20 SE {errors[p]}")
        if not expected:
            continue
        # (a gyro bias beyond the declared turn-on spread is not absorbed by *before*: "before"
        # holds the turn-on bias to 2.58 sigma of the declared spread, issue 16)
        if not res.after <= 0.5 * res.before:
            problems.append(f"{name}: held-out {res.before:.4g} -> {res.after:.4g} not halved")
    return problems


def test_clean_recording_adds_no_effect(clean: dict[str, StreamResult]) -> None:
    # Measured on this recording, so the cases cannot pass by themselves: every candidate of
    # every stream is rejected, the turn-on bias draw is -0.0009 rad/s (z = 0.4 under the
    # declared 0.002), and an injected 0.004 rad/s (z = 1.6) is not named either.
    assert set(clean) == STREAMS
    assert {k: [i.name for i in r.effects] for k, r in clean.items() if r.effects} == {}


@pytest.mark.parametrize("name", sorted(CASES))
def test_injected_effect_is_found(
    name: str,
    recording: Path,
    clean: dict[str, StreamResult],
    default_config: Config,
    tmp_path: Path,
) -> None:
    bundle = Path(shutil.copytree(recording, tmp_path / "bundle"))
    config = CASES[name].inject(bundle, copy.deepcopy(default_config)) or default_config
    turn_on = float(clean["gyro"].selection.after.x[0])
    assert _check(CASES[name], _calibrate(bundle, config), turn_on) == []
