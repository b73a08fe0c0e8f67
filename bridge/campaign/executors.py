"""Where cases run: a local process pool, or a Dask cluster -- one interface,
:class:`concurrent.futures.Executor`, so the campaign has one code path.

* :func:`local_executor`: a :class:`~concurrent.futures.ProcessPoolExecutor` sized to the
  machine's cores (each case is two more processes, bridge and firmware, mostly waiting on each
  other in lockstep). Nothing to install.
* :func:`dask_executor`: ``distributed.Client(address).get_executor(...)``, Dask's
  ``concurrent.futures`` executor: the same ``submit`` and futures, tasks run on the cluster's
  workers (``resources=`` caps how many at once per worker). ``distributed`` is imported only
  here, only for ``--cluster`` (``pip install koala-bridge[cluster]``).

Each comes with its :class:`~koala_bridge.campaign.runner.StopSignal`: a file for the pool's
processes (they share the file system), a Dask ``Event`` for the cluster's workers.
"""

from __future__ import annotations

import math
import multiprocessing
import os
import signal
import time
from collections.abc import Callable, Iterator, Mapping
from concurrent.futures import Executor, ProcessPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from koala_bridge.campaign.runner import StopSignal
from koala_bridge.core.errors import KoalaBridgeError


class ClusterError(KoalaBridgeError):
    """The Dask cluster cannot be reached or ``distributed`` is not installed."""


@dataclass(frozen=True)
class FileStop:
    """Stop signal of the local pool: set when ``path`` exists."""

    path: str

    def is_set(self) -> bool:
        return os.path.exists(self.path)

    def set(self) -> None:
        Path(self.path).touch()

    def clear(self) -> None:
        Path(self.path).unlink(missing_ok=True)


@dataclass
class DaskStop:
    """Stop signal of a cluster: a named ``distributed.Event``, asked from the worker at most
    every :attr:`every_s` seconds (each ask is a round trip to the scheduler)."""

    name: str
    every_s: float = 0.5
    _asked: float = field(default=-math.inf, repr=False, compare=False)
    _set: bool = field(default=False, repr=False, compare=False)

    def is_set(self) -> bool:
        now = time.monotonic()
        if not self._set and now - self._asked >= self.every_s:
            from distributed import Event

            self._asked = now
            self._set = bool(Event(self.name).is_set())
        return self._set


def _pool_worker_signals() -> None:
    # Ctrl-C reaches the whole foreground group: the pool's processes leave it to the campaign,
    # which stops the runs through the stop signal (each ends its own process groups). SIGTERM
    # (the campaign's process killed) ends the worker through the run's `finally`, which ends
    # the bridge's and the firmware's process groups first.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _exit_on_sigterm)


def _exit_on_sigterm(signum: int, frame: object) -> None:
    raise SystemExit(128 + signum)


def default_workers() -> int:
    return max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity")
               else os.cpu_count() or 1)


@contextmanager
def local_executor(workers: int, stop_path: Path
                   ) -> Iterator[tuple[Executor, StopSignal, Callable[[], None]]]:
    """A process pool of ``workers`` processes (spawned: no thread of this process is copied
    into them), its stop signal and what sets it."""
    stop = FileStop(str(stop_path))
    stop.clear()
    pool = ProcessPoolExecutor(max_workers=workers,
                               mp_context=multiprocessing.get_context("spawn"),
                               initializer=_pool_worker_signals)
    try:
        yield pool, stop, stop.set
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
        stop.clear()


#: Wall seconds to wait for a first worker before judging the cluster's resources.
WORKER_WAIT_S = 30.0


def workers_offering(info: Mapping[str, Any], resources: Mapping[str, float]) -> list[str]:
    """The workers of ``info`` (``Client.scheduler_info()``) that offer every resource of
    ``resources`` in at least that amount (a task asking for more than any worker has never
    starts)."""
    return [address for address, w in info.get("workers", {}).items()
            if all(w.get("resources", {}).get(k, 0) >= v for k, v in resources.items())]


def _check_resources(client: Any, resources: Mapping[str, float], address: str) -> None:
    """:class:`ClusterError` unless a worker offers what the campaign's ``resources`` ask:
    Dask would otherwise keep the tasks waiting for such a worker, silently, for ever."""
    try:
        client.wait_for_workers(1, timeout=WORKER_WAIT_S)
    except TimeoutError:
        raise ClusterError(f"the Dask scheduler {address} has no worker (waited "
                           f"{WORKER_WAIT_S:g} s): start workers (dask worker) first") from None
    info = client.scheduler_info()
    if workers_offering(info, resources):
        return
    asked = ",".join(f"{k}={v:g}" for k, v in resources.items())
    offered = sorted({",".join(f"{k}={v:g}" for k, v in w.get("resources", {}).items())
                      or "none" for w in info.get("workers", {}).values()})
    raise ClusterError(
        f"no worker of {address} offers the campaign's resources {asked} (what its "
        f"workers offer: {'; '.join(offered)}), so no run "
        f"would ever start: start workers with --resources \"{asked}\" or change [campaign] "
        "resources")


@contextmanager
def dask_executor(address: str, resources: Mapping[str, float], name: str
                  ) -> Iterator[tuple[Executor, StopSignal, Callable[[], None]]]:
    """Dask's executor on the scheduler at ``address`` (``tcp://HOST:PORT``, or a scheduler
    file's path), the cluster's stop signal and what sets it."""
    try:
        from distributed import Client, Event
    except ImportError as e:
        raise ClusterError("--cluster needs Dask's distributed: pip install "
                           "'koala-bridge[cluster]'") from e
    kwargs: dict[str, Any] = {"timeout": 30}
    if address.startswith(("tcp://", "tls://", "ws://", "wss://", "inproc://")):
        kwargs["address"] = address
    else:
        kwargs["scheduler_file"] = address
    try:
        client = Client(**kwargs)
    except (OSError, TimeoutError, ValueError) as e:
        raise ClusterError(f"cannot reach the Dask scheduler {address}: {e}") from e
    try:
        if resources:
            _check_resources(client, resources, address)
        event = Event(name, client=client)
        event.clear()
        executor = client.get_executor(pure=False, resources=dict(resources) or None)
        yield executor, DaskStop(name), event.set
    finally:
        client.close()
