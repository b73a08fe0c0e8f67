"""Campaign files (issue 17): the schema's policy (unknown keys with a did-you-mean, strict
types), the cases a matrix makes, what isolates each case, and the JUnit XML's structure."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
from koala_bridge.campaign.checks import CheckResult
from koala_bridge.campaign.results import write_junit
from koala_bridge.campaign.spec import PLACEHOLDERS, load_campaign
from koala_bridge.core.errors import ConfigError

pytestmark = pytest.mark.unit

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"

GOOD = """\
[campaign]
name = "t"
firmware = ["{python}", "fw.py", "--endpoints", "{endpoints}", "--seed", "{seed}"]
sim_duration_s = 10
set = ["lockstep.period_s=0.05"]
[matrix]
worlds = ["lab_walls_1", "lab_walls_2"]
seeds = [0, 7]
[matrix.faults]
none = []
gyro_bias = ["bias:gyro:start_s=2,bias=0.02"]
[matrix.overrides]
base = []
slow = ["robot.drive_error.ideal=false"]
[checks]
no_wall_contact = true
coverage_min_percent = 50
"""


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "c.toml"
    path.write_text(text)
    return path


def test_the_matrix_is_the_product_of_its_axes_with_readable_ids(tmp_path: Path) -> None:
    c = load_campaign(write(tmp_path, GOOD))
    assert len(c.cases) == 2 * 2 * 2 * 2
    assert c.cases[0].case_id == "lab_walls_1-s0-none-base"
    assert c.cases[-1].case_id == "lab_walls_2-s7-gyro_bias-slow"
    assert len({x.case_id for x in c.cases}) == len(c.cases)
    case = c.case("lab_walls_2-s7-gyro_bias-slow")
    assert case.axes == {"world": "lab_walls_2", "seed": 7, "faults": "gyro_bias",
                         "overrides": "slow"}
    cfg = case.config
    # the case's own settings ...
    assert cfg["sim"]["seed"] == 7
    assert cfg["lockstep"]["period_s"] == 0.05
    assert cfg["robot"]["drive_error"]["ideal"] is False
    assert cfg["faults"][-1] == {"kind": "bias", "target": "gyro", "start_s": 2, "bias": 0.02}
    # ... and what isolates it from every other run on the host
    assert cfg["run"]["clock"] == "lockstep"
    assert cfg["buses"]["can"]["socketcand_port"] == 0
    assert cfg["buses"]["mavlink"]["port"] == 0
    assert cfg["zenoh"]["listen"] == ["tcp/127.0.0.1:0"]
    assert cfg["zenoh"]["multicast_scouting"] is False
    prefixes = {x.config["zenoh"]["prefix"] for x in c.cases}
    assert len(prefixes) == len(c.cases)
    # the worlds differ
    assert c.cases[0].config["world"] != c.cases[-1].config["world"]


@pytest.mark.parametrize(("edit", "message"), [
    (("sim_duration_s", "sim_durations"), "[campaign] unknown key 'sim_durations'; did you mean "
                                          "'sim_duration_s' (campaign.sim_duration_s)?"),
    (("seeds =", "seed ="), "[matrix] unknown key 'seed'; did you mean 'seeds'"),
    (("no_wall_contact", "no_wall_contacts"), "did you mean 'no_wall_contact'"),
    (("[checks]", "[check]"), "[campaign file] unknown key 'check'; did you mean 'checks'"),
    (("sim_duration_s = 10", "sim_duration_s = \"10\""), "'sim_duration_s' must be a number"),
    (("coverage_min_percent = 50", "coverage_min_percent = 150"), "must be <= 100"),
    (("{seed}", "{sede}"), "unknown placeholder {sede}"),
    (("lab_walls_2", "lab_wals_2"), "no world 'lab_wals_2'"),
    (("bias=0.02", "bias=0.02,bais=1"), "case lab_walls_1-s0-gyro_bias-base"),
    (("robot.drive_error.ideal=false", "robot.drive_eror.ideal=false"),
     "case lab_walls_1-s0-none-slow"),
    (("gyro_bias =", "\"gyro bias\" ="), "must be a name of letters"),
    (("[checks]", "[checks]\nsim_time_min_s = 11"), "'sim_time_min_s' = 11 can never be met"),
])
def test_mistakes_are_one_line_errors_naming_the_key(tmp_path: Path, edit: tuple[str, str],
                                                      message: str) -> None:
    with pytest.raises(ConfigError) as e:
        load_campaign(write(tmp_path, GOOD.replace(*edit)))
    assert message in str(e.value)
    assert "\n" not in str(e.value)


def test_the_sim_time_check_is_on_by_default_and_turns_off(tmp_path: Path) -> None:
    checks = load_campaign(write(tmp_path, GOOD)).checks
    assert checks.sim_time_advanced is True and checks.sim_time_min_s is None
    off = GOOD.replace("[checks]", "[checks]\nsim_time_advanced = false\nsim_time_min_s = 10")
    checks = load_campaign(write(tmp_path, off)).checks
    assert checks.sim_time_advanced is False and checks.sim_time_min_s == 10


def test_an_unknown_case_id_suggests_the_nearest(tmp_path: Path) -> None:
    c = load_campaign(write(tmp_path, GOOD))
    with pytest.raises(ConfigError, match="did you mean 'lab_walls_1-s7-none-base'"):
        c.case("lab_walls_1-s7-none-bas")


def test_the_example_campaign_parses_to_the_issue_matrix() -> None:
    c = load_campaign(EXAMPLES / "campaign_coverage.toml")
    worlds = {x.world for x in c.cases}
    assert worlds == {"lab_walls_1", "lab_walls_2", "lab_walls_3"}
    assert {x.seed for x in c.cases} == set(range(5))
    assert {x.faults_name for x in c.cases} == {"none", "gyro_bias_step", "can_drop_10"}
    assert len(c.cases) == 3 * 5 * 3
    assert set(c.table.firmware[1:]) >= {"{endpoints}", "{config}", "{world}", "{seed}"}
    assert all(p in PLACEHOLDERS for p in ("endpoints", "config", "world", "seed", "report"))


def test_junit_xml_has_one_testcase_per_run_and_failures_with_their_checks(
        tmp_path: Path) -> None:
    def record(case_id: str, seed: int, passed: bool) -> dict:  # type: ignore[type-arg]
        checks = [CheckResult("exit_code", True, "exited 0").__dict__,
                  CheckResult("no_wall_contact", passed, "-0.01 m").__dict__]
        return {"case_id": case_id, "verdict": "pass" if passed else "fail",
                "axes": {"world": "lab_walls_1", "seed": seed, "faults": "none",
                         "overrides": "base"},
                "checks": checks, "figures": {"digest": "ab"}, "wall_s": 1.5,
                "recording": None if passed else f"recordings/{case_id}.mcap"}

    path = tmp_path / "junit.xml"
    write_junit(path, "nightly", [record("a-s0", 0, True), record("a-s1", 1, False)])
    root = ET.parse(path).getroot()
    assert root.tag == "testsuites"
    (suite,) = root.findall("testsuite")
    assert (suite.get("name"), suite.get("tests"), suite.get("failures"), suite.get("errors")) \
        == ("nightly", "2", "1", "0")
    cases = suite.findall("testcase")
    assert [c.get("name") for c in cases] == ["a-s0", "a-s1"]
    assert all(c.get("classname") == "nightly.lab_walls_1" for c in cases)
    assert float(cases[0].get("time")) == 1.5
    assert cases[0].find("failure") is None
    failure = cases[1].find("failure")
    assert failure is not None and failure.get("message") == "no_wall_contact: -0.01 m"
    assert "recordings/a-s1.mcap" in (failure.text or "")
    props = {p.get("name"): p.get("value") for p in cases[1].iter("property")}
    assert props == {"world": "lab_walls_1", "seed": "1", "faults": "none", "overrides": "base"}
    assert json.loads(cases[1].findtext("system-out") or "") == {"digest": "ab"}


def test_the_cli_answers_a_bad_campaign_in_one_line_and_lists_cases(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from koala_bridge.cli.main import main

    bad = write(tmp_path, GOOD.replace("seeds =", "seed ="))
    assert main(["campaign", str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("koala-bridge campaign: configuration error: [matrix] unknown key "
                          "'seed'") and "\n" not in err
    good = write(tmp_path, GOOD)
    assert main(["campaign", str(good), "--list"]) == 0
    listed = capsys.readouterr().out.split()
    assert listed == [c.case_id for c in load_campaign(good).cases]
    assert main(["campaign", str(good), "--only", "nope"]) == 2
    assert "no case 'nope'" in capsys.readouterr().err
    # --list with --only lists those only (an unknown one is still an error)
    assert main(["campaign", str(good), "--list", "--only", "lab_walls_2-s7-none-slow",
                 "--only", "lab_walls_1-s0-none-base"]) == 0
    assert capsys.readouterr().out.split() == ["lab_walls_2-s7-none-slow",
                                               "lab_walls_1-s0-none-base"]
    assert main(["campaign", str(good), "--list", "--only", "nope"]) == 2


def test_workers_offering_names_the_workers_with_enough_of_every_resource() -> None:
    from koala_bridge.campaign.executors import workers_offering

    info = {"workers": {"tcp://a": {"resources": {}},
                        "tcp://b": {"resources": {"simulators": 1.0}},
                        "tcp://c": {"resources": {"simulators": 2.0, "gpu": 1.0}}}}
    assert workers_offering(info, {"simulators": 1}) == ["tcp://b", "tcp://c"]
    assert workers_offering(info, {"simulators": 2}) == ["tcp://c"]
    assert workers_offering(info, {"simulators": 1, "gpu": 1}) == ["tcp://c"]
    assert workers_offering(info, {"fpga": 1}) == []
    assert workers_offering({"workers": {}}, {"simulators": 1}) == []
