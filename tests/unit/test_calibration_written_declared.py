"""A written key's parts the data did not show are said in the written file's header.

A simulator config needs a compass's hard iron in three axes, but a compass fitted in its
horizontal plane (two dimensions) shows only x and y: the z written is the declared one. A new
user's ``hard_iron_uT = [40.93, -89.46, 0.0]`` read as a measured zero where the raw z sat at
560 uT."""

from __future__ import annotations

import tomllib
from pathlib import Path

from koala_bridge.calibration.bundle import load_bundle
from koala_bridge.calibration.config_update import declared_parts, found_keys, write_config
from koala_bridge.calibration.model import declared_model
from koala_bridge.calibration.pipeline import calibrate
from koala_bridge.calibration.synthetic import DECLARED, Injected, make_bundle

DATA = Path(__file__).parents[1] / "data" / "real"


def test_a_planar_hard_iron_says_its_z_is_the_declared_one(tmp_path: Path) -> None:
    d = make_bundle(tmp_path / "b", seed=1, inj=Injected(hard_iron=(5.0, -3.0)),
                    duration_s=120.0)
    bundle = load_bundle(d)
    results = [r for r in calibrate(bundle, declared_model(DECLARED, bundle.meta))
               if r.problem.name == "compass"]
    assert [i.name for i in results[0].effects] == ["hard_iron"]
    (note,) = declared_parts(results)
    assert note.startswith("sensors.compass: hard_iron_uT's z is the declared ")
    assert "uT, not measured" in note
    out = tmp_path / "model.toml"
    keys = found_keys(results)
    write_config(out, {"sensors": {"compass": {"hard_iron_uT": keys[
        "sensors.compass.hard_iron_uT"]}}}, fragment=True, notes=[note])
    text = out.read_text(encoding="utf-8")
    header = [line for line in text.splitlines() if line.startswith("#")]
    assert any("hard_iron_uT's z" in line for line in header)
    assert tomllib.loads(text)["sensors"]["compass"]["hard_iron_uT"][:2] == keys[
        "sensors.compass.hard_iron_uT"][:2]


def test_a_full_sphere_compass_has_nothing_to_say(tmp_path: Path) -> None:
    bundle = load_bundle(DATA / "hmc5883l_sphere")
    sphere = calibrate(bundle, declared_model({}, bundle.meta))
    compass = [r for r in sphere if r.problem.name == "compass"]
    assert {"hard_iron", "soft_iron"} <= {i.name for i in compass[0].effects}
    assert declared_parts(sphere) == []
    # staged with a planar run, before or after it: the sphere measured the vertical
    planar = load_bundle(make_bundle(tmp_path / "b", seed=1, inj=Injected(hard_iron=(5.0, -3.0)),
                                     duration_s=120.0))
    flat = calibrate(planar, declared_model(DECLARED, planar.meta))
    assert declared_parts([*flat, *sphere]) == declared_parts([*sphere, *flat]) == []
