#!/usr/bin/env python3
"""A tiny lockstep firmware for the campaign tests (K-Team serial only, pyserial).

Seed 0 stands still; any other seed drives straight ahead at ``--speed`` (K-Team ``D`` units)
and never looks: in a lab world it meets a wall. One ``D`` per control period for
``--duration`` simulated seconds (minus one period, so that it ends before the bridge does),
then ``D,0,0`` and the port is closed, which ends a lockstep run. It writes a JSON report with
its cycle count and, with ``--estimate X,Y``, a fixed "estimate" (for the localisation check).

    python _campaign_firmware.py ENDPOINTS.json --seed 1 --duration 20 --report r.json
"""

from __future__ import annotations

import argparse
import json
import sys

import serial


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("endpoints")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--duration", type=float, default=20.0, help="simulated seconds")
    ap.add_argument("--period", type=float, default=0.05, help="[lockstep] period_s")
    ap.add_argument("--speed", type=int, default=40)
    ap.add_argument("--report")
    ap.add_argument("--estimate", help="X,Y reported as the final estimate")
    ap.add_argument("--exit", type=int, default=0, help="exit status")
    ap.add_argument("--no-cycle", action="store_true",
                    help="read the endpoints file and exit: simulated time never moves")
    args = ap.parse_args(argv)
    with open(args.endpoints) as f:
        ep = json.load(f)
    if args.no_cycle:
        return args.exit
    port = serial.Serial(ep["serial"]["kteam"], 115200, timeout=10)
    speed = 0 if args.seed == 0 else args.speed
    cycles = int(round(args.duration / args.period)) - 1
    for _ in range(cycles):
        port.write(f"D,{speed},{speed}\n".encode())
        if port.readline().strip() != b"d":
            sys.exit("D not acknowledged")
    port.write(b"D,0,0\n")
    port.readline()
    port.close()
    report: dict[str, object] = {"cycles": cycles}
    if args.estimate:
        x, y = (float(v) for v in args.estimate.split(","))
        report["estimate"] = {"t": cycles * args.period, "x": x, "y": y}
    if args.report:
        with open(args.report, "w") as f:
            json.dump(report, f)
    return args.exit


if __name__ == "__main__":
    sys.exit(main())
