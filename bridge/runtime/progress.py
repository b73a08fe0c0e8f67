"""A live line on a terminal while a run steps: simulated time, real-time factor, ETA.

Shown only when the stream (stderr) is a terminal, as calibrate's progress bar is; never in a
pipe, a log file or the endpoints file. rich redraws it a few times a second from its own thread,
reading the simulated time through a callable, so the step loop pays nothing for it. Log lines
written meanwhile are printed above the line instead of through it.
"""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, TextIO

if TYPE_CHECKING:
    from rich.console import Console, ConsoleOptions, RenderResult

REFRESH_PER_SECOND = 4
BAR_WIDTH, MIN_BAR_WIDTH, BAR_GAP = 30, 10, 2  # columns


def progress_text(sim_t: float, wall_s: float, duration_s: float, compact: bool = False) -> str:
    """The line for simulated time ``sim_t`` reached after ``wall_s`` wall seconds of a run of
    ``duration_s`` simulation seconds (0: until stopped). ``compact``: the same facts in fewer
    columns, for a narrow terminal."""
    rtf = sim_t / wall_s if wall_s > 0 else 0.0
    if compact:
        parts = [f"t {sim_t:.1f}" + (f"/{duration_s:g} s" if duration_s > 0 else " s")]
        parts.append(f"rtf {rtf:.2f}" if rtf > 0 else "rtf -")
    else:
        parts = [f"t = {sim_t:.1f} s" + (f" of {duration_s:g} s" if duration_s > 0 else "")]
        parts.append(f"real-time factor {rtf:.2f}" if rtf > 0 else "real-time factor -")
    if duration_s <= 0:
        parts.append("until Ctrl-C")
    elif rtf > 0:
        parts.append(f"ETA {_clock_time(max(0.0, duration_s - sim_t) / rtf)}")
    else:
        parts.append("ETA -")
    return ("  " if compact else "   ").join(parts)


def shows_progress(stream: TextIO) -> bool:
    """Whether a live line goes to ``stream``: only a terminal (tests and pipes read plain text)."""
    try:
        return stream.isatty()
    except (AttributeError, ValueError):  # no isatty, or a closed stream
        return False


@contextmanager
def run_progress(
    sim_time: Callable[[], float] | None,
    duration_s: float,
    stream: TextIO | None = None,
    monotonic: Callable[[], float] = time.monotonic,
) -> Iterator[None]:
    """While the ``with`` block runs, keep a live progress line on ``stream`` (default stderr)
    if it is a terminal; ``sim_time`` returns the simulated time (None: no line). The line is
    cleared at the end (transient), so what is printed after it reads as without it."""
    stream = sys.stderr if stream is None else stream
    if sim_time is None or not shows_progress(stream):
        yield
        return
    from rich.console import Console
    from rich.live import Live

    line = ProgressLine(sim_time, duration_s, monotonic)
    live = Live(
        line,
        console=Console(file=stream),
        refresh_per_second=REFRESH_PER_SECOND,
        transient=True,
        redirect_stdout=False,  # stdout may be a pipe while stderr is the terminal
        redirect_stderr=True,
    )
    with live:
        # Entered, rich has replaced sys.stderr by a proxy that prints above the line.
        with _logging_through(stream, sys.stderr):
            yield


class ProgressLine:
    """rich renderable: reads the simulated time each time rich redraws, and fits the line to
    the terminal's width (a wrapped line would leave a trail of half lines): the bar shrinks,
    the text turns compact, then the bar goes; the text is cut with an ellipsis only if it is
    still too long."""

    def __init__(
        self, sim_time: Callable[[], float], duration_s: float, monotonic: Callable[[], float]
    ) -> None:
        self.sim_time = sim_time
        self.duration_s = duration_s
        self.monotonic = monotonic
        self.t0 = monotonic()

    def __rich_console__(self, console: Console, options: ConsoleOptions) -> RenderResult:
        from rich.progress_bar import ProgressBar
        from rich.table import Table
        from rich.text import Text

        t = self.sim_time()
        wall = self.monotonic() - self.t0
        width = options.max_width
        full, compact = (progress_text(t, wall, self.duration_s, c) for c in (False, True))
        # The first that fits: full text and bar, compact text and bar, either text alone.
        room = width - BAR_GAP - MIN_BAR_WIDTH
        with_bar = self.duration_s > 0 and len(compact) <= room
        words = full if len(full) <= (room if with_bar else width) else compact
        text = Text(words, no_wrap=True, overflow="ellipsis")
        if not with_bar:
            yield text
            return
        bar = min(BAR_WIDTH, width - len(words) - BAR_GAP)
        grid = Table.grid(padding=(0, BAR_GAP))
        grid.add_row(
            ProgressBar(total=self.duration_s, completed=min(t, self.duration_s), width=bar), text
        )
        yield grid


@contextmanager
def _logging_through(stream: TextIO, proxy: TextIO) -> Iterator[None]:
    """Point the root logger's handlers on ``stream`` at rich's ``proxy`` while the line is
    shown (logging.basicConfig keeps the stream object it was given, out of rich's reach)."""
    handlers = [
        h
        for h in logging.getLogger().handlers
        if isinstance(h, logging.StreamHandler) and h.stream is stream
    ]
    if proxy is stream:
        handlers = []
    for h in handlers:
        h.setStream(proxy)
    try:
        yield
    finally:
        for h in handlers:
            h.setStream(stream)


def _clock_time(seconds: float) -> str:
    """``42 s``, ``3 min 05 s``, ``2 h 03 min``."""
    s = int(round(seconds))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s // 3600} h {s % 3600 // 60:02d} min"


@contextmanager
def count_progress(
    total: int, description: str, stream: TextIO | None = None
) -> Iterator[Callable[[str], None]]:
    """A bar of ``total`` items of work (runs of a campaign) with elapsed time and ETA, on
    ``stream`` (default stderr) if it is a terminal; yields ``advance(status)``, called once per
    item done with a short status text (e.g. ``"12 pass, 1 fail"``). Transient, as
    :func:`run_progress`'s line, and log lines go above it."""
    stream = sys.stderr if stream is None else stream
    if total <= 0 or not shows_progress(stream):
        yield lambda status: None
        return
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    progress = Progress(
        TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
        TextColumn("{task.fields[status]}"), TimeElapsedColumn(), TextColumn("ETA"),
        TimeRemainingColumn(), console=Console(file=stream), transient=True,
        refresh_per_second=REFRESH_PER_SECOND, redirect_stdout=False, redirect_stderr=True,
    )
    with progress:
        task = progress.add_task(description, total=total, status="")
        with _logging_through(stream, sys.stderr):
            yield lambda status: progress.update(task, advance=1, status=status)
