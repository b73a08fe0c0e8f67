"""How long a campaign run waits for one side after the other ended (campaign.runner).

The firmware gone, nothing can advance a lockstep bridge: it gets ``BRIDGE_GRACE_S`` to end by
itself, then SIGTERM (a firmware that exited before its first cycle left it held at t = 0, and
each such run waited 20 s). The bridge gone, the firmware gets ``GRACE_S`` to notice and write
its report. Real processes, a patched clock: the waits are counted, not timed (the clock's time when
the first signal is sent).
"""

from __future__ import annotations

import subprocess
import sys
from types import SimpleNamespace

import pytest
from koala_bridge.campaign import runner


class _Clock:
    """``time.monotonic`` and ``time.sleep`` of the runner: sleeping advances it at once."""

    def __init__(self) -> None:
        self.now = 1000.0

    def monotonic(self) -> float:
        return self.now

    def sleep(self, s: float) -> None:
        self.now += s


def _proc(code: str) -> subprocess.Popen[bytes]:
    return subprocess.Popen([sys.executable, "-c", code], start_new_session=True,
                            stdin=subprocess.DEVNULL)


@pytest.mark.parametrize(("first", "grace"), [("firmware", "BRIDGE_GRACE_S"),
                                              ("bridge", "GRACE_S")])
def test_the_side_left_running_gets_its_grace_then_sigterm(
    monkeypatch: pytest.MonkeyPatch, first: str, grace: str
) -> None:
    clock = _Clock()
    monkeypatch.setattr(runner.time, "monotonic", clock.monotonic)
    monkeypatch.setattr(runner.time, "sleep", clock.sleep)
    signalled: list[tuple[float, int]] = []
    real_signal = runner._signal_group

    def signal_group(p: subprocess.Popen[bytes], sig: int) -> None:
        signalled.append((clock.now, sig))
        real_signal(p, sig)

    monkeypatch.setattr(runner, "_signal_group", signal_group)
    ended, held = _proc("pass"), _proc("import time; time.sleep(120)")
    try:
        ended.wait(timeout=60)
        procs = {first: ended, ("bridge" if first == "firmware" else "firmware"): held}
        start = clock.now
        returncode, timed_out = runner._wait_both(
            SimpleNamespace(stop=None), procs["bridge"], procs["firmware"], start + 600.0)
        assert not timed_out
        assert held.wait(timeout=60) == -15          # SIGTERM, not the wall timeout
        assert returncode == procs["firmware"].returncode
        at, sig = signalled[0]
        g = getattr(runner, grace)
        assert sig == runner.signal.SIGTERM
        assert g < at - start <= g + 2 * runner.POLL_S
    finally:
        for p in (ended, held):
            if p.poll() is None:
                p.kill()
            p.wait()


def test_the_bridge_is_given_less_than_the_firmware() -> None:
    assert runner.BRIDGE_GRACE_S < runner.GRACE_S
