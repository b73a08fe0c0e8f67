"""Smoke test of koala-bridge as a user installs it (`make smoke`, part of `make test`).

Run with the python of a virtualenv where the wheel was installed (not editable); every command
runs from a fresh temporary directory outside the checkout, through the installed console script:
every --help, `config path` and `config init`, `run --clock fast --record` (shipped config and a
copied one), `export`, `calibrate` (bundle and recording, with and without --config), `replay`,
`monitor --once` and `snapshot` against a real-time run, and `python -m koala_bridge`. Paths
the bridge prints (DBC, endpoints file, recording) must exist. Exits 1 at the first failure,
with the command's output; not collected by pytest (file name).

    build/smoke-venv/bin/python tests/smoke_installed.py
"""

from __future__ import annotations

import json
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CHECKOUT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
KOALA = BIN / "koala-bridge"
TIMEOUT_S = 180


class SmokeFailure(Exception):
    pass


def free_port(kind: int) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def bus_options() -> list[str]:
    """Free loopback ports, so the smoke test runs beside a bridge or a test suite."""
    return [
        "--set", "buses.can.socketcand_port=0",
        "--set", f"buses.mavlink.port={free_port(socket.SOCK_DGRAM)}",
        "--set", f'zenoh.listen=["tcp/127.0.0.1:{free_port(socket.SOCK_STREAM)}"]',
    ]


def check(cwd: Path, *args: str | Path, expect: int = 0) -> subprocess.CompletedProcess[str]:
    """Run ``args`` in ``cwd``; fail unless it exits ``expect`` without a traceback."""
    cmd = [str(a) for a in args]
    shown = " ".join(Path(c).name if c in (str(KOALA), sys.executable) else c for c in cmd)
    shown = shown if len(shown) <= 150 else shown[:147] + "..."
    t0 = time.monotonic()
    try:
        p = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, timeout=TIMEOUT_S)
    except subprocess.TimeoutExpired as e:
        raise SmokeFailure(f"{shown}: no exit within {TIMEOUT_S} s\n{e.stdout}\n{e.stderr}") from e
    print(f"smoke: {shown}  -> {p.returncode} ({time.monotonic() - t0:.1f} s)", flush=True)
    if p.returncode != expect or "Traceback" in p.stderr:
        raise SmokeFailure(
            f"{shown}: exit {p.returncode}, expected {expect}\n"
            f"--- stdout\n{p.stdout}--- stderr\n{p.stderr}"
        )
    return p


def expect_file(path: Path, what: str) -> None:
    if not path.is_file():
        raise SmokeFailure(f"{what} names {path}, which does not exist")


def installed_package(cwd: Path) -> Path:
    """Where the smoke venv imports koala_bridge from (its site-packages, not the checkout's
    folders through an editable install); and no generic top-level names."""
    probe = (
        "import importlib.util, json, sysconfig, koala_bridge; "
        "print(json.dumps([koala_bridge.__file__, sysconfig.get_paths()['purelib'], "
        "[n for n in ('bridge', 'drivers', 'sim', 'config') if importlib.util.find_spec(n)]]))"
    )
    where, site, generic = json.loads(check(cwd, sys.executable, "-I", "-c", probe).stdout)
    package = Path(where).resolve().parent
    if package != Path(site).resolve() / "koala_bridge":
        raise SmokeFailure(f"koala_bridge is imported from {package}, not installed in {site}")
    if generic:
        raise SmokeFailure(f"the install provides generic top-level packages: {generic}")
    return package


def every_help(cwd: Path) -> None:
    names = check(
        cwd, sys.executable, "-I", "-c",
        "from koala_bridge.cli.main import SUBCOMMANDS; print(' '.join(SUBCOMMANDS))",
    ).stdout.split()
    for args in [[], *([n] for n in names), ["config", "init"], ["config", "path"]]:
        out = check(cwd, KOALA, *args, "--help").stdout
        if "usage: koala-bridge" not in out:
            raise SmokeFailure(f"koala-bridge {' '.join(args)} --help: no usage\n{out}")
    out = check(cwd, sys.executable, "-m", "koala_bridge", "--help").stdout
    if "koala-bridge" not in out:
        raise SmokeFailure(f"python -m koala_bridge --help:\n{out}")


def live_clients(cwd: Path) -> None:
    """`monitor --once` and `snapshot` against a real-time bridge, stopped by SIGTERM (exit 0)."""
    endpoints = cwd / "live.json"
    log = cwd / "live.log"
    with log.open("wb") as out:
        bridge = subprocess.Popen(
            [str(KOALA), "run", "--duration", "60", "--endpoints-file", str(endpoints),
             *bus_options()],
            cwd=cwd, stdout=out, stderr=subprocess.STDOUT,
        )
        try:
            deadline = time.monotonic() + 60
            while not endpoints.exists():
                if bridge.poll() is not None or time.monotonic() > deadline:
                    raise SmokeFailure(f"run (real time): no endpoints file\n{log.read_text()}")
                time.sleep(0.1)
            monitor = check(
                cwd, KOALA, "monitor", "--endpoints-file", endpoints, "--once", "--duration", "1"
            )
            if "truth/pose" not in monitor.stdout:
                raise SmokeFailure(f"monitor --once: no truth/pose\n{monitor.stdout}")
            check(cwd, KOALA, "snapshot", "--endpoints-file", endpoints, "--out", "snap.png")
            expect_file(cwd / "snap.png", "snapshot")
        finally:
            bridge.send_signal(signal.SIGTERM)
            try:
                code = bridge.wait(30)
            except subprocess.TimeoutExpired:
                bridge.kill()
                code = bridge.wait()
    if code != 0 or "Traceback" in log.read_text():
        raise SmokeFailure(f"run (real time) stopped by SIGTERM: exit {code}\n{log.read_text()}")
    print("smoke: koala-bridge run (real time) + monitor + snapshot, SIGTERM  -> 0", flush=True)


def smoke(cwd: Path) -> None:
    package = installed_package(cwd)
    every_help(cwd)

    shipped = Path(check(cwd, KOALA, "config", "path").stdout.strip())
    if package not in shipped.parents:
        raise SmokeFailure(f"config path {shipped} is not in the installed package {package}")
    expect_file(shipped / "default.toml", "config path")

    check(cwd, KOALA, "config", "init", "my-koala")
    for name in ("default.toml", "ideal.toml", "koala.dbc", "worlds/lab_walls_1.toml"):
        expect_file(cwd / "my-koala" / name, "config init")
    check(cwd, KOALA, "config", "init", "my-koala", expect=1)  # no overwrite without --force
    check(cwd, KOALA, "config", "init", "my-koala", "--force")

    # The shipped config, recorded: the banner and the endpoints file name files that exist.
    run = check(
        cwd, KOALA, "run", "--clock", "fast", "--duration", "3", "--record", "run.mcap",
        "--endpoints-file", "endpoints.json", *bus_options(),
    )
    endpoints = json.loads((cwd / "endpoints.json").read_text())
    expect_file(Path(endpoints["can"]["dbc"]), "the endpoints file")
    if f"CAN database (DBC)      {endpoints['can']['dbc']}" not in run.stdout:
        raise SmokeFailure(f"the banner does not name the DBC of the endpoints file\n{run.stdout}")
    if "Recorded" not in run.stdout:
        raise SmokeFailure(f"run --record: no 'Recorded' line\n{run.stdout}")
    if "ETA" in run.stdout + run.stderr:  # the live progress line is for a terminal only
        raise SmokeFailure(f"run, piped, printed the progress line\n{run.stdout}{run.stderr}")
    expect_file(cwd / "run.mcap", "run --record")

    # A copied config, CAN off and on: no DBC traceback either way.
    check(
        cwd, KOALA, "run", "--config", "my-koala/ideal.toml", "--clock", "fast", "--duration", "1",
        *bus_options(),
    )

    check(cwd, KOALA, "export", "run.mcap", "--bundle", "bundle")
    expect_file(cwd / "bundle" / "meta.json", "export")
    check(cwd, KOALA, "calibrate", "bundle", "--out", "cal", "--no-plots", "--quiet")
    expect_file(cwd / "cal" / "report.md", "calibrate")
    check(
        cwd, KOALA, "calibrate", "run.mcap", "--config", "my-koala/default.toml",
        "--out", "cal-config", "--write-config", "cal-config/koala.toml", "--quiet",
    )
    expect_file(cwd / "cal-config" / "koala.toml", "calibrate --write-config")

    replay = check(
        cwd, KOALA, "replay", "run.mcap", "--speed", "10", "--no-zenoh", "--linger", "0",
        "--endpoints-file", "replay.json", *bus_options()[:4],
    )
    expect_file(Path(json.loads((cwd / "replay.json").read_text())["can"]["dbc"]), "replay")
    if "Replay done" not in replay.stdout:
        raise SmokeFailure(f"replay: no 'Replay done'\n{replay.stdout}")

    live_clients(cwd)


def main() -> int:
    if not KOALA.is_file():
        print(f"smoke: no console script {KOALA}; run me with the installed venv's python",
              file=sys.stderr)
        return 1
    t0 = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="koala-smoke-") as tmp:
        try:
            smoke(Path(tmp))
        except SmokeFailure as e:
            print(f"smoke: FAILED: {e}", file=sys.stderr)
            return 1
    print(f"smoke: the installed koala-bridge works ({time.monotonic() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
