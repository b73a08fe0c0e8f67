"""What the Foxglove scene costs the fast-clock loop: live with a client connected and
subscribed to every channel, and in a recording.

    python -m bench.bench_foxglove [--seconds S] [--window W]

What is timed: one :class:`koala_bridge.runtime.sim_source.SimulatedRobotSource` on
``config/default.toml`` with everything on (every bus, Zenoh, the localisation node; the
bench_fast.py set-up), the robot driving an arc, in alternating windows of ``W`` simulated
seconds, each with another tap:

- ``bare``: no tap (the floor of this comparison, measured in the same run);
- ``live``: a :class:`runtime.foxglove_io.FoxgloveTap` with the live server, and a client in
  another process (``--client``, the protocol from its spec) subscribed to every channel the
  server advertises and reading everything it is sent;
- ``record``: the recorder alone (the bridge's JSON channels and bus frames);
- ``record+scene``: the recorder behind a FoxgloveTap writing the scene channels too.

Each figure is the best window (the least disturbed on a shared machine, the ``timeit``
convention) as us per step and the loop thread's CPU per step; the ratios live / bare and
record+scene / record are the scene's added cost (issue 18's target: live <= 1.10).

Measured on the 2-core build machine (Python 3.11), 2026-11-27, other jobs loading it;
``python -m bench.bench_foxglove --seconds 40``: see docs/foxglove.md "Cost".
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from bench._common import REPO, fast_bridge_config, per_step_us

VARIANTS = ("bare", "live", "record", "record+scene")


def client(url: str) -> int:
    """Subscribe to every advertised channel and read until the server goes; print the count
    of messages per topic as JSON (a Foxglove app's share of the work, in its own process)."""
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    counts: dict[str, int] = {}
    topics: dict[int, str] = {}
    subs: dict[int, str] = {}
    with connect(url, subprotocols=["foxglove.sdk.v1", "foxglove.websocket.v1"],  # type: ignore[list-item]
                 proxy=None, max_size=None) as ws:
        try:
            for frame in ws:
                if isinstance(frame, str):
                    msg = json.loads(frame)
                    if msg.get("op") == "advertise":
                        new = []
                        for ch in msg["channels"]:
                            topics[ch["id"]] = ch["topic"]
                            sub = len(subs) + 1
                            subs[sub] = ch["topic"]
                            new.append({"id": sub, "channelId": ch["id"]})
                        ws.send(json.dumps({"op": "subscribe", "subscriptions": new}))
                elif frame[0] == 1:
                    topic = subs[int.from_bytes(frame[1:5], "little")]
                    counts[topic] = counts.get(topic, 0) + 1
        except ConnectionClosed:  # the server stopped: report what came
            pass
    print(json.dumps(counts))
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=20.0, help="wall seconds in all (default 20)")
    ap.add_argument("--window", type=float, default=4.0,
                    help="simulated seconds per window (default 4)")
    ap.add_argument("--client", metavar="URL", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.client:
        return client(args.client)

    from koala_bridge.recording.mcap_file import Recorder
    from koala_bridge.runtime.foxglove_io import FoxgloveServer, FoxgloveTap
    from koala_bridge.runtime.foxglove_scene import SceneTranslator
    from koala_bridge.runtime.settings import BridgeSettings
    from koala_bridge.runtime.sim_source import SimulatedRobotSource

    config = fast_bridge_config()
    settings = BridgeSettings.from_config(config)
    service = SimulatedRobotSource(config, settings)
    steps = round(args.window / service.dt)
    stop = threading.Event()
    wall: dict[str, list[float]] = {v: [] for v in VARIANTS}
    cpu: dict[str, list[float]] = {v: [] for v in VARIANTS}
    server = FoxgloveServer("127.0.0.1", 0)
    viewer = None
    with tempfile.TemporaryDirectory() as tmp:
        recorder = Recorder(Path(tmp) / "bench.mcap", world=service.world_answer())
        translator = SceneTranslator(service.world_answer(), settings.robot_name)
        taps = {
            "bare": None,
            "live": FoxgloveTap(translator, server=server),
            "record": recorder,
            "record+scene": FoxgloveTap(translator, recorder, recorder=recorder),
        }
        service.open()
        try:
            service.arbiter.set(0.10, 0.14, "bench")
            service.tap = taps["live"]
            service.run(stop, duration_s=0.5)  # warm-up; every channel advertised
            viewer = subprocess.Popen(
                [sys.executable, "-m", "bench.bench_foxglove", "--client", server.url],
                cwd=REPO, stdout=subprocess.PIPE, text=True)
            deadline = time.monotonic() + 60
            while not server.subscribed() and time.monotonic() < deadline:
                service.run(stop, duration_s=0.2)  # the client connects and subscribes
            if not server.subscribed():
                raise SystemExit("the client did not subscribe in 60 s")
            end = time.perf_counter() + args.seconds
            while time.perf_counter() < end or min(len(v) for v in wall.values()) < 2:
                for variant in VARIANTS:
                    service.tap = taps[variant]  # type: ignore[assignment]
                    c0, t0 = time.thread_time(), time.perf_counter()
                    service.run(stop, duration_s=args.window)
                    wall[variant].append(time.perf_counter() - t0)
                    cpu[variant].append(time.thread_time() - c0)
        finally:
            service.close()
            server.close()
            recorder.close()
            received = {}
            if viewer is not None:
                out, _ = viewer.communicate(timeout=30)
                received = json.loads(out.strip().splitlines()[-1]) if out.strip() else {}

    dt = service.dt
    us, med, cpu_us = per_step_us(wall, cpu, steps)
    print(f"bridge loop, config/default.toml, every bus + Zenoh + localisation, fast clock, "
          f"{len(wall['bare'])} windows of {args.window:g} sim-s per variant (best / median)")
    for k in VARIANTS:
        print(f"  {k:14s} {us[k]:7.1f} us/step (median {med[k]:7.1f}; CPU {cpu_us[k]:7.1f})"
              f"  = {dt * 1e6 / us[k]:6.1f} x real time")
    live, rec = us["live"] / us["bare"], us["record+scene"] / us["record"]
    print(f"  live / bare            {live:5.3f}  (CPU "
          f"{cpu_us['live'] / cpu_us['bare']:.3f}; median {med['live'] / med['bare']:.3f})  "
          f"target <= 1.10: {'met' if live <= 1.10 else 'NOT met'}")
    print(f"  record+scene / record  {rec:5.3f}  (CPU "
          f"{cpu_us['record+scene'] / cpu_us['record']:.3f}; median "
          f"{med['record+scene'] / med['record']:.3f})")
    print(f"  the client received {sum(received.values())} messages on {len(received)} topics")
    return 0


if __name__ == "__main__":
    sys.exit(main())
