"""Shared fixtures: free loopback ports, a bridge subprocess, and a leak check.

- ``free_tcp_port`` / ``free_udp_port``: a port the OS just handed out on 127.0.0.1.
- ``bridge``: a factory that starts ``koala-bridge run`` as a subprocess on free ports, waits for
  its endpoints file (written only once every endpoint accepts clients) and returns a
  :class:`BridgeProcess`. Every process it started is terminated at teardown (SIGTERM, then
  SIGKILL), so no test leaves a bridge behind.
- ``leak_check`` (autouse): fails the test that leaves a child process, a non-daemon thread, or an
  open socket / pty / file descriptor behind.

Tests are kept by kind, and each folder's tests carry the marker of the same name:
``tests/unit`` (pure functions, in-process, seconds), ``tests/integration`` (real transports and
sessions on loopback, in-process) and ``tests/e2e`` (``koala-bridge`` as a subprocess; also marked
``slow``). ``make test`` runs them all; ``pytest -m unit`` or ``pytest -m "not slow"`` picks.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import tomllib
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

REPO = Path(__file__).resolve().parents[1]
DEFAULT_CONFIG = REPO / "config" / "default.toml"
IDEAL_SECTIONS = ("robot.drive_error", "sensors.ir", "sensors.sonar", "sensors.encoders",
                  "sensors.gyro", "sensors.compass", "sensors.camera")


# -- property-based tests ------------------------------------------------------------------------

def pytest_configure(config: pytest.Config) -> None:
    """Hypothesis draws the same examples on every run of the suite (``derandomize``: a failure in
    CI reproduces on a laptop) and keeps no example database in the checkout. ``make fuzz`` is the
    place for fresh random inputs. Also registers the leak check's opt-out marker."""
    config.addinivalue_line("markers", "no_leak_check: skip the autouse leak check")
    from hypothesis import settings

    settings.register_profile("suite", derandomize=True, database=None)
    settings.load_profile("suite")


# -- kinds ---------------------------------------------------------------------------------------

KINDS = ("unit", "integration", "e2e")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Mark each test with its folder's kind (and end-to-end tests ``slow``)."""
    for item in items:
        kind = next((k for k in KINDS if k in item.path.parts), None)
        if kind is not None:
            item.add_marker(getattr(pytest.mark, kind))
        if kind == "e2e":
            item.add_marker(pytest.mark.slow)


# -- ports -------------------------------------------------------------------------------------

def commented_real_block(config_file: Path) -> dict[str, Any]:
    """The commented-out ``[real]`` table of a shipped config file, uncommented and parsed."""
    lines = config_file.read_text().splitlines()
    start = lines.index("# [real]")
    block = []
    for line in lines[start:]:
        if not line.startswith("# "):
            break
        block.append(line[2:])
    return tomllib.loads("\n".join(block))["real"]


#: a bridge whose port was taken between choosing and binding it is started again, on new
#: ports, this many times at most
PORT_ATTEMPTS = 3


class PortTaken(AssertionError):
    """The bridge exited before serving because a port chosen free was taken meanwhile."""


def _free_port(kind: int) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def free_port(kind: str = "tcp") -> int:
    """A port free on 127.0.0.1 right now (``kind`` "tcp" or "udp")."""
    return _free_port(socket.SOCK_STREAM if kind == "tcp" else socket.SOCK_DGRAM)


@pytest.fixture
def free_tcp_port() -> int:
    return free_port("tcp")


@pytest.fixture
def free_udp_port() -> int:
    return free_port("udp")


# -- leak check --------------------------------------------------------------------------------

def _fd_targets() -> dict[int, str]:
    """Open descriptors that a test could leak: sockets, ptys, regular files (not Zenoh's
    long-lived runtime descriptors: eventpoll/eventfd, its /dev/shm segment)."""
    out: dict[int, str] = {}
    for name in os.listdir("/proc/self/fd"):
        try:
            target = os.readlink(f"/proc/self/fd/{name}")
        except OSError:
            continue
        if target.startswith(("anon_inode:", "/dev/shm/", "pipe:", "/dev/null")):
            continue
        out[int(name)] = target
    return out


def _children() -> set[int]:
    me = str(os.getpid())
    kids: set[int] = set()
    for pid in os.listdir("/proc"):
        if not pid.isdigit():
            continue
        try:
            with open(f"/proc/{pid}/stat", encoding="ascii", errors="replace") as f:
                stat = f.read()
        except OSError:
            continue
        fields = stat.rsplit(")", 1)[-1].split()
        if len(fields) > 1 and fields[1] == me and fields[0] != "Z":
            kids.add(int(pid))
    return kids


def _wait_until(predicate: Callable[[], bool], timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.05)
    return predicate()


@pytest.fixture(autouse=True)
def leak_check(request: pytest.FixtureRequest) -> Iterator[None]:
    if request.node.get_closest_marker("no_leak_check"):
        yield
        return
    fds_before = _fd_targets()
    threads_before = set(threading.enumerate())
    kids_before = _children()
    yield

    def leaked_threads() -> list[threading.Thread]:
        return [
            t for t in threading.enumerate()
            if t not in threads_before and t.is_alive() and not t.daemon
        ]

    def leaked_fds() -> dict[int, str]:
        now = _fd_targets()
        return {fd: t for fd, t in now.items() if fds_before.get(fd) != t}

    _wait_until(lambda: not leaked_threads() and not leaked_fds()
                and not (_children() - kids_before), timeout=2.0)
    problems = []
    if threads := leaked_threads():
        problems.append(f"threads still running: {[t.name for t in threads]}")
    if fds := leaked_fds():
        problems.append(f"descriptors left open: {fds}")
    if kids := _children() - kids_before:
        problems.append(f"child processes left running: {sorted(kids)}")
        for pid in kids:  # do not let one leak poison the rest of the session
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
    if problems:
        pytest.fail("leak check: " + "; ".join(problems), pytrace=False)


# -- bridge subprocess -------------------------------------------------------------------------

@dataclass
class BridgeProcess:
    """A running ``koala-bridge run`` and what its endpoints file says."""

    proc: subprocess.Popen[bytes]
    endpoints: dict[str, Any]
    endpoints_file: Path
    log_path: Path
    zenoh_endpoint: str
    mavlink_port: int
    args: list[str] = field(default_factory=list)

    @property
    def prefix(self) -> str:
        return str(self.endpoints["zenoh"]["prefix"])

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")

    def stop(self, sig: int = signal.SIGTERM, timeout: float = 15.0) -> int:
        """Send ``sig`` and wait; returns the exit code (SIGKILL after ``timeout``)."""
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        return int(self.proc.returncode)


def bridge_command(*args: str) -> list[str]:
    return [sys.executable, "-m", "koala_bridge", *args]


def wait_endpoints(proc: subprocess.Popen[bytes], endpoints_file: Path, log_path: Path,
                   timeout: float = 60.0) -> dict[str, Any]:
    """The endpoints file a starting koala-bridge (run or replay) writes, atomically, once it
    serves; fails with the process's log if it exits first or ``timeout`` s pass."""
    deadline = time.monotonic() + timeout
    while not endpoints_file.exists():
        if proc.poll() is not None:
            raise AssertionError(
                f"koala-bridge exited with {proc.returncode} before serving:\n"
                f"{log_path.read_text()}"
            )
        if time.monotonic() > deadline:
            raise AssertionError(f"no endpoints file after {timeout:g} s:\n{log_path.read_text()}")
        time.sleep(0.02)
    return json.loads(endpoints_file.read_text())


@pytest.fixture
def bridge(tmp_path: Path) -> Iterator[Callable[..., BridgeProcess]]:
    """Factory: ``bridge(clock="fast", sets=[...], extra=[...])`` -> a started BridgeProcess.

    Every port is a free one (Zenoh listen, MAVLink UDP, socketcand 0 = chosen by the OS), so
    tests run side by side with ``make run``. With ``ideal`` (the default) every sensor and the
    drive are noise-free whatever the config file says, so tests can compare exactly.
    ``sets`` are extra ``--set`` overrides.
    """
    started: list[BridgeProcess] = []

    def start(
        clock: str = "fast",
        sets: list[str] | None = None,
        extra: list[str] | None = None,
        config: Path = DEFAULT_CONFIG,
        timeout: float = 120.0,  # a loaded 2-core machine takes ~10 s to import and open
        ideal: bool = True,
    ) -> BridgeProcess:
        for attempt in range(PORT_ATTEMPTS):
            try:
                return _start_once(clock, sets, extra, config, timeout, ideal)
            except PortTaken:
                if attempt == PORT_ATTEMPTS - 1:
                    raise
        raise AssertionError("unreachable")

    def _start_once(
        clock: str, sets: list[str] | None, extra: list[str] | None, config: Path,
        timeout: float, ideal: bool,
    ) -> BridgeProcess:
        n = len(started)
        endpoints_file = tmp_path / f"endpoints-{n}.json"
        log_path = tmp_path / f"bridge-{n}.log"
        zenoh_endpoint = f"tcp/127.0.0.1:{free_port('tcp')}"
        mavlink_port = free_port("udp")
        args = [
            "run", "--config", str(config), "--clock", clock,
            "--endpoints-file", str(endpoints_file),
            "--set", f'zenoh.listen=["{zenoh_endpoint}"]',
            "--set", f"buses.mavlink.port={mavlink_port}",
            "--set", "buses.can.socketcand_port=0",
        ]
        if ideal:
            for section in IDEAL_SECTIONS:
                args += ["--set", f"{section}.ideal=true"]
        for s in sets or []:
            args += ["--set", s]
        args += extra or []
        log = open(log_path, "wb")  # noqa: SIM115 - closed right after Popen duplicated it
        try:
            proc = subprocess.Popen(
                bridge_command(*args), cwd=REPO, stdout=log, stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
            )
        finally:
            log.close()
        handle = BridgeProcess(proc, {}, endpoints_file, log_path, zenoh_endpoint,
                               mavlink_port, args)
        started.append(handle)
        try:
            handle.endpoints = wait_endpoints(proc, endpoints_file, log_path, timeout)
        except AssertionError as e:
            # a free port is free when asked, not when the bridge binds it: another test's
            # process may take it in between (a K-Team test's Zenoh port, once in 2000 tests)
            if proc.poll() is not None and "already in use" in log_path.read_text():
                raise PortTaken(str(e)) from e
            raise
        return handle

    yield start
    for handle in started:
        handle.stop()


# -- Zenoh client ------------------------------------------------------------------------------

class ZenohWatch:
    """A Zenoh peer connected to a bridge, keeping every message under its prefix by key."""

    def __init__(self, endpoint: str, prefix: str) -> None:
        import zenoh

        self.prefix = prefix
        self._cond = threading.Condition()
        self.messages: dict[str, list[dict[str, Any]]] = {}
        config = zenoh.Config()
        config.insert_json5("mode", '"peer"')
        config.insert_json5("scouting/multicast/enabled", "false")
        config.insert_json5("connect/endpoints", json.dumps([endpoint]))
        self.session = zenoh.open(config)
        self._sub = self.session.declare_subscriber(f"{prefix}/**", self._on_sample)

    def _on_sample(self, sample: Any) -> None:
        key = str(sample.key_expr)[len(self.prefix) + 1:]
        msg = json.loads(sample.payload.to_bytes())
        with self._cond:
            self.messages.setdefault(key, []).append(msg)
            self._cond.notify_all()

    def latest(self, key: str) -> dict[str, Any] | None:
        with self._cond:
            got = self.messages.get(key)
            return got[-1] if got else None

    def wait_for(
        self, key: str, predicate: Callable[[dict[str, Any]], bool] = lambda m: True,
        timeout: float = 60.0,
    ) -> dict[str, Any]:
        """The first message of ``key`` arriving from now on (or already latest) that satisfies
        ``predicate``."""
        deadline = time.monotonic() + timeout
        with self._cond:
            seen = 0
            got = self.messages.get(key, [])
            if got and predicate(got[-1]):
                return got[-1]
            seen = len(got)
            while True:
                got = self.messages.get(key, [])
                for msg in got[seen:]:
                    if predicate(msg):
                        return msg
                seen = len(got)
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    last = got[-1] if got else None
                    raise AssertionError(f"no {key} message matched in {timeout} s; last {last}")
                self._cond.wait(remaining)

    def collect(self, wanted: dict[str, int], timeout: float = 60.0) -> dict[str, list[dict]]:
        """Wait until at least ``wanted[key]`` messages of each key have arrived; return them
        all (a copy), per key."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                short = {k: (len(self.messages.get(k, [])), n) for k, n in wanted.items()
                         if len(self.messages.get(k, [])) < n}
                if not short:
                    return {k: list(self.messages.get(k, [])) for k in wanted}
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise AssertionError(f"too few messages after {timeout} s (got, want): {short}")
                self._cond.wait(remaining)

    def after(self, key: str, t: float, timeout: float = 60.0) -> dict[str, Any]:
        """The first ``key`` message with simulation time ``t`` or later."""
        return self.wait_for(key, lambda m: m["t"] >= t, timeout)

    def query(self, suffix: str, timeout: float = 30.0) -> dict[str, Any]:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            for reply in self.session.get(f"{self.prefix}/{suffix}", timeout=2.0):
                if reply.ok is not None:
                    return json.loads(reply.ok.payload.to_bytes())
            time.sleep(0.1)
        raise AssertionError(f"no answer to {self.prefix}/{suffix}")

    def close(self) -> None:
        self._sub.undeclare()
        self.session.close()


@pytest.fixture
def zenoh_watch() -> Iterator[Callable[[BridgeProcess], ZenohWatch]]:
    """Factory: ``zenoh_watch(bridge_process)`` -> a connected :class:`ZenohWatch` (closed at
    teardown)."""
    opened: list[ZenohWatch] = []

    def connect(b: BridgeProcess) -> ZenohWatch:
        w = ZenohWatch(b.endpoints["zenoh"]["endpoints"][0], b.prefix)
        opened.append(w)
        return w

    yield connect
    for w in opened:
        w.close()
