"""Soak/fuzz run against a live bridge: what the issue-12 attack did once, on demand.

    make fuzz                                   # the defaults below
    .venv/bin/python bench/fuzz.py --kteam 100000 --socketcand 50000 --mavlink 50000 \\
        --zenoh 5000 --reconnects 50 --seconds 900

Starts ``koala-bridge run`` on free loopback ports (as tests/conftest.py does: Zenoh on
``tcp/127.0.0.1``, MAVLink UDP and socketcand on free ports) and attacks it, one client thread
per bus, until every count is done or ``--seconds`` have passed:

- K-Team: fuzzed command lines over the pty with pyserial (valid commands with arguments in and
  out of range, the same with bits flipped / truncated / glued / sliced, random bytes, over-long
  lines); replies are drained. Every ``--batch`` lines the client leaves a command half-sent,
  closes the port and a fresh client probes: it sends ``B`` (again each second) and must read a
  ``b,...`` reply within ``--probe-timeout`` seconds, or the bridge counts as hung.
- socketcand: malformed elements over TCP (random text or bytes between ``<`` ``>``, unbalanced
  brackets, bad ``send`` elements, over-long elements) on a client that reads, and ``< x >`` on
  ``--silent-clients`` clients that never read a byte.
- MAVLink: corrupted datagrams sent back to the bridge's UDP socket (valid HEARTBEAT and
  SCALED_IMU packets with bits flipped, truncated, glued, sliced; random bytes).
- Zenoh: puts of random payloads under the bridge's prefix and elsewhere, gets (the ``world``
  queryable, wildcards, nothing), invalid key expressions; multicast scouting off.
- Clients that never read (the range-frame and slcan ptys, the silent socketcand clients) for
  the whole run, and ``--reconnects`` disconnect/reconnect rounds per bus (ptys, socketcand
  closed with a TCP reset, Zenoh sessions).

It prints the inputs tried per bus, crashes (the bridge exited before it was stopped, or its log
holds a traceback: a decoder raised), hangs (a ``B`` probe unanswered), the bridge's counters
from its Zenoh ``status`` (rejected and dropped per bus) and the bridge's peak RSS (the kernel's
``VmHWM`` on Linux; elsewhere the largest RSS psutil sampled). ``--json PATH`` also writes the
report as JSON. The exit status is 1 on a crash or a hang, 2 if the bridge did not start.

Not part of ``make test`` (it is a bench); tests/e2e/test_fuzz_smoke.py runs it with tiny counts
so that it cannot rot. Inputs come from ``random.Random(--seed)``; the threads interleave as the
machine schedules them, so a run is repeatable in what is sent, not in its timing.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import random
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
DEFAULT_CONFIG = REPO / "config" / "default.toml"
TRACEBACK = "Traceback (most recent call last)"


# -- the bridge under attack -----------------------------------------------------------------------


def free_port(kind: int) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Bridge:
    """``koala-bridge run`` as a subprocess on free loopback ports, and what it tells."""

    def __init__(self, workdir: Path, clock: str, config: Path, start_timeout: float) -> None:
        self.endpoints_file = workdir / "endpoints.json"
        self.log_path = workdir / "bridge.log"
        self.zenoh_endpoint = f"tcp/127.0.0.1:{free_port(socket.SOCK_STREAM)}"
        self.mavlink_port = free_port(socket.SOCK_DGRAM)
        args = [
            sys.executable, "-m", "koala_bridge", "run", "--config", str(config),
            "--clock", clock, "--endpoints-file", str(self.endpoints_file),
            "--set", f'zenoh.listen=["{self.zenoh_endpoint}"]',
            "--set", f"buses.mavlink.port={self.mavlink_port}",
            "--set", "buses.can.socketcand_port=0",
        ]  # fmt: skip
        with open(self.log_path, "wb") as log:
            self.proc = subprocess.Popen(
                args, cwd=REPO, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL
            )
        self.stopped_by_us = False
        self._rss_peak_kib = 0
        self._rss_source = "unknown"
        deadline = time.monotonic() + start_timeout
        while not self.endpoints_file.exists():
            if self.proc.poll() is not None or time.monotonic() > deadline:
                self.stop()
                raise RuntimeError(f"the bridge did not start:\n{self.log()}")
            time.sleep(0.05)
        self.endpoints: dict[str, Any] = json.loads(self.endpoints_file.read_text())

    @property
    def prefix(self) -> str:
        return str(self.endpoints["zenoh"]["prefix"])

    def alive(self) -> bool:
        return self.proc.poll() is None

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")

    def sample_rss(self) -> None:
        """Keep the peak RSS up to date (call now and then while the bridge runs)."""
        self._rss_peak_kib = max(self._rss_peak_kib, self._read_rss_kib() or 0)

    def peak_rss(self) -> tuple[int | None, str]:
        """(peak RSS in KiB, how it was measured)."""
        self.sample_rss()
        return (self._rss_peak_kib or None), self._rss_source

    def rss_now(self) -> int | None:
        """The bridge's resident set now, KiB (Linux)."""
        return self._proc_status_kib("VmRSS:")

    def _proc_status_kib(self, key: str) -> int | None:
        try:
            with open(f"/proc/{self.proc.pid}/status", encoding="ascii") as f:
                for line in f:
                    if line.startswith(key):
                        return int(line.split()[1])
        except OSError:
            pass
        return None

    def _read_rss_kib(self) -> int | None:
        hwm = self._proc_status_kib("VmHWM:")  # the kernel's high-water mark: exact, whenever
        if hwm is not None:
            self._rss_source = "VmHWM"
            return hwm
        try:
            import psutil  # type: ignore[import-untyped]
        except ImportError:
            return None
        try:
            rss = int(psutil.Process(self.proc.pid).memory_info().rss // 1024)
        except psutil.Error:
            return None
        self._rss_source = "largest RSS sampled by psutil"
        return rss

    def stop(self, timeout: float = 20.0) -> int | None:
        """SIGTERM (SIGKILL after ``timeout``); the exit code, or None if it had already died."""
        if self.proc.poll() is not None:
            return None
        self.sample_rss()
        self.stopped_by_us = True
        self.proc.send_signal(signal.SIGTERM)
        try:
            self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(10)
        return self.proc.returncode


# -- mutations -------------------------------------------------------------------------------------


def mutate(rng: random.Random, data: bytes) -> bytes:
    """``data`` with one to three of: a bit flipped, truncated, random bytes inserted, a slice
    deleted, glued to itself."""
    out = bytearray(data)
    for _ in range(rng.randint(1, 3)):
        op = rng.randrange(5)
        if op == 0 and out:
            i = rng.randrange(len(out))
            out[i] ^= 1 << rng.randrange(8)
        elif op == 1:
            del out[rng.randint(0, len(out)) :]
        elif op == 2:
            i = rng.randint(0, len(out))
            out[i:i] = rng.randbytes(rng.randint(1, 8))
        elif op == 3 and out:
            i = rng.randrange(len(out))
            del out[i : i + rng.randint(1, 8)]
        else:
            out += bytes(out)
    return bytes(out)


def kteam_input(rng: random.Random) -> bytes:
    """One fuzzed K-Team command line, terminator included."""
    letter = rng.choice("BDEGHNOLLZ")
    arity = {"D": 2, "G": 2, "L": 2}.get(letter, 0) + rng.choice((0, 0, 0, 0, -1, 1))
    args = [rng.choice((rng.randint(-130, 130), rng.randint(-(2**32), 2**32))) for _ in
            range(max(arity, 0))]
    valid = ",".join([letter, *map(str, args)]).encode() + rng.choice((b"\r", b"\n", b"\r\n"))
    r = rng.random()
    if r < 0.3:
        return valid
    if r < 0.6:
        return mutate(rng, valid) + b"\r"
    if r < 0.85:
        return rng.randbytes(rng.randint(1, 80)) + b"\r"
    if r < 0.97:
        alphabet = "BDEGHLNOZ,-+0123456789 \t"
        return "".join(rng.choice(alphabet) for _ in range(rng.randint(1, 40))).encode() + b"\r"
    return rng.randbytes(rng.randint(257, 3000)).replace(b"\r", b"").replace(b"\n", b"") + b"\r"


def socketcand_input(rng: random.Random) -> bytes:
    """One malformed (now and then valid) socketcand element."""
    ident = rng.choice((0x100, 0x110, 0x120, rng.randrange(0x800), rng.randrange(1 << 32)))
    dlc = rng.randint(0, 9)
    count = rng.choice((dlc, rng.randint(0, 9)))
    data = " ".join(f"{rng.randrange(256):02X}" for _ in range(count))
    if rng.random() < 0.5:  # a MotorCommand the bridge accepts: two int16 speeds, mm/s
        speeds = struct.pack("<hh", rng.randint(-2000, 2000), rng.randint(-2000, 2000))
        ident, dlc, data = 0x100, 4, " ".join(f"{b:02X}" for b in speeds)
    valid = f"< send {ident:X} {dlc:X} {data} >".encode()
    r = rng.random()
    if r < 0.25:
        return valid
    if r < 0.5:
        return mutate(rng, valid)
    if r < 0.65:
        words = ["open", "rawmode", "bcmmode", "echo", "send", "frame", "x", "koala0", "add",
                 "filter", "subscribe", "controlmode", "statistics", "error", "<", ">", "ok"]
        picked = [rng.choice(words) for _ in range(rng.randint(0, 6))]
        return ("< " + " ".join(picked) + " >").encode()
    if r < 0.8:
        return b"<" + rng.randbytes(rng.randint(0, 60)) + b">"
    if r < 0.9:
        return rng.choice((b"<<<<", b">>>>", b"< <", b"> <", b"<>", b"< >", b"<\x00>"))
    return b"< " + b"A" * rng.randint(100, 5000) + b" >"


def mavlink_input(rng: random.Random, packets: list[bytes]) -> bytes:
    """One corrupted (now and then valid) MAVLink datagram."""
    r = rng.random()
    if r < 0.1:
        return rng.choice(packets)
    if r < 0.7:
        glued = b"".join(rng.choice(packets) for _ in range(rng.randint(1, 3)))
        return mutate(rng, glued)
    if r < 0.99:
        return rng.randbytes(rng.randint(0, 300))
    return rng.randbytes(rng.randint(1000, 60000))


def mavlink_packets(rng: random.Random) -> list[bytes]:
    from koala_bridge.drivers.mavlink_codec import CompassEncoder
    from koala_bridge.drivers.messages import CompassSample

    encoder = CompassEncoder()
    out = [encoder.heartbeat() for _ in range(4)]
    for i in range(60):
        out.append(encoder.scaled_imu(CompassSample(
            i * 20, rng.uniform(-60, 60), rng.uniform(-60, 60), rng.uniform(-60, 60))))
    return out


# -- the attack ------------------------------------------------------------------------------------


@dataclass
class Options:
    kteam: int
    socketcand: int
    mavlink: int
    zenoh: int
    reconnects: int
    silent_clients: int
    batch: int
    seconds: float
    probe_timeout: float
    seed: int


@dataclass
class Tally:
    """What the clients did and saw, shared by the attack threads."""

    inputs: dict[str, int] = field(default_factory=dict)
    reconnects: dict[str, int] = field(default_factory=dict)
    probes: int = 0
    hangs: list[str] = field(default_factory=list)
    client_errors: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def add(self, table: str, key: str, n: int = 1) -> None:
        with self.lock:
            counts = getattr(self, table)
            counts[key] = counts.get(key, 0) + n

    def set(self, table: str, key: str, n: int) -> None:
        with self.lock:
            getattr(self, table)[key] = n

    def note(self, table: str, text: str) -> None:
        with self.lock:
            getattr(self, table).append(text)


class Attack:
    def __init__(self, bridge: Bridge, opts: Options) -> None:
        self.bridge = bridge
        self.opts = opts
        self.tally = Tally()
        self.stop = threading.Event()
        self.deadline = time.monotonic() + opts.seconds
        ep = bridge.endpoints
        self.kteam_path = ep["serial"]["kteam"]
        self.ranges_path = ep["serial"]["rangefinders"]
        self.slcan_path = ep["can"].get("slcan")
        cand = ep["can"]["socketcand"]
        self.cand_addr = (cand["host"], int(cand["port"]))
        self.cand_channel = cand["channel"]
        self.rss_at_start: int | None = None

    def running(self) -> bool:
        if time.monotonic() > self.deadline:
            self.stop.set()
        return not self.stop.is_set()

    def rng(self, name: str) -> random.Random:
        return random.Random(f"{self.opts.seed}:{name}")

    # ------------------------------------------------------------------ K-Team

    def probe(self) -> bool:
        """A fresh client sends ``B`` (again every second) until a ``b,...`` line comes back."""
        import serial

        with self.tally.lock:
            self.tally.probes += 1
        deadline = time.monotonic() + self.opts.probe_timeout
        with serial.Serial(self.kteam_path, 115200, timeout=0.1, write_timeout=5) as port:
            buf, next_send = b"", 0.0
            while time.monotonic() < deadline:
                if time.monotonic() >= next_send:
                    port.write(b"\rB\r")  # CR first: whatever came before is a line of its own
                    next_send = time.monotonic() + 1.0
                buf += port.read(256)
                lines = buf.split(b"\r\n")
                if any(line.startswith(b"b,") for line in lines[:-1]):
                    return True
                buf = lines[-1][-512:]
        return False

    def kteam(self) -> None:
        import serial

        rng = self.rng("kteam")
        sent = 0
        while sent < self.opts.kteam and self.running():
            try:
                with serial.Serial(self.kteam_path, 115200, timeout=0, write_timeout=10) as port:
                    for _ in range(min(self.opts.batch, self.opts.kteam - sent)):
                        if not self.running():
                            break
                        port.write(kteam_input(rng))
                        sent += 1
                        if sent % 50 == 0:
                            port.read(port.in_waiting)
                    port.write(b"D,1")  # a half-sent command left for the next client
            except serial.SerialTimeoutException:
                self.tally.note("notes", f"K-Team write blocked for 10 s after {sent} lines")
            finally:
                self.tally.set("inputs", "kteam", sent)
            self.tally.add("reconnects", "kteam")
            self.check_probe(f"after {sent} K-Team lines")

    def check_probe(self, when: str) -> None:
        if not self.bridge.alive():
            self.stop.set()
            return
        if not self.probe():
            self.tally.note("hangs", f"no reply to B within {self.opts.probe_timeout:g} s {when}")

    # ------------------------------------------------------------------ socketcand

    def cand_connect(self, handshake: bool = True) -> socket.socket:
        sock = socket.create_connection(self.cand_addr, timeout=10)
        if handshake:
            sock.recv(64)  # < hi >
            sock.sendall(f"< open {self.cand_channel} >".encode())
            sock.recv(64)
            sock.sendall(b"< rawmode >")
            sock.recv(64)
        sock.setblocking(False)
        return sock

    def socketcand(self) -> None:
        rng = self.rng("socketcand")
        silent = [self.cand_connect() for _ in range(self.opts.silent_clients)]
        sock = self.cand_connect()
        sent = silent_sent = 0
        try:
            while sent < self.opts.socketcand and self.running():
                element = socketcand_input(rng)
                try:
                    _send_all(sock, element)
                except OSError:  # the bridge may drop a client past its limits: come back
                    self.tally.add("reconnects", "socketcand (dropped by the bridge)")
                    sock.close()
                    sock = self.cand_connect()
                    continue
                sent += 1
                if sent % 20 == 0:
                    _drain(sock)
                    for s in silent:  # `<x>` by the hundred, never reading a byte
                        with contextlib.suppress(OSError):
                            silent_sent += s.send(b"< x >" * 100) // 5
        finally:
            self.tally.set("inputs", "socketcand", sent)
            self.tally.set("inputs", "socketcand (never read)", silent_sent)
            sock.close()
            for s in silent:
                s.close()

    # ------------------------------------------------------------------ MAVLink

    def mavlink(self) -> None:
        rng = self.rng("mavlink")
        packets = mavlink_packets(rng)
        sent = 0
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            sock.bind(("127.0.0.1", self.bridge.mavlink_port))  # where the bridge sends
            sock.settimeout(30)
            _, peer = sock.recvfrom(65536)  # the bridge's own address: reply to it
            sock.setblocking(False)
            try:
                while sent < self.opts.mavlink and self.running():
                    with contextlib.suppress(OSError):
                        sock.sendto(mavlink_input(rng, packets), peer)
                    sent += 1
                    if sent % 20 == 0:
                        # The bridge reads 64 datagrams per step; flooded faster, the kernel
                        # drops them before they reach it (the report's "received" and
                        # "rejected" tell how many arrived).
                        _drain(sock)
                        time.sleep(0.005)
            finally:
                self.tally.set("inputs", "mavlink", sent)

    # ------------------------------------------------------------------ Zenoh

    def zenoh(self) -> None:
        rng = self.rng("zenoh")
        prefix = self.bridge.prefix
        done = 0
        session = _zenoh_session(self.bridge.zenoh_endpoint)
        rounds = 0
        every = max(1, self.opts.zenoh // (self.opts.reconnects + 1))  # ops between reconnects
        try:
            while done < self.opts.zenoh and self.running():
                r = rng.random()
                word = "fuzz" + rng.randbytes(3).hex()
                try:
                    if r < 0.7:
                        key = rng.choice((f"{prefix}/{word}", f"{prefix}/cmd/{word}", word,
                                          f"{prefix}/sensors/{word}"))
                        session.put(key, rng.randbytes(rng.randint(0, 2000)))
                    elif r < 0.9:
                        key = rng.choice((f"{prefix}/world", f"{prefix}/**", f"{prefix}/*",
                                          f"{word}/**", f"{prefix}/{word}"))
                        for _ in session.get(key, timeout=2.0):
                            pass
                    else:
                        key = rng.choice(("", "a//b", "/x", "x/", "**/**", "$*x", "a?b", "#"))
                        session.put(key, b"x")
                except Exception:  # an invalid key expression is refused by zenoh itself
                    pass
                done += 1
                if rounds < self.opts.reconnects and done % every == 0:
                    session.close()
                    session = _zenoh_session(self.bridge.zenoh_endpoint)
                    rounds += 1
                    self.tally.add("reconnects", "zenoh")
        finally:
            self.tally.set("inputs", "zenoh", done)
            session.close()

    # ------------------------------------------------------------------ reconnects, silence

    def reconnect_rounds(self) -> None:
        """Open, half-use and drop every bus's client ``--reconnects`` times."""
        import serial

        rng = self.rng("reconnects")
        for _ in range(self.opts.reconnects):
            if not self.running():
                return
            with serial.Serial(self.ranges_path, 115200, timeout=0.05) as port:
                port.read(rng.randint(1, 200))
            self.tally.add("reconnects", "rangefinders")
            if self.slcan_path:
                with serial.Serial(self.slcan_path, 115200, timeout=0.05, write_timeout=5) as port:
                    port.write(b"O\r" + rng.choice((b"t1", b"t10081122", b"\x07", b"S")))
                    port.read(rng.randint(1, 200))
                self.tally.add("reconnects", "slcan")
            sock = self.cand_connect(handshake=rng.random() < 0.5)
            with contextlib.suppress(OSError):
                sock.send(b"< open koa")  # half an element, then a TCP reset
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
            sock.close()
            self.tally.add("reconnects", "socketcand")
            time.sleep(0.01)

    def silent_ptys(self) -> list[Any]:
        """Clients that open the range-frame and slcan ptys (channel open) and never read."""
        import serial

        ports = [serial.Serial(self.ranges_path, 115200, timeout=0)]
        if self.slcan_path:
            slcan = serial.Serial(self.slcan_path, 115200, timeout=0, write_timeout=5)
            slcan.write(b"O\r")
            ports.append(slcan)
        return ports

    # ------------------------------------------------------------------ run

    def run(self) -> None:
        workers = {
            "kteam": self.kteam,
            "socketcand": self.socketcand,
            "mavlink": self.mavlink,
            "zenoh": self.zenoh,
            "reconnects": self.reconnect_rounds,
        }
        self.rss_at_start = self.bridge.rss_now()
        silent = self.silent_ptys()
        threads = [
            threading.Thread(target=self._guard(name, fn), name=f"fuzz-{name}", daemon=True)
            for name, fn in workers.items()
        ]
        try:
            for t in threads:
                t.start()
            while any(t.is_alive() for t in threads):
                self.bridge.sample_rss()
                if not self.bridge.alive():
                    self.stop.set()
                for t in threads:
                    t.join(0.2)
                self.running()
        finally:
            self.stop.set()
            for t in threads:
                t.join(30)
            for port in silent:
                port.close()
        if self.bridge.alive():
            self.check_probe("at the end")

    def _guard(self, name: str, fn: Callable[[], None]) -> Callable[[], None]:
        def run() -> None:
            try:
                fn()
            except Exception as e:  # reported; a dead bridge explains most
                self.tally.note("client_errors", f"{name}: {type(e).__name__}: {e}")

        return run


def _send_all(sock: socket.socket, data: bytes) -> None:
    view = memoryview(data)
    deadline = time.monotonic() + 10
    while view:
        try:
            view = view[sock.send(view) :]
        except BlockingIOError:
            if time.monotonic() > deadline:
                raise TimeoutError("the bridge stopped reading for 10 s") from None
            _drain(sock)
            time.sleep(0.001)


def _drain(sock: socket.socket) -> None:
    with contextlib.suppress(BlockingIOError, InterruptedError):
        while True:
            if not sock.recv(65536):
                raise ConnectionResetError("closed by the bridge")


def _zenoh_session(endpoint: str) -> Any:
    import zenoh

    config = zenoh.Config()
    config.insert_json5("mode", '"peer"')
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("connect/endpoints", json.dumps([endpoint]))
    return zenoh.open(config)


class StatusWatch:
    """The bridge's latest Zenoh ``status`` message (its counters per bus)."""

    def __init__(self, bridge: Bridge) -> None:
        self._cond = threading.Condition()
        self.latest: dict[str, Any] | None = None
        self.count = 0
        self.session = _zenoh_session(bridge.zenoh_endpoint)
        self._sub = self.session.declare_subscriber(f"{bridge.prefix}/status", self._on_sample)

    def _on_sample(self, sample: Any) -> None:
        try:
            msg = json.loads(sample.payload.to_bytes())
        except ValueError:
            return
        if isinstance(msg, dict) and isinstance(msg.get("buses"), dict):
            with self._cond:
                self.latest, self.count = msg, self.count + 1
                self._cond.notify_all()

    def fresh(self, timeout: float) -> dict[str, Any] | None:
        """The next status message (or the latest one if none comes within ``timeout``)."""
        with self._cond:
            seen = self.count
            self._cond.wait_for(lambda: self.count > seen, timeout)
            return self.latest

    def close(self) -> None:
        self._sub.undeclare()
        self.session.close()


# -- report ----------------------------------------------------------------------------------------


def build_report(attack: Attack, bridge: Bridge, status: dict[str, Any] | None,
                 exit_code: int | None, seconds: float) -> dict[str, Any]:
    log = bridge.log()
    crashes = []
    if not bridge.stopped_by_us:
        crashes.append(f"the bridge exited by itself with code {bridge.proc.returncode}")
    elif exit_code not in (0, None):
        crashes.append(f"the bridge exited with code {exit_code} when stopped")
    if TRACEBACK in log:
        crashes.append(f"{log.count(TRACEBACK)} traceback(s) in the bridge's log {bridge.log_path}")
    rss_kib, rss_source = bridge.peak_rss()
    buses = (status or {}).get("buses", {})
    tally = attack.tally
    return {
        "seconds": round(seconds, 1),
        "inputs": dict(tally.inputs),
        "reconnects": dict(tally.reconnects),
        "probes": tally.probes,
        "crashes": crashes,
        "hangs": list(tally.hangs),
        "received": {bus: int(c.get("received", 0)) for bus, c in buses.items()},
        "rejected": {bus: int(c.get("rejected", 0)) for bus, c in buses.items()},
        "dropped": {bus: int(c.get("dropped", 0)) for bus, c in buses.items()},
        "status_seen": status is not None,
        "peak_rss_kib": rss_kib,
        "peak_rss_source": rss_source,
        "rss_at_start_kib": attack.rss_at_start,
        "client_errors": list(tally.client_errors),
        "notes": list(tally.notes),
        "log": str(bridge.log_path),
        "ok": not crashes and not tally.hangs,
    }


def print_report(r: dict[str, Any]) -> None:
    def counts(d: dict[str, int]) -> str:
        return "  ".join(f"{k} {v}" for k, v in d.items()) or "-"

    rss = f"{r['peak_rss_kib'] / 1024:.1f} MiB ({r['peak_rss_source']})" if r["peak_rss_kib"] \
        else "unknown"
    if r["rss_at_start_kib"]:
        rss += f"; {r['rss_at_start_kib'] / 1024:.1f} MiB resident when the attack began"
    print(f"fuzz run: {r['seconds']} s")
    print(f"  inputs tried   {counts(r['inputs'])}")
    print(f"  reconnects     {counts(r['reconnects'])}")
    print(f"  crashes        {len(r['crashes'])}" + "".join(f"\n    {c}" for c in r["crashes"]))
    print(f"  hangs          {len(r['hangs'])} in {r['probes']} B probes"
          + "".join(f"\n    {h}" for h in r["hangs"]))
    print(f"  rejected       {counts(r['rejected'])}" if r["status_seen"]
          else "  rejected       (no Zenoh status received)")
    print(f"  received       {counts(r['received'])}")
    print(f"  dropped        {counts(r['dropped'])}")
    print(f"  peak RSS       {rss}")
    for e in r["client_errors"]:
        print(f"  client error   {e}")
    for n in r["notes"]:
        print(f"  note           {n}")
    print(f"  bridge log     {r['log']}")
    print("OK" if r["ok"] else "FAILED: crash or hang")


# -- command line ----------------------------------------------------------------------------------


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        prog="bench/fuzz.py",
        description="Attack a live koala-bridge on every bus; report crashes, hangs, rejects "
        "and peak RSS.",
        epilog="example: bench/fuzz.py --kteam 100000 --socketcand 50000 --mavlink 50000 "
        "--zenoh 5000 --reconnects 50 --seconds 900",
    )
    p.add_argument("--kteam", type=int, default=20_000, help="fuzzed K-Team lines (20000)")
    p.add_argument("--socketcand", type=int, default=20_000,
                   help="socketcand elements (20000)")
    p.add_argument("--mavlink", type=int, default=20_000, help="MAVLink datagrams (20000)")
    p.add_argument("--zenoh", type=int, default=2_000, help="Zenoh puts/gets (2000)")
    p.add_argument("--reconnects", type=int, default=20,
                   help="disconnect/reconnect rounds per bus (20)")
    p.add_argument("--silent-clients", type=int, default=2,
                   help="socketcand clients that send `< x >` and never read (2)")
    p.add_argument("--batch", type=int, default=2_000,
                   help="K-Team lines per client, then a B probe by a fresh one (2000)")
    p.add_argument("--seconds", type=float, default=600.0,
                   help="stop the attack after this long whatever the counts (600)")
    p.add_argument("--probe-timeout", type=float, default=10.0,
                   help="seconds a B probe waits for its reply before the bridge counts as hung")
    p.add_argument("--clock", choices=("fast", "realtime"), default="fast")
    p.add_argument("--config", type=Path, default=DEFAULT_CONFIG)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", type=Path, help="also write the report here")
    p.add_argument("--workdir", type=Path,
                   help="where the bridge's log and endpoints go (default: a temporary folder)")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    opts = Options(args.kteam, args.socketcand, args.mavlink, args.zenoh, args.reconnects,
                   args.silent_clients, max(1, args.batch), args.seconds, args.probe_timeout,
                   args.seed)
    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="koala-fuzz-"))
    workdir.mkdir(parents=True, exist_ok=True)
    started = time.monotonic()
    try:
        bridge = Bridge(workdir, args.clock, args.config, start_timeout=120)
    except RuntimeError as e:
        print(f"bench/fuzz.py: {e}", file=sys.stderr)
        return 2
    attack = Attack(bridge, opts)
    status: dict[str, Any] | None = None
    try:
        watch = StatusWatch(bridge)
        try:
            attack.run()
            if bridge.alive():
                status = watch.fresh(timeout=10.0)
        finally:
            watch.close()
    finally:
        exit_code = bridge.stop()
    report = build_report(attack, bridge, status, exit_code, time.monotonic() - started)
    print_report(report)
    if args.json:
        args.json.write_text(json.dumps(report, indent=2) + "\n")
    return 0 if report["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
