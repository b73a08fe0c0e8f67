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


def per_step_us(
    wall: dict[str, list[float]], cpu: dict[str, list[float]], steps: int
) -> tuple[dict[str, float], dict[str, float], dict[str, float]]:
    """Microseconds per step of each variant's timed windows (``steps`` steps each): the best
    window's wall time (the least disturbed, the ``timeit`` convention), the median window's,
    and the best window's CPU time."""
    import statistics

    best = {k: 1e6 * min(v) / steps for k, v in wall.items()}
    med = {k: 1e6 * statistics.median(v) / steps for k, v in wall.items()}
    cpu_best = {k: 1e6 * min(v) / steps for k, v in cpu.items()}
    return best, med, cpu_best
