"""Clocks that pace the fixed-step simulation loop.

The simulation always advances by the same step ``dt`` (simulation seconds). A clock only decides
*when* step ``n`` may run in wall time:

- :class:`RealtimeClock` lets step ``n`` run at ``start + n * dt`` on the monotonic clock. Every
  deadline is computed from the start, never from the previous wake-up, so sleep overshoot does
  not accumulate into drift. If the loop falls behind (a slow step, a paused process) it runs the
  late steps back to back until it has caught up.
- :class:`FastClock` never waits: the simulation runs as fast as the machine allows.
- :class:`LockstepClock` lets a step run only when the firmware has granted it: each cycle
  message the firmware sends grants one control period (``steps_per_cycle`` steps), so
  simulated time advances exactly as far as the firmware has acted, however slow or stopped
  the firmware or the machine is (PX4 SITL lockstep, ArduPilot's JSON backend; here for a
  firmware that does not know it is simulated: docs/protocols.md "Lockstep").

Both report the real-time factor: simulation seconds per wall second since :meth:`start`.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Protocol

CLOCK_NAMES = ("realtime", "fast", "lockstep")


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


class LockstepClock(_MonotonicClock):
    """Step ``n`` may run once ``n`` steps have been granted; :meth:`grant` grants cycles.

    Threads: the simulation loop calls :meth:`wait_for_step` and :meth:`step_done`; the bus
    readers call :meth:`wait_idle` (before acting on any command, so a command always takes
    effect at a cycle boundary), :meth:`grant` (for the cycle message) and
    :meth:`wait_done` (before replying to it). Every wait takes a ``timeout`` in wall seconds
    and returns False when it ran out, so callers can check for shutdown.

    Before the first grant the clock is *holding*: :attr:`engaged` is False and simulated time
    stands at 0 (``wait_for_step`` returns False), so the run does not depend on how long the
    firmware took to start. With ``on_quiet = "step"``, an engaged clock that was granted nothing
    for ``quiet_timeout_s`` wall seconds grants one cycle itself and counts a :attr:`misses`.
    """

    def __init__(
        self,
        dt: float,
        steps_per_cycle: int = 1,
        on_quiet: str = "wait",
        quiet_timeout_s: float = 1.0,
        monotonic: Callable[[], float] = time.monotonic,
    ) -> None:
        super().__init__(dt, monotonic)
        if steps_per_cycle < 1:
            raise ValueError(f"steps_per_cycle must be >= 1, got {steps_per_cycle!r}")
        if on_quiet not in ("wait", "step"):
            raise ValueError(f"on_quiet must be 'wait' or 'step', got {on_quiet!r}")
        self.steps_per_cycle = steps_per_cycle
        self.on_quiet = on_quiet
        self.quiet_timeout_s = float(quiet_timeout_s)
        self._cond = threading.Condition()
        self._granted = 0           # the last step index that may run
        self._done = 0              # the last step index the loop finished (step 0 = reset)
        self._last_grant_wall: float | None = None
        self.cycles = 0             # cycles granted by the firmware (cycle messages)
        self.explicit = 0           # cycles granted by an explicit step (Zenoh queryable)
        self.misses = 0             # cycles granted by on_quiet = "step"

    @property
    def done(self) -> int:
        return self._done

    @property
    def engaged(self) -> bool:
        """False while held at t = 0 (nothing granted yet)."""
        return self._granted > 0

    def _extend(self, cycles: int) -> int:
        """Grant ``cycles`` more periods from where the loop is (it may have run ahead of every
        grant: steps taken while a fault cut the firmware's line, docs/protocols.md §6)."""
        self._granted = max(self._granted, self._done) + cycles * self.steps_per_cycle
        self._last_grant_wall = self._monotonic()
        self._cond.notify_all()
        return self._granted

    def grant(self, cycles: int = 1, explicit: bool = False) -> int:
        """Grant ``cycles`` more periods; return the step index the loop will then reach. A
        grant while steps are still running extends the run (it does not start a new cycle
        early): callers that must act at a cycle boundary :meth:`wait_idle` first."""
        if cycles < 1:
            raise ValueError(f"cycles must be >= 1, got {cycles!r}")
        with self._cond:
            if explicit:
                self.explicit += cycles
            else:
                self.cycles += cycles
            return self._extend(cycles)

    def wait_for_step(self, n: int, timeout: float | None = None) -> bool:
        with self._cond:
            deadline = None if timeout is None else self._monotonic() + timeout
            while self._granted < n:
                if self._quiet_expired():
                    self.misses += 1
                    self._extend(1)
                    break
                remaining = None if deadline is None else deadline - self._monotonic()
                if remaining is not None and remaining <= 0:
                    return False
                wait = remaining
                if self.engaged and self.on_quiet == "step":
                    assert self._last_grant_wall is not None
                    left = self._last_grant_wall + self.quiet_timeout_s - self._monotonic()
                    wait = max(left, 0.0) if wait is None else max(min(wait, left), 0.0)
                self._cond.wait(wait)
            return True

    def _quiet_expired(self) -> bool:
        return (self.engaged and self.on_quiet == "step" and self._done >= self._granted
                and self._last_grant_wall is not None
                and self._monotonic() - self._last_grant_wall >= self.quiet_timeout_s)

    def step_done(self, n: int) -> None:
        """The loop finished step ``n`` (its readings are on every bus)."""
        with self._cond:
            self._done = n
            if n >= self._granted:
                # the quiet timeout counts from the end of the last granted period
                self._last_grant_wall = self._monotonic()
            self._cond.notify_all()

    def wait_done(self, n: int, timeout: float | None = None) -> bool:
        """Block until step ``n`` is done; False if ``timeout`` wall seconds ran out first."""
        with self._cond:
            return self._cond.wait_for(lambda: self._done >= n, timeout)

    def wait_idle(self, timeout: float | None = None) -> bool:
        """Block until every granted step is done (the loop waits at a cycle boundary)."""
        with self._cond:
            return self._cond.wait_for(lambda: self._done >= self._granted, timeout)

    def wake(self) -> None:
        """Wake every waiter (shutdown: they re-check their stop condition)."""
        with self._cond:
            self._cond.notify_all()


def make_clock(name: str, dt: float, steps_per_cycle: int = 1, on_quiet: str = "wait",
               quiet_timeout_s: float = 1.0) -> Clock:
    """The clock called ``name`` (one of :data:`CLOCK_NAMES`) for a step of ``dt`` seconds
    (the last three arguments: :class:`LockstepClock`'s)."""
    if name == "realtime":
        return RealtimeClock(dt)
    if name == "fast":
        return FastClock(dt)
    if name == "lockstep":
        return LockstepClock(dt, steps_per_cycle, on_quiet, quiet_timeout_s)
    raise ValueError(f"unknown clock {name!r}; choose one of {', '.join(CLOCK_NAMES)}")
