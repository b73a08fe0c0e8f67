"""Latency per bus: from a sample's simulation to its decode at a client, as a ratio to the bare
transport's latency measured in the same run.

Two child processes, clients in this one:

- ``--serve``: a bridge (`koala_bridge.runtime.sim_source.SimulatedRobotSource`, real-time
  clock, the robot driving so that every encoder sample is distinct) that logs, for every step,
  ``time.monotonic()`` right after the simulator produced the step's readings. CLOCK_MONOTONIC is
  system-wide on Linux, so the client's decode time minus that is the sample's latency.
- ``--bare``: the bare transports: the same kinds of link (a pty, a minimal socketcand server on
  TCP, a pty carrying slcan lines, UDP datagrams, a Zenoh publisher) carrying the bridge's own
  frames (range frames IR and sonar, socketcand ``< frame >`` elements and slcan lines for the
  odometry and the gyro, MAVLink ``SCALED_IMU``, the ``sensors/odometry`` JSON) at the same
  rates, in the bridge's order, all of a step's frames in one burst every 10 ms from one writer
  thread, each frame stamped with ``time.monotonic()`` just before it is written.

Why one burst per step: the clients share one interpreter here, so clients woken together queue
for it. The bridge wakes them together (a step writes every bus within ~0.3 ms); a floor with
one writer thread per link, each on its own phase, woke them one at a time and measured a floor
the bridge could not reach by construction (2026-11-25, one client at a time: bare mavlink p50
0.035 ms, socketcand 0.025 ms; with all six clients: 0.085 ms and 0.039 ms). The floor also
writes what the bridge writes besides the measured frames (the gyro frame after each odometry
frame, the sonar frames): the clients read and parse those too.

Clients: pyserial + RangeFrameDecoder (range frames, keyed by sample time), python-can
socketcand and slcan (WheelOdometry, keyed by encoder count), pymavlink (SCALED_IMU, keyed by
time_boot_ms), Zenoh (sensors/odometry, keyed by t); K-Team is request/response, so its figure is
the round trip of ``H`` against a pty that echoes each line back (CR -> CR LF).

    .venv/bin/python -m bench.bench_latency --seconds 10
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
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

def bare(udp_port: int, zenoh_endpoint: str, ready_file: Path, log_file: Path) -> int:
    """The same frames as the bridge's (bytes, sizes, rates, order within a step), written by one
    thread with nothing else to do: the floor. It logs ``time.monotonic()`` just before each
    write, keyed as the clients key the bridge's samples."""
    import pty as ptymod
    import tty

    import can
    import zenoh
    from koala_bridge.core.topics import OdometryMessage, OdometryTruth
    from koala_bridge.drivers.can_codec import KoalaCanCodec
    from koala_bridge.drivers.mavlink_codec import CompassEncoder, MavlinkIdentity
    from koala_bridge.drivers.messages import CompassSample, GyroFrame, RangeFrame, RangeKind
    from koala_bridge.drivers.messages import WheelOdometryFrame as Odo
    from koala_bridge.drivers.rangeframes import encode_range_frame
    from koala_bridge.drivers.transports.slcan import format_slcan_frame
    from koala_bridge.drivers.transports.socketcand import format_frame_element

    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    log: dict[str, list[tuple[str, Any, float]]] = {}
    codec = KoalaCanCodec()

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
    publisher = session.declare_publisher("bench/sensors/odometry")
    mav = CompassEncoder(MavlinkIdentity(1, 1))

    # The socketcand connection the stepper writes to once its handshake is done (one client).
    socketcand_conn: list[socket.socket] = []

    def log_write(name: str, frame: tuple[str, Any, bytes],
                  write: Callable[[bytes], object]) -> None:
        """Stamp ``frame`` (the key the client will decode) just before it is written."""
        kind, key, data = frame
        log.setdefault(name, []).append((kind, key, time.monotonic()))
        try:
            write(data)
        except OSError:
            pass  # no reader yet, or it has gone

    def stepper() -> None:
        """The bridge's step, minus everything but the writes: every 10 ms, the frames of that
        step on every link, in the order the bridge's loop writes them (range frames, CAN
        odometry then gyro on socketcand then slcan, MAVLink, Zenoh), each stamped just before
        its write. One burst per step as the bridge's, so the clients are woken together as by
        the bridge (with one writer thread per link they were woken one at a time, and the
        clients, sharing one interpreter, did not queue for it)."""
        t0 = time.monotonic()
        k = 0
        while not stop.is_set():
            k += 1
            delay = t0 + k * 0.01 - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            if k % 5 == 0:  # IR at 20 Hz
                log_write("rangefinders (pty)", range_frame(k // 5),
                          lambda b: os.write(frame_master, b))
            if k % 20 == 0:  # sonar at 5 Hz: written, not measured
                log_write("-", ("t_us", 0, sonar_frame(k // 20)),
                          lambda b: os.write(frame_master, b))
            conn = socketcand_conn[0] if socketcand_conn else None
            for msg, measured in ((odometry_msg(k), True), (gyro_msg(k), False)):
                if conn is not None:
                    element = format_frame_element(msg, msg.timestamp)
                    log_write("can.socketcand (TCP)" if measured else "-", ("ticks", k, element),
                              conn.sendall)
                if slcan_open.is_set():
                    log_write("can.slcan (pty)" if measured else "-",
                              ("ticks", k, format_slcan_frame(msg)),
                              lambda b: os.write(slcan_master, b))
            if k % 2 == 0:  # SCALED_IMU at 50 Hz
                log_write("mavlink (UDP)", mavlink_frame(k // 2),
                          lambda b: udp.sendto(b, ("127.0.0.1", udp_port)))
            log_write("zenoh (TCP)", zenoh_frame(k), publisher.put)

    def range_frame(k: int) -> tuple[str, Any, bytes]:
        t_us = (k * 50_000) & 0xFFFFFFFF  # 20 Hz
        return "t_us", t_us, encode_range_frame(RangeFrame(RangeKind.IR, k & 0xFFFF, t_us,
                                                           (512,) * 16))

    def sonar_frame(k: int) -> bytes:
        t_us = (k * 200_000) & 0xFFFFFFFF
        return encode_range_frame(RangeFrame(RangeKind.SONAR, k & 0xFFFF, t_us, (1000,) * 9))

    def gyro_msg(k: int) -> can.Message:
        msg = codec.encode(GyroFrame(0.1))
        msg.timestamp = k * 0.01
        return msg

    def odometry_msg(k: int) -> can.Message:
        msg = codec.encode(Odo(k, k))
        msg.timestamp = k * 0.01
        return msg

    def mavlink_frame(k: int) -> tuple[str, Any, bytes]:
        return "ms", k * 20, mav.scaled_imu(CompassSample(k * 20, 20.0, -5.0, -40.0))  # 50 Hz

    def zenoh_frame(k: int) -> tuple[str, Any, bytes]:
        t = round(k * 0.01, 6)
        msg = OdometryMessage(t, k, k, OdometryTruth(k, k))
        return "t", t, msg.to_bytes()

    def socketcand_server() -> None:
        """socketcand's handshake (hi, open, rawmode), then the frames, one client at a time."""
        listener.settimeout(0.5)
        while not stop.is_set():
            try:
                conn, _ = listener.accept()
            except TimeoutError:
                continue
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            conn.settimeout(5)
            try:
                conn.sendall(b"< hi >")
                buf = b""
                for _ in range(2):  # < open CHANNEL >, < rawmode >
                    while b">" not in buf:
                        buf += conn.recv(256)
                    buf = buf[buf.index(b">") + 1:]
                    conn.sendall(b"< ok >")
                time.sleep(0.05)  # the bridge's handshake grace
                socketcand_conn.append(conn)   # the stepper writes the frames from now on
                conn.settimeout(0.2)
                while not stop.is_set():   # what the client sends is ignored, until it goes
                    try:
                        if not conn.recv(256):
                            break
                    except TimeoutError:
                        continue
            except OSError:
                pass
            socketcand_conn.clear()
            conn.close()

    def echo_loop() -> None:
        import select

        while not stop.is_set():
            r, _, _ = select.select([echo_master], [], [], 0.2)
            if r:
                try:  # "H\r" -> "H\r\n": a reply line as the K-Team client reads it
                    os.write(echo_master, os.read(echo_master, 256).replace(b"\r", b"\r\n"))
                except OSError:
                    time.sleep(0.05)

    slcan_open = threading.Event()

    def slcan_commands(fd: int) -> None:
        """What the slcan client sends: its ``O`` (open) starts the frames, as on the bridge's
        adapter (python-can sleeps 2 s after opening the port: frames queued meanwhile would be
        stale); the rest is read and ignored."""
        import select

        while not stop.is_set():
            if select.select([fd], [], [], 0.2)[0]:
                try:
                    if b"O\r" in os.read(fd, 4096):
                        slcan_open.set()
                except OSError:
                    time.sleep(0.05)

    threads = [
        threading.Thread(target=stepper),
        threading.Thread(target=socketcand_server),
        threading.Thread(target=echo_loop),
        threading.Thread(target=slcan_commands, args=(slcan_master,)),
    ]
    for t in threads:
        t.start()
    ready_file.write_text(json.dumps({
        "serial": {"rangefinders": frame_path, "kteam": echo_path},
        "can": {"socketcand": {"host": "127.0.0.1", "port": tcp_port, "channel": "koala0"},
                "slcan": slcan_path},
        "zenoh": {"endpoints": [zenoh_endpoint], "prefix": "bench"},
    }))
    while not stop.is_set():
        stop.wait(0.2)
    for t in threads:
        t.join(5)
    log_file.write_text(json.dumps(log))
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


def bare_latencies(events: dict[str, list[tuple[Any, float]]],
                   log: dict[str, list[list[Any]]]) -> dict[str, list[float]]:
    """Decode time minus the bare writer's stamp of the same frame, per link."""
    out: dict[str, list[float]] = {}
    for name, evs in events.items():
        stamps = {(kind, round(key, 6) if kind == "t" else key): w
                  for kind, key, w in log.get(name, [])}
        lat = []
        for (kind, key), when in evs:
            if kind == "rtt":
                lat.append(key)
                continue
            w = stamps.get((kind, round(key, 6) if kind == "t" else key))
            if w is not None:
                lat.append(when - w)
        out[name] = lat
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=8.0, help="measuring time per phase")
    parser.add_argument("--serve", nargs=2, metavar=("READY", "LOG"), help=argparse.SUPPRESS)
    parser.add_argument("--bare", nargs=4, metavar=("UDP", "ZENOH", "READY", "LOG"),
                        help=argparse.SUPPRESS)
    parser.add_argument("--set", action="append", default=[], help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.serve:
        return serve(args.set, Path(args.serve[0]), Path(args.serve[1]))
    if args.bare:
        return bare(int(args.bare[0]), args.bare[1], Path(args.bare[2]), Path(args.bare[3]))

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
        # Phase 2: the bare transports: the same frames at the same rates, read by the same
        # clients (same decoders, same threads), so the ratio is what the bridge adds.
        udp_port = free_port(socket.SOCK_DGRAM)
        zenoh_ep = f"tcp/127.0.0.1:{free_port()}"
        proc = subprocess.Popen([*me, "--bare", str(udp_port), zenoh_ep,
                                 str(tmpdir / "bare.json"), str(tmpdir / "bare-log.json")],
                                cwd=REPO)
        try:
            info = wait_file(tmpdir / "bare.json", proc)
            c2 = Collector()
            bridge_clients(info, udp_port, c2)
            c2.run_for(args.seconds)
        finally:
            proc.send_signal(signal.SIGTERM)
            proc.wait(30)
        bare_lat = bare_latencies(c2.events,
                                  json.loads((tmpdir / "bare-log.json").read_text()))

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
