"""Clocks that pace the fixed-step simulation loop.

The simulation always advances by the same step ``dt`` (simulation seconds). A clock only decides
*when* step ``n`` may run in wall time:

- :class:`RealtimeClock` lets step ``n`` run at ``start + n * dt`` on the monotonic clock. Every
  deadline is computed from the start, never from the previous wake-up, so sleep overshoot does
  not accumulate into drift. If the loop falls behind (a slow step, a paused process) it runs the
  late steps back to back until it has caught up.
- :class:`FastClock` never waits: the simulation runs as fast as the machine allows.

Both report the real-time factor: simulation seconds per wall second since :meth:`start`.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Protocol

CLOCK_NAMES = ("realtime", "fast")


class Clock(Protocol):
    """Paces step ``n`` of a simulation with fixed step ``dt``."""

    dt: float

    def start(self) -> None:
        """Mark wall time zero (simulation step 0)."""

    def wait_for_step(self, n: int, timeout: float | None = None) -> bool:
        """Block until step ``n`` is due; return False if ``timeout`` wall seconds ran out first."""

    def real_time_factor(self, sim_t: float) -> float:
        """Simulation seconds per wall second since :meth:`start` (0.0 before any time passed)."""


class _MonotonicClock:
    def __init__(self, dt: float, monotonic: Callable[[], float] = time.monotonic) -> None:
        if not dt > 0:
            raise ValueError(f"clock step dt must be > 0, got {dt!r}")
        self.dt = float(dt)
        self._monotonic = monotonic
        self._t0: float | None = None

    def start(self) -> None:
        self._t0 = self._monotonic()

    def elapsed(self) -> float:
        """Wall seconds since :meth:`start`."""
        if self._t0 is None:
            raise RuntimeError("clock not started")
        return self._monotonic() - self._t0

    def real_time_factor(self, sim_t: float) -> float:
        wall = self.elapsed()
        return sim_t / wall if wall > 0 else 0.0


class RealtimeClock(_MonotonicClock):
    """Step ``n`` runs at wall time ``start + n * dt`` (monotonic clock, no drift accumulation)."""

    def __init__(
        self,
        dt: float,
        monotonic: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        super().__init__(dt, monotonic)
        self._sleep = sleep

    def deadline(self, n: int) -> float:
        """Wall seconds after :meth:`start` at which step ``n`` is due."""
        return n * self.dt

    def wait_for_step(self, n: int, timeout: float | None = None) -> bool:
        remaining = self.deadline(n) - self.elapsed()
        if remaining <= 0:
            return True
        if timeout is not None and remaining > timeout:
            self._sleep(max(timeout, 0.0))
            return False
        self._sleep(remaining)
        return True


class FastClock(_MonotonicClock):
    """Every step is due at once: the simulation runs as fast as possible."""

    def wait_for_step(self, n: int, timeout: float | None = None) -> bool:
        return True


def make_clock(name: str, dt: float) -> Clock:
    """The clock called ``name`` (one of :data:`CLOCK_NAMES`) for a step of ``dt`` seconds."""
    if name == "realtime":
        return RealtimeClock(dt)
    if name == "fast":
        return FastClock(dt)
    raise ValueError(f"unknown clock {name!r}; choose one of {', '.join(CLOCK_NAMES)}")
