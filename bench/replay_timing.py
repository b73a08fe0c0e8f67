"""Replay timing: how far the intervals between replayed frames, as a client receives them, are
from the intervals recorded.

Records ``--duration`` simulation seconds with ``run --clock fast --record``, replays the file with
``koala-bridge replay --speed X`` and reads every bus as a client would (pyserial on the range
frames pty, python-can socketcand, a UDP socket for MAVLink). For consecutive frames i-1, i of a
bus the error is ``(arrival_i - arrival_{i-1}) - (t_i - t_{i-1}) / speed``; the script prints its
p50 / p99 / max per bus, and checks that every frame arrived, in order, unchanged.

The floor, measured in the same run just before the replay: a bare sender (this script with
``--floor-send``, no bridge code but the replay's sleep-then-spin wait) puts the recording's
MAVLink datagrams on a UDP socket on the same schedule, to a UDP reader thread here. Its p99 is
what this machine allows a timed sender at normal priority just then; the replay's p99 is
reported against it. The CPU pressure over each run (/proc/pressure/cpu, "some" avg10) says how
busy the machine was.

    .venv/bin/python -m bench.replay_timing --duration 60
"""

from __future__ import annotations

import argparse
import json
import pickle
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path

import can
import numpy as np
import serial
from koala_bridge.drivers.rangeframes import RangeFrameDecoder, encode_range_frame
from koala_bridge.recording.mcap_file import FROM_ROBOT, open_recording

REPO = Path(__file__).resolve().parents[1]
BUSES = ("serial/rangefinders", "can", "mavlink")


def _free_port(kind: int) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _koala(*args: str) -> list[str]:
    return [sys.executable, "-m", "koala_bridge", *args]


def _wait_file(path: Path, proc: subprocess.Popen[bytes], timeout: float = 30) -> dict:
    deadline = time.monotonic() + timeout
    while not path.exists():
        if proc.poll() is not None or time.monotonic() > deadline:
            raise SystemExit(f"{proc.args[3]} did not start")
        time.sleep(0.02)
    return json.loads(path.read_text())


def record(tmp: Path, duration: float) -> Path:
    path = tmp / "run.mcap"
    subprocess.run(
        _koala(
            "run",
            "--clock",
            "fast",
            "--duration",
            str(duration),
            "--record",
            str(path),
            "--set",
            f'zenoh.listen=["tcp/127.0.0.1:{_free_port(socket.SOCK_STREAM)}"]',
            "--set",
            f"buses.mavlink.port={_free_port(socket.SOCK_DGRAM)}",
            "--set",
            "buses.can.socketcand_port=0",
        ),
        cwd=REPO,
        check=True,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    return path


def replay_and_receive(
    path: Path, tmp: Path, speed: float, fifo_priority: int = 0
) -> tuple[dict[str, list], str]:
    mav_port = _free_port(socket.SOCK_DGRAM)
    udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    udp.bind(("127.0.0.1", mav_port))
    udp.settimeout(0.1)
    endpoints_file = tmp / "replay.json"
    log_path = tmp / "replay.log"
    with log_path.open("wb") as log:
        fifo = ["--fifo-priority", str(fifo_priority)] if fifo_priority else []
        proc = subprocess.Popen(
            _koala(
                "replay",
                *fifo,
                str(path),
                "--speed",
                str(speed),
                "--wait-clients",
                "20",
                "--endpoints-file",
                str(endpoints_file),
                "--set",
                f"buses.mavlink.port={mav_port}",
                "--set",
                "buses.can.slcan=false",
                "--linger",  # the client drains the last frames before the ports close
                "2",
            ),
            cwd=REPO,
            stdout=log,
            stderr=subprocess.STDOUT,
        )
    ep = _wait_file(endpoints_file, proc)
    sc = ep["can"]["socketcand"]
    got: dict[str, list[tuple[float, bytes]]] = {b: [] for b in BUSES}
    stop = threading.Event()
    with (
        serial.Serial(ep["serial"]["rangefinders"], 115200, timeout=0.05) as ranges,
        can.Bus(
            interface="socketcand", host=sc["host"], port=sc["port"], channel=sc["channel"]
        ) as bus,
    ):
        decoder = RangeFrameDecoder()

        def read_ranges() -> list[bytes]:
            return [
                encode_range_frame(f) for f in decoder.feed(ranges.read(ranges.in_waiting or 1))
            ]

        def read_can() -> list[bytes]:
            msg = bus.recv(timeout=0.05)
            return [] if msg is None else [bytes(msg.data)]

        def read_udp() -> list[bytes]:
            try:
                return [udp.recv(4096)]
            except TimeoutError:
                return []

        def loop(name: str, read: Callable[[], list[bytes]]) -> None:
            while not stop.is_set():
                try:
                    frames = read()
                except (OSError, can.CanError):
                    return
                now = time.monotonic()
                got[name] += [(now, f) for f in frames]

        threads = [
            threading.Thread(target=loop, args=a)
            for a in (
                ("serial/rangefinders", read_ranges),
                ("can", read_can),
                ("mavlink", read_udp),
            )
        ]
        for t in threads:
            t.start()
        proc.wait()
        time.sleep(0.2)
        stop.set()
        for t in threads:
            t.join()
    udp.close()
    return got, log_path.read_text()


def _cpu_pressure() -> str:
    """``some avg10`` of /proc/pressure/cpu (the share of time a task waited for a CPU)."""
    try:
        line = Path("/proc/pressure/cpu").read_text().splitlines()[0]
    except (OSError, IndexError):
        return "n/a"
    return next((f.split("=")[1] + " %" for f in line.split() if f.startswith("avg10=")), "n/a")


def floor_send(schedule: Path, port: int, speed: float) -> None:
    """Send the pickled ``(times, datagrams)`` to 127.0.0.1:``port`` on their schedule, with the
    replay's wait (sleep to ``SPIN_S`` before, then spin yielding the GIL) and nothing else."""
    from koala_bridge.runtime.replay import SPIN_S

    times, datagrams = pickle.loads(schedule.read_bytes())
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    start = time.monotonic() + 0.2
    for t, data in zip(times, datagrams, strict=True):
        due = start + (t - times[0]) / speed
        while (remaining := due - time.monotonic()) > 0:
            time.sleep(remaining - SPIN_S if remaining > SPIN_S else 0)
        sock.sendto(data, ("127.0.0.1", port))
    sock.close()


def measure_floor(path: Path, tmp: Path, speed: float) -> tuple[np.ndarray, str]:
    """Timing errors (ms) of the bare UDP sender at a reader thread, and the CPU pressure."""
    rec = open_recording(path)
    frames = [m for m in rec.topic("/bus/mavlink") if m.json()["dir"] == FROM_ROBOT]
    times = [m.t for m in frames]
    schedule = tmp / "floor.pickle"
    schedule.write_bytes(pickle.dumps((times, [m.frame_bytes() for m in frames])))
    port = _free_port(socket.SOCK_DGRAM)
    udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    udp.bind(("127.0.0.1", port))
    udp.settimeout(1.0)
    sender = subprocess.Popen(
        [sys.executable, "-m", "bench.replay_timing", "--floor-send", str(schedule), str(port)]
        + ["--speed", str(speed)],
        cwd=REPO,
    )
    arrivals = []
    try:
        while len(arrivals) < len(times):
            try:
                udp.recv(4096)
            except TimeoutError:
                if sender.poll() is not None:
                    break
                continue
            arrivals.append(time.monotonic())
    finally:
        sender.wait()
        udp.close()
    pressure = _cpu_pressure()
    a = np.array(arrivals)
    return np.abs(np.diff(a) - np.diff(np.array(times[: a.size])) / speed) * 1e3, pressure


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=60.0)
    parser.add_argument("--speed", type=float, default=1.0)
    parser.add_argument(
        "--fifo-priority",
        type=int,
        default=0,
        metavar="P",
        help="replay --fifo-priority P (SCHED_FIFO; needs CAP_SYS_NICE); the client side can be "
        "raised too by starting this script under chrt -f",
    )
    parser.add_argument(
        "--floor-send", nargs=2, metavar=("SCHEDULE", "PORT"), help=argparse.SUPPRESS
    )
    args = parser.parse_args(argv)
    if args.floor_send:
        floor_send(Path(args.floor_send[0]), int(args.floor_send[1]), args.speed)
        return 0
    # Three reader threads share this process's GIL: hand it over every 0.5 ms (default 5 ms),
    # or a reader waits for it and the measurement shows the client's delay, not the replay's.
    sys.setswitchinterval(0.0005)
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        path = record(tmp, args.duration)
        rec = open_recording(path)
        floor, floor_pressure = measure_floor(path, tmp, args.speed)
        got, log = replay_and_receive(path, tmp, args.speed, args.fifo_priority)
        pressure = _cpu_pressure()
    fifo = f", replay under SCHED_FIFO {args.fifo_priority}" if args.fifo_priority else ""
    print(f"recording: {args.duration:g} s, replay speed {args.speed:g}{fifo}")
    print(f"{'bus':<22}{'frames':>8}{'in order':>10}{'p50 ms':>9}{'p99 ms':>9}{'max ms':>9}")
    all_err = []
    ok = True
    for b in BUSES:
        frames = [m for m in rec.topic(f"/bus/{b}") if m.json()["dir"] == FROM_ROBOT]
        sent = [m.frame_bytes() for m in frames]
        received = [f for _, f in got[b]]
        same = received == sent
        ok &= same
        if not same:
            pairs = enumerate(zip(received, sent, strict=False))
            first = next((i for i, (x, y) in pairs if x != y), None)
            print(f"{b}: received {len(received)} of {len(sent)}, first difference at {first}")
        arrivals = np.array([a for a, _ in got[b]])
        recorded = np.array([m.t for m in frames])[: len(arrivals)]
        err = np.abs(np.diff(arrivals) - np.diff(recorded) / args.speed) * 1e3
        all_err.append(err)
        print(
            f"{b:<22}{len(frames):>8}{'yes' if same else 'NO':>10}"
            f"{np.percentile(err, 50):>9.3f}{np.percentile(err, 99):>9.3f}{err.max():>9.3f}"
        )
    e = np.concatenate(all_err)
    print(
        f"{'all buses':<22}{len(e) + len(all_err):>8}{'':>10}"
        f"{np.percentile(e, 50):>9.3f}{np.percentile(e, 99):>9.3f}{e.max():>9.3f}"
    )
    print(
        f"{'floor: bare UDP sender':<22}{floor.size + 1:>8}{'':>10}"
        f"{np.percentile(floor, 50):>9.3f}{np.percentile(floor, 99):>9.3f}{floor.max():>9.3f}"
    )
    p99_floor = np.percentile(floor, 99)
    print(
        f"replay / floor at p99: mavlink {np.percentile(all_err[2], 99) / p99_floor:.2f}, "
        f"all buses {np.percentile(e, 99) / p99_floor:.2f}; CPU pressure "
        f"(some, avg10) {floor_pressure} after the floor, {pressure} after the replay"
    )
    print(log.strip().splitlines()[-1])
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
