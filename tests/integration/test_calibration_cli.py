"""The calibrate subcommand end to end: report shape, plots, written config, errors."""

from __future__ import annotations

import argparse
import json
import tomllib
from pathlib import Path

import numpy as np
import pytest
from _mpl import fonts_loaded  # noqa: F401 - autouse fixture: fonts open before the leak check
from koala_bridge.calibration.bundle import load_input
from koala_bridge.calibration.effects import Effect, available_effects, register_effect
from koala_bridge.calibration.effects.quantisation import lattice_step
from koala_bridge.calibration.errors import (
    BundleError,
    CalibrationError,
    EffectRegistryError,
)
from koala_bridge.cli import calibrate as cli
from koala_bridge.cli.main import main
from koala_bridge.core.geometry import circle_centre

DATA = Path(__file__).parents[1] / "data" / "real"


@pytest.fixture(scope="module", autouse=True)
def _matplotlib_fonts_loaded() -> None:
    """Render once before the per-test leak check takes its baseline: matplotlib's font cache
    keeps the font files it has loaded open for the life of the process, by design."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots()
    ax.set_title("t")
    ax.plot([0, 1], [0, 1], ".")
    fig.suptitle("x")
    fig.savefig(io.BytesIO(), format="png")
    plt.close(fig)


def _args(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    cli.add_arguments(parser)
    return parser.parse_args(list(argv))


def test_report_shape_and_written_config(tmp_path: Path) -> None:
    model = tmp_path / "model.toml"
    model.write_text('[robot]\nname = "lego"\nwheel_base_m = 0.15\n', encoding="utf-8")
    out, new = tmp_path / "out", tmp_path / "new.toml"
    args = _args(
        str(DATA / "lego_brenner"),
        "--config",
        str(model),
        "--out",
        str(out),
        "--write-config",
        str(new),
        "--quiet",
    )
    assert cli.run(args) == 0
    report = json.loads((out / "report.json").read_text())
    assert list(report) == ["streams", "not_calibrated"]
    assert report["not_calibrated"] == []
    entry = report["streams"][0]
    assert list(entry) == [
        "stream",
        "metric",
        "unit",
        "before",
        "after",
        "change",
        "relative_change",
        "heldout_errors",
        "split",
        "effects",
    ]
    assert entry["stream"] == "odometry" and entry["unit"] == "m"
    assert (
        list(entry["split"]) == ["fit", "score"]
        and entry["split"]["fit"][1] == entry["split"]["score"][0]
    )
    assert all(list(e) == ["name", "params", "evidence", "written"] for e in entry["effects"])
    md = (out / "report.md").read_text()
    assert "```diff" in md and "wheel_base_m" in md
    assert (out / "residuals_odometry.png").stat().st_size > 1000
    cfg = tomllib.loads(new.read_text())
    assert cfg["robot"]["name"] == "lego"  # the rest of the model is kept
    assert 0.165 < cfg["robot"]["wheel_base_m"] < 0.195
    assert "ticks_per_metre" in cfg["robot"]


def test_ir_config_keys(tmp_path: Path) -> None:
    new = tmp_path / "new.toml"
    assert (
        cli.run(
            _args(
                str(DATA / "khepera2_ir"),
                "--out",
                str(tmp_path / "o"),
                "--write-config",
                str(new),
                "--no-plots",
                "--quiet",
            )
        )
        == 0
    )
    ir = tomllib.loads(new.read_text())["sensors"]["ir"]
    assert len(ir["per_sensor_offset_counts"]) == 8
    assert len(ir["response_range_m"]) == len(ir["response_counts"]) >= 2


def test_effects_by_the_names_the_report_prints(tmp_path: Path) -> None:
    """``--effects`` takes an effect (``offset_per``) or one proposal of it, as the report
    names it (``offset_per:sensor``)."""
    out = tmp_path / "out"
    argv = [str(DATA / "khepera2_ir"), f"--out={out}", "--quiet", "--no-plots"]
    assert cli.run(_args(*argv, "--effects", "offset_per:sensor")) == 0
    (entry,) = json.loads((out / "report.json").read_text())["streams"]
    assert [e["name"] for e in entry["effects"]] == ["offset_per:sensor"]
    assert entry["after"] < entry["before"] / 1.5


def test_staged_inputs_carry_effects_into_the_next_model(tmp_path: Path) -> None:
    """Two inputs: the second is calibrated on the model the first wrote; the report says
    which stage found what, and ``before`` stays the declared model's error."""
    out, new = tmp_path / "out", tmp_path / "imu.toml"
    inputs = [str(DATA / "mpu6050_gyro_static"), str(DATA / "mpu6050_turns")]
    assert cli.run(_args(*inputs, f"--out={out}", f"--write-config={new}", "--quiet")) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["inputs"] == inputs
    entries = {(e["stage"], e["stream"], e["metric"]): e for e in report["streams"]}
    turns_gyro = entries[(2, "gyro", "heading_error_10s_running_rms")]
    assert turns_gyro["input"] == str(DATA / "mpu6050_turns")
    (bias,) = (e for e in turns_gyro["effects"] if e["name"] == "bias")
    assert bias["evidence"]["carried_from"] == str(DATA / "mpu6050_gyro_static")
    assert bias["evidence"]["stage"] == 1
    # before: the declared (ideal) gyro; before_with_carried: with the still recording's bias.
    assert turns_gyro["before_with_carried"] < turns_gyro["before"]
    # The held-out errors' before is the declared model's too: their RMS is the metric.
    errors = turns_gyro["heldout_errors"]
    assert errors["before"]["rms"] == pytest.approx(turns_gyro["before"], rel=1e-5)
    assert errors["after"]["rms"] == pytest.approx(turns_gyro["after"], rel=1e-5)
    still_gyro = entries[(1, "gyro", "rms_rate_error")]
    assert "before_with_carried" not in still_gyro
    assert "not a whole bridge" in new.read_text()  # no --config: a fragment, and it says so
    written = tomllib.loads(new.read_text())["sensors"]
    assert written["gyro"]["bias_rad_s"] == pytest.approx(0.0196, abs=3e-4)
    assert len(written["compass"]["hard_iron_uT"]) == 3
    md = (out / "report.md").read_text()
    assert "stage 2 (`" in md and "Carried from earlier stages" in md
    assert (out / "stage2_residuals_compass.png").is_file()


def test_help_first_line_and_example() -> None:
    assert cli.__doc__ is not None and cli.__doc__.splitlines()[0].strip()
    parser = argparse.ArgumentParser()
    cli.add_arguments(parser)
    assert "examples:" in parser.format_help()


def test_bad_inputs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Each bad input is one line on stderr naming it, exit code 2, no traceback."""
    not_mcap = tmp_path / "run.mcap"
    not_mcap.write_bytes(b"hello")
    with pytest.raises(BundleError, match="MCAP"):
        load_input(not_mcap, tmp_path)
    with pytest.raises(BundleError):
        load_input(tmp_path / "missing", tmp_path)
    bad_model = tmp_path / "model.toml"
    bad_model.write_text("[robot\n", encoding="utf-8")
    typo = tmp_path / "typo.toml"
    typo.write_text("[robot]\nwheel_bass_m = 0.15\n", encoding="utf-8")
    text_cell = tmp_path / "text_cell"
    text_cell.mkdir()
    (text_cell / "gyro.csv").write_text("t,yaw_rate\n0,0.1\n0.1,abc\n", encoding="utf-8")
    no_reference = tmp_path / "no_reference"
    no_reference.mkdir()
    (no_reference / "truth_pose.csv").write_text("t,x,y\n0,1,1\n1,1,1\n", encoding="utf-8")
    for argv in (
        [str(text_cell)],  # a text cell in a numeric column
        [str(no_reference)],  # nothing to hold against the reference
        [str(DATA / "khepera2_ir"), "--effects", "bais"],  # no such effect
        [str(DATA / "lego_brenner"), "--config", str(typo)],  # a misspelt key
        [str(tmp_path / "missing")],
        [str(tmp_path / "missing.mcap")],
        [str(not_mcap)],
        [str(DATA / "lego_brenner"), "--config", str(bad_model)],
        [str(DATA / "lego_brenner"), str(not_mcap)],  # a bad second stage
    ):
        capsys.readouterr()
        # The subcommand raises; cli/main.py prints the one line (core/errors.py's tree).
        with pytest.raises(CalibrationError):
            cli.run(_args(*argv, "--out", str(tmp_path / "o"), "--quiet", "--no-plots"))
        argv = ["calibrate", *argv, "--out", str(tmp_path / "o"), "--quiet", "--no-plots"]
        assert main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("koala-bridge calibrate: "), err


def test_registry_rejects_duplicates() -> None:
    effects = available_effects()
    assert {
        "bias",
        "scale",
        "bias_drift",
        "covariate",
        "range_dependent",
        "hard_iron",
        "soft_iron",
        "tick_scale",
        "wheel_base",
        "wheel_ratio",
        "time_offset",
        "glitch",
        "quantisation",
    } <= set(effects)
    with pytest.raises(EffectRegistryError):
        register_effect("bias")(type("OtherBias", (Effect,), {}))


def test_helpers() -> None:
    import numpy as np

    assert lattice_step(np.array([0.1, 0.3, 0.35, 0.5, 1.0])) == pytest.approx(0.05)
    assert lattice_step(np.random.default_rng(0).normal(size=100)) is None
    a = np.linspace(0, 2 * np.pi, 50)
    pts = np.column_stack([3 + 2 * np.cos(a), -1 + 2 * np.sin(a)])
    assert np.allclose(circle_centre(pts), [3, -1])


def test_a_compass_that_did_not_turn_gets_no_iron(tmp_path: Path) -> None:
    """Standing still, a hard or soft iron cannot be told from north: neither is tried, the
    report says why, and nothing singular reaches the written config (a stationary recording
    once got a soft iron of 3e15)."""
    rng = np.random.default_rng(3)
    t = np.arange(0.0, 30.0, 0.05)
    bundle = tmp_path / "still"
    bundle.mkdir()
    theta = np.full_like(t, 0.7)
    np.savetxt(
        bundle / "truth_pose.csv",
        np.column_stack([t, t * 0 + 1, t * 0 + 1, theta]),
        delimiter=",",
        header="t,x,y,theta",
        comments="",
    )
    field = 20.0 * np.array([np.cos(np.pi / 2 - 0.7), np.sin(np.pi / 2 - 0.7)])
    m = np.array([[1.1, 0.05], [0.05, 0.9]]) @ field + np.array([8.0, -5.0])
    mxy = m + rng.normal(0, 0.3, (t.size, 2))
    np.savetxt(
        bundle / "compass.csv",
        np.column_stack([t, mxy, t * 0 - 43]),
        delimiter=",",
        header="t,mx,my,mz",
        comments="",
    )
    out, new = tmp_path / "out", tmp_path / "new.toml"
    assert cli.run(_args(str(bundle), f"--out={out}", f"--write-config={new}", "--quiet")) == 0
    (compass,) = json.loads((out / "report.json").read_text())["streams"]
    assert compass["stream"] == "compass" and compass["effects"] == []
    md = (out / "report.md").read_text()
    assert "hard_iron not tried" in md and "soft_iron not tried" in md
    assert "soft_iron" not in tomllib.loads(new.read_text()).get("sensors", {}).get("compass", {})


def test_a_singular_soft_iron_is_not_plausible() -> None:
    soft = available_effects()["soft_iron"]
    assert soft.plausible(None, np.array([0.2, 0.05]))  # type: ignore[arg-type]
    assert not soft.plausible(None, np.array([-0.9996, 0.0]))  # type: ignore[arg-type]


def test_written_config_finds_its_dbc_and_never_overwrites_the_model(tmp_path: Path) -> None:
    """A config from `config init` names koala.dbc beside itself: the calibrated copy written
    elsewhere must still find it; --write-config onto --config itself is refused (its comments
    would be lost); report.json is strict JSON (no NaN)."""
    model_dir, out = tmp_path / "mine", tmp_path / "out"
    model_dir.mkdir()
    (model_dir / "koala.dbc").write_text("VERSION \"\"\n", encoding="utf-8")
    model = model_dir / "model.toml"
    model.write_text('[robot]\nwheel_base_m = 0.15\n[buses.can]\n'
                     'dbc = "koala.dbc"  # the CAN database, beside me\n', encoding="utf-8")
    new = tmp_path / "elsewhere" / "new.toml"
    argv = (str(DATA / "lego_brenner"), "--config", str(model), "--out", str(out), "--quiet")
    assert cli.run(_args(*argv, "--write-config", str(new))) == 0
    dbc = tomllib.loads(new.read_text())["buses"]["can"]["dbc"]
    assert (new.parent / dbc).resolve() == (model_dir / "koala.dbc").resolve()
    # the path's own comment stays: only where it is relative to changed
    (line,) = [x for x in new.read_text().splitlines() if x.startswith("dbc")]
    assert line.endswith("# the CAN database, beside me")
    json.loads((out / "report.json").read_text(),
               parse_constant=lambda c: pytest.fail(f"report.json holds {c}"))
    before = model.read_text()
    assert cli.run(_args(*argv, "--write-config", str(model))) == 2
    assert cli.run(_args(*argv, "--write-config", str(tmp_path))) == 2    # a directory
    assert model.read_text() == before


def test_written_config_keeps_the_models_comments_and_layout(tmp_path: Path) -> None:
    """--write-config with --config writes MODEL.toml's own text with the found values set: its
    comments, order and layout stay (the whole file was once re-emitted without a comment); a
    changed key's inline comment says what it was. It loads as the dict the diff describes."""
    from koala_bridge.calibration.config_update import _edited, updated_config

    template = (
        "# my robot, measured 2026-11\n"
        "[robot]\n"
        "wheel_base_m = 0.15   # tape measure\n"
        "ticks_per_metre = 2000.0\n"
        "\n"
        "# gyro from the datasheet\n"
        "[sensors.gyro]\n"
        "ideal = false\n"
        "bias_rad_s = 0.0      # unknown\n"
        "scale_factor_error = 0.0\n"
        "\n"
        "[sensors.compass]\n"
        "ideal = false\n"
        "hard_iron_uT = [0.0, 0.0, 0.0]  # none measured\n"
    )
    base = tomllib.loads(template)
    new = updated_config(base, {"sensors.gyro.bias_rad_s": 0.0123, "robot.wheel_base_m": 0.178,
                                "sensors.compass.hard_iron_uT": [4.0, -2.5, 1.0]})
    text = _edited(template, base, new)
    assert tomllib.loads(text) == new
    lines = text.splitlines()
    assert lines[0] == "# my robot, measured 2026-11"
    assert "# gyro from the datasheet" in lines
    assert "ticks_per_metre = 2000.0" in lines  # untouched lines exactly as they were
    assert "scale_factor_error = 0.0" in lines
    (bias,) = [line for line in lines if line.startswith("bias_rad_s")]
    assert "0.0123" in bias and "calibrate: was 0.0" in bias
    (base_line,) = [line for line in lines if line.startswith("wheel_base_m")]
    assert "0.178" in base_line and "calibrate: was 0.15" in base_line
    # an array: its old value on one comment line (a multi-line one once crashed the write)
    (iron,) = [line for line in lines if line.startswith("hard_iron_uT")]
    assert "calibrate: was [0.0, 0.0, 0.0]" in iron


def test_cli_written_config_is_the_model_edited(tmp_path: Path) -> None:
    model = tmp_path / "model.toml"
    model.write_text("# keep me\n[robot]\nwheel_base_m = 0.15  # guess\n"
                     "ticks_per_metre = 2778.0\n", encoding="utf-8")
    new, out = tmp_path / "new.toml", tmp_path / "out"
    argv = (str(DATA / "lego_brenner"), "--config", str(model), "--out", str(out), "--quiet")
    assert cli.run(_args(*argv, "--write-config", str(new))) == 0
    text = new.read_text()
    assert "# keep me" in text
    assert tomllib.loads(text)["robot"]["wheel_base_m"] != 0.15  # the lego robot's is 0.18
