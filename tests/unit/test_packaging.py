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


def _data_folders() -> set[Path]:
    """Folders under config/ that hold data (no __init__.py: setuptools ships each as a package
    of its own, listed in ``packages``, or warns that it is absent from them)."""
    return {p.parent for p in (REPO / "config").rglob("*")
            if p.is_file() and "__pycache__" not in p.parts and p.parent != REPO / "config"}


def test_every_package_folder_is_listed() -> None:
    listed = set(_pyproject()["tool"]["setuptools"]["packages"])
    found = set()
    for folder, name in TOP.items():
        folders = {init.parent for init in (REPO / folder).rglob("__init__.py")}
        if folder == "config":
            folders |= _data_folders()
        for path in folders:
            rel = path.relative_to(REPO / folder)
            found.add(".".join([name, *rel.parts]))
    assert "koala_bridge.config.worlds" in found
    assert found - listed == set(), "add these to [tool.setuptools] packages"
    assert listed - found == set(), "listed packages without a folder"


def test_package_dir_maps_the_design_card_folders() -> None:
    assert _pyproject()["tool"]["setuptools"]["package-dir"] == {v: k for k, v in TOP.items()}


def test_shipped_config_is_found_as_package_data() -> None:
    assert default_config_path().is_file()
    assert default_dbc_path().is_file()
    worlds = sorted(p.name for p in (config_dir() / "worlds").glob("*.toml"))
    assert "lab_walls_1.toml" in worlds
    package_data = _pyproject()["tool"]["setuptools"]["package-data"]
    # Every data file, whatever its suffix: a new kind of file under config/ must be carried too.
    shipped = {p.relative_to(config_dir()).as_posix() for p in config_dir().rglob("*")
               if p.is_file() and p.suffix not in {".py", ".pyc"}
               and "__pycache__" not in p.parts}
    # Each package's patterns, relative to config/ (koala_bridge.config.worlds -> worlds/*.toml).
    patterns = [
        "/".join([*package.split(".")[2:], pattern])
        for package, pats in package_data.items() if package.startswith(TOP["config"])
        for pattern in pats
    ]
    unmatched = {s for s in shipped if not any(_matches(s, p) for p in patterns)}
    assert unmatched == set(), "config files the wheel would not carry"


def _matches(path: str, pattern: str) -> bool:
    """``path`` matched by a package-data ``pattern`` (a glob within one folder, not below)."""
    return path.count("/") == pattern.count("/") and Path(path).match(pattern)
