"""Helpers shared by the CAN transport tests: poll for a condition, receive one frame."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Protocol

import can


class _Receiver(Protocol):
    def recv(self, timeout: float | None = ...) -> can.Message | None: ...


def wait_for(predicate: Callable[[], bool], timeout: float = 10.0) -> None:
    """Poll ``predicate`` until it holds; fail the test after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, "condition not met in time"
        time.sleep(0.005)


def recv(bus: _Receiver, timeout: float = 5.0) -> can.Message:
    """The next frame from ``bus`` (a python-can bus or a bridge transport); fail if none comes."""
    msg = bus.recv(timeout)
    assert msg is not None, "no frame received"
    return msg
