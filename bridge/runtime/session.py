"""One session's life cycle, shared by ``run`` (simulated or real robot) and ``replay``.

:func:`run_session` takes a :class:`runtime.source.Source` and does, in this order:

1. SIGINT and SIGTERM set the stop event (a clean stop, exit status 0); the previous handlers
   come back at the end;
2. ``source.open()`` -- a failure is one line on stderr and exit status 1;
3. the start banner (where each client connects) on stdout;
4. the endpoints file, if one is asked for, written atomically once every endpoint accepts
   clients (:func:`runtime.endpoints.write_endpoints_file`); it is left in place at the end,
   naming the last session's endpoints;
5. ``source.describe()``, ``source.run(stop)``, ``source.summary()``;
6. always: ``source.close()``, then the recorder's close and its one-line summary.

The lines for people go to ``out`` (stdout by default) and are flushed at once: a program that
started the bridge reads them as they come.
"""

from __future__ import annotations

import logging
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from types import FrameType
from typing import Any, TextIO

from koala_bridge.drivers.messages import DriverError
from koala_bridge.runtime.endpoints import write_endpoints_file
from koala_bridge.runtime.progress import run_progress
from koala_bridge.runtime.settings import BridgeSettings, ConfigError
from koala_bridge.runtime.source import SOURCE_KINDS, RobotSource, Source

__all__ = ["make_source", "run_session", "stop_on_signals"]

log = logging.getLogger(__name__)

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


@contextmanager
def stop_on_signals(stop: threading.Event) -> Iterator[threading.Event]:
    """While inside, SIGINT and SIGTERM set ``stop`` instead of ending the process.

    Handlers can only be installed from the main thread; elsewhere (a test running a session in
    a thread) this does nothing and ``stop`` is the only way to end the session.
    """
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return

    def on_signal(signum: int, frame: FrameType | None) -> None:
        log.info("%s received: stopping", signal.Signals(signum).name)
        stop.set()

    previous = {s: signal.signal(s, on_signal) for s in STOP_SIGNALS}
    try:
        yield stop
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


def run_session(
    source: Source,
    *,
    prog: str,
    endpoints_file: str | os.PathLike[str] | None = None,
    after_close: Callable[[], str | None] | None = None,
    stop: threading.Event | None = None,
    out: TextIO | None = None,
    sim_time: Callable[[], float] | None = None,
    duration_s: float = 0.0,
) -> int:
    """Open, announce, run and close ``source``; the exit status (0 done or stopped, 1 the
    source or the endpoints file could not be opened).

    Args:
        source: what is served.
        prog: the command's name in error messages (``koala-bridge run``).
        endpoints_file: where to write the endpoints JSON; None: nowhere.
        after_close: called once the source is closed (a recorder's close); the line it returns,
            if any, is printed.
        stop: the event that ends the session; by default a new one, set by SIGINT/SIGTERM.
        out: where the lines for people go; stdout by default.
        sim_time: the source's simulated time, for the live progress line shown while it runs
            when stderr is a terminal (:func:`runtime.progress.run_progress`); None: no line.
        duration_s: the run's length in simulated seconds (0: until stopped), for the ETA.
    """
    stop = stop or threading.Event()

    def say(line: str) -> None:
        print(line, file=out or sys.stdout, flush=True)

    with stop_on_signals(stop):
        try:
            try:
                endpoints = source.open()
            except (OSError, DriverError) as e:
                print(f"{prog}: {e}", file=sys.stderr)
                return 1
            say(endpoints.describe())
            if endpoints_file:
                try:
                    path = write_endpoints_file(endpoints_file, endpoints)
                except OSError as e:
                    print(
                        f"{prog}: cannot write the endpoints file {endpoints_file}: "
                        f"{e.strerror or e}",
                        file=sys.stderr,
                    )
                    return 1
                say(f"  Endpoints file          {Path(path)}")
            say(source.describe())
            with run_progress(sim_time, duration_s):
                source.run(stop)
            say(source.summary())
        finally:
            source.close()
            if after_close is not None:
                line = after_close()
                if line:
                    say(line)
    return 0


def make_source(kind: str, config: Mapping[str, Any], settings: BridgeSettings) -> RobotSource:
    """The source ``run --source KIND`` serves: ``sim`` (the simulator) or ``real`` (the robot's
    ports of ``[real]``). Raises :class:`ConfigError` for a configuration it cannot serve."""
    # Imported here: a real-robot run does not load the simulation loop, nor a simulated one
    # the real robot's readers.
    from koala_bridge.runtime.fleet_config import robot_entries

    entries = robot_entries(config)
    if kind == "sim":
        if entries is not None:
            from koala_bridge.runtime.fleet_source import FleetSource

            return FleetSource(config, settings, entries)
        from koala_bridge.runtime.sim_source import SimulatedRobotSource

        return SimulatedRobotSource(config, settings)
    if entries is not None:
        raise ConfigError("[[robots]] runs several simulated robots; --source real reads one "
                          "real robot (drop [[robots]])")
    if kind == "real":
        if config.get("faults"):
            raise ConfigError("faults ([[faults]], --fault) are injected into the simulated "
                              "robot; a real robot's faults are its own (drop them for "
                              "--source real)")
        if settings.run.clock == "lockstep":
            raise ConfigError("--clock lockstep paces the simulation by the firmware; a real "
                              "robot runs on its own time (use realtime for --source real)")
        from koala_bridge.core.topics import WorldMessage
        from koala_bridge.runtime.real_source import RealRobotSource
        from koala_bridge.sim.simulator import Simulator

        # The world and the robot's description answer the world queryable; nothing is
        # simulated.
        description = Simulator(config)
        world = WorldMessage.of(description.world, description.robot_description()).to_json()
        return RealRobotSource(config, settings, lambda: world)
    raise ValueError(f"unknown source {kind!r}; known: {', '.join(SOURCE_KINDS)}")
