"""matplotlib keeps its font files open once loaded (a process-wide cache, not a leak): modules
that draw use :func:`fonts_loaded` so the fonts are open before the per-test leak check counts."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="module", autouse=True)
def fonts_loaded(tmp_path_factory: pytest.TempPathFactory) -> None:
    from koala_bridge.tools.snapshot import Scene, render_scene

    world = {"cols": 1, "rows": 1, "cell_m": 1.0, "segments": [[0, 0, 1, 0]], "name": "warm-up"}
    render_scene(Scene(world=world), tmp_path_factory.mktemp("fonts") / "warm.png")
