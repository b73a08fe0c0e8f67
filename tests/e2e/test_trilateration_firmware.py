"""examples/trilateration_firmware.py (seeds/003 Lab 4, Task 1) against a real bridge subprocess.

The bridge runs ``config/worlds/lab_trilateration.toml`` in lockstep with every seed error model
on (camera misses, wrong ids and range errors included) and records the run; the firmware sees
only the K-Team pty, socketcand, MAVLink over UDP and the camera on Zenoh. Judged on the
recording's truth (``/truth/pose``):

* **the fix is as good as the camera allows.** The firmware averages the ``n_i`` agreeing
  sightings of landmark ``i`` and removes the camera's mean far-range error, so each mean range
  has (seeds/000 eq. 10-12, ``koala_bridge.sim.models.camera``) zero mean and standard deviation
  ``s_i = sqrt(eps_near(d_i)^2 + eps_far(d_i)^2 (1 - 2/pi)) / sqrt(n_i)`` at the *true* distance
  ``d_i``. Linearised at the true position ``p``, a fix is ``p + G dr``: for ``wls_fix`` on
  ranges ``G = (J^T W J)^-1 J^T W`` (``J`` rows: unit vectors landmark -> robot, ``W =
  diag(1/s_i^2)``), so ``cov = (J^T W J)^-1``; for the lab's closed form ``G`` is the Jacobian of
  ``trilaterate3`` in the ranges (by central differences), ``cov = G diag(s_i^2) G^T``. A 2-D
  Gaussian error leaves the ellipse ``e^T cov^-1 e <= chi2_2(1 - 1e-4) = 18.4`` with probability
  1e-4, so ``|e| <= sqrt(18.4 lambda_max(cov))``. Two terms are added: the robot's spin centre
  moves a little during the turn (``wobble``: the largest distance of the truth from its mean
  over the turn, measured), and the bias is removed at the measured rather than the true range:
  ``|b(r) - b(d)| <= b'(d) |r - d| = ln2 / far_doubling * b(d) * |r - d|`` with ``|r - d| <= 5
  s_i``, which moves the fix by at most ``||G||_2`` times the vector of those.
* **the reported cell is the true one** (the truth's cell during the turn);
* **coverage completes**: the truth passes within 10 cm of every cell's centre.

Also, process-free, on synthetic sightings: the landmark grouping drops wrong ids; an id whose
largest group is another landmark's is regrouped from its own sightings; a first three that a
wrong id makes inconsistent is replaced by a consistent set (the chi-square check).

``python tests/e2e/test_trilateration_firmware.py --seeds N`` runs seeds 0..N-1 and prints each
run's errors against their bounds (docs/localisation.md, "Lab Task 1 over the buses").
"""

from __future__ import annotations

import importlib.util
import json
import math
import signal
import socket
import subprocess
import sys
import time
import tomllib
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest
from koala_bridge.estimation import trilaterate3
from koala_bridge.recording.mcap_file import open_recording
from koala_bridge.sim.models.camera import CameraErrorParams, distance_error_std, far_sigma
from koala_bridge.sim.world import World
from scipy.stats import chi2
from test_coverage_firmware import free_port, visited_cells, write_config

ROOT = Path(__file__).resolve().parents[2]
FIRMWARE = ROOT / "examples" / "trilateration_firmware.py"
WORLD = "lab_trilateration"
SEED = 3
#: e^T cov^-1 e of a 2-D Gaussian exceeds this with probability 1e-4
CHI2_2 = float(chi2.ppf(1 - 1e-4, 2))


def load_firmware(monkeypatch: pytest.MonkeyPatch) -> ModuleType:
    """The firmware as a module (it imports coverage_firmware from beside it)."""
    monkeypatch.syspath_prepend(str(FIRMWARE.parent))
    spec = importlib.util.spec_from_file_location("trilateration_firmware", FIRMWARE)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, spec.name, mod)  # dataclasses look their module up
    had_coverage = "coverage_firmware" in sys.modules
    try:
        spec.loader.exec_module(mod)
    finally:
        if not had_coverage:  # leave sys.modules as it was (imported from beside the firmware)
            sys.modules.pop("coverage_firmware", None)
    return mod


def run_once(tmp: Path, seed: int, timeout_s: float = 120.0,
             firmware_args: tuple[str, ...] = (),
             start: tuple[float, float, float] | None = None) -> dict[str, Any]:
    """Bridge (lockstep, recording) + firmware (with ``firmware_args``); the firmware's report,
    the truth track, the config the bridge ran. ``start``: the robot's ``(x, y, theta_deg)``
    instead of the world's."""
    cfg = write_config(tmp, WORLD, free_port(), free_port(socket.SOCK_DGRAM), start)
    endpoints, mcap, report = tmp / "endpoints.json", tmp / "run.mcap", tmp / "report.json"
    bridge = subprocess.Popen(
        [sys.executable, "-m", "koala_bridge", "run", "--config", str(cfg), "--clock",
         "lockstep", "--seed", str(seed), "--endpoints-file", str(endpoints), "--record",
         str(mcap), "--log-level", "WARNING"],
        cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
    )
    fw: subprocess.CompletedProcess[str] | None = None
    try:
        deadline = time.monotonic() + 60
        while not endpoints.exists():
            if bridge.poll() is not None or time.monotonic() > deadline:
                err = bridge.stderr.read().decode() if bridge.stderr else ""
                raise RuntimeError(f"bridge did not start: {err[-2000:]}")
            time.sleep(0.05)
        fw = subprocess.run(
            [sys.executable, str(FIRMWARE), "--endpoints-file", str(endpoints), "--config",
             str(cfg), "--world", str(ROOT / "config" / "worlds" / f"{WORLD}.toml"),
             "--seed", str(seed), "--report", str(report), "--timeout-s", str(timeout_s),
             "--log-level", "INFO", *firmware_args],
            cwd=ROOT, capture_output=True, text=True, timeout=timeout_s + 30,
        )
    finally:
        try:
            bridge.wait(timeout=30)  # lockstep: the firmware closed its port, the bridge stops
        except subprocess.TimeoutExpired:
            bridge.send_signal(signal.SIGTERM)
            try:
                bridge.wait(timeout=30)
            except subprocess.TimeoutExpired:
                bridge.kill()
                bridge.wait()
        if bridge.stderr:
            bridge.stderr.close()
    (tmp / "firmware.log").write_text(fw.stderr)
    assert fw.returncode in (0, 1), fw.stderr[-3000:]
    result = json.loads(report.read_text())
    result["log"] = fw.stderr[-4000:]
    result["truth"] = [m.json() for m in open_recording(mcap).topic("/truth/pose")]
    result["mcap"] = mcap
    result["config"] = tomllib.loads(cfg.read_text())
    return result


def camera_params(config: dict[str, Any]) -> CameraErrorParams:
    """The camera error model the bridge ran (its keys of ``[sensors.camera]``)."""
    table = config["sensors"]["camera"]
    keys = CameraErrorParams.__dataclass_fields__
    return CameraErrorParams.from_dict({k: v for k, v in table.items() if k in keys})


def _bound(g: np.ndarray, cov: np.ndarray, debias: np.ndarray, wobble: float) -> float:
    """``sqrt(chi2_2 lambda_max(cov)) + wobble + ||G||_2 |debias|`` (module doc), m."""
    lam = float(np.max(np.linalg.eigvalsh(cov)))
    return math.sqrt(CHI2_2 * lam) + wobble + float(np.linalg.norm(g, 2) * np.linalg.norm(debias))


def error_model(p: np.ndarray, landmarks: np.ndarray, n: np.ndarray, cam: CameraErrorParams
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """At the true position ``p``: true distances, the sigma of each mean range (``n`` sightings)
    and the bound on each range's bias-removal error (module doc)."""
    d = np.hypot(*(landmarks - p).T)
    s = distance_error_std(d, cam) / np.sqrt(n)
    bias = far_sigma(d, cam) * math.sqrt(2 / math.pi)
    return d, s, math.log(2) / cam.far_doubling_m * bias * 5 * s


def wls_bound(p: np.ndarray, landmarks: np.ndarray, n: np.ndarray, cam: CameraErrorParams,
              wobble: float) -> float:
    """Bound (m) on the error of ``wls_fix`` on the ranges: ``cov = (J^T W J)^-1``."""
    d, s, debias = error_model(p, landmarks, n, cam)
    jac = (p - landmarks) / d[:, None]
    w = np.diag(1 / s**2)
    cov = np.linalg.inv(jac.T @ w @ jac)
    return _bound(cov @ jac.T @ w, cov, debias, wobble)


def closed_form_bound(p: np.ndarray, landmarks: np.ndarray, n: np.ndarray,
                      cam: CameraErrorParams, wobble: float) -> float:
    """Bound (m) on the error of ``trilaterate3`` (three landmarks): its Jacobian ``G`` in the
    ranges by central differences, ``cov = G diag(s^2) G^T``."""
    d, s, debias = error_model(p, landmarks, n, cam)
    h = 1e-6
    g = np.column_stack([
        (trilaterate3(landmarks, d + h * e) - trilaterate3(landmarks, d - h * e)) / (2 * h)
        for e in np.eye(3)
    ])
    return _bound(g, g @ np.diag(s**2) @ g.T, debias, wobble)


def judge(res: dict[str, Any]) -> dict[str, Any]:
    """A run against the truth: the fix's errors and their bounds, the cells."""
    tri = res["trilateration"]
    world = World.from_dict(res["config"]["world"])
    cam = camera_params(res["config"])
    # Where the robot really was while it turned (the spin centre moves a little).
    turn = np.array([[m["x"], m["y"]] for m in res["truth"] if m["t"] <= tri["t"]])
    p = turn.mean(axis=0)
    wobble = float(np.max(np.hypot(*(turn - p).T)))
    by_id = {lm.id: np.array([lm.x, lm.y]) for lm in world.landmarks}
    found = {f["id"]: f for f in tri["landmarks"]}
    used = [found[i] for i in tri["ids"]]
    lms = np.array([by_id[f["id"]] for f in used])
    n = np.array([f["sightings"] for f in used], dtype=float)
    d, s, _ = error_model(p, lms, n, cam)
    ranges = np.array([f["range_m"] for f in used])
    return {
        "true_xy": p.tolist(),
        "true_cell": world.cell_of(*p),
        "wobble": wobble,
        "range_z": ((ranges - d) / s).tolist(),   # each used mean range vs the true distance
        "range_ok": bool(np.all(np.abs(ranges - d) <= 5 * s + wobble)),
        "err": math.dist(tri["xy"], p),
        "bound": wls_bound(p, lms, n, cam, wobble),
        "err_closed": (None if tri["closed_form"] is None
                       else math.dist(tri["closed_form"], p)),
        "bound_closed": closed_form_bound(p, lms[:3], n[:3], cam, wobble),
        "covered": visited_cells(res["mcap"], world) == set(world.free_cells()),
        "ideal": cam.ideal,
    }


@pytest.mark.e2e
@pytest.mark.slow
@pytest.mark.timeout(240)
def test_trilaterates_reports_the_cell_and_covers_through_the_buses(tmp_path: Path) -> None:
    res = run_once(tmp_path, SEED)
    tri = res["trilateration"]
    assert tri is not None and tri["consistent"], res["log"]
    j = judge(res)
    assert not j["ideal"]
    assert j["wobble"] < 0.05, j
    # The landmarks used are the ones their ids say (no wrong id survived): each mean range is
    # within 5 sigma of the true distance to the landmark of that id.
    assert j["range_ok"], j
    # The fix and the lab's closed form, within the bounds the camera's range model gives.
    assert j["err"] <= j["bound"], (j, tri, res["log"])
    assert j["err_closed"] is not None and j["err_closed"] <= j["bound_closed"], j
    # The reported cell is the true one.
    assert tuple(tri["cell"]) == j["true_cell"] == tuple(res["localised_cell"]), j
    # Coverage completes, on the truth.
    assert res["complete"], res["log"]
    assert j["covered"], res["log"]
    assert res["skipped_periods"] == 0 and res["silent_streams"] == 0


# --------------------------------------------------------------------------- process-free


def _sightings(fw: ModuleType, p: np.ndarray, world_lms: dict[int, np.ndarray],
               rng: np.random.Generator, wrong: float) -> list[Any]:
    """A full turn at ``p`` (start heading 0), one camera frame every 7 deg, FOV 60 deg: every
    landmark in view with a 2 cm range error and 1 deg bearing error; a fraction ``wrong`` of
    the sightings carry another landmark's id."""
    out = []
    ids = sorted(world_lms)
    for k in range(52):
        heading = math.radians(7.0 * k)
        for lid, xy in world_lms.items():
            v = xy - p
            bearing = fw.wrap(math.atan2(v[1], v[0]) - heading)
            if abs(bearing) > math.radians(30):
                continue
            seen = lid
            if rng.random() < wrong:
                seen = int(rng.choice([i for i in ids if i != lid]))
            r = float(np.hypot(*v) + 0.02 * rng.standard_normal())
            b = bearing + math.radians(1) * rng.standard_normal()
            out.append(fw.Sighting(0.2 * k, seen, r, float(fw.wrap(heading + b))))
    return out


#: lab_trilateration's corner landmarks
LANDMARKS = {1: np.array([0.05, 1.95]), 2: np.array([1.95, 1.95]), 3: np.array([1.95, 0.05]),
             4: np.array([0.05, 0.05])}


def test_landmark_grouping_drops_wrong_ids(monkeypatch: pytest.MonkeyPatch) -> None:
    fw = load_firmware(monkeypatch)
    lms = LANDMARKS
    p = np.array([0.75, 1.25])
    sightings = _sightings(fw, p, lms, np.random.default_rng(7), wrong=0.2)
    found = fw.find_landmarks(sightings, _TwoCm(fw), math.radians(12), 2)
    assert [f.id for f in found] and {f.id for f in found} == {1, 2, 3, 4}
    assert sum(f.dropped for f in found) > 0  # wrong ids were seen, and dropped
    for f in found:
        assert abs(f.range_m - np.hypot(*(lms[f.id] - p))) < 0.05
    fix = fw.trilaterate(found, {k: tuple(v) for k, v in lms.items()}, 0.999)
    assert fix.consistent and math.dist(fix.xy, p) < 0.05


def test_an_id_mostly_seen_on_another_landmark_is_regrouped(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Landmark 1 is seen twice under its id, but landmark 2 three times under id 1: id 1's
    largest group sits on landmark 2's, which has more sightings there, so id 1 loses it and is
    grouped from its own two; the first three are then consistent."""
    fw = load_firmware(monkeypatch)
    p = np.array([0.75, 0.75])
    cam = _TwoCm(fw)
    sightings = [s for s in _sightings(fw, p, LANDMARKS, np.random.default_rng(5), wrong=0.0)
                 if s.id != 1]
    for lid, k, times in ((2, 1, (0.1, 0.3, 0.5)), (1, 1, (3.1, 3.3))):
        v = LANDMARKS[lid] - p
        for i, t in enumerate(times):
            sightings.append(fw.Sighting(t, k, float(np.hypot(*v)) + 0.01 * i,
                                         math.atan2(v[1], v[0]) + 0.01 * i))
    found = {f.id: f for f in fw.find_landmarks(sightings, cam, math.radians(12), 2)}
    assert set(found) == {1, 2, 3, 4}
    assert found[1].sightings == 2 and found[1].dropped == 3
    assert abs(found[1].range_m - np.hypot(*(LANDMARKS[1] - p))) < 0.02
    fix = fw.trilaterate(sorted(found.values(), key=lambda f: f.first_t),
                         {k: tuple(v) for k, v in LANDMARKS.items()}, 0.999)
    assert fix.consistent and fix.sets_tried == 1 and math.dist(fix.xy, p) < 0.05


def test_an_inconsistent_first_three_is_replaced(monkeypatch: pytest.MonkeyPatch) -> None:
    """A fifth landmark is seen only under id 4, first, and landmark 4 not at all: the first
    three (4, 1, 2) fail the chi-square check and the firmware takes 1, 2, 3."""
    fw = load_firmware(monkeypatch)
    lms = {**LANDMARKS, 5: np.array([1.0, 1.95])}
    p = np.array([1.25, 0.75])
    cam = _TwoCm(fw)
    seen = {k: v for k, v in lms.items() if k in (1, 2, 3)}
    sightings = _sightings(fw, p, seen, np.random.default_rng(3), wrong=0.0)
    v = lms[5] - p
    r5, dir5 = float(np.hypot(*v)), math.atan2(v[1], v[0])
    sightings += [fw.Sighting(-0.4, 4, r5, dir5), fw.Sighting(-0.2, 4, r5 + 0.01, dir5 + 0.01)]
    found = fw.find_landmarks(sightings, cam, math.radians(12), 2)
    assert [f.id for f in found][0] == 4
    fix = fw.trilaterate(found, {k: tuple(v) for k, v in lms.items()}, 0.999)
    assert fix.consistent and 4 not in fix.ids and fix.sets_tried > 1
    assert math.dist(fix.xy, p) < 0.05


def _TwoCm(fw: ModuleType) -> Any:  # noqa: N802 -- reads as the calibration it builds
    """The synthetic sightings' camera: 2 cm range sigma, no mean error, 1 deg bearings."""
    cam = fw.CameraParams(rate_hz=5.0, ideal=False, dist=0.0, d_mid_m=1.0, far_doubling_m=1.0,
                          bearing_sigma_rad=math.radians(1.0))

    class TwoCm(type(cam)):  # type: ignore[misc]
        def range_sigma(self, d: float) -> float:
            return 0.02

    return TwoCm(**{f: getattr(cam, f) for f in cam.__dataclass_fields__})


def main() -> None:
    import argparse
    import random
    import tempfile

    ap = argparse.ArgumentParser(description="the trilateration firmware over seeds")
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--random-start", action="store_true",
                    help="start each run at a seeded random cell's centre and cardinal heading")
    args = ap.parse_args()
    world = World.from_dict(
        tomllib.loads((ROOT / "config" / "worlds" / f"{WORLD}.toml").read_text())["world"])
    for seed in range(args.seeds):
        start = None
        if args.random_start:
            rng = random.Random(seed)
            x, y = world.cell_centre(*rng.choice(world.free_cells()))
            start = (x, y, float(rng.choice([0, 90, 180, 270])))
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.monotonic()
            try:
                res = run_once(Path(tmp), seed, start=start)
                tri, j = res["trilateration"], judge(res)
                print(f"seed {seed} start {start}: ids {tri['ids']} consistent {tri['consistent']} "
                      f"sets {tri['sets_tried']} err {j['err']:.3f} <= {j['bound']:.3f} m, "
                      f"closed form {j['err_closed']:.3f} <= {j['bound_closed']:.3f} m, "
                      f"cell {tri['cell']} (true {j['true_cell']}), range z "
                      f"{[round(z, 1) for z in j['range_z']]}, covered {j['covered']}, "
                      f"robot {res['robot_time_s']:.0f} s, wall {time.monotonic() - t0:.0f} s",
                      flush=True)
            except Exception as e:  # report and go on
                print(f"seed {seed}: FAILED {e!r}", flush=True)


if __name__ == "__main__":
    main()
