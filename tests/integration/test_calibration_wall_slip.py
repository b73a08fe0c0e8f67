"""A recording of the bridge's simulator pushing into walls stays clean (issue 16, point 5).

The simulator (``config/default.toml``, every model on) drives 90 s of three 30 s cycles: a
weave (8 s, ``tools.sim_recording.weave_command``), straight ahead at 0.12 m/s for 12 s into
whatever wall is ahead, back 6 s, a turn on the spot (4 s) to face another way. With seed 3 the
body stands against a wall for 45 s in all while the wheels turn (10-20 s, 36-50 s, 60-80 s, and
briefly at 55 and 85.5 s when backing into one): it stops, the wheels slip
(``wall_traction_*``) and the encoders keep counting the commanded rotation.

Calibrated against the config it ran with, that slip reads as a tick scale: with nothing set
aside (``STALL_FRACTION = 0``) the tool names ``tick_scale`` 22 222 -> 49 662 ticks/m (standard
error 31 400; held-out 5 s window error 0.239 -> 0.128 m). With the stalls set aside
(``streams/odometry.py``, :func:`find_stalls`: 51.5 s in 5 spans) no stream gets an effect and the
held-out error is 0.0013 m, the level of a recording without walls (0.0015 m,
``test_calibration_sim_inject``); every interval where the truth stood still while the encoders
counted lies in a set-aside span, every span holds one, and the report's notes say how much was
set aside. The same recording with a genuinely wrong tick size (``tests/_sim_inject.tick_scale``:
+13 %, 2889 ticks/m, as in ``test_calibration_sim_inject``) still gets ``tick_scale`` within 10 %
of the injected change, at >= 20 standard errors, and the held-out window error at least halves.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from _sim_inject import tick_scale
from _sim_support import default_config
from koala_bridge.calibration.bundle import load_bundle
from koala_bridge.calibration.model import declared_model
from koala_bridge.calibration.pipeline import StreamResult, calibrate
from koala_bridge.calibration.streams import odometry
from koala_bridge.recording.export import export_bundle
from koala_bridge.tools.sim_recording import CommandSchedule, record_simulator, weave_command

SEED = 3
DURATION_S = 90.0
TPM = 22222.222  # [robot] ticks_per_metre of config/default.toml
TICKS = 0.13
H = odometry.STALL_INTERVAL_S


def wall_pushes(cycle_s: float = 30.0) -> CommandSchedule:
    """The cycles of the module docstring: body speed ``(v m/s, omega rad/s)`` at time t."""
    weave = weave_command()

    def command(t: float) -> tuple[float, float]:
        u = t % cycle_s
        if u < 8.0:
            return weave(u)
        if u < 20.0:
            return 0.12, 0.0
        if u < 26.0:
            return -0.12, 0.0
        return 0.0, 0.8

    return command


@pytest.fixture(scope="module")
def config() -> dict[str, Any]:
    return default_config()


@pytest.fixture(scope="module")
def recording(config: dict[str, Any], tmp_path_factory: pytest.TempPathFactory) -> Path:
    tmp = tmp_path_factory.mktemp("wall_slip")
    mcap = record_simulator(config, tmp / "run.mcap", DURATION_S, seed=SEED, command=wall_pushes())
    return export_bundle(mcap, tmp / "bundle")


def _calibrate(path: Path, config: dict[str, Any]) -> dict[str, StreamResult]:
    bundle = load_bundle(path)
    return {r.problem.name: r for r in calibrate(bundle, declared_model(config, bundle.meta))}


def _stalls_in_truth(path: Path) -> list[float]:
    """Starts of the intervals (``H``, on the detector's grid) in which the truth moved < 1 mm
    while the encoders counted >= 2 cm of travel (mean of both wheels): the robot pushing into
    a wall."""
    bundle = load_bundle(path)
    truth, odo = bundle.get("truth_pose"), bundle.get("odometry")
    assert truth is not None and odo is not None
    edges = np.arange(0.0, DURATION_S, H)
    x, y = np.interp(edges, truth["t"], truth["x"]), np.interp(edges, truth["t"], truth["y"])
    ticks = 0.5 * (odo["left_ticks"] + odo["right_ticks"])
    counted = np.abs(np.diff(np.interp(edges, odo["t"], ticks))) / TPM
    moved = np.hypot(np.diff(x), np.diff(y))
    return [float(t) for t in edges[:-1][(moved < 1e-3) & (counted >= 0.02)]]


def test_wall_pushes_are_set_aside_and_add_no_effect(
    recording: Path, config: dict[str, Any]
) -> None:
    stalls = _stalls_in_truth(recording)
    assert H * len(stalls) >= 20.0, "the robot did not push into walls for 20 s"
    results = _calibrate(recording, config)
    assert {k: [i.name for i in r.effects] for k, r in results.items() if r.effects} == {}
    problem = results["odometry"].problem
    assert isinstance(problem, odometry.OdometryProblem)
    spans = problem.set_aside.spans
    # Every stall is set aside, and every span holds one ...
    assert all(any(a <= t and t + H <= b for a, b in spans) for t in stalls), (stalls, spans)
    assert all(any(a <= t and t + H <= b for t in stalls) for a, b in spans), (stalls, spans)
    # ... and little more: the stalled intervals, one interval of padding on each side of a
    # span, and one more where a contact begins or ends inside an interval.
    assert problem.set_aside.seconds <= H * len(stalls) + 3 * H * len(spans)
    assert min(problem.describe()["windows"].values()) >= 3  # windows left in both parts
    assert any(n.startswith(f"set aside {len(spans)} span(s)") for n in problem.notes)


def test_without_setting_stalls_aside_the_slip_reads_as_a_tick_scale(
    recording: Path, config: dict[str, Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    # What the test above guards against: nothing is stalled at a fraction of 0.
    monkeypatch.setattr(odometry, "STALL_FRACTION", 0.0)
    odo = _calibrate(recording, config)["odometry"]
    assert not odo.problem.set_aside.spans  # type: ignore[attr-defined]
    assert [i.name for i in odo.effects] == ["tick_scale"]
    assert odo.effect_params()[0][0]["ticks_per_metre"] > 1.5 * TPM


def test_a_wrong_tick_size_is_still_found(
    recording: Path, config: dict[str, Any], tmp_path: Path
) -> None:
    bundle = Path(shutil.copytree(recording, tmp_path / "bundle"))
    tick_scale(bundle, TICKS)
    odo = _calibrate(bundle, config)["odometry"]
    assert [i.name for i in odo.effects] == ["tick_scale"]
    ((params, se),) = odo.effect_params()
    assert params["ticks_per_metre"] == pytest.approx(TPM * (1 + TICKS), abs=0.1 * TPM * TICKS)
    assert TPM * TICKS >= 20 * se["ticks_per_metre"]
    assert odo.after <= 0.5 * odo.before
