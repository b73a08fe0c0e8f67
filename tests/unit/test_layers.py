"""The layers of docs/architecture.md hold: import-linter's contracts ([tool.importlinter] in
pyproject.toml) run on the installed layout, so a wrong arrow fails ``make test``.

In the checkout, ``drivers/`` and ``sim/`` sit beside ``bridge/`` and are mapped into
``koala_bridge`` by pyproject's ``package-dir``; import-linter finds a package's modules by
walking its folder, so the test copies the tree into the layout a wheel installs
(``koala_bridge/drivers``, ``koala_bridge/sim``) and lints that copy.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
LINT = ("from importlinter.cli import lint_imports_command; import sys; "
        "sys.exit(lint_imports_command())")


def installed_layout(dest: Path) -> Path:
    """Copy the Python sources into ``dest`` as a wheel lays them out; return ``dest``."""
    pyproject = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))
    mapping: dict[str, str] = pyproject["tool"]["setuptools"]["package-dir"]
    for package, folder in sorted(mapping.items(), key=lambda kv: kv[0].count(".")):
        shutil.copytree(REPO / folder, dest.joinpath(*package.split(".")),
                        ignore=shutil.ignore_patterns("__pycache__", "*.pyc"),
                        dirs_exist_ok=True)
    return dest


def lint(layout: Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(layout)}
    return subprocess.run(
        [sys.executable, "-c", LINT, "--no-cache", "--config", str(REPO / "pyproject.toml")],
        cwd=layout, env=env, capture_output=True, text=True, timeout=240,
    )


@pytest.fixture(scope="module")
def layout(tmp_path_factory: pytest.TempPathFactory) -> Path:
    try:
        import importlinter  # noqa: F401
    except ImportError:  # a failure, not a skip: a skipped layer check is a check nobody sees
        pytest.fail("import-linter is missing: pip install -e '.[dev]' (the dev extra has it)")
    return installed_layout(tmp_path_factory.mktemp("installed"))


def test_the_import_contracts_hold(layout: Path) -> None:
    p = lint(layout)
    assert p.returncode == 0, p.stdout + p.stderr
    assert "0 broken" in p.stdout, p.stdout


def test_a_wrong_arrow_breaks_a_contract(layout: Path, tmp_path: Path) -> None:
    """The oracle can fail: an estimator importing the simulator is reported."""
    bad = installed_layout(tmp_path / "bad")
    module = bad / "koala_bridge" / "estimation" / "trilateration.py"
    module.write_text(module.read_text(encoding="utf-8")
                      + "\nfrom koala_bridge.sim.world import World  # noqa\n", encoding="utf-8")
    p = lint(bad)
    assert p.returncode != 0
    assert "koala_bridge.estimation.trilateration -> koala_bridge.sim.world" in p.stdout, p.stdout


def test_firmware_side_code_loads_without_the_simulator() -> None:
    """What a firmware imports (the codecs and the estimators, with the grid they localise on)
    loads no module of the simulator."""
    code = ("import sys, koala_bridge.drivers.kteam, koala_bridge.drivers.rangeframes, "
            "koala_bridge.drivers.can_codec, koala_bridge.drivers.mavlink_codec, "
            "koala_bridge.estimation, koala_bridge.core.grid; "
            "print(sorted(m for m in sys.modules if m.startswith('koala_bridge.sim')))")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip() == "[]", p.stdout
