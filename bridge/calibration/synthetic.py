"""A small pure generator of measurement bundles from a known truth, for tests and benches.

A differential-drive robot follows a smooth trajectory (speed and turn rate are sums of
sinusoids); from it come wheel ticks, gyro yaw rate (with a temperature column), compass field,
sonar ranges to a varying obstacle (4 sensors), and range/bearing observations of 3 mapped
landmarks, each with white noise. :class:`Injected` names the effects put into the measurements
that the declared model (:data:`DECLARED`) does not have. Later the simulator can feed the same
bundle writer.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from koala_bridge.core.geometry import wrap_angle

#: The declared model the synthetic bundles are checked against (what MODEL.toml would say).
DECLARED: Mapping[str, Any] = {
    "robot": {"ticks_per_metre": 10000.0, "wheel_base_m": 0.30},
    "sensors": {"gyro": {"ideal": True}, "compass": {"ideal": True}, "sonar": {"ideal": True}},
}

NOISE = {
    "gyro": 0.005,
    "compass_uT": 0.3,
    "sonar": 0.01,
    "landmark_range": 0.02,
    "landmark_bearing": 0.01,
}
EARTH_UT = (0.0, 20.0, -43.0)  # horizontal field pointing along +y (north), vertical down
SONAR_MAX_M = 5.0
SONAR_MIN_M = 0.1


@dataclass(frozen=True)
class Injected:
    """Effects put into the measurements; every default is 'absent'."""

    gyro_bias: float = 0.0
    gyro_scale: float = 0.0
    gyro_drift: float = 0.0  # rad/s per s, about the middle of the fit part
    gyro_temperature: float = 0.0  # rad/s per degC
    gyro_time_offset: float = 0.0  # s, gyro lags the truth
    hard_iron: tuple[float, float] = (0.0, 0.0)  # uT
    soft_iron: tuple[float, float] = (0.0, 0.0)  # e_xx, e_xy of S = I + E
    tick_scale: float = 0.0  # true ticks per metre = declared (1 + tick_scale)
    wheel_base: float = 0.0  # true wheel base = declared (1 + wheel_base)
    wheel_ratio: float = 0.0  # D_left / D_right = 1 + wheel_ratio
    heading_drift: float = 0.0  # rad/s the odometry's heading turns relative to the truth
    sonar_range_dependent: float = 0.0  # m per m^2
    sonar_glitch: float = 0.0  # probability of a max-range reading
    sonar_quantisation: float = 0.0  # m
    sonar_per_sensor: tuple[float, ...] = field(default_factory=tuple)  # m, one per sensor
    sonar_noise: float | None = None  # m; None: NOISE["sonar"]
    # probability of a short reading U(SONAR_MIN_M, true range): a floor or beam-edge echo
    sonar_short: float = 0.0
    sonar_temperature: bool = False  # a temperature_c column in range.csv (no effect of its own)


def _trajectory(t: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    ph = rng.uniform(0, 2 * np.pi, 4)
    v = 0.25 + 0.1 * np.sin(2 * np.pi * t / 23 + ph[0]) + 0.05 * np.sin(2 * np.pi * t / 7 + ph[1])
    # A steady 0.2 rad/s turn makes the heading cover full circles (compass identifiability).
    w = 0.2 + 0.5 * np.sin(2 * np.pi * t / 11 + ph[2]) + 0.3 * np.sin(2 * np.pi * t / 5.3 + ph[3])
    return v, w


def write_columns(path: Path, header: str, cols: list[np.ndarray], fmt: str = "%.9g") -> None:
    """One bundle CSV from equal-length columns (the synthetic bundles' writer)."""
    np.savetxt(path, np.column_stack(cols), delimiter=",", header=header, comments="", fmt=fmt)


def make_bundle(
    out: Path,
    seed: int,
    inj: Injected | None = None,
    duration_s: float = 60.0,
    rate_hz: float = 20.0,
) -> Path:
    """Write a bundle to ``out`` and return it. Same seed, same noise, whatever is injected."""
    inj = inj or Injected()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    ss = np.random.SeedSequence(seed).spawn(6)
    rng_traj, rng_gyro, rng_comp, rng_son, rng_lm, rng_odo = (np.random.default_rng(s) for s in ss)
    dt = 1.0 / rate_hz
    t = np.arange(0.0, duration_s + dt / 2, dt)
    v, w = _trajectory(t, rng_traj)
    theta = np.r_[0.0, np.cumsum(0.5 * (w[1:] + w[:-1]) * dt)]
    mid = theta[:-1] + 0.5 * np.diff(theta)
    ds = 0.5 * (v[1:] + v[:-1]) * dt
    x = np.r_[0.0, np.cumsum(ds * np.cos(mid))] + 1.0
    y = np.r_[0.0, np.cumsum(ds * np.sin(mid))] + 1.0
    write_columns(out / "truth_pose.csv", "t,x,y,theta", [t, x, y, theta])

    # Odometry: true wheel distances from the true geometry, counted with the true tick size.
    tpm = DECLARED["robot"]["ticks_per_metre"]
    b = DECLARED["robot"]["wheel_base_m"] * (1 + inj.wheel_base)
    dth = np.diff(theta)
    s_l, s_r = ds - dth * b / 2, ds + dth * b / 2
    # A heading drift as opposite tick streams: with the true wheel base, (s_r - s_l) / b gains
    # d dt, so the odometry of the calibrated geometry drifts by d.
    s_l, s_r = s_l - 0.5 * inj.heading_drift * dt * b, s_r + 0.5 * inj.heading_drift * dt * b
    rho = 1 + inj.wheel_ratio
    tpm_true = tpm * (1 + inj.tick_scale)
    slip = rng_odo.normal(0, 2e-4, (2, ds.size)) * np.sqrt(np.abs(ds) / max(ds.mean(), 1e-9))
    # Inverse of the model: s_l = dL / tpm 2 rho / (1 + rho), s_r = dR / tpm 2 / (1 + rho)
    cum_l = np.cumsum((s_l + slip[0]) * tpm_true * (1 + rho) / (2 * rho))
    cum_r = np.cumsum((s_r + slip[1]) * tpm_true * (1 + rho) / 2)
    ticks_l = np.rint(np.concatenate([[0.0], cum_l]))
    ticks_r = np.rint(np.concatenate([[0.0], cum_r]))
    write_columns(out / "odometry.csv", "t,left_ticks,right_ticks", [t, ticks_l, ticks_r],
                  fmt="%.10g")

    # Gyro with a temperature covariate.
    t_mid_fit = 0.3 * duration_s
    temp = 25 + 4 * np.sin(2 * np.pi * t / (0.7 * duration_s) + rng_gyro.uniform(0, 6.28))
    w_lag = np.interp(t - inj.gyro_time_offset, t, w)
    rate = (
        (1 + inj.gyro_scale) * w_lag
        + inj.gyro_bias
        + inj.gyro_drift * (t - t_mid_fit)
        + inj.gyro_temperature * (temp - temp[t < 0.6 * duration_s].mean())
        + rng_gyro.normal(0, NOISE["gyro"], t.size)
    )
    write_columns(out / "gyro.csv", "t,yaw_rate,temperature_c", [t, rate, temp])

    # Compass: body-frame field m = R(-theta) b_world; measured = S m + h + noise.
    bx, by, bz = EARTH_UT
    c, s = np.cos(theta), np.sin(theta)
    m = np.column_stack([c * bx + s * by, -s * bx + c * by])
    e_xx, e_xy = inj.soft_iron
    S = np.array([[1 + e_xx, e_xy], [e_xy, 1 - e_xx]])
    m = m @ S.T + np.asarray(inj.hard_iron) + rng_comp.normal(0, NOISE["compass_uT"], m.shape)
    mz = bz + rng_comp.normal(0, NOISE["compass_uT"], t.size)
    write_columns(out / "compass.csv", "t,mx,my,mz", [t, m[:, 0], m[:, 1], mz])

    # Sonar: 4 sensors, true range to a moving obstacle, 0.2..3 m.
    n_s = 4
    ts = np.repeat(t, n_s)
    sensor = np.tile(np.arange(n_s), t.size)
    true_r = 1.6 + 1.3 * np.sin(2 * np.pi * ts / 9.0 + sensor) * np.cos(2 * np.pi * ts / 31.0)
    true_r = np.clip(true_r + 0.1 * sensor, 0.2, 3.2)
    meas = (
        true_r
        + inj.sonar_range_dependent * true_r**2
        + rng_son.normal(0, NOISE["sonar"] if inj.sonar_noise is None else inj.sonar_noise, ts.size)
    )
    if inj.sonar_per_sensor:
        meas = meas + np.asarray(inj.sonar_per_sensor)[sensor]
    if inj.sonar_quantisation:
        meas = inj.sonar_quantisation * np.round(meas / inj.sonar_quantisation)
    glitch = rng_son.random(ts.size) < inj.sonar_glitch
    meas = np.where(glitch, SONAR_MAX_M, meas)
    # Drawn whatever is injected (after every other sonar variate), so the rest stays the same.
    short = rng_son.random(ts.size) < inj.sonar_short
    short_r = SONAR_MIN_M + (true_r - SONAR_MIN_M) * rng_son.random(ts.size)
    meas = np.where(short & ~glitch, short_r, meas)
    cols, header = [ts, sensor, meas, true_r], "t,sensor,measured,true_range"
    if inj.sonar_temperature:
        # a room warming over the run, as a sonar logged against a ruler would see it
        cols.append(25 + 3 * np.sin(2 * np.pi * ts / (0.8 * duration_s) + rng_son.uniform(0, 6.28)))
        header += ",temperature_c"
    write_columns(out / "range.csv", header, cols)

    # Landmarks: 3 mapped landmarks, one observation each per 0.5 s.
    lm = np.array([[1, 4.0, 4.0], [2, -2.0, 3.0], [3, 2.0, -3.0]])
    write_columns(out / "landmark_map.csv", "id,x,y", [lm[:, 0], lm[:, 1], lm[:, 2]])
    step = max(1, int(round(0.5 * rate_hz)))
    idx = np.arange(0, t.size, step)
    ti = np.repeat(t[idx], 3)
    li = np.tile(np.arange(3), idx.size)
    px, py, pth = np.repeat(x[idx], 3), np.repeat(y[idx], 3), np.repeat(theta[idx], 3)
    dx, dy = lm[li, 1] - px, lm[li, 2] - py
    rng_ = np.hypot(dx, dy) + rng_lm.normal(0, NOISE["landmark_range"], ti.size)
    brg = np.arctan2(dy, dx) - pth + rng_lm.normal(0, NOISE["landmark_bearing"], ti.size)
    brg = wrap_angle(brg)
    write_columns(out / "landmarks.csv", "t,landmark_id,range,bearing", [ti, lm[li, 0], rng_, brg])

    meta = {
        "name": f"synthetic-{seed}",
        "source": "koala_bridge.calibration.synthetic",
        "injected": {k: v for k, v in inj.__dict__.items() if v not in (0.0, (0.0, 0.0), ())},
        "units": {"compass.mx": "uT", "range.measured": "m"},
    }
    (out / "meta.json").write_text(json.dumps(meta, indent=1), encoding="utf-8")
    return out


@dataclass(frozen=True)
class Case:
    """An injection and what the tool must find: ``{stream: {effect: {param: (value, tol)}}}``.

    Tolerances are 10 % of the injected magnitude (absolute where a parameter is a matrix entry
    or an offset): every magnitude is at least 20 standard errors of its estimate on a 60 s,
    20 Hz bundle (see the ``param_se`` evidence in the reports), so 10 % is beyond 2 SE yet
    tight enough to tell a recovered parameter from a merely correlated one.
    """

    inject: Injected
    expect: Mapping[str, Mapping[str, Mapping[str, tuple[float, float]]]]


CASES: Mapping[str, Case] = {
    "bias": Case(Injected(gyro_bias=0.02), {"gyro": {"bias": {"bias": (0.02, 0.002)}}}),
    "scale": Case(Injected(gyro_scale=0.05), {"gyro": {"scale": {"scale_error": (0.05, 0.005)}}}),
    "bias_drift": Case(
        Injected(gyro_drift=5e-4), {"gyro": {"bias_drift": {"rate_per_s": (5e-4, 5e-5)}}}
    ),
    "covariate": Case(
        Injected(gyro_temperature=0.004),
        {"gyro": {"covariate:temperature_c": {"coefficient": (0.004, 4e-4)}}},
    ),
    "time_offset": Case(
        Injected(gyro_time_offset=0.1), {"gyro": {"time_offset": {"tau_s": (0.1, 0.01)}}}
    ),
    "hard_iron": Case(
        Injected(hard_iron=(8.0, -5.0)),
        {"compass": {"hard_iron": {"dh_x": (8.0, 0.8), "dh_y": (-5.0, 0.8)}}},
    ),
    "soft_iron": Case(
        Injected(soft_iron=(0.12, 0.05)),
        {"compass": {"soft_iron": {"e_xx": (-0.12, 0.012), "e_xy": (-0.05, 0.012)}}},
    ),
    "tick_scale": Case(
        Injected(tick_scale=0.05),
        {"odometry": {"tick_scale": {"ticks_per_metre": (10500.0, 50.0)}}},
    ),
    "wheel_base": Case(
        Injected(wheel_base=0.1), {"odometry": {"wheel_base": {"wheel_base_m": (0.33, 0.003)}}}
    ),
    # 0.04: the ratio's spread over seeds is 0.0013 (bench), so 0.02 was only 15 SE and its
    # 10 % tolerance 1.5 SE; 0.04 keeps the rule of the class docstring (>= 20 SE, 10 % >= 2 SE).
    "wheel_ratio": Case(
        Injected(wheel_ratio=0.04),
        {"odometry": {"wheel_ratio": {"ratio_left_right": (1.04, 0.004)}}},
    ),
    # 0.03 rad/s: the fitted drift's spread over clean seeds is 0.0011 rad/s (27 SE).
    "heading_drift": Case(
        Injected(heading_drift=0.03),
        {"odometry": {"heading_drift": {"rate_rad_s": (0.03, 0.003)}}},
    ),
    "range_dependent": Case(
        Injected(sonar_range_dependent=0.02),
        {"range": {"range_dependent": {"k_per_m2": (0.02, 0.002)}}},
    ),
    "glitch": Case(
        Injected(sonar_glitch=0.05),
        {"range": {"glitch": {"probability": (0.05, 0.015), "value": (5.0, 1e-9)}}},
    ),
    # Rounding explains the error only when the noise before it is small against the step.
    "quantisation": Case(
        Injected(sonar_quantisation=0.05, sonar_noise=0.0005),
        {"range": {"quantisation": {"step": (0.05, 1e-6)}}},
    ),
    "offset_per": Case(
        Injected(sonar_per_sensor=(0.05, -0.03, 0.02, -0.04)),
        {"range": {"offset_per:sensor": {"offset_0": (0.05, 0.005), "offset_1": (-0.03, 0.005)}}},
    ),
    "bias+scale": Case(
        Injected(gyro_bias=0.02, gyro_scale=0.05),
        {"gyro": {"bias": {"bias": (0.02, 0.002)}, "scale": {"scale_error": (0.05, 0.005)}}},
    ),
    "hard+soft_iron": Case(
        Injected(hard_iron=(8.0, -5.0), soft_iron=(0.12, 0.05)),
        {
            "compass": {
                "hard_iron": {"dh_x": (8.0, 0.8), "dh_y": (-5.0, 0.8)},
                "soft_iron": {"e_xx": (-0.12, 0.012)},
            }
        },
    ),
    "tick_scale+wheel_base": Case(
        Injected(tick_scale=0.05, wheel_base=0.1),
        {
            "odometry": {
                "tick_scale": {"ticks_per_metre": (10500.0, 50.0)},
                "wheel_base": {"wheel_base_m": (0.33, 0.003)},
            }
        },
    ),
    "glitch+range_dependent": Case(
        Injected(sonar_glitch=0.05, sonar_range_dependent=0.02),
        {
            "range": {
                "glitch": {"probability": (0.05, 0.015)},
                "range_dependent": {"k_per_m2": (0.02, 0.002)},
            }
        },
    ),
}


def check_case(case: Case, results: Any) -> list[str]:
    """Problems with a calibration of ``case``'s bundle (empty: the case passed).

    Passing means: on each stream with injected effects, exactly those effects are named, their
    parameters are within tolerance, and the held-out metric at least halves; on every other
    stream no effect is added.
    """
    problems: list[str] = []
    for res in results:
        name = res.problem.name
        found = {
            inst.name: params
            for inst, (params, _) in zip(res.effects, res.effect_params(), strict=True)
        }
        expected = case.expect.get(name, {})
        if set(found) != set(expected):
            problems.append(f"{name}: found {sorted(found)}, expected {sorted(expected)}")
            continue
        for eff, params in expected.items():
            for p, (value, tol) in params.items():
                if abs(found[eff][p] - value) > tol:
                    problems.append(
                        f"{name}: {eff}.{p} = {found[eff][p]:.6g}, "
                        f"expected {value:.6g} +- {tol:.3g}"
                    )
        if expected and not res.after <= 0.5 * res.before:
            problems.append(f"{name}: held-out {res.before:.4g} -> {res.after:.4g} not halved")
    return problems


#: The random study's families (issue 16: "outliers, drift, tilt, temperature, bias, scale,
#: several at once"): per family, the stream it acts on, the effect the tool must name, and the
#: Injected field with its magnitude range. Each range starts at the CASES value (>= 20 SE, see
#: the Case docstring) and reaches twice it; signs are drawn. Tilt is not in this generator (a
#: planar robot): tests/unit/test_calibration_level.py covers it.
STUDY_FAMILIES: Mapping[str, tuple[str, str, str, tuple[float, float]]] = {
    "gyro bias": ("gyro", "bias", "gyro_bias", (0.02, 0.04)),
    "gyro scale": ("gyro", "scale", "gyro_scale", (0.05, 0.10)),
    "gyro drift": ("gyro", "bias_drift", "gyro_drift", (5e-4, 1e-3)),
    "gyro temperature": ("gyro", "covariate:temperature_c", "gyro_temperature", (0.004, 0.008)),
    "hard iron": ("compass", "hard_iron", "hard_iron", (8.0, 16.0)),
    "tick scale": ("odometry", "tick_scale", "tick_scale", (0.05, 0.10)),
    "wheel base": ("odometry", "wheel_base", "wheel_base", (0.10, 0.20)),
    "heading drift": ("odometry", "heading_drift", "heading_drift", (0.03, 0.06)),
    "sonar outliers": ("range", "outlier:short", "sonar_short", (0.05, 0.12)),
    "sonar range-dependent": ("range", "range_dependent", "sonar_range_dependent", (0.02, 0.04)),
}


def random_case(rng: np.random.Generator) -> tuple[list[str], Injected, dict[str, set[str]]]:
    """One case of the random study: 1-3 families on different streams (several at once),
    magnitudes and signs drawn. Returns the families, the injection and the expected effect
    names per stream (streams not named: none expected)."""
    names = list(STUDY_FAMILIES)
    order = rng.permutation(len(names))
    k = int(rng.integers(1, 4))
    chosen: list[str] = []
    streams: set[str] = set()
    for i in order:
        stream = STUDY_FAMILIES[names[i]][0]
        if stream not in streams:
            chosen.append(names[i])
            streams.add(stream)
        if len(chosen) == k:
            break
    fields: dict[str, Any] = {}
    expect: dict[str, set[str]] = {}
    for name in chosen:
        stream, effect, attr, (lo, hi) = STUDY_FAMILIES[name]
        size = float(rng.uniform(lo, hi))
        sign = 1.0 if attr in ("sonar_short", "sonar_range_dependent", "gyro_drift") \
            else float(rng.choice((-1.0, 1.0)))
        if attr == "hard_iron":
            a = rng.uniform(0, 2 * np.pi)
            fields[attr] = (size * float(np.cos(a)), size * float(np.sin(a)))
        else:
            fields[attr] = sign * size
        expect.setdefault(stream, set()).add(effect)
    return chosen, Injected(**fields), expect
