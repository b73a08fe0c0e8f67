"""The gyro on its level segments (``gyro:level``): where the z axis is vertical, the z rate is the
heading rate, so a z-rate bias is plain there.

An IMU moved in 3-D (tilts up to 90 deg) reads on its z axis ``psi' cos(pitch) cos(roll)`` plus
the tilt rates mixed in, not the heading rate ``psi'`` the reference gives. On the whole stream
that error looks like a coupling to the x/y rates (``covariate:rate_y``, ``scale``), and the bias
is lost under it. On the level segments the declared model holds, and the bias is fitted and
scored there alone: a second stream, ``gyro:level``, with the gyro's own section and keys (its
``bias`` is the gyro's ``bias_rad_s``; listed after ``gyro``, so the written config takes it).
The tilt coupling stays on the whole stream.

Level segments:

* with an accelerometer in ``gyro.csv`` (``acc_x, acc_y, acc_z``, m/s^2, body frame, z up):
  the tilt of the z axis from the measured gravity, ``atan2(hypot(a_x, a_y), a_z)``, below
  :data:`LEVEL_TILT_DEG`, where the accelerometer reads gravity alone (``|a|`` within
  :data:`GRAVITY_TOLERANCE` of its median: a body that accelerates is not measured for tilt);
* without one, from ``rate_x, rate_y``: where neither rotates (each within
  :data:`ROTATION_SIGMAS` noise sigmas, at least :data:`MIN_ROTATION_RAD_S`, of its median).
  That finds the body not *tilting*, not the body level: a tilt held still passes for level, so an
  accelerometer is the better evidence (the report says which was used);

kept only in stretches of at least :data:`MIN_LEVEL_S`. At 3 deg a heading rate psi' is read as
``psi' cos 3 deg``, 0.14 % low: far below a bias at any turn rate the robot has.

Built only when it tells something new: a heading reference from ``truth_pose.theta`` (a
compass-derived reference is compared over windows, which gaps would break), some samples not
level (else the gyro stream is the level stream), and at least :data:`MIN_LEVEL_SAMPLES` level
ones in each of the fit and score parts.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import numpy as np
from koala_bridge.calibration.bundle import Bundle, Table
from koala_bridge.calibration.model import DeclaredModel
from koala_bridge.calibration.robust import mad_sigma, white_noise_sigma
from koala_bridge.calibration.streams.scalar import ScalarProblem
from numpy.typing import NDArray
from scipy.ndimage import uniform_filter1d

ACC_COLUMNS = ("acc_x", "acc_y", "acc_z")
RATE_COLUMNS = ("rate_x", "rate_y")
#: z axis within this of the vertical: level
LEVEL_TILT_DEG = 3.0
#: |a| within this fraction of its median: the accelerometer reads gravity alone
GRAVITY_TOLERANCE = 0.05
#: without an accelerometer: x/y rates within this many noise sigmas (and at least
#: MIN_ROTATION_RAD_S) of their medians are "not rotating"
ROTATION_SIGMAS = 4.0
MIN_ROTATION_RAD_S = 0.005
#: shortest level stretch used (s)
MIN_LEVEL_S = 1.0
#: the accelerometer is read for attitude as its mean over this span (s): the attitude a
#: level stretch needs lasts MIN_LEVEL_S, vibration is faster
ATTITUDE_SMOOTH_S = 0.25
#: fewest level samples in each of the fit and score parts
MIN_LEVEL_SAMPLES = 50
#: a gyro level on more than this fraction of its samples needs no level stream
MAX_LEVEL_FRACTION = 0.95


def tilt_from_accelerometer(acc: NDArray[np.float64]) -> NDArray[np.float64]:
    """(n,) angle between the body z axis and the measured gravity (rad), from (n, 3) m/s^2."""
    return np.asarray(np.arctan2(np.hypot(acc[:, 0], acc[:, 1]), acc[:, 2]), dtype=float)


def _long_runs(mask: NDArray[np.bool_], t: NDArray[np.float64], min_s: float) -> NDArray[np.bool_]:
    """``mask`` with its true runs shorter than ``min_s`` seconds cleared."""
    out = mask.copy()
    edges = np.flatnonzero(np.diff(np.r_[0, mask.astype(np.int8), 0]))
    for start, stop in zip(edges[::2], edges[1::2], strict=True):
        if t[stop - 1] - t[start] < min_s:
            out[start:stop] = False
    return out


def not_rotating(gyro: Table) -> NDArray[np.bool_] | None:
    """Samples where neither x/y rate rotates (each within :data:`ROTATION_SIGMAS` noise
    sigmas, at least :data:`MIN_ROTATION_RAD_S`, of its median); None without the rates."""
    if not all(c in gyro.columns for c in RATE_COLUMNS):
        return None
    still = np.ones(len(gyro), dtype=bool)
    for c in RATE_COLUMNS:
        v = gyro[c]
        limit = max(ROTATION_SIGMAS * white_noise_sigma(v), MIN_ROTATION_RAD_S)
        still &= np.isfinite(v) & (np.abs(v - np.nanmedian(v)) < limit)
    return still


def level_mask(gyro: Table) -> tuple[NDArray[np.bool_], str] | None:
    """Level samples of ``gyro.csv`` and how they were found (module docstring); None when the
    file has neither an accelerometer nor the x/y rates."""
    t = gyro["t"]
    if all(c in gyro.columns for c in ACC_COLUMNS):
        acc, calm = _gravity(gyro)
        level = calm & (
            np.abs(tilt_from_accelerometer(np.nan_to_num(acc))) < np.deg2rad(LEVEL_TILT_DEG)
        )
        how = (
            f"accelerometer: tilt of z from gravity < {LEVEL_TILT_DEG:g} deg, |a| within "
            f"{100 * GRAVITY_TOLERANCE:g} % of g"
        )
    elif (still := not_rotating(gyro)) is not None:
        level = still
        how = (
            "no accelerometer: x/y rates ~0 (not tilting; a tilt held still is not told from level)"
        )
    else:
        return None
    return _long_runs(level, t, MIN_LEVEL_S), f"{how}, stretches >= {MIN_LEVEL_S:g} s"


def _gravity(gyro: Table) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """The accelerometer's ``(n, 3)`` readings, each the mean over :data:`ATTITUDE_SMOOTH_S`
    about it, and where they are gravity alone: ``|a|`` finite and within
    :data:`GRAVITY_TOLERANCE` of its median (a body that accelerates is not measured for
    attitude). The mean keeps the attitude and drops vibration: a car's raw 100 Hz
    accelerometer scattered by 3 deg about its direction, so that not one 1 s stretch was
    level, and its compass stream was left out as tilting."""
    acc = np.column_stack([gyro[c] for c in ACC_COLUMNS])
    finite = np.all(np.isfinite(acc), axis=1)
    t = gyro["t"][finite]
    if t.size > 1:
        n = int(round(ATTITUDE_SMOOTH_S / max(float(np.median(np.diff(t))), 1e-9)))
        if n > 1:
            acc[finite] = uniform_filter1d(acc[finite], size=n, axis=0, mode="nearest")
    norm = np.linalg.norm(acc, axis=1)
    ok = np.isfinite(norm)
    g = float(np.median(norm[ok])) if ok.any() else 0.0
    return acc, ok & (np.abs(norm - g) < GRAVITY_TOLERANCE * g)


def mounting_mask(gyro: Table) -> tuple[NDArray[np.bool_], str] | None:
    """Samples of ``gyro.csv`` at the sensor's usual attitude: the measured gravity within
    :data:`LEVEL_TILT_DEG` of its median direction (the mounting), where the accelerometer reads
    gravity alone, in stretches of :data:`MIN_LEVEL_S`; and how that was found. None without an
    accelerometer, or when the attitude held nearly throughout (then nothing needs setting
    aside). A constant mounting tilt (a few degrees, or an accelerometer's zero-g offset) is not
    tilting: for a compass turning about the vertical it moves x/y by a constant and a gain,
    which the iron effects model; a tilt that varies is what spoils a heading."""
    if not all(c in gyro.columns for c in ACC_COLUMNS):
        return None
    t = gyro["t"]
    acc, calm = _gravity(gyro)
    if not calm.any():
        return None
    unit = np.zeros_like(acc)
    unit[calm] = acc[calm] / np.linalg.norm(acc[calm], axis=1, keepdims=True)
    mount = np.median(unit[calm], axis=0)
    mount /= max(float(np.linalg.norm(mount)), 1e-12)
    steady = calm & (unit @ mount > np.cos(np.deg2rad(LEVEL_TILT_DEG)))
    mask = _long_runs(steady, t, MIN_LEVEL_S)
    if mask.mean() > MAX_LEVEL_FRACTION:
        return None
    tilt = float(np.degrees(np.arccos(np.clip(mount[2], -1.0, 1.0))))
    how = (f"accelerometer: gravity within {LEVEL_TILT_DEG:g} deg of its median direction "
           f"(the mounting, {tilt:.3g} deg from the z axis), |a| within "
           f"{100 * GRAVITY_TOLERANCE:g} % of g, stretches >= {MIN_LEVEL_S:g} s")
    return mask, how


#: a gap between level rows longer than this many of their median intervals, and than
#: LEVEL_GAP_S, separates two level segments (heading-space windows start again after it)
LEVEL_GAP_INTERVALS = 10
LEVEL_GAP_S = 0.5


def build_gyro_level(bundle: Bundle, model: DeclaredModel) -> ScalarProblem | None:
    """The ``gyro:level`` stream (module docstring), or None."""
    from koala_bridge.calibration.streams import build_gyro, heading_reference

    gyro = bundle.get("gyro")
    if gyro is None or heading_reference(bundle) is None:
        return None
    found = level_mask(gyro)
    if found is None:
        return None
    mask, how = found
    if mask.mean() > MAX_LEVEL_FRACTION:
        return None
    tables = dict(bundle.tables)
    tables["gyro"] = gyro.select(mask)
    # level rows only: the whole stream's rows (of a decimated subset) would bring the tilted
    # stretches back into the means over the reference's intervals
    problem = build_gyro(replace(bundle, tables=tables, whole=None), model)
    if problem is None:
        return None
    fit = problem.split.mask(problem.t, "fit")
    if min(int(fit.sum()), int((~fit).sum())) < MIN_LEVEL_SAMPLES:
        return None
    problem.name = "gyro:level"
    problem.heading_window_s = None  # the rate-space heading metric's windows run on over gaps
    # heading space's windows start again after each tilted gap (a noisy reference's rate is
    # compared there, as the whole stream's is: pipeline._heading_space_if_noisy)
    dt = np.diff(problem.t)
    problem.window_gap_s = max(LEVEL_GAP_INTERVALS * float(np.median(dt)), LEVEL_GAP_S)
    problem.notes.append(
        f"level segments only ({how}): {int(mask.sum())} of {mask.size} samples; the z-rate "
        "bias is fitted and scored here, apart from the tilt coupling of the whole stream"
    )
    return problem


#: where the accelerometer's tilt changes faster than this (rad/s, 3 deg/s; and than 4 robust
#: sigmas of its rate on the level samples, its noise), the x/y rates are asked whether a
#: rotation made the change
MIN_TILT_RATE = 0.05
#: the share of those changes that no rotation made (the x/y rates, smoothed as the
#: accelerometer is, below half the tilt's rate), beyond which the note says the
#: accelerometer's "tilt" may be an acceleration
UNTURNED_TILT_SHARE = 0.5
#: fewest such changes the share is read on
MIN_TILT_CHANGES = 10


def _accelerating(t: NDArray[np.float64], level_t: NDArray[np.float64], columns: Any) -> str:
    """A clause for the tilt note where most changes of the accelerometer's tilt come with no
    rotation in the x/y rates (:data:`UNTURNED_TILT_SHARE`): an accelerometer reads a
    horizontal acceleration as a tilt (1 m/s^2 is 5.8 deg), which no rotation makes, and the
    |a| test cannot see it (it lengthens the vector by 0.5 %). A navX on a driving robot read
    "tilted on 76 %" where motion capture had it within 5 deg on all but 0.1 %: 93 % of its
    tilt's changes came with no rotation. A robot driving onto a ramp rotates as its tilt
    changes (7 % did not, the rates' noise): its tilt is one. Rates compared at the same time,
    not integrated since a level sample: the integral of a gyro's residual bias over a few
    seconds is degrees (the navX's 2 deg)."""
    if not all(c in columns for c in (*RATE_COLUMNS, *ACC_COLUMNS)) or t.size < 3:
        return ""
    level = np.isin(t, level_t)
    if level.all() or not level.any():
        return ""
    acc, _ = _gravity(Table("gyro", {"t": t, **{c: columns[c] for c in ACC_COLUMNS}}))
    tilt_rate = np.abs(np.gradient(tilt_from_accelerometer(np.nan_to_num(acc)), t))
    n = max(int(round(ATTITUDE_SMOOTH_S / max(float(np.median(np.diff(t))), 1e-9))), 1)
    rotation = np.hypot(*(
        uniform_filter1d(np.nan_to_num(columns[c] - np.nanmedian(columns[c])), n)
        for c in RATE_COLUMNS
    ))
    noise = 4 * mad_sigma(tilt_rate[level])
    changing = tilt_rate > max(MIN_TILT_RATE, noise)
    if changing.sum() < MIN_TILT_CHANGES:
        return ""
    share = float(np.mean(rotation[changing] < 0.5 * tilt_rate[changing]))
    if share <= UNTURNED_TILT_SHARE:
        return ""
    return (
        f". But {100 * share:.0f} % of the accelerometer's tilt changes come with no rotation "
        "in the x/y rates: a horizontal acceleration reads as a tilt (1 m/s^2 is 5.8 deg: a "
        "driving robot's turns and starts), which no rotation makes; a sensor that stays "
        "level is one stream (drop acc_x, acc_y, acc_z from gyro.csv to calibrate it so)"
    )


def note_level_bias(results: Sequence[Any]) -> None:
    """On the whole ``gyro`` stream, say where the written bias comes from when ``gyro:level``
    found one (``results``: :class:`koala_bridge.calibration.pipeline.StreamResult`)."""
    by_name = {res.problem.name: res for res in results}
    whole, level = by_name.get("gyro"), by_name.get("gyro:level")
    if whole is None or level is None:
        return
    share = 1.0 - level.problem.t.size / max(whole.problem.t.size, 1)
    whole.problem.notes.append(
        f"the sensor is tilted off its level mounting on about {100 * share:.0f} % of the "
        "samples (the accelerometer's gravity): there its z gyro does not read the heading's "
        "rate, and this stream's error holds the tilt, not only the sensor's; the level "
        "segments alone are stream gyro:level"
        + _accelerating(whole.problem.t, level.problem.t, whole.problem.columns)
    )
    if not any(i.name == "bias" for i in level.effects):
        return
    whole.problem.notes.append(
        "the gyro's bias is the level segments' (stream gyro:level, written as bias_rad_s): "
        "on the whole stream the tilted segments' error mixes into any bias fitted here"
    )
