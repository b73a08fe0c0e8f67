"""matplotlib keeps its font files open once loaded (a process-wide cache, not a leak): modules
that draw use :func:`fonts_loaded` so the fonts are open before the per-test leak check counts."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="module", autouse=True)
def fonts_loaded(tmp_path_factory: pytest.TempPathFactory) -> None:
    from koala_bridge.core.topics import EarthFieldInfo, WorldMessage
    from koala_bridge.tools.snapshot import Scene, render_scene

    world = WorldMessage(
        "warm-up", 1, 1, 1.0, walls=((0, 0, "S"),), segments=((0.0, 0.0, 1.0, 0.0),), blocked=(),
        landmarks=(), magnetic_sources=(), earth_field=EarthFieldInfo(20.0, 40.0, 90.0),
        start=None, robot={},
    ).to_json()
    out = tmp_path_factory.mktemp("fonts")
    render_scene(Scene(world=world), out / "warm.png")
    # log axes (the calibration report's Allan plot) draw their ticks in math text, with fonts
    # of their own
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots()
    ax.loglog([1e-3, 1.0, 1e3], [1e-3, 1.0, 1e3], label=r"$\sigma$ (rad/s)")
    ax.legend()
    fig.savefig(out / "warm-log.png")
    plt.close(fig)
