"""bridge.clock: deadlines from the start (no drift), fast clock never waits."""

from __future__ import annotations

import time

import pytest
from koala_bridge.runtime.clock import FastClock, RealtimeClock, make_clock


class FakeTime:
    """A monotonic clock whose sleep overshoots by a fixed amount, like a loaded machine."""

    def __init__(self, overshoot: float) -> None:
        self.now = 100.0
        self.overshoot = overshoot
        self.sleeps: list[float] = []

    def monotonic(self) -> float:
        return self.now

    def sleep(self, s: float) -> None:
        self.sleeps.append(s)
        self.now += s + self.overshoot


def test_realtime_deadlines_do_not_accumulate_overshoot() -> None:
    fake = FakeTime(overshoot=0.002)
    clock = RealtimeClock(0.01, monotonic=fake.monotonic, sleep=fake.sleep)
    clock.start()
    for n in range(1, 1001):
        assert clock.wait_for_step(n)
    # 1000 steps of 10 ms: wall time is 10 s plus at most one overshoot, not 1000 of them.
    assert fake.now - 100.0 == pytest.approx(10.0, abs=0.0021)
    # Each sleep was shortened by the previous overshoot.
    assert fake.sleeps[5] == pytest.approx(0.008)


def test_realtime_catches_up_without_sleeping_when_late() -> None:
    fake = FakeTime(overshoot=0.0)
    clock = RealtimeClock(0.01, monotonic=fake.monotonic, sleep=fake.sleep)
    clock.start()
    fake.now += 0.0501  # a 50 ms stall
    assert all(clock.wait_for_step(n) for n in range(1, 6))
    assert fake.sleeps == []


def test_realtime_timeout_returns_false_so_the_loop_can_check_for_stop() -> None:
    fake = FakeTime(overshoot=0.0)
    clock = RealtimeClock(1.0, monotonic=fake.monotonic, sleep=fake.sleep)
    clock.start()
    assert not clock.wait_for_step(1, timeout=0.25)
    assert fake.sleeps == [0.25]


def test_realtime_on_the_real_clock() -> None:
    clock = RealtimeClock(0.005)
    clock.start()
    for n in range(1, 41):
        clock.wait_for_step(n)
    elapsed = clock.elapsed()
    # Never early; how late a loaded machine makes it is a benchmark's business, not a test's.
    assert elapsed >= 0.2
    assert clock.real_time_factor(40 * 0.005) == pytest.approx(0.2 / elapsed, rel=1e-2)


def test_fast_clock_never_waits(monkeypatch: pytest.MonkeyPatch) -> None:
    def no_sleep(_: float) -> None:
        raise AssertionError("the fast clock slept")

    monkeypatch.setattr(time, "sleep", no_sleep)
    clock = FastClock(1.0)
    clock.start()
    assert all(clock.wait_for_step(n) for n in range(1000))


def test_make_clock_rejects_unknown_names() -> None:
    assert isinstance(make_clock("fast", 0.01), FastClock)
    with pytest.raises(ValueError, match="realtime, fast"):
        make_clock("slow", 0.01)
    with pytest.raises(ValueError):
        RealtimeClock(0.0)


# -- lockstep ----------------------------------------------------------------------------------

def test_lockstep_holds_until_a_grant_then_runs_exactly_the_granted_steps() -> None:
    from koala_bridge.runtime.clock import LockstepClock

    clock = LockstepClock(0.01, steps_per_cycle=3)
    clock.start()
    assert not clock.wait_for_step(1, timeout=0.0) and not clock.engaged
    assert clock.grant() == 3 and clock.engaged
    for n in (1, 2, 3):
        assert clock.wait_for_step(n, timeout=0.0)
        clock.step_done(n)
    assert not clock.wait_for_step(4, timeout=0.0)        # the firmware has not asked for more
    assert clock.wait_idle(timeout=0.0) and clock.wait_done(3, timeout=0.0)
    assert clock.grant(2) == 9 and clock.cycles == 3
    assert not clock.wait_idle(timeout=0.0)


def test_lockstep_grants_from_where_the_loop_is_after_it_ran_ahead() -> None:
    """Steps taken without a grant (a fault cut the firmware's line): the next cycle is one
    period from where the loop is, not from the last grant."""
    from koala_bridge.runtime.clock import LockstepClock

    clock = LockstepClock(0.01, steps_per_cycle=2)
    clock.start()
    clock.grant()
    for n in range(1, 8):
        clock.step_done(n)
    assert clock.grant() == 9


def test_lockstep_quiet_policy_step_grants_a_miss_after_the_timeout() -> None:
    from koala_bridge.runtime.clock import LockstepClock

    fake = FakeTime(overshoot=0.0)
    clock = LockstepClock(0.01, 1, on_quiet="step", quiet_timeout_s=0.5,
                          monotonic=fake.monotonic)
    clock.start()
    assert not clock.wait_for_step(1, timeout=0.0)        # held: no miss before the first grant
    clock.grant()
    assert clock.wait_for_step(1, timeout=0.0)
    clock.step_done(1)
    fake.now += 0.4
    assert not clock.wait_for_step(2, timeout=0.0) and clock.misses == 0
    fake.now += 0.2
    assert clock.wait_for_step(2, timeout=0.0) and clock.misses == 1


@pytest.mark.parametrize("kwargs, message", [
    ({"steps_per_cycle": 0}, "steps_per_cycle must be >= 1"),
    ({"on_quiet": "sleep"}, "on_quiet must be 'wait' or 'step'"),
])
def test_lockstep_rejects_bad_arguments(kwargs: dict[str, object], message: str) -> None:
    from koala_bridge.runtime.clock import LockstepClock

    with pytest.raises(ValueError, match=message):
        LockstepClock(0.01, **kwargs)  # type: ignore[arg-type]
