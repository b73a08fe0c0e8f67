"""The live progress line of `koala-bridge run`: on a terminal only, never in a pipe."""

from __future__ import annotations

import io
import itertools
import logging
import threading

import pytest
from koala_bridge.runtime.progress import (
    ProgressLine,
    progress_text,
    run_progress,
    shows_progress,
)
from rich.console import Console


class FakeTerminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_text_gives_simulated_time_real_time_factor_and_eta() -> None:
    assert progress_text(30.0, 2.0, 60.0) == (
        "t = 30.0 s of 60 s   real-time factor 15.00   ETA 2 s"
    )
    assert progress_text(100.0, 100.0, 3700.0).endswith("ETA 1 h 00 min")
    assert progress_text(10.0, 5.0, 400.0).endswith("ETA 3 min 15 s")
    assert progress_text(0.0, 0.0, 60.0) == "t = 0.0 s of 60 s   real-time factor -   ETA -"
    assert progress_text(5.0, 5.0, 0.0) == "t = 5.0 s   real-time factor 1.00   until Ctrl-C"


def test_only_a_terminal_shows_it() -> None:
    assert shows_progress(FakeTerminal())
    assert not shows_progress(io.StringIO())
    closed = io.StringIO()
    closed.close()
    assert not shows_progress(closed)


def test_a_pipe_gets_nothing_and_no_thread_starts() -> None:
    pipe = io.StringIO()
    before = threading.active_count()
    with run_progress(lambda: 1.0, 10.0, stream=pipe):
        assert threading.active_count() == before
    assert pipe.getvalue() == ""


def test_no_time_source_no_line() -> None:
    terminal = FakeTerminal()
    with run_progress(None, 10.0, stream=terminal):
        pass
    assert terminal.getvalue() == ""


def test_a_terminal_gets_the_line_and_logging_goes_around_it() -> None:
    terminal = FakeTerminal()
    handler = logging.StreamHandler(terminal)
    root = logging.getLogger()
    root.addHandler(handler)
    wall = itertools.chain([0.0], itertools.repeat(2.0))  # started at 0, then 2 s later
    try:
        with run_progress(lambda: 30.0, 60.0, stream=terminal, monotonic=lambda: next(wall)):
            assert handler.stream is not terminal  # rich's proxy prints above the line
    finally:
        root.removeHandler(handler)
    assert handler.stream is terminal
    assert "t = 30.0 s of 60 s   real-time factor 15.00" in terminal.getvalue()


@pytest.mark.parametrize("width", [80, 60, 40])
@pytest.mark.parametrize("sim_t, wall_s, duration_s", [
    (1234.5, 10.0, 3600.0),        # long run, fast: the widest numbers
    (30.0, 2.0, 60.0),
    (123456.7, 100000.0, 999999.0),  # hours to go
])
def test_the_line_fits_the_terminal_and_keeps_the_eta(
    width: int, sim_t: float, wall_s: float, duration_s: float
) -> None:
    out = io.StringIO()
    console = Console(file=out, width=width, force_terminal=True, color_system=None)
    wall = itertools.chain([0.0], itertools.repeat(wall_s))
    console.print(ProgressLine(lambda: sim_t, duration_s, lambda: next(wall)))
    lines = out.getvalue().splitlines()
    assert len(lines) == 1, lines  # one line: nothing wrapped
    assert len(lines[0].rstrip()) <= width, lines[0]
    assert "ETA" in lines[0]
    if width == 80:
        assert "━" in lines[0]  # the bar still shows on an 80-column terminal


def test_compact_text_has_the_same_facts() -> None:
    assert progress_text(30.0, 2.0, 60.0, compact=True) == "t 30.0/60 s  rtf 15.00  ETA 2 s"
    assert progress_text(5.0, 5.0, 0.0, compact=True) == "t 5.0 s  rtf 1.00  until Ctrl-C"


def test_count_progress_shows_runs_done_on_a_terminal_only() -> None:
    """The campaign's bar (count_progress): nothing in a pipe; on a terminal the count, the
    status text and an ETA, with logging routed around it."""
    from koala_bridge.runtime.progress import count_progress

    pipe = io.StringIO()
    with count_progress(3, "campaign c", stream=pipe) as advance:
        advance("1 pass, 0 fail")
    assert pipe.getvalue() == ""
    terminal = FakeTerminal()
    handler = logging.StreamHandler(terminal)
    root = logging.getLogger()
    root.addHandler(handler)
    try:
        with count_progress(3, "campaign c", stream=terminal) as advance:
            assert handler.stream is not terminal
            advance("1 pass, 0 fail")
            advance("1 pass, 1 fail")
    finally:
        root.removeHandler(handler)
    assert handler.stream is terminal
    shown = terminal.getvalue()
    assert "campaign c" in shown and "2/3" in shown and "1 pass, 1 fail" in shown
    assert "ETA" in shown
