"""Lockstep throughput: control cycles per wall second with a CAN firmware that answers every
cycle, against the bare socketcand round trip measured in the same run (issue 14: >= 1000
cycles/s).

Two child processes, the client in this one:

- ``--echo``: the floor. A :class:`SocketcandServer` (the bridge's own) that sends every frame
  it receives straight back; the client sends a frame and waits for it: one bare round trip
  through python-can's socketcand client, TCP loopback and the server's service thread.
- the bridge: ``koala-bridge run --clock lockstep`` with ``[lockstep] cycle_bus = "can"``,
  ``cycle_message = "MotorCommand"``, ``period_s`` = one 10 ms step, config/default.toml
  otherwise (every bus, Zenoh, the estimator node: everything on). The client is the firmware:
  it sends ``MotorCommand`` and reads until the ``WheelOdometry`` frame stamped at the cycle's
  end; each such exchange is one control cycle = 10 ms of simulated time.

Prints both rates, the ratio (lockstep cycle time / bare round trip) and the real-time factor
the lockstep run reached. Best of ``--windows`` windows of ``--seconds`` each (the ``timeit``
convention: other processes only ever slow a window down), median beside it.

    python -m bench.bench_lockstep [--seconds 3] [--windows 3]
"""

from __future__ import annotations

import argparse
import json
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench._common import REPO, free_port


def echo(port_file: Path) -> int:
    """Child: a socketcand server that echoes every frame."""
    from koala_bridge.drivers.transports.socketcand import SocketcandServer

    server = SocketcandServer("127.0.0.1", 0, "koala0")
    port_file.write_text(str(server.endpoint.port))
    try:
        while True:
            msg = server.recv(timeout=1.0)
            if msg is not None:
                server.send(msg)
    except KeyboardInterrupt:
        return 0
    finally:
        server.close()


def wait_for(path: Path, proc: subprocess.Popen[bytes], timeout: float = 120.0) -> None:
    deadline = time.monotonic() + timeout
    while not path.exists() or not path.read_text().strip():
        if proc.poll() is not None:
            raise SystemExit(f"child exited: {proc.returncode}")
        if time.monotonic() > deadline:
            raise SystemExit(f"child did not start: {path}")
        time.sleep(0.05)


def windows(step, seconds: float, n: int) -> list[float]:  # noqa: ANN001
    """Rates (steps per wall second) of ``n`` windows of ``seconds``."""
    out = []
    for _ in range(n):
        count, t0 = 0, time.perf_counter()
        while (elapsed := time.perf_counter() - t0) < seconds:
            step()
            count += 1
        out.append(count / elapsed)
    return out


def bare_round_trips(seconds: float, n: int, tmp: Path) -> list[float]:
    import can

    port_file = tmp / "echo.port"
    child = subprocess.Popen([sys.executable, "-m", "bench.bench_lockstep", "--echo",
                              str(port_file)], cwd=REPO)
    try:
        wait_for(port_file, child)
        bus = can.Bus(interface="socketcand", host="127.0.0.1",
                      port=int(port_file.read_text()), channel="koala0")
        try:
            msg = can.Message(arbitration_id=0x100, data=bytes(4), is_extended_id=False)

            def step() -> None:
                bus.send(msg)
                if bus.recv(5.0) is None:
                    raise SystemExit("echo server did not answer")

            for _ in range(200):
                step()      # warm up
            return windows(step, seconds, n)
        finally:
            bus.shutdown()
    finally:
        child.terminate()
        child.wait(30)


def lockstep_cycles(seconds: float, n: int, tmp: Path) -> tuple[list[float], float]:
    import can
    from koala_bridge.drivers.can_codec import KoalaCanCodec, load_koala_dbc
    from koala_bridge.drivers.messages import MotorCommandFrame, WheelOdometryFrame

    endpoints = tmp / "endpoints.json"
    child = subprocess.Popen(
        [sys.executable, "-m", "koala_bridge", "run", "--clock", "lockstep",
         "--endpoints-file", str(endpoints), "--log-level", "WARNING",
         "--set", 'lockstep.cycle_bus="can"', "--set", 'lockstep.cycle_message="MotorCommand"',
         "--set", "lockstep.period_s=0.01", "--set", "buses.can.socketcand_port=0",
         "--set", f"buses.mavlink.port={free_port(socket.SOCK_DGRAM)}",
         "--set", f'zenoh.listen=["tcp/127.0.0.1:{free_port()}"]'],
        cwd=REPO, stdout=subprocess.DEVNULL,
    )
    try:
        wait_for(endpoints, child)
        ep = json.loads(endpoints.read_text())
        sc = ep["can"]["socketcand"]
        codec = KoalaCanCodec(load_koala_dbc(ep["can"]["dbc"]))
        bus = can.Bus(interface="socketcand", host=sc["host"], port=sc["port"],
                      channel=sc["channel"])
        state = {"k": 0, "t": -1.0}
        speeds = (0.1, 0.12)        # an arc: every sample distinct

        def cycle() -> None:
            bus.send(codec.encode(MotorCommandFrame(*speeds)))
            state["k"] += 1
            end = state["k"] * 0.01 - 1e-9
            while state["t"] < end:
                msg = bus.recv(5.0)
                if msg is None:
                    raise SystemExit("the bridge sent no odometry")
                if isinstance(codec.decode(msg), WheelOdometryFrame):
                    state["t"] = max(state["t"], msg.timestamp)

        for _ in range(200):
            cycle()         # warm up (also leaves the hold at t = 0)
        t0, k0 = time.perf_counter(), state["k"]
        rates = windows(cycle, seconds, n)
        rtf = (state["k"] - k0) * 0.01 / (time.perf_counter() - t0)
        bus.shutdown()
        return rates, rtf
    finally:
        child.terminate()
        child.wait(30)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=3.0, help="per window (default 3)")
    ap.add_argument("--windows", type=int, default=3, help="(default 3)")
    ap.add_argument("--echo", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.echo is not None:
        return echo(args.echo)
    with tempfile.TemporaryDirectory(prefix="bench-lockstep-") as d:
        tmp = Path(d)
        bare = bare_round_trips(args.seconds, args.windows, tmp)
        cycles, rtf = lockstep_cycles(args.seconds, args.windows, tmp)
    best_bare, best_cyc = max(bare), max(cycles)
    print(f"bare socketcand round trip : {best_bare:8.0f} /s  "
          f"(median {statistics.median(bare):.0f})")
    print(f"lockstep control cycles    : {best_cyc:8.0f} /s  "
          f"(median {statistics.median(cycles):.0f}; target >= 1000)  "
          f"real-time factor {rtf:.1f}")
    print(f"ratio cycle time / bare round trip: {best_bare / best_cyc:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
