"""meta.json's declared geometry and the config: one model, the one calibrated against.

A new-user trial (OptiOdom, encoder ticks against OptiTrack) found two ways they parted:

* staged runs: stage 1 found the wheel base (0.20639 m against the declared 0.2); stage 2's
  meta.json, declaring the nominal 0.2 again, won over the carried value, so stage 2 ran on
  the nominal geometry while its report listed the carried effect;
* a config of another robot (``default.toml``'s Koala) with a bundle whose meta.json declares
  its own geometry: the calibration ran on meta.json's tick size and wheel base, but the written
  config kept the Koala's tick size beside the found wheel base, a robot that never was.

Now meta.json's values are laid into the config where it states others (meta.json wins, as
before), and an earlier stage's finding is not undone by a later meta.json.
"""

from __future__ import annotations

import json
from pathlib import Path

from koala_bridge.calibration.config_update import config_diff
from koala_bridge.calibration.pipeline import Options
from koala_bridge.calibration.stages import calibrate_stages
from koala_bridge.calibration.synthetic import DECLARED, Injected, make_bundle

NOMINAL = {"ticks_per_metre": 10000.0, "wheel_base_m": 0.30}  # synthetic.DECLARED's robot


def _bundle(tmp_path: Path, seed: int) -> Path:
    d = make_bundle(tmp_path / f"b{seed}", seed=seed, inj=Injected(wheel_base=0.05))
    meta = json.loads((d / "meta.json").read_text())
    meta["robot"] = dict(NOMINAL)  # the robot's nominal geometry, as a user's meta.json says
    (d / "meta.json").write_text(json.dumps(meta))
    return d


def _odometry(stage):  # type: ignore[no-untyped-def]
    (res,) = [r for r in stage.results if r.problem.name == "odometry"]
    return res


def test_a_later_meta_json_does_not_undo_a_found_wheel_base(tmp_path: Path) -> None:
    config = {k: v for k, v in DECLARED.items() if k != "robot"}
    stages, final = calibrate_stages(
        [_bundle(tmp_path, 1), _bundle(tmp_path, 2)], config, Options(), tmp_path / "tmp")
    first, second = (_odometry(s) for s in stages)
    assert [i.name for i in first.effects] == ["wheel_base"]
    # stage 2 runs on the carried wheel base: nothing left to find, and its model already
    # does as well as stage 1's did (the same robot), far better than the nominal geometry
    assert [i.name for i in second.effects] == []
    assert [c.name for c in stages[1].carried["sensors.odometry"]] == ["wheel_base"]
    nominal = stages[1].declared_before[("odometry", second.problem.metric)]
    assert second.after < 0.5 * nominal
    assert final["robot"]["wheel_base_m"] != NOMINAL["wheel_base_m"]


def test_the_written_config_is_the_robot_calibrated(tmp_path: Path) -> None:
    other_robot = {**DECLARED, "robot": {"ticks_per_metre": 22222.222, "wheel_base_m": 0.285}}
    stages, final = calibrate_stages(
        [_bundle(tmp_path, 1)], other_robot, Options(), tmp_path / "tmp")
    assert [i.name for i in _odometry(stages[0]).effects] == ["wheel_base"]
    # meta.json's tick size, which the calibration used, not the config's other robot's
    assert final["robot"]["ticks_per_metre"] == NOMINAL["ticks_per_metre"]
    # found: 0.30 (1 + 0.05) injected (synthetic.Injected), 1 % its tolerance here
    assert abs(final["robot"]["wheel_base_m"] - 0.315) < 0.01 * 0.315


def test_a_config_without_a_robot_section_gets_the_bundles_geometry(tmp_path: Path) -> None:
    """A --config that states no [robot] is completed by the simulator's defaults (the
    Koala's tick size) when simulated: the bundle's declared geometry goes into the written
    config, beside the found wheel base, so that is the robot simulated."""
    partial = {k: v for k, v in DECLARED.items() if k != "robot"}
    stages, final = calibrate_stages([_bundle(tmp_path, 1)], partial, Options(), tmp_path / "t")
    assert [i.name for i in _odometry(stages[0]).effects] == ["wheel_base"]
    assert final["robot"]["ticks_per_metre"] == NOMINAL["ticks_per_metre"]
    assert abs(final["robot"]["wheel_base_m"] - 0.315) < 0.01 * 0.315


def test_without_a_config_the_written_keys_are_those_found_and_the_declared_geometry(
    tmp_path: Path,
) -> None:
    """The written file is the model scored: a new user's held ``wheel_base_m`` alone, which
    its header's advice (copy the keys into config/default.toml) put on the Koala's tick size
    (22 222 ticks/m against the robot's 10 598)."""
    stages, final = calibrate_stages([_bundle(tmp_path, 1)], {}, Options(), tmp_path / "t")
    assert set(final["robot"]) == {"wheel_base_m", "ticks_per_metre"}
    assert final["robot"]["ticks_per_metre"] == NOMINAL["ticks_per_metre"]
    assert "sensors" not in final  # nothing else found, nothing else laid


def test_without_a_config_the_model_change_shows_what_was_found_only(tmp_path: Path) -> None:
    """The geometry meta.json declared, laid into the written file, is no change: the report's
    diff is against the first input's declared model (a reviewer saw ticks_per_metre listed
    as a change beside the found wheel base)."""
    stages, final = calibrate_stages([_bundle(tmp_path, 1)], {}, Options(), tmp_path / "t")
    diff = config_diff(stages[0].config, final)
    changed = [line for line in diff.splitlines() if line[:1] in "+-" and line[:3] not in
               ("+++", "---")]
    assert any(line.startswith("+wheel_base_m") for line in changed), diff
    assert not any("ticks_per_metre" in line for line in changed), diff

