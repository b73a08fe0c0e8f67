"""The bridge fixture's ports: a port chosen free may be taken before the bridge binds it (a
K-Team test's Zenoh port was, once in 2000 tests on a clean clone); the fixture then starts
the bridge again on new ports instead of failing the test."""

from __future__ import annotations

import socket
from collections.abc import Callable
from typing import Any

import conftest
import pytest


def test_a_taken_port_starts_the_bridge_again(
    bridge: Callable[..., Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        taken = int(held.getsockname()[1])
        picks = iter([taken])
        real = conftest.free_port

        def first_taken(kind: str = "tcp") -> int:
            return next(picks, None) or real(kind) if kind == "tcp" else real(kind)

        monkeypatch.setattr(conftest, "free_port", first_taken)
        b = bridge(clock="fast")
        assert not b.zenoh_endpoint.endswith(f":{taken}")
        assert "already in use" in (b.log_path.parent / "bridge-0.log").read_text()
