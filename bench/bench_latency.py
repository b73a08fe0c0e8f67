"""Latency per bus: from a sample's simulation to its decode at a client, as a ratio to the bare
transport's latency measured in the same run.

Two child processes, clients in this one:

- ``--serve``: a bridge (`koala_bridge.runtime.sim_source.SimulatedRobotSource`, real-time
  clock, the robot driving so that every encoder sample is distinct) that logs, for every step,
  ``time.monotonic()`` right after the simulator produced the step's readings. CLOCK_MONOTONIC is system-wide on Linux, so
  the client's decode time minus that is the sample's latency.
- ``--bare``: the bare transports: the same kinds of link (a pty, a TCP server, UDP datagrams, a
  Zenoh publisher) carrying raw payloads of the same size at the same rates, each stamped with
  ``time.monotonic()`` just before it is written.

Clients: pyserial + RangeFrameDecoder (range frames, keyed by sample time), python-can
socketcand and slcan (WheelOdometry, keyed by encoder count), pymavlink (SCALED_IMU, keyed by
time_boot_ms), Zenoh (sensors/odometry, keyed by t); K-Team is request/response, so its figure is
the round trip of ``H`` against a raw echo over a pty.

    .venv/bin/python -m bench.bench_latency --seconds 10
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
STAMP = struct.Struct("<d")


# -- child: the bridge ---------------------------------------------------------------------------

def serve(config_overrides: list[str], ready_file: Path, log_file: Path) -> int:
    from koala_bridge.runtime.endpoints import write_endpoints_file
    from koala_bridge.runtime.settings import (
        BridgeSettings,
        apply_override,
        load_config,
        parse_override,
    )
    from koala_bridge.runtime.sim_source import SimulatedRobotSource

    config = load_config(REPO / "config" / "default.toml")
    for text in ["run.clock=realtime", *config_overrides]:
        config = apply_override(config, *parse_override(text))
    service = SimulatedRobotSource(config, BridgeSettings.from_config(config))
    steps: list[tuple[float, float, int]] = []
    simulate = service.sim.step

    def logged_step(command: Any) -> Any:
        r = simulate(command)
        ticks = r.odometry.left_ticks if r.odometry is not None else -1
        steps.append((r.t, time.monotonic(), int(ticks)))
        return r

    service.sim.step = logged_step  # type: ignore[method-assign]
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    with service:
        write_endpoints_file(ready_file, service.open())
        service.arbiter.set(0.3, 0.3, "bench")  # every encoder sample distinct
        service.run(stop, duration_s=0)
    log_file.write_text(json.dumps(steps))
    return 0


# -- child: the bare transports ------------------------------------------------------------------

def bare(udp_port: int, zenoh_endpoint: str, ready_file: Path) -> int:
    import pty as ptymod
    import tty

    import zenoh

    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())

    def open_pty() -> tuple[int, str]:
        master, slave = ptymod.openpty()
        tty.setraw(slave)
        name = os.ttyname(slave)
        os.close(slave)
        return master, name

    frame_master, frame_path = open_pty()
    slcan_master, slcan_path = open_pty()
    echo_master, echo_path = open_pty()
    listener = socket.create_server(("127.0.0.1", 0))
    tcp_port = listener.getsockname()[1]
    udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    zc = zenoh.Config()
    zc.insert_json5("mode", '"peer"')
    zc.insert_json5("scouting/multicast/enabled", "false")
    zc.insert_json5("listen/endpoints", json.dumps([zenoh_endpoint]))
    session = zenoh.open(zc)
    publisher = session.declare_publisher("bench/bare")

    def paced(rate_hz: float, size: int, write: Callable[[bytes], object]) -> Callable[[], None]:
        def loop() -> None:
            t0 = time.monotonic()
            n = 0
            while not stop.is_set():
                n += 1
                delay = t0 + n / rate_hz - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                payload = STAMP.pack(time.monotonic()).ljust(size, b"\x55")
                try:
                    write(payload)
                except OSError:
                    pass  # no reader yet
        return loop

    def tcp_loop() -> None:
        listener.settimeout(0.5)
        while not stop.is_set():
            try:
                conn, _ = listener.accept()
            except TimeoutError:
                continue
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            paced(100, 30, conn.sendall)()
            conn.close()

    def echo_loop() -> None:
        import select

        while not stop.is_set():
            r, _, _ = select.select([echo_master], [], [], 0.2)
            if r:
                try:
                    os.write(echo_master, os.read(echo_master, 256))
                except OSError:
                    time.sleep(0.05)

    threads = [
        threading.Thread(target=paced(20, 45, lambda b: os.write(frame_master, b))),  # IR frame
        threading.Thread(target=paced(100, 23, lambda b: os.write(slcan_master, b))),  # slcan
        threading.Thread(target=paced(50, 37, lambda b: udp.sendto(b, ("127.0.0.1", udp_port)))),
        threading.Thread(target=paced(100, 90, publisher.put)),  # odometry JSON size
        threading.Thread(target=tcp_loop),
        threading.Thread(target=echo_loop),
    ]
    for t in threads:
        t.start()
    ready_file.write_text(json.dumps({"pty": frame_path, "slcan_pty": slcan_path,
                                      "echo_pty": echo_path, "tcp_port": tcp_port}))
    while not stop.is_set():
        stop.wait(0.2)
    for t in threads:
        t.join(5)
    publisher.undeclare()
    session.close()
    for fd in (frame_master, slcan_master, echo_master):
        os.close(fd)
    listener.close()
    udp.close()
    return 0


# -- parent: clients ---------------------------------------------------------------------------

def free_port(kind: int = socket.SOCK_STREAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_file(path: Path, proc: subprocess.Popen[bytes], timeout: float = 30) -> dict[str, Any]:
    deadline = time.monotonic() + timeout
    while not path.exists() or not path.read_text():
        if proc.poll() is not None or time.monotonic() > deadline:
            raise RuntimeError(f"child {proc.args!r} did not start")
        time.sleep(0.05)
    time.sleep(0.05)
    return dict(json.loads(path.read_text()))


def stats(latencies: list[float]) -> dict[str, float]:
    a = np.asarray(latencies) * 1e3
    return {"n": len(a), "p50_ms": float(np.median(a)), "p95_ms": float(np.percentile(a, 95))}


class Collector:
    """Client threads append ``(key, decode time)``; stopped together."""

    def __init__(self) -> None:
        self.stop = threading.Event()
        self.events: dict[str, list[tuple[Any, float]]] = {}
        self.threads: list[threading.Thread] = []

    def add(self, name: str, loop: Callable[[Callable[[Any], None]], None]) -> None:
        events: list[tuple[Any, float]] = []
        self.events[name] = events

        def record(key: Any) -> None:
            events.append((key, time.monotonic()))

        def run() -> None:
            try:
                loop(record)
            except Exception as e:  # report, do not hang the bench
                print(f"client {name} failed: {e!r}", file=sys.stderr)

        self.threads.append(threading.Thread(target=run, name=name, daemon=True))

    def run_for(self, seconds: float) -> None:
        for t in self.threads:
            t.start()
        time.sleep(seconds)
        self.stop.set()
        for t in self.threads:
            t.join(5)


def bridge_clients(ep: dict[str, Any], mav_port: int, c: Collector) -> None:
    import can
    import serial
    import zenoh
    from koala_bridge.drivers.messages import RangeKind
    from koala_bridge.drivers.rangeframes import RangeFrameDecoder
    from pymavlink.dialects.v20 import common as mavlink2

    def rangefinders(record: Callable[[Any], None]) -> None:
        decoder = RangeFrameDecoder()
        with serial.Serial(ep["serial"]["rangefinders"], timeout=0.2) as port:
            while not c.stop.is_set():
                for f in decoder.feed(port.read(port.in_waiting or 1)):
                    if f.kind == RangeKind.IR:
                        record(("t_us", f.t_us))

    def can_client(bus_factory: Callable[[], Any]) -> Callable[[Callable[[Any], None]], None]:
        def loop(record: Callable[[Any], None]) -> None:
            with bus_factory() as bus:
                while not c.stop.is_set():
                    msg = bus.recv(0.2)
                    if msg is not None and msg.arbitration_id == 0x110:
                        record(("ticks", int.from_bytes(msg.data[:4], "little", signed=True)))
        return loop

    sc = ep["can"]["socketcand"]

    def mavlink(record: Callable[[Any], None]) -> None:
        parser = mavlink2.MAVLink(None)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            sock.bind(("127.0.0.1", mav_port))
            sock.settimeout(0.2)
            while not c.stop.is_set():
                try:
                    data = sock.recv(2048)
                except TimeoutError:
                    continue
                for m in parser.parse_buffer(data) or []:
                    if m.get_type() == "SCALED_IMU":
                        record(("ms", m.time_boot_ms))

    def zenoh_client(record: Callable[[Any], None]) -> None:
        zc = zenoh.Config()
        zc.insert_json5("mode", '"peer"')
        zc.insert_json5("scouting/multicast/enabled", "false")
        zc.insert_json5("connect/endpoints", json.dumps(ep["zenoh"]["endpoints"]))
        session = zenoh.open(zc)
        sub = session.declare_subscriber(
            f"{ep['zenoh']['prefix']}/sensors/odometry",
            lambda s: record(("t", json.loads(s.payload.to_bytes())["t"])),
        )
        c.stop.wait()
        sub.undeclare()
        session.close()

    def kteam(record: Callable[[Any], None]) -> None:
        with serial.Serial(ep["serial"]["kteam"], timeout=1) as port:
            while not c.stop.is_set():
                t0 = time.monotonic()
                port.write(b"H\r")
                port.read_until(b"\r\n")
                record(("rtt", time.monotonic() - t0))
                time.sleep(0.01)

    c.add("rangefinders (pty)", rangefinders)
    c.add("can.socketcand (TCP)", can_client(lambda: can.Bus(
        interface="socketcand", host=sc["host"], port=sc["port"], channel=sc["channel"])))
    c.add("can.slcan (pty)", can_client(lambda: can.Bus(
        interface="slcan", channel=ep["can"]["slcan"])))
    c.add("mavlink (UDP)", mavlink)
    c.add("zenoh (TCP)", zenoh_client)
    c.add("kteam (pty, round trip)", kteam)


def bare_clients(info: dict[str, Any], udp_port: int, zenoh_endpoint: str, c: Collector) -> None:
    import serial
    import zenoh

    def stamped(record: Callable[[Any], None], data: bytes) -> None:
        record(("stamp", STAMP.unpack_from(data)[0]))

    def pty_reader(path: str, size: int) -> Callable[[Callable[[Any], None]], None]:
        def loop(record: Callable[[Any], None]) -> None:
            with serial.Serial(path, timeout=0.2) as port:
                while not c.stop.is_set():
                    data = port.read(size)
                    if len(data) == size:
                        stamped(record, data)
        return loop

    def tcp(record: Callable[[Any], None]) -> None:
        with socket.create_connection(("127.0.0.1", info["tcp_port"])) as s:
            s.settimeout(0.2)
            buf = b""
            while not c.stop.is_set():
                try:
                    buf += s.recv(4096)
                except TimeoutError:
                    continue
                while len(buf) >= 30:
                    stamped(record, buf[:30])
                    buf = buf[30:]

    def udp(record: Callable[[Any], None]) -> None:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            sock.bind(("127.0.0.1", udp_port))
            sock.settimeout(0.2)
            while not c.stop.is_set():
                try:
                    stamped(record, sock.recv(2048))
                except TimeoutError:
                    continue

    def zenoh_client(record: Callable[[Any], None]) -> None:
        zc = zenoh.Config()
        zc.insert_json5("mode", '"peer"')
        zc.insert_json5("scouting/multicast/enabled", "false")
        zc.insert_json5("connect/endpoints", json.dumps([zenoh_endpoint]))
        session = zenoh.open(zc)
        sub = session.declare_subscriber("bench/bare", lambda s: stamped(record,
                                                                         s.payload.to_bytes()))
        c.stop.wait()
        sub.undeclare()
        session.close()

    def echo(record: Callable[[Any], None]) -> None:
        with serial.Serial(info["echo_pty"], timeout=1) as port:
            while not c.stop.is_set():
                t0 = time.monotonic()
                port.write(b"H\r")
                port.read_until(b"\r")
                record(("rtt", time.monotonic() - t0))
                time.sleep(0.01)

    c.add("rangefinders (pty)", pty_reader(info["pty"], 45))
    c.add("can.socketcand (TCP)", tcp)
    c.add("can.slcan (pty)", pty_reader(info["slcan_pty"], 23))
    c.add("mavlink (UDP)", udp)
    c.add("zenoh (TCP)", zenoh_client)
    c.add("kteam (pty, round trip)", echo)


def bridge_latencies(events: dict[str, list[tuple[Any, float]]],
                     steps: list[list[float]]) -> dict[str, list[float]]:
    by_t_us = {int(round(t * 1e6)) & 0xFFFFFFFF: w for t, w, _ in steps}
    by_ms = {int(round(t * 1000)): w for t, w, _ in steps}
    by_t = {round(t, 6): w for t, w, _ in steps}
    by_ticks = {int(k): w for _, w, k in steps if k >= 0}
    out: dict[str, list[float]] = {}
    for name, evs in events.items():
        lat = []
        for (kind, key), when in evs:
            if kind == "rtt":
                lat.append(key)
                continue
            tables: dict[str, dict[Any, float]] = {
                "t_us": by_t_us, "ms": by_ms, "t": by_t, "ticks": by_ticks
            }
            table = tables[kind]
            w = table.get(round(key, 6) if kind == "t" else key)
            if w is not None:
                lat.append(when - w)
        out[name] = lat
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=8.0, help="measuring time per phase")
    parser.add_argument("--serve", nargs=2, metavar=("READY", "LOG"), help=argparse.SUPPRESS)
    parser.add_argument("--bare", nargs=3, metavar=("UDP", "ZENOH", "READY"),
                        help=argparse.SUPPRESS)
    parser.add_argument("--set", action="append", default=[], help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.serve:
        return serve(args.set, Path(args.serve[0]), Path(args.serve[1]))
    if args.bare:
        return bare(int(args.bare[0]), args.bare[1], Path(args.bare[2]))

    with tempfile.TemporaryDirectory() as tmp:
        tmpdir = Path(tmp)
        me = [sys.executable, "-m", "bench.bench_latency"]
        # Phase 1: the bridge.
        mav_port = free_port(socket.SOCK_DGRAM)
        zenoh_ep = f"tcp/127.0.0.1:{free_port()}"
        sets = [f"buses.mavlink.port={mav_port}", f'zenoh.listen=["{zenoh_ep}"]',
                "buses.can.socketcand_port=0", "buses.can.virtual=false"]
        cmd = [*me, "--serve", str(tmpdir / "ep.json"), str(tmpdir / "steps.json")]
        for s in sets:
            cmd += ["--set", s]
        proc = subprocess.Popen(cmd, cwd=REPO)
        try:
            ep = wait_file(tmpdir / "ep.json", proc)
            c = Collector()
            bridge_clients(ep, mav_port, c)
            c.run_for(args.seconds)
        finally:
            proc.send_signal(signal.SIGTERM)
            proc.wait(30)
        bridge_lat = bridge_latencies(c.events, json.loads((tmpdir / "steps.json").read_text()))
        # Phase 2: the bare transports, same kinds, sizes and rates.
        udp_port = free_port(socket.SOCK_DGRAM)
        zenoh_ep = f"tcp/127.0.0.1:{free_port()}"
        proc = subprocess.Popen([*me, "--bare", str(udp_port), zenoh_ep,
                                 str(tmpdir / "bare.json")], cwd=REPO)
        try:
            info = wait_file(tmpdir / "bare.json", proc)
            c2 = Collector()
            bare_clients(info, udp_port, zenoh_ep, c2)
            c2.run_for(args.seconds)
        finally:
            proc.send_signal(signal.SIGTERM)
            proc.wait(30)
        bare_lat = {
            name: [key if kind == "rtt" else when - key for (kind, key), when in evs]
            for name, evs in c2.events.items()
        }

    print(f"{'bus':<26}{'bridge p50':>12}{'p95':>9}{'bare p50':>11}{'p95':>9}"
          f"{'ratio p50':>11}{'n':>7}")
    results = {}
    for name in bridge_lat:
        b, r = bridge_lat[name], bare_lat.get(name, [])
        if not b or not r:
            print(f"{name:<26} no samples (bridge {len(b)}, bare {len(r)})")
            continue
        sb, sr = stats(b), stats(r)
        ratio = sb["p50_ms"] / sr["p50_ms"]
        results[name] = {"bridge": sb, "bare": sr, "ratio_p50": ratio}
        print(f"{name:<26}{sb['p50_ms']:>10.3f}ms{sb['p95_ms']:>7.3f}ms{sr['p50_ms']:>9.3f}ms"
              f"{sr['p95_ms']:>7.3f}ms{ratio:>11.1f}{sb['n']:>7}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
