"""What a session serves: one protocol that the simulated robot, the real robot and a replay
implement, and the pieces they share.

A :class:`Source` is opened, run until stopped, and closed, by :func:`runtime.session.run_session`
(the command line's ``run`` and ``replay``)::

    endpoints = source.open()     # buses / ports and Zenoh open: clients may connect now
    source.describe()             # one line for the banner: what is about to happen
    source.run(stop)              # blocks until ``stop`` is set or the source is done
    source.summary()              # one line: how it ended
    source.close()                # always, also after a failed open(); idempotent

Implementations:

- :class:`runtime.sim_source.SimulatedRobotSource` -- the simulator, stepped on a clock, served
  on every bus of ``[buses]`` and on Zenoh (``run``);
- :class:`runtime.real_source.RealRobotSource` -- the robot's own ports of ``[real]``, decoded
  with the same codecs and published the same way (``run --source real``);
- :class:`runtime.replay.ReplaySource` -- a recording's frames put back on the buses of
  ``[buses]`` with their original timing (``replay``).

Every port a source opens goes through the transport registry
(:mod:`koala_bridge.drivers.transports`).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Iterable, Mapping
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

from koala_bridge.drivers.messages import TransportError
from koala_bridge.runtime.endpoints import Endpoints

if TYPE_CHECKING:
    pass

__all__ = [
    "READ_TIMEOUT_S",
    "SOURCE_KINDS",
    "RobotSource",
    "Source",
    "Tap",
    "start_reader",
    "until_text",
]

#: ``run --source``: the simulated robot or the real one.
SOURCE_KINDS = ("sim", "real")

log = logging.getLogger(__name__)

READ_TIMEOUT_S = 0.1        # how long a reader thread blocks before it checks for stop


@runtime_checkable
class Source(Protocol):
    """A robot (or a recording of one) that a session opens, runs and closes."""

    def world_answer(self) -> Mapping[str, Any]:
        """The answer of the ``<prefix>/world`` queryable (the world plus ``robot``)."""
        ...

    def open(self) -> Endpoints:
        """Open every port and the Zenoh session; return where clients connect. On failure
        raise (:class:`OSError` or a driver error) with a message naming what failed."""
        ...

    def describe(self) -> str:
        """One line for the start banner: what :meth:`run` is about to do."""
        ...

    def run(self, stop: threading.Event) -> object:
        """Serve until ``stop`` is set or the source is done (duration reached, recording
        replayed)."""
        ...

    def summary(self) -> str:
        """One line saying how :meth:`run` ended."""
        ...

    def close(self) -> None:
        """Stop every thread and close every port; idempotent."""
        ...


class RobotSource(Source, Protocol):
    """A robot -- simulated or real -- whose messages and bus frames a recorder can tap."""

    tap: Tap | None



class Tap(Protocol):
    """Something that sees what a source publishes and every raw bus frame (a recorder)."""

    def declare(self, keys: Iterable[str] = (), buses: Iterable[str] = ()) -> None: ...

    def record(self, channel: str, t: float, payload: Mapping[str, Any]) -> None: ...

    def record_frame(
        self, bus: str, direction: str, t: float, data: bytes, **fields: object
    ) -> None: ...


def until_text(duration_s: float) -> str:
    """``for 5 s`` or ``until Ctrl-C`` (``duration_s`` 0: no limit), for :meth:`Source.describe`."""
    return f"for {duration_s:g} s" if duration_s else "until Ctrl-C"


def start_reader(
    name: str,
    step: Callable[[], None],
    stop: threading.Event,
    *,
    thread_prefix: str = "bridge",
    transient: tuple[type[Exception], ...] = (TransportError,),
    logger: logging.Logger = log,
) -> threading.Thread:
    """Start a daemon thread ``<thread_prefix>-<name>`` that calls ``step`` until ``stop`` is
    set; return it.

    A ``transient`` error (a port failing) is logged as a warning and waited out for
    :data:`READ_TIMEOUT_S` before the next ``step``, or ends the thread if ``stop`` is set by then
    (the port was closed under it). Any other exception is logged with its traceback and the loop
    goes on: a reader must outlive any one bad input.
    """

    def loop() -> None:
        while not stop.is_set():
            try:
                step()
            except transient as e:
                if stop.is_set():
                    return
                logger.warning("%s: %s", name, e)
                stop.wait(READ_TIMEOUT_S)
            except Exception:
                logger.exception("%s reader failed on one input; going on", name)

    thread = threading.Thread(target=loop, name=f"{thread_prefix}-{name}", daemon=True)
    thread.start()
    return thread
