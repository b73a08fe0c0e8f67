"""`run --source real` on a Koala 2.5 (``[real] kteam_dialect = "koala25"``): a simulated bridge
whose K-Team pty speaks koala25 plays the robot; the real source polls it (or lets it push in
auto mode), publishes ``sensors/*`` in SI, and its recording replays and calibrates.

The expected values come from the Koala 2.5 manual's units and the simulated robot's own
recording, not from the bridge's code: a ``G`` value is the simulated range in whole cm (0 below
25 cm, 1000 for no echo), ``&`` the field in whole mGauss (1 uT = 10 mGauss), ``N`` the yaw rate
in whole 0.066 deg/s units (libkoala ``KOALA_GYRO_DEG_S``), ``P`` the encoder counters.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import signal
import subprocess
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import can
import pytest
import serial
from conftest import (
    DEFAULT_CONFIG,
    REPO,
    BridgeProcess,
    ZenohWatch,
    bridge_command,
    commented_real_block,
    free_port,
    wait_endpoints,
)
from koala_bridge.core.schema import ConfigError
from koala_bridge.drivers.can_codec import KoalaCanCodec
from koala_bridge.drivers.dialects import dialect
from koala_bridge.drivers.messages import KteamReply, MotorCommandFrame
from koala_bridge.recording.mcap_file import FROM_ROBOT, TO_ROBOT, Recording, open_recording
from koala_bridge.runtime.real_kteam import KteamReplyDecoder
from koala_bridge.runtime.real_source import RealPorts
from koala_bridge.runtime.settings import load_config
from koala_bridge.sim.config import load_sim_config

KOALA25 = dialect("koala25")
GYRO_LSB_RAD_S = math.radians(0.066)     # libkoala KOALA_GYRO_DEG_S
TURN_MPS = 0.05                          # wheel speeds of the turn on the spot: +v left, -v right
REAL_SECONDS = 3.0


# ----------------------------------------------------------------------------- hand-made lines


def decode(line: bytes, t: float = 1.0, decoder: KteamReplyDecoder | None = None) -> list[Any]:
    reply = KOALA25.parse_reply(line)
    assert isinstance(reply, KteamReply), reply
    return [m.to_json() for m in (decoder or KteamReplyDecoder(KOALA25)).messages(t, reply)]


def test_koala25_replies_become_the_simulated_robots_messages_in_si() -> None:
    (odo,) = decode(b"p,5520,-4500")
    assert (odo["left_ticks"], odo["right_ticks"]) == (5520, -4500)
    (sonar,) = decode(b"g,50,60,180,250,200,1000,2000,0,25")
    # cm -> m; 1000 (nothing in range) and 2000 (disabled) -> null; 0 (< 25 cm) -> 0.0 m as the
    # simulator publishes a range below its min_range_m
    assert sonar["ranges"] == [0.5, 0.6, 1.8, 2.5, 2.0, None, None, 0.0, 0.25]
    (compass,) = decode(b"@,-721,1074,-2393")
    assert (compass["mx"], compass["my"], compass["mz"]) == pytest.approx((-72.1, 107.4, -239.3))
    assert decode(b"e,100,100") == []        # wheel speeds: recorded, no topic
    assert decode(b"#,Unknown command") == []


def test_a_gyro_line_is_ten_samples_oldest_first_and_overlaps_are_not_repeated() -> None:
    # newest first: sample i has z = 100 * (i + 1) (x, y arbitrary)
    fields = [v for i in range(10) for v in (7, -7, 100 * (i + 1))]
    line = ("n," + ",".join(map(str, fields))).encode()
    decoder = KteamReplyDecoder(KOALA25)
    first = decode(line, t=1.0, decoder=decoder)
    assert [m["yaw_rate"] for m in first] == pytest.approx(
        [math.radians(0.066 * 100 * k) for k in range(10, 0, -1)])
    stamps = [m["t"] for m in first]
    assert stamps[-1] == 1.0 and stamps == sorted(stamps) and len(set(stamps)) == 10
    period = (stamps[-1] - stamps[0]) / 9
    assert period == pytest.approx(1 / 95)          # the manual's 95 Hz
    # polled again 3 sample periods later: only the 3 newer samples are new
    again = decode(line, t=1.0 + 3 * period, decoder=decoder)
    assert len(again) == 3 and again[0]["t"] > stamps[-1]
    # samples before the start (t < 0) are not published
    assert len(decode(line, t=0.05)) == 5


def test_koala1_replies_are_read_as_before() -> None:
    d = KteamReplyDecoder(dialect("koala1"))
    (ir,) = d.messages(0.5, KteamReply("n", tuple(str(i) for i in range(16))))
    (odo,) = d.messages(0.5, KteamReply("h", ("3", "-4")))
    assert ir.to_json()["counts"] == list(range(16))
    assert ir.to_json()["ambient"] == [None] * 16
    assert (odo.left_ticks, odo.right_ticks) == (3, -4)


def test_real_section_koala25_keys() -> None:
    p = RealPorts.from_dict({"kteam": "loop://", "kteam_dialect": "koala25"})
    assert p.kteam_line() == {"baudrate": 115200, "bytesize": 8, "parity": "N", "stopbits": 1}
    assert RealPorts.from_dict({"kteam": "loop://"}).kteam_line() == {
        "baudrate": 38400, "bytesize": 8, "parity": "N", "stopbits": 2}
    assert RealPorts.from_dict({"kteam": "loop://", "kteam_baud": 9600}).kteam_line()[
        "baudrate"] == 9600
    with pytest.raises(ConfigError, match="did you mean 'kteam_dialect'"):
        RealPorts.from_dict({"kteam_dialct": "koala25"})
    with pytest.raises(ConfigError, match="must be one of koala1, koala25"):
        RealPorts.from_dict({"kteam": "loop://", "kteam_dialect": "koala2"})
    with pytest.raises(ConfigError, match="'kteam_poll' has 'P'.*koala1"):
        RealPorts.from_dict({"kteam": "loop://", "kteam_poll": ["P"]})
    with pytest.raises(ConfigError, match="'kteam_poll' has 'D'"):
        RealPorts.from_dict({"kteam": "loop://", "kteam_dialect": "koala25", "kteam_poll": ["D"]})
    with pytest.raises(ConfigError, match="'kteam_auto'.*koala25"):
        RealPorts.from_dict({"kteam": "loop://", "kteam_auto": 4})
    with pytest.raises(ConfigError, match="0..511"):
        RealPorts.from_dict({"kteam": "loop://", "kteam_dialect": "koala25", "kteam_auto": 512})


def test_koala25_toml_shows_the_real_section_in_its_dialect() -> None:
    """config/koala25.toml's commented [real] table is default.toml's but for kteam_dialect."""
    shown = RealPorts.from_dict(commented_real_block(DEFAULT_CONFIG.parent / "koala25.toml"))
    assert shown == dataclasses.replace(RealPorts(), kteam_dialect="koala25")


# ----------------------------------------------------------------------------- a robot on a pty


def turning_koala25(bridge: Callable[..., BridgeProcess], robot_rec: Path) -> BridgeProcess:
    """A simulated Koala 2.5 (ideal sensors and drive) turning on the spot, recorded, in real
    time; returns once its own gyro shows the steady turn."""
    robot = bridge(clock="realtime", sets=["buses.kteam.dialect=koala25"],
                   extra=["--record", str(robot_rec)])
    sc = robot.endpoints["can"]["socketcand"]
    base = load_sim_config(load_config(DEFAULT_CONFIG)).robot.wheel_base_m
    steady = -2 * TURN_MPS / base                    # (v_right - v_left) / wheel base
    watch = ZenohWatch(robot.endpoints["zenoh"]["endpoints"][0], robot.prefix)
    try:
        with can.Bus(interface="socketcand", host=sc["host"], port=sc["port"],
                     channel=sc["channel"]) as client:
            client.send(KoalaCanCodec().encode(MotorCommandFrame(TURN_MPS, -TURN_MPS)))
            watch.wait_for("sensors/gyro", lambda m: abs(m["yaw_rate"] - steady) < 1e-9)
    finally:
        watch.close()
    return robot


def run_real(tmp_path: Path, name: str, real_table: str,
             duration: float = REAL_SECONDS) -> tuple[Path, Path]:
    """``koala-bridge run --source real`` for ``duration`` s with ``[real]`` = ``real_table``;
    returns (recording, log)."""
    config = tmp_path / f"{name}.toml"
    config.write_text(DEFAULT_CONFIG.read_text() + "\n[real]\n" + real_table)
    rec, log_path = tmp_path / f"{name}.mcap", tmp_path / f"{name}.log"
    with log_path.open("wb") as log:
        proc = subprocess.run(
            bridge_command(
                "run", "--source", "real", "--config", str(config), "--duration",
                str(duration), "--record", str(rec),
                "--set", f'zenoh.listen=["tcp/127.0.0.1:{free_port()}"]',
                "--set", f"buses.mavlink.port={free_port('udp')}",
            ),
            cwd=REPO, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
            timeout=120,
        )
    assert proc.returncode == 0, log_path.read_text()
    return rec, log_path


def values(rec: Recording, key: str) -> list[Any]:
    pick = {
        "odometry": lambda m: (m["left_ticks"], m["right_ticks"]),
        "sonar": lambda m: tuple(m["ranges"]),
        "gyro": lambda m: m["yaw_rate"],
        "compass": lambda m: (m["mx"], m["my"], m["mz"]),
    }[key]
    return [pick(m.json()) for m in rec.topic(f"sensors/{key}")]


def as_koala25_reads(robot: Recording) -> dict[str, set[Any]]:
    """What a Koala 2.5 would answer for each message the simulated robot published, quantised
    as its manual says, converted back to SI: the set a real-source reading must fall in."""

    def cm(r: float | None) -> float | None:
        if r is None or not math.isfinite(r):
            return None                              # 1000: nothing in range
        if r < 0.25:
            return 0.0                               # 0: closer than 25 cm
        return min(250, round(r * 100)) / 100        # whole cm, at most 250

    return {
        "odometry": set(values(robot, "odometry")),
        "sonar": {tuple(cm(r) for r in rs) for rs in values(robot, "sonar")},
        "gyro": {round(w / GYRO_LSB_RAD_S) * GYRO_LSB_RAD_S for w in values(robot, "gyro")},
        "compass": {tuple(round(b * 10) / 10 for b in f) for f in values(robot, "compass")},
    }


def assert_read_what_the_robot_had(real: Recording, robot: Recording) -> None:
    possible = as_koala25_reads(robot)
    for key in ("odometry", "sonar", "gyro", "compass"):
        got = values(real, key)
        assert len(got) >= 5, key
        for v in got:
            if key == "gyro":
                assert any(abs(v - p) < 1e-9 for p in possible[key]), (key, v)
            elif key == "compass":
                assert any(max(abs(a - b) for a, b in zip(v, p, strict=True)) < 1e-9
                           for p in possible[key]), (key, v)
            else:
                assert v in possible[key], (key, v)
    assert len(set(values(real, "odometry"))) > 3, "the robot was turning"
    # The turn, in SI: every gyro sample is the steady yaw rate within half an LSB.
    base = json.loads(robot.metadata["world"]["json"])["robot"]["wheel_base_m"]
    steady = -2 * TURN_MPS / base
    assert all(abs(w - steady) <= GYRO_LSB_RAD_S / 2 + 1e-12 for w in values(real, "gyro"))


def test_real_source_polls_a_koala25_and_its_recording_replays_and_calibrates(
    bridge: Callable[..., BridgeProcess], tmp_path: Path
) -> None:
    robot_rec = tmp_path / "robot.mcap"
    robot = turning_koala25(bridge, robot_rec)
    real_rec, _ = run_real(tmp_path, "real", f"""
kteam = "{robot.endpoints["serial"]["kteam"]}"
kteam_dialect = "koala25"
kteam_poll = ["P", "G", "N", "&", "E"]
kteam_poll_hz = 10.0
""")
    assert robot.stop() == 0
    real, robot_recording = open_recording(real_rec), open_recording(robot_rec)
    assert real.complete
    assert real.metadata["koala-bridge"]["kteam_dialect"] == "koala25"
    assert_read_what_the_robot_had(real, robot_recording)
    kteam = real.topic("/bus/serial/kteam")
    asked = {m.frame_bytes() for m in kteam if m.json()["dir"] == TO_ROBOT}
    replies = [m.frame_bytes() for m in kteam if m.json()["dir"] == FROM_ROBOT]
    # the firmware version once at the start (as libkoala's start-up), then the polls
    assert asked == {b"B\r", b"P\r", b"G\r", b"N\r", b"&\r", b"E\r"}
    assert replies and all(r.endswith(b"\n") and not r.endswith(b"\r\n") for r in replies)
    assert {r[:1] for r in replies} == {b"b", b"p", b"g", b"n", b"@", b"e"}
    assert replies[0] == b"b,A-02\n"
    # The estimator node took the same lines in the same dialect (status counts what it took;
    # the last status comes after the last poll)
    took = real.topic("status")[-1].json()["localisation"]["frames"]
    assert {k: took.get(k) for k in ("odometry", "sonar", "gyro", "compass")} == {
        k: len(values(real, k)) for k in ("odometry", "sonar", "gyro", "compass")}

    # replay: the recorded Koala 2.5 answers a libkoala-style client in its own dialect
    answers = replay_kteam(real_rec, tmp_path,
                           [b"&\r", b"P\r", b"E\r", b"U\r", b"D,1\r", b"B\r"])
    last = {r[:1]: r for r in replies}
    assert answers[:3] == [last[b"@"], last[b"p"], last[b"e"]]
    assert answers[3] == b"#,Not recorded\n"                              # U was never asked
    assert answers[4] == b"#,Protocol error\n"                            # bad arity
    assert answers[5] == b"b,A-02\n"              # the robot's version, asked at the start
    # ... and the real source reads the replay as it read the robot: every value it publishes
    # is one the recording holds
    with replaying(real_rec, tmp_path, "replay-real") as (pty, _):
        again_rec, _ = run_real(tmp_path, "again", f"""
kteam = "{pty}"
kteam_dialect = "koala25"
kteam_poll = ["P", "&"]
""", duration=1.0)
    again = open_recording(again_rec)
    for key in ("odometry", "compass"):
        assert values(again, key), key
        assert set(values(again, key)) <= set(values(real, key)), key

    # calibrate: runs on the recording of a real robot; without truth/pose the gyro is referred
    # to the compass heading, and the streams without a reference are skipped and said so
    out = tmp_path / "cal"
    cal = subprocess.run(
        bridge_command("calibrate", str(real_rec), "--config", str(DEFAULT_CONFIG),
                       "--out", str(out)),
        cwd=REPO, capture_output=True, text=True, timeout=300,
    )
    assert cal.returncode == 0, cal.stdout + cal.stderr
    # (every stream of the input is calibrated or named with what it lacks, issue 16)
    assert "not calibrated: odometry: no reference pose: the bundle has no truth_pose.csv" \
        in cal.stderr
    assert "range:sonar: true_range is empty in every row" in cal.stderr
    streams = json.loads((out / "report.json").read_text())["streams"]
    assert {s["stream"] for s in streams} == {"gyro", "compass"}


@contextlib.contextmanager
def replaying(rec: Path, tmp_path: Path, name: str) -> Iterator[tuple[str, Path]]:
    """``koala-bridge replay REC`` (K-Team only, ports open until the end); yields its K-Team
    pty and log, then stops it with SIGINT and checks it ended cleanly."""
    endpoints_file, log_path = tmp_path / f"{name}.json", tmp_path / f"{name}.log"
    with log_path.open("wb") as log:
        proc = subprocess.Popen(
            bridge_command(
                "replay", str(rec), "--bus", "serial/kteam", "--wait-clients", "120",
                "--linger", "120", "--endpoints-file", str(endpoints_file),
                "--set", f'zenoh.listen=["tcp/127.0.0.1:{free_port()}"]',
                "--set", f"buses.mavlink.port={free_port('udp')}",
                "--set", "buses.can.socketcand_port=0",
            ),
            cwd=REPO, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
        )
    try:
        yield wait_endpoints(proc, endpoints_file, log_path)["serial"]["kteam"], log_path
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=60) == 0, log_path.read_text()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def replay_kteam(rec: Path, tmp_path: Path, commands: list[bytes]) -> list[bytes]:
    """Once a replay of ``rec`` has sent every frame, send ``commands`` on its K-Team pty and
    return the lines it answers."""
    with replaying(rec, tmp_path, "replay") as (pty, log_path), \
            serial.Serial(pty, 115200, timeout=30) as port:
        deadline = time.monotonic() + 120
        while "Every frame sent" not in log_path.read_text():
            assert time.monotonic() < deadline, log_path.read_text()
            time.sleep(0.02)
        answers = []
        for c in commands:
            port.write(c)
            answers.append(port.read_until(b"\n"))
    return answers


def test_real_source_in_koala25_auto_mode(
    bridge: Callable[..., BridgeProcess], tmp_path: Path
) -> None:
    robot_rec = tmp_path / "robot.mcap"
    robot = turning_koala25(bridge, robot_rec)
    bits = 1 | 4 | 32 | 256            # sonar, position, gyro, magnetometer (libkoala bits)
    real_rec, _ = run_real(tmp_path, "auto", f"""
kteam = "{robot.endpoints["serial"]["kteam"]}"
kteam_dialect = "koala25"
kteam_auto = {bits}
""")
    assert robot.stop() == 0
    real = open_recording(real_rec)
    assert_read_what_the_robot_had(real, open_recording(robot_rec))
    kteam = real.topic("/bus/serial/kteam")
    asked = [m.frame_bytes() for m in kteam if m.json()["dir"] == TO_ROBOT]
    pushed = [m.frame_bytes() for m in kteam if m.json()["dir"] == FROM_ROBOT]
    # the version, auto mode on at the start, off at the end
    assert asked == [b"B\r", f"A,{bits}\r".encode(), b"A,0\r"]
    assert pushed[:2] == [b"b,A-02\n", b"a\n"]             # B's reply, A's acknowledgement
    # then the pushed lines (and, if it came before the port closed, A,0's "a")
    data = pushed[2:-1] if pushed[-1] == b"a\n" else pushed[2:]
    assert {p[:1] for p in data} == {b"g", b"p", b"n", b"@"}
    took = real.topic("status")[-1].json()["localisation"]["frames"]
    assert all(took.get(k, 0) > 0 for k in ("odometry", "sonar", "gyro", "compass")), took

    # the replay of this recording pushes its recorded lines to a client in auto mode: the real
    # source, in auto mode again, publishes values the recording holds (and nothing else)
    with replaying(real_rec, tmp_path, "replay-auto") as (pty, _):
        again_rec, _ = run_real(tmp_path, "again-auto", f"""
kteam = "{pty}"
kteam_dialect = "koala25"
kteam_auto = {4 | 256}
""", duration=1.0)
    again = open_recording(again_rec)
    again_pushed = [m.frame_bytes() for m in again.topic("/bus/serial/kteam")
                    if m.json()["dir"] == FROM_ROBOT]
    assert {p[:1] for p in again_pushed} == {b"b", b"a", b"p", b"@"}
    for key in ("odometry", "compass"):
        assert values(again, key), key
        assert set(values(again, key)) <= set(values(real, key)), key


def test_a_real_source_in_the_wrong_dialect_says_so(
    bridge: Callable[..., BridgeProcess], tmp_path: Path
) -> None:
    # the classic dialect's polls against a Koala 2.5: N carries 30 gyro values there, not 16 IR
    # counts, and H is a PID setting without a reply field
    robot = bridge(clock="realtime", sets=["buses.kteam.dialect=koala25"])
    _, log_path = run_real(tmp_path, "wrong", f"""
kteam = "{robot.endpoints["serial"]["kteam"]}"
kteam_dialect = "koala1"
kteam_poll = ["N", "H"]
""", duration=2.0)
    assert robot.stop() == 0
    log = log_path.read_text()
    assert log.count("not understood in the koala1 dialect") == 1, log   # said once, not per reply
    assert "is [real] kteam_dialect right for this robot" in log
