"""Synthetic IMU bundles with 3-D motion (tilts up to 90 deg) and a z-rate bias, for tests.

The body turns about the vertical (yaw psi) while, in episodes, it rolls or pitches up to 90 deg
and back; between episodes it is level. Euler angles ZYX (yaw psi, pitch th, roll ph); body rates
(e.g. Titterton & Weston, "Strapdown Inertial Navigation Technology", eq. 3.35 inverted)::

    p = ph' - psi' sin th
    q = th' cos ph + psi' cos th sin ph
    r = -th' sin ph + psi' cos th cos ph

and the accelerometer at rest reads the specific force of gravity in the body frame,
``g (-sin th, cos th sin ph, cos th cos ph)`` (z up: ``+g`` when level). ``gyro.csv`` holds
``yaw_rate = r + bias + noise``, ``rate_x = p``, ``rate_y = q`` (plus noise) and, with
``accelerometer``, ``acc_x, acc_y, acc_z``; ``truth_pose.csv`` the heading psi. When tilted the
z gyro reads ``psi' cos th cos ph`` plus the tilt rates mixed in, not ``psi'``: the declared
model's error there is not a bias.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from koala_bridge.calibration.synthetic import write_columns
from numpy.typing import NDArray

GRAVITY = 9.80665


@dataclass(frozen=True)
class TiltCase:
    bias: float = 0.02  # rad/s on the z gyro
    noise: float = 0.005  # rad/s per sample, every gyro axis
    acc_noise: float = 0.05  # m/s^2 per sample
    duration_s: float = 240.0
    rate_hz: float = 50.0
    #: every ``period_s`` an episode of ``episode_s`` tilts the body to the next amplitude and back
    period_s: float = 40.0
    episode_s: float = 20.0
    amplitudes_deg: tuple[float, ...] = (90.0, 60.0, 75.0, 45.0, 90.0, 30.0)


def tilt_angles(
    case: TiltCase,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """``(t, psi, th, ph)``: time, yaw, pitch and roll (rad); even episodes roll, odd pitch."""
    t = np.arange(0.0, case.duration_s, 1.0 / case.rate_hz)
    psi = 0.3 * t + 0.4 * 13 / (2 * np.pi) * (1 - np.cos(2 * np.pi * t / 13))
    th = np.zeros_like(t)
    ph = np.zeros_like(t)
    for k, amp in enumerate(case.amplitudes_deg):
        t0 = k * case.period_s + (case.period_s - case.episode_s) / 2
        inside = (t >= t0) & (t <= t0 + case.episode_s)
        shape = np.deg2rad(amp) * np.sin(np.pi * (t - t0) / case.episode_s) ** 2
        (ph if k % 2 == 0 else th)[inside] = shape[inside]
    return t, psi, th, ph


def make_tilt_bundle(out: Path, seed: int, case: TiltCase, accelerometer: bool = True) -> Path:
    """Write ``gyro.csv`` and ``truth_pose.csv`` (module docstring) to ``out`` and return it."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    t, psi, th, ph = tilt_angles(case)
    d_psi, d_th, d_ph = (np.gradient(a, t) for a in (psi, th, ph))
    p = d_ph - d_psi * np.sin(th)
    q = d_th * np.cos(ph) + d_psi * np.cos(th) * np.sin(ph)
    r = -d_th * np.sin(ph) + d_psi * np.cos(th) * np.cos(ph)
    gyro = [
        t,
        r + case.bias + rng.normal(0, case.noise, t.size),
        p + rng.normal(0, case.noise, t.size),
        q + rng.normal(0, case.noise, t.size),
    ]
    header = "t,yaw_rate,rate_x,rate_y"
    if accelerometer:
        f = GRAVITY * np.column_stack(
            [-np.sin(th), np.cos(th) * np.sin(ph), np.cos(th) * np.cos(ph)]
        )
        gyro += list((f + rng.normal(0, case.acc_noise, f.shape)).T)
        header += ",acc_x,acc_y,acc_z"
    write_columns(out / "gyro.csv", header, gyro)
    zeros = np.zeros_like(t)
    write_columns(out / "truth_pose.csv", "t,x,y,theta", [t, zeros, zeros, psi])
    return out
