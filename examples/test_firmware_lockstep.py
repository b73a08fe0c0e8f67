"""Test a Koala firmware against the simulated robot, in lockstep -- a file to copy.

This is the pattern a firmware team puts in its own repository's tests. Each test:

1. writes a bridge configuration to a temporary folder (the shipped ``default.toml``, a world,
   every sensor error model on, free loopback ports, the firmware's control period);
2. starts ``koala-bridge run --clock lockstep --record run.mcap --endpoints-file ...`` as a
   subprocess. In lockstep, simulated time advances one ``[lockstep] period_s`` each time the
   firmware sends K-Team ``D``, and stands still while the firmware thinks, so the outcome does
   not depend on how fast or how loaded the machine is (docs/protocols.md "Lockstep");
3. runs the firmware as another subprocess, pointed at the endpoints file -- it opens the serial
   port, the CAN bus and the MAVLink link as it would on the robot;
4. waits for both (the bridge ends its run when the firmware closes the K-Team port) and then
   judges the run on the recording's *truth* (``/truth/pose``, what the robot really did), not
   on what the firmware says about itself.

The firmware here is ``examples/coverage_firmware.py`` (calibrate, localise on the walls, visit
every cell). To adapt the file to your firmware:

- ``FIRMWARE_COMMAND``: the command that starts your firmware; it gets ``--endpoints-file`` and
  ``--config`` (the same configuration as the bridge: your firmware reads its control period,
  ``[lockstep] period_s``, from it or must use the same value). Replace
  :func:`firmware_arguments` if your program takes other options.
- ``WORLD``, ``SEED``, :func:`bridge_config`: your arena, the seed (one fixed seed per test makes
  a failure reproducible: the same seed and config give the same run, bit for bit), and the
  robot/sensor settings you want to test against (``[sensors.*] ideal``, noise, faults).
- The ``test_*`` functions: your assertions. The helpers (``koala_bridge.campaign.truth``) read
  the truth track from the recording (:func:`truth_track`) and compute what the tests need
  (:func:`wall_clearance`, :func:`first_visits`); the firmware's own JSON report is in
  ``run.report``. ``koala-bridge campaign`` (docs/campaigns.md) runs such checks over a matrix.
- Faults: ``run_in_lockstep(..., faults=["bias:gyro:start_s=20,bias=0.02"])`` passes
  ``--fault KIND:TARGET[:key=value,...]`` to the bridge (docs/faults.md).

Run it::

    pip install koala-bridge pytest          # (in this repository: make test, or .venv/bin/python)
    pytest -v examples/test_firmware_lockstep.py

A failing run leaves its files in pytest's temporary folder (printed in the failure): the
recording ``run.mcap`` (``koala-bridge export run.mcap --bundle DIR`` for CSV files,
``koala-bridge replay run.mcap`` to play it back to a debugger), the firmware's log and report,
the bridge's log. docs/firmware-testing.md shows how to run this in CI.
"""

from __future__ import annotations

import json
import math
import os
import signal
import socket
import subprocess
import sys
import time
import tomllib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import tomli_w
from koala_bridge.campaign.truth import (
    first_visits,
    reachable_cells,
    truth_track,
    wall_clearance,
    wall_segments,
)
from koala_bridge.core.grid import Grid
from koala_bridge.core.resources import config_dir, default_config_path

HERE = Path(__file__).resolve().parent

#: Each test runs two processes for about a minute: ``pytest -m "not slow"`` leaves them out
#: (register the marker in your pytest configuration, or delete this line).
pytestmark = pytest.mark.slow

# -- what is tested: your firmware, your world, your seed ----------------------------------------

#: Starts the firmware under test (the arguments of :func:`firmware_arguments` follow).
FIRMWARE_COMMAND = [sys.executable, str(HERE / "coverage_firmware.py")]
#: The arena: a TOML file with a ``[world]`` table (here a lab world shipped with koala-bridge).
WORLD = config_dir() / "worlds" / "lab_walls_1.toml"
#: One fixed seed: the sensor noise and the firmware's own choices are the same on every run.
SEED = 1
#: The firmware's control period, simulated seconds per K-Team ``D`` (``[lockstep] period_s``).
#: 0.02 s is five times the wheel PID rate of the robot's base and, with the bridge's cost per
#: simulation step dominating, as fast in wall time as any longer period.
PERIOD_S = 0.02
#: Robot-time budget for covering every reachable cell (seeds 0-19 of the lab worlds took
#: 318-436 s, docs/localisation.md); the firmware gives up at --max-sim-s.
COVERAGE_BUDGET_S = 450.0
#: Liveness only: a firmware or bridge that hangs fails the test after this many wall seconds.
WALL_TIMEOUT_S = 240.0


def firmware_arguments(endpoints: Path, config: Path, report: Path, seed: int,
                       extra: Sequence[str]) -> list[str]:
    """The firmware's command line after ``FIRMWARE_COMMAND``."""
    return ["--endpoints-file", str(endpoints), "--config", str(config), "--world", str(WORLD),
            "--seed", str(seed), "--report", str(report), "--timeout-s", str(WALL_TIMEOUT_S),
            "--log-level", "INFO", *extra]


def bridge_config(folder: Path) -> Path:
    """The bridge's configuration: the shipped default, the world, every error model on, free
    loopback ports, the firmware's control period. Returns the file written."""
    d = tomllib.loads(default_config_path().read_text())
    d["world"] = tomllib.loads(WORLD.read_text())["world"]
    for name, sensor in d["sensors"].items():
        if name != "encoders":  # encoders count the commanded rotation; drive error is below
            sensor["ideal"] = False
    d["robot"]["drive_error"]["ideal"] = False
    d["buses"]["motor_watchdog_s"] = 0.5  # a firmware that stops commanding stops the robot
    d["buses"]["rangefinders"]["enabled"] = False  # not used by this firmware
    d["buses"]["can"].update(socketcand_port=0, slcan=False, virtual=False)  # 0: a free port
    d["buses"]["mavlink"]["port"] = free_port(socket.SOCK_DGRAM)
    d["zenoh"]["listen"] = [f"tcp/127.0.0.1:{free_port()}"]
    d["lockstep"].update(cycle_bus="kteam", cycle_message="D", period_s=PERIOD_S)
    path = folder / "bridge.toml"
    path.write_bytes(tomli_w.dumps(d).encode())
    return path


# -- running the bridge and the firmware ---------------------------------------------------------

def free_port(kind: int = socket.SOCK_STREAM) -> int:
    """A port the OS just handed out on 127.0.0.1 (TCP, or UDP with ``socket.SOCK_DGRAM``)."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def bridge_takes_faults() -> bool:
    """Whether this koala-bridge has ``run --fault`` (docs/faults.md)."""
    out = subprocess.run([sys.executable, "-m", "koala_bridge", "run", "--help"],
                         capture_output=True, text=True, timeout=60)
    return "--fault" in out.stdout


@dataclass
class LockstepRun:
    """What one bridge + firmware run left behind (all files in ``folder``)."""

    folder: Path
    returncode: int            # the firmware's exit status
    report: dict[str, Any]     # the firmware's JSON report ({} if it wrote none)
    recording: Path            # the bridge's MCAP recording
    firmware_log: str

    def explain(self) -> str:
        """Where to look when an assertion fails."""
        return (f"run files in {self.folder} (recording {self.recording.name}, "
                f"firmware.log, bridge.log); firmware log tail:\n{self.firmware_log[-2000:]}")


def run_in_lockstep(folder: Path, seed: int = SEED, faults: Sequence[str] = (),
                    firmware_extra: Sequence[str] = ()) -> LockstepRun:
    """Start the bridge in lockstep, run the firmware against it to the end, stop both."""
    config = bridge_config(folder)
    endpoints = folder / "endpoints.json"
    recording = folder / "run.mcap"
    report = folder / "report.json"
    bridge_cmd = [sys.executable, "-m", "koala_bridge", "run", "--clock", "lockstep",
                  "--config", str(config), "--seed", str(seed), "--record", str(recording),
                  "--endpoints-file", str(endpoints), "--log-level", "WARNING"]
    for fault in faults:
        bridge_cmd += ["--fault", fault]
    with open(folder / "bridge.log", "wb") as bridge_log, \
            open(folder / "firmware.log", "w+") as fw_log:
        bridge = subprocess.Popen(bridge_cmd, stdout=bridge_log, stderr=subprocess.STDOUT)
        try:
            # The endpoints file appears once every bus accepts clients.
            deadline = time.monotonic() + 60
            while not endpoints.exists():
                if bridge.poll() is not None or time.monotonic() > deadline:
                    pytest.fail(f"the bridge did not start:\n"
                                f"{(folder / 'bridge.log').read_text()[-3000:]}")
                time.sleep(0.05)
            firmware = subprocess.run(
                [*FIRMWARE_COMMAND,
                 *firmware_arguments(endpoints, config, report, seed, firmware_extra)],
                stdout=subprocess.DEVNULL, stderr=fw_log, timeout=WALL_TIMEOUT_S + 30,
            )
            # Lockstep: the firmware closed the K-Team port, so the bridge ends the run and
            # finishes the recording by itself.
            bridge.wait(timeout=60)
        finally:
            if bridge.poll() is None:  # a hung bridge: stop it (SIGTERM still closes the file)
                bridge.send_signal(signal.SIGTERM)
                try:
                    bridge.wait(timeout=30)
                except subprocess.TimeoutExpired:
                    bridge.kill()
                    bridge.wait()
        fw_log.seek(0)
        log_text = fw_log.read()
    return LockstepRun(
        folder=folder,
        returncode=firmware.returncode,
        report=json.loads(report.read_text()) if report.exists() else {},
        recording=recording,
        firmware_log=log_text,
    )


# -- reading the truth -----------------------------------------------------------------------------
# truth_track, wall_segments, wall_clearance, reachable_cells and first_visits come from
# koala_bridge.campaign.truth (imported above): the same judges as `koala-bridge campaign`'s
# checks (docs/campaigns.md), which run this kind of test over a whole matrix of worlds, seeds
# and faults.


def robot_config(config: Path) -> dict[str, Any]:
    return tomllib.loads(config.read_text())["robot"]


# -- the tests -------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def nominal(tmp_path_factory: pytest.TempPathFactory) -> LockstepRun:
    """One run without faults, shared by the tests that judge it."""
    return run_in_lockstep(tmp_path_factory.mktemp("nominal"),
                           firmware_extra=["--max-sim-s", str(COVERAGE_BUDGET_S)])


def test_firmware_finishes_its_job(nominal: LockstepRun) -> None:
    assert nominal.returncode == 0, nominal.explain()
    assert nominal.report["complete"], nominal.explain()


def test_robot_never_touches_a_wall(nominal: LockstepRun) -> None:
    """The body (a circle of ``robot.body_radius_m``) never reached a wall. The truth is sampled
    every 20 ms; between two samples the centre moves along a path of length ~``L`` (a straight
    segment at these speeds; turning on the spot does not move it), and the distance to the
    nearest wall changes by at most the distance moved (it is 1-Lipschitz), so along the path it
    stays above ``(d_i + d_i+1 - L) / 2``. That must exceed the radius for every pair."""
    track = truth_track(nominal.recording)
    radius = float(robot_config(nominal.folder / "bridge.toml")["body_radius_m"])
    d = wall_clearance(track[:, 1:3], wall_segments(nominal.recording))
    step = np.linalg.norm(np.diff(track[:, 1:3], axis=0), axis=1)
    lowest = (d[:-1] + d[1:] - step) / 2
    worst = int(np.argmin(lowest))
    assert lowest[worst] > radius, (
        f"the robot touched a wall near t = {track[worst, 0]:.2f} s at "
        f"({track[worst, 1]:.3f}, {track[worst, 2]:.3f}): clearance bound "
        f"{lowest[worst] - radius:+.4f} m; {nominal.explain()}")


def test_every_reachable_cell_is_covered_in_time(nominal: LockstepRun) -> None:
    """Judged on the truth: the robot passed near the centre of every cell reachable from where
    it started, the last of them within ``COVERAGE_BUDGET_S`` of robot time."""
    world = Grid.from_dict(tomllib.loads(WORLD.read_text())["world"])
    track = truth_track(nominal.recording)
    start = world.cell_of(track[0, 1], track[0, 2])
    visits = first_visits(track, world)
    missed = reachable_cells(world, start) - set(visits)
    assert not missed, f"never visited {sorted(missed)}; {nominal.explain()}"
    last = max(visits.values())
    assert last < COVERAGE_BUDGET_S, f"covered at t = {last:.1f} s; {nominal.explain()}"
    # the firmware's own account of where it went agrees with where it went
    assert {tuple(c) for c in nominal.report["visited"]} == set(visits), nominal.explain()


#: The gyro fault: from t = 20 s (after the calibration turn) the yaw rate reads 0.02 rad/s
#: (1.1 deg/s) high -- uncorrected, 90 deg of heading error in 80 s.
GYRO_BIAS_FAULT = "bias:gyro:start_s=20,bias=0.02"
#: Robot time the fault run is given: calibration and wall localisation end near t = 37 s
#: here (3 moves; the lab worlds need 2-5), and a constant 0.02 rad/s bias changes neither.
FAULT_RUN_S = 150.0
#: A cell-centred Koala has 0.25 - 0.19 = 0.06 m between its body and a wall: an estimate
#: further from the truth than this drives the body into walls at its stops.
LOCALISED_WITHIN_M = 0.05


@pytest.mark.skipif(not bridge_takes_faults(),
                    reason="this koala-bridge has no `run --fault` (docs/faults.md)")
def test_localises_despite_a_gyro_bias_step(tmp_path: Path) -> None:
    """With the gyro biased from t = 20 s, the firmware still names its cell and its final
    estimate is within ``LOCALISED_WITHIN_M`` of the truth (its EKF estimates the bias; the
    compass and the walls correct heading and position)."""
    run = run_in_lockstep(tmp_path, faults=[GYRO_BIAS_FAULT],
                          firmware_extra=["--max-sim-s", str(FAULT_RUN_S)])
    assert run.report, f"the firmware wrote no report; {run.explain()}"
    assert run.report["localised_cell"] is not None, run.explain()
    est = run.report["estimate"]
    track = truth_track(run.recording)
    i = int(np.argmin(np.abs(track[:, 0] - est["t"])))  # the truth at the estimate's time
    error = math.hypot(est["x"] - track[i, 1], est["y"] - track[i, 2])
    assert error < LOCALISED_WITHIN_M, (
        f"estimate ({est['x']:.3f}, {est['y']:.3f}) is {error:.3f} m from the truth "
        f"({track[i, 1]:.3f}, {track[i, 2]:.3f}) at t = {est['t']:.2f} s; {run.explain()}")


if __name__ == "__main__":  # python examples/test_firmware_lockstep.py = pytest on this file
    raise SystemExit(pytest.main([os.fspath(Path(__file__)), "-v", *sys.argv[1:]]))
