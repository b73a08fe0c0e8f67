"""What several benchmarks share: free loopback ports and the fast-clock bridge configuration."""

from __future__ import annotations

import socket
import tomllib
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]


def free_port(kind: int = socket.SOCK_STREAM) -> int:
    """A port free on 127.0.0.1 right now (``kind``: SOCK_STREAM or SOCK_DGRAM)."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def fast_bridge_config() -> dict[str, Any]:
    """config/default.toml on the fast clock, every bus on free loopback ports, the estimator
    node on."""
    from koala_bridge.runtime.settings import apply_override

    config = tomllib.loads((REPO / "config" / "default.toml").read_text())
    for key, value in (
        (["run", "clock"], "fast"),
        (["zenoh", "listen"], [f"tcp/127.0.0.1:{free_port(socket.SOCK_STREAM)}"]),
        (["buses", "mavlink", "port"], free_port(socket.SOCK_DGRAM)),
        (["buses", "can", "socketcand_port"], 0),
        (["localisation", "enabled"], True),
    ):
        config = apply_override(config, key, value)
    return config
