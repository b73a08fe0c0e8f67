"""Multi-host layout on loopback (docs/multihost.md): a Zenoh router, the bridge as a client of
it, and a remote monitor / snapshot that know only the router's endpoint."""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import zenoh
from _mpl import fonts_loaded  # noqa: F401 - autouse fixture
from conftest import BridgeProcess, free_port
from koala_bridge.cli import monitor as monitor_cli
from koala_bridge.cli import snapshot as snapshot_cli


@pytest.fixture
def router() -> Iterator[str]:
    """A Zenoh session in router mode (what zenohd is on a real network), loopback only."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    conf = zenoh.Config()
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("listen/endpoints", json.dumps([endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(conf)
    try:
        yield endpoint
    finally:
        session.close()


def _args(module, argv: list[str]) -> argparse.Namespace:  # type: ignore[no-untyped-def]
    parser = argparse.ArgumentParser()
    module.add_arguments(parser)
    return parser.parse_args(argv)


def test_remote_monitor_reaches_a_client_mode_bridge_through_a_router(
    router: str,
    bridge: Callable[..., BridgeProcess],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    b = bridge(
        clock="realtime",
        sets=['zenoh.mode="client"', f'zenoh.connect=["{router}"]', "zenoh.listen=[]"],
    )
    assert b.endpoints["zenoh"]["endpoints"] == []  # the bridge listens nowhere itself
    args = _args(monitor_cli, ["--connect", router, "--prefix", b.prefix, "--once",
                               "--duration", "1.5"])
    assert monitor_cli.run(args) == 0
    out = capsys.readouterr().out
    for key in ("truth/pose", "sensors/gyro", "sensors/sonar", "status"):
        assert key in out, key

    png = tmp_path / "remote.png"
    args = _args(snapshot_cli, ["--out", str(png), "--connect", router, "--prefix", b.prefix,
                                "--listen", "0.5"])
    assert snapshot_cli.run(args) == 0  # the world query went through the router too
    assert png.stat().st_size > 10_000
