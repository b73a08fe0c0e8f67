"""`koala-bridge config init DIR` / `config path`: the shipped configuration, copied to edit."""

from __future__ import annotations

from pathlib import Path

import pytest
from koala_bridge.cli.main import main
from koala_bridge.core.resources import config_dir
from koala_bridge.runtime.settings import BridgeSettings, load_config

EXPECTED = {
    "default.toml",
    "ideal.toml",
    "koala25.toml",
    "koala.dbc",
    "README.md",
    "worlds/lab_trilateration.toml",
    "worlds/lab_walls_1.toml",
    "worlds/lab_walls_2.toml",
    "worlds/lab_walls_3.toml",
}


def _tree(root: Path) -> set[str]:
    return {p.relative_to(root).as_posix() for p in root.rglob("*") if p.is_file()}


def test_init_writes_a_byte_identical_copy_that_runs(tmp_path, capsys) -> None:
    target = tmp_path / "my-koala"
    assert main(["config", "init", str(target)]) == 0
    assert _tree(target) == EXPECTED
    for rel in EXPECTED:
        shipped = (config_dir() / rel).read_bytes()
        if rel in ("default.toml", "ideal.toml", "koala25.toml"):  # uses the DBC copied beside it
            assert shipped.count(b'dbc = ""') == 1, rel
            shipped = shipped.replace(b'dbc = ""         ', b'dbc = "koala.dbc"', 1)
        assert (target / rel).read_bytes() == shipped, rel
    out = capsys.readouterr().out
    assert f"run --config {target / 'default.toml'}" in out
    assert str(target / "worlds" / "lab_walls_1.toml") in out
    # the copy is a complete bridge configuration, as the shipped one
    config = load_config(target / "default.toml")
    shipped = load_config(config_dir() / "default.toml")
    assert config["buses"]["can"].pop("dbc") == str(target / "koala.dbc")
    assert shipped["buses"]["can"].pop("dbc") == ""
    assert config == shipped
    BridgeSettings.from_config(config)


def test_init_refuses_to_overwrite_unless_forced(tmp_path, capsys) -> None:
    (tmp_path / "worlds").mkdir()
    edited = tmp_path / "worlds" / "lab_walls_2.toml"
    edited.write_text("# mine\n")
    assert main(["config", "init", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert "--force" in err and str(edited) in err
    assert _tree(tmp_path) == {"worlds/lab_walls_2.toml"}  # nothing written
    assert edited.read_text() == "# mine\n"

    assert main(["config", "init", str(tmp_path), "--force"]) == 0
    assert _tree(tmp_path) == EXPECTED
    assert edited.read_bytes() == (config_dir() / "worlds" / "lab_walls_2.toml").read_bytes()


@pytest.mark.parametrize("where", ["notes.txt", "notes.txt/my-koala"])
def test_init_into_a_file_is_one_clear_line(tmp_path, capsys, where) -> None:
    (tmp_path / "notes.txt").write_text("mine\n")
    assert main(["config", "init", str(tmp_path / where)]) == 2
    err = capsys.readouterr().err
    assert err == (f"koala-bridge config init: {tmp_path / 'notes.txt'} is a file, not a folder: "
                   "DIR must be a folder (new or existing)\n")
    assert (tmp_path / "notes.txt").read_text() == "mine\n"


def test_init_into_a_new_name_ending_in_toml_says_dir_is_a_folder(tmp_path, capsys) -> None:
    # A new user typed `config init my.toml`, got a folder of that name, and `run --config
    # my.toml` answered "Is a directory".
    assert main(["config", "init", str(tmp_path / "my.toml")]) == 2
    err = capsys.readouterr().err
    assert "looks like a config file's name" in err and "config init my-koala" in err
    assert not (tmp_path / "my.toml").exists()
    (tmp_path / "old.toml").mkdir()              # a folder that exists under such a name: used
    assert main(["config", "init", str(tmp_path / "old.toml")]) == 0
    assert (tmp_path / "old.toml" / "default.toml").is_file()


def test_path_prints_the_shipped_folder(capsys) -> None:
    assert main(["config", "path"]) == 0
    printed = Path(capsys.readouterr().out.strip())
    assert printed == config_dir() and (printed / "default.toml").is_file()


def test_config_needs_an_action(capsys) -> None:
    with pytest.raises(SystemExit) as e:
        main(["config"])
    assert e.value.code == 2
    assert "ACTION" in capsys.readouterr().err
