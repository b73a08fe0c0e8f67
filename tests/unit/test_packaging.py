"""Packaging: every code folder is listed in pyproject's package map, and the shipped data is found
through the installed package (not through the checkout's layout)."""

from __future__ import annotations

import tomllib
from pathlib import Path

from koala_bridge.core.resources import config_dir, default_config_path, default_dbc_path

REPO = Path(__file__).resolve().parents[2]
TOP = {"bridge": "koala_bridge", "drivers": "koala_bridge.drivers", "sim": "koala_bridge.sim",
       "config": "koala_bridge.config"}


def _pyproject() -> dict:
    with (REPO / "pyproject.toml").open("rb") as f:
        return tomllib.load(f)


def test_every_package_folder_is_listed() -> None:
    listed = set(_pyproject()["tool"]["setuptools"]["packages"])
    found = set()
    for folder, name in TOP.items():
        for init in (REPO / folder).rglob("__init__.py"):
            rel = init.parent.relative_to(REPO / folder)
            found.add(".".join([name, *rel.parts]))
    assert found - listed == set(), "add these to [tool.setuptools] packages"
    assert listed - found == set(), "listed packages without a folder"


def test_package_dir_maps_the_design_card_folders() -> None:
    assert _pyproject()["tool"]["setuptools"]["package-dir"] == {v: k for k, v in TOP.items()}


def test_shipped_config_is_found_as_package_data() -> None:
    assert default_config_path().is_file()
    assert default_dbc_path().is_file()
    worlds = sorted(p.name for p in (config_dir() / "worlds").glob("*.toml"))
    assert "lab_walls_1.toml" in worlds
    data = _pyproject()["tool"]["setuptools"]["package-data"]["koala_bridge.config"]
    shipped = {p.relative_to(config_dir()).as_posix() for p in config_dir().rglob("*")
               if p.is_file() and p.suffix in {".toml", ".dbc", ".md"}}
    patterns = [p for p in data]
    unmatched = {s for s in shipped if not any(Path(s).match(p) for p in patterns)}
    assert unmatched == set(), "config files the wheel would not carry"
