"""Fault injection (bridge/runtime/faults.py, docs/faults.md): the spec, the ``--fault`` grammar,
the seed, each kind's effect, events and counts, and the simulator's hooks (sim/simulator.py)."""

from __future__ import annotations

import dataclasses
import math
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import tomli_w
from koala_bridge.core.schema import ConfigError
from koala_bridge.drivers.mavlink_codec import CompassDecoder, CompassEncoder, MavlinkIdentity
from koala_bridge.drivers.messages import CompassSample, RangeFrame, RangeKind, Reject
from koala_bridge.drivers.rangeframes import decode_range_frame, encode_range_frame
from koala_bridge.runtime.faults import (
    CAN_ERR_BUSOFF,
    CAN_ERR_PROT,
    CAN_ERR_PROT_LOC_CRC_SEQ,
    CAN_ERR_RESTARTED,
    FAULT_HELP,
    FAULT_KINDS,
    Delivery,
    FaultEvent,
    FaultInjector,
    FaultSpec,
    anomaly_field_world,
    fault_spec,
    faults_from_config,
    flip_bits,
    parse_fault_option,
)
from koala_bridge.runtime.settings import BridgeSettings, load_config
from koala_bridge.sim.sensors.compass import field_body
from koala_bridge.sim.simulator import Simulator
from koala_bridge.sim.types import Readings, WheelCommand

REPO = Path(__file__).resolve().parents[2]
DEFAULT = REPO / "config" / "default.toml"
IDEAL = REPO / "config" / "ideal.toml"


def injector(*cli: str, seed: int = 7) -> FaultInjector:
    return FaultInjector(faults_from_config({}, cli), seed)


def spec(text: str) -> FaultSpec:
    return faults_from_config({}, [text])[0]


# --------------------------------------------------------------------------- spec and grammar


@pytest.mark.parametrize(("table", "message"), [
    ({"kind": "delay", "target": "can", "probability": 1.5},
     "[[faults]] #1 'probability' must be in [0, 1], got 1.5"),
    ({"kind": "drop", "target": "cann"},
     "[[faults]] #1: unknown target 'cann'; did you mean 'can'?"),
    ({"kind": "dorp", "target": "can"},
     "[[faults]] #1: unknown kind 'dorp'; did you mean 'drop'?"),
    ({"target": "can"}, "[[faults]] #1 missing required key 'kind'"),
    ({"kind": "drop"}, "[[faults]] #1 missing required key 'target'"),
    ({"kind": "delay", "target": "can", "dealy_s": 1},
     "unknown key 'dealy_s'; did you mean 'delay_s'?"),
    ({"kind": "drop", "target": "can", "bits": 2},
     "'bits' does not apply to drop (a parameter of corrupt)"),
    ({"kind": "bias", "target": "gyro"}, "missing required key 'bias'"),
    ({"kind": "glitch", "target": "ir"}, "missing required key 'magnitude'"),
    ({"kind": "glitch", "target": "ir", "magnitude": 0}, "'magnitude' must be > 0"),
    ({"kind": "glitch", "target": "encoders", "magnitude": 1},
     "unknown target 'encoders' for glitch"),
    ({"kind": "magnetic_anomaly", "target": "compass", "x": 1, "y": 1},
     "missing required key 'strength_uT'"),
    ({"kind": "kidnap", "target": "robot", "x": 1, "y": 1, "end_s": 3},
     "'end_s' does not apply to kidnap"),
    ({"kind": "drop", "target": "can", "start_s": 5, "end_s": 5},
     "'end_s' must be > 'start_s' (5)"),
    ({"kind": "drop", "target": "can", "start_s": -1}, "'start_s' must be >= 0, got -1"),
    ({"kind": "drop", "target": "can", "start_s": "5"}, "'start_s' must be a number, got '5'"),
    ({"kind": "drop", "target": "can", "end_s": math.nan}, "'end_s' must be a number, not nan"),
    ({"kind": "corrupt", "target": "can", "bits": 0}, "'bits' must be >= 1, got 0"),
    ({"kind": "corrupt", "target": "can", "bits": 1.0}, "'bits' must be an integer"),
    ({"kind": "delay", "target": "kteam", "jitter_s": -0.1}, "'jitter_s' must be >= 0"),
    ({"kind": "stuck", "target": "ir", "sensors": [0, -1]}, "'sensors'[1] must be >= 0"),
    ({"kind": "stuck", "target": "ir", "sensors": 3}, "'sensors' must be a list"),
    ({"kind": "stuck_max", "target": "gyro"},
     "unknown target 'gyro' for stuck_max (targets: ir, sonar)"),
    ({"kind": "wheel_slip", "target": "both", "traction": 1.2},
     "'traction' must be a traction in [0, 1]"),
    ({"kind": "error_frames", "target": "can", "error": "stuf"}, "'error' must be one of crc"),
    ({"kind": "error_frames", "target": "can", "period_s": 0}, "'period_s' must be > 0"),
    ({"kind": "drop", "target": "can", "name": 3}, "'name' must be a string, got 3"),
])
def test_bad_fault_tables_name_the_fault_and_the_field(table: dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError) as e:
        faults_from_config({"faults": [table]})
    text = str(e.value)
    assert message in text
    assert text.startswith("[[faults]] #1")
    assert "\n" not in text


def test_cli_errors_name_the_option() -> None:
    with pytest.raises(ConfigError, match=r"^--fault 'drop:cann': unknown target 'cann'; did you "
                                          r"mean 'can'\?$"):
        faults_from_config({}, ["drop:cann"])
    ok = {"kind": "drop", "target": "can"}
    with pytest.raises(ConfigError, match=r"^--fault 'drop:can:probability=2' 'probability'"):
        faults_from_config({"faults": [ok]}, ["drop:can:probability=2"])


def test_faults_must_be_an_array_of_tables() -> None:
    with pytest.raises(ConfigError, match=r"write \[\[faults\]\]"):
        faults_from_config({"faults": {"kind": "drop", "target": "can"}})
    with pytest.raises(ConfigError, match=r"\[\[faults\]\] #2 must be a table"):
        faults_from_config({"faults": [{"kind": "drop", "target": "can"}, 3]})


def test_names_default_to_kind_target_position_and_must_be_unique() -> None:
    specs = faults_from_config({"faults": [{"kind": "drop", "target": "can"}]},
                               ["bias:gyro:bias=0.1", "drop:kteam:name=mine"])
    assert [s.name for s in specs] == ["drop:can#1", "bias:gyro#2", "mine"]
    with pytest.raises(ConfigError, match=r"^--fault 'drop:mavlink:name=\"drop:can#1\"' 'name' "):
        faults_from_config({"faults": [{"kind": "drop", "target": "can"}]},
                           ['drop:mavlink:name="drop:can#1"'])


def test_defaults_and_every_kind_validates() -> None:
    s = spec("drop:can")
    assert (s.start_s, s.end_s, s.probability) == (0.0, math.inf, 1.0)
    examples = {
        "drop": "drop:can", "corrupt": "corrupt:mavlink:bits=3", "delay": "delay:kteam:delay_s=0.1",
        "duplicate": "duplicate:rangefinders", "reorder": "reorder:can",
        "disconnect": "disconnect:kteam:start_s=1,end_s=2", "error_frames": "error_frames:can",
        "bus_off": "bus_off:can:start_s=1,end_s=2", "stuck": "stuck:encoders:sensors=[1]",
        "stuck_max": "stuck_max:sonar", "bias": "bias:gyro:bias=-0.02",
        "glitch": "glitch:sonar:magnitude=0.5",
        "magnetic_anomaly": "magnetic_anomaly:compass:x=1,y=2,strength_uT=30",
        "wheel_slip": "wheel_slip:left:traction=0.1", "kidnap": "kidnap:robot:x=1,y=2",
    }
    assert set(examples) == set(FAULT_KINDS)
    for kind, text in examples.items():
        assert spec(text).kind == kind


def test_cli_grammar() -> None:
    assert parse_fault_option("drop:can:start_s=5,end_s=10,probability=0.3") == {
        "kind": "drop", "target": "can", "start_s": 5, "end_s": 10, "probability": 0.3}
    assert parse_fault_option("kidnap:robot:start_s=20,x=1.0,y=0.5,theta_deg=90") == {
        "kind": "kidnap", "target": "robot", "start_s": 20, "x": 1.0, "y": 0.5, "theta_deg": 90}
    # arrays and quoted strings keep their commas; a bare word is a string; spaces are fine
    assert parse_fault_option('stuck:ir: sensors = [0, 3] , name="a,b"') == {
        "kind": "stuck", "target": "ir", "sensors": [0, 3], "name": "a,b"}
    assert parse_fault_option("error_frames:can:error=stuff") == {
        "kind": "error_frames", "target": "can", "error": "stuff"}
    assert parse_fault_option("drop:can:") == {"kind": "drop", "target": "can"}
    assert parse_fault_option("drop:can:end_s=inf")["end_s"] == math.inf
    for bad, why in [("drop", "must look like KIND:TARGET"), (":can", "must look like"),
                     ("drop:can:start_s", "'start_s' must look like key=value"),
                     ("drop:can:start_s=1,start_s=2", "'start_s' is given twice"),
                     ("drop:can:kind=x", "give the kind as KIND:TARGET"),
                     ("stuck:ir:sensors=[0,1", "unclosed"), ("stuck:ir:sensors=0]", "unbalanced"),
                     ("drop:can:name=\"x", "unclosed"), ("drop:can:name=[1,", "unclosed")]:
        with pytest.raises(ConfigError, match=why) as e:
            parse_fault_option(bad)
        assert str(e.value).startswith(f"--fault {bad!r}")
    assert "KIND:TARGET" in FAULT_HELP and all(k in FAULT_HELP for k in FAULT_KINDS)


@pytest.mark.parametrize("path", [DEFAULT, IDEAL, REPO / "config" / "koala25.toml"])
def test_shipped_configs_have_no_fault_and_a_valid_commented_example(path: Path) -> None:
    config = load_config(path)
    assert faults_from_config(config) == []
    lines = path.read_text().splitlines()
    start = lines.index("# [[faults]]")
    block = "\n".join(line[2:] if line.startswith("# ") else "" for line in lines[start:])
    example = tomllib.loads(block)
    specs = faults_from_config(example)
    assert [s.kind for s in specs] == ["drop", "bias"]
    # with the example in, the configuration still loads ([[faults]] is a known table)
    BridgeSettings.from_config({**config, **example})


def test_every_default_is_written_in_the_shipped_configs() -> None:
    """The config policy's one-default rule for a table that is not there by default: the
    commented [[faults]] block of default.toml states each key's default as ``key = value``."""
    text = DEFAULT.read_text()
    header = text[text.index("# Fault injection"):text.index("\n# [[faults]]\n")]
    header = " ".join(line.removeprefix("#").strip() for line in header.splitlines())
    for f in dataclasses.fields(FaultSpec):
        if f.default is dataclasses.MISSING or f.default is None:
            continue   # kind, target; the required parameters and theta_deg (absent: kept)
        written = tomli_w.dumps({f.name: f.default}).strip()
        assert written in header, f"{written!r} is not in default.toml's [[faults]] comment"


def test_fault_spec_is_the_same_validation_for_runtime_tables() -> None:
    s = fault_spec({"kind": "bias", "target": "gyro", "bias": 0.1}, "zenoh fault", 3)
    assert s.name == "bias:gyro#3"
    with pytest.raises(ConfigError, match=r"^zenoh fault 'bias' must be a number"):
        fault_spec({"kind": "bias", "target": "gyro", "bias": "x"}, "zenoh fault", 3)


# --------------------------------------------------------------------------- seed and statistics


def decisions(inj: FaultInjector, bus: str = "can", n: int = 400) -> list[bool]:
    return [bool(inj.on_frame(bus, i * 0.01, b"\x01\x02", 0x101)) for i in range(n)]


def test_same_seed_same_decisions_other_seed_other_decisions() -> None:
    a = decisions(injector("drop:can:probability=0.5", seed=1))
    assert a == decisions(injector("drop:can:probability=0.5", seed=1))
    assert a != decisions(injector("drop:can:probability=0.5", seed=2))


def test_a_faults_draws_do_not_depend_on_other_faults() -> None:
    """Fault i draws from default_rng([seed, 0x0FA1, i]) only: another fault behind it, and
    its calls interleaved, change nothing."""
    alone = injector("drop:can:probability=0.5")
    both = injector("drop:can:probability=0.5", "drop:mavlink:probability=0.5")
    got = []
    for i in range(400):
        got.append(bool(both.on_frame("can", i * 0.01, b"\x01", 0x101)))
        both.on_frame("mavlink", i * 0.01, b"\xfd")
    assert got == decisions(alone)


def test_drop_probability_is_binomial() -> None:
    """p = 0.3 over n = 10 000 frames: the dropped count is Binomial(n, p), mean np = 3000,
    sigma sqrt(np(1-p)) = 45.8; the seed is fixed and the bound 5 sigma."""
    n, p = 10_000, 0.3
    inj = injector(f"drop:rangefinders:probability={p}", seed=11)
    dropped = sum(not inj.on_frame("rangefinders", i * 0.01, b"x") for i in range(n))
    assert abs(dropped - n * p) <= 5 * math.sqrt(n * p * (1 - p))
    assert inj.counts() == {"drop:rangefinders#1": dropped}


def test_windowed_faults_draw_once_per_window() -> None:
    """probability 0.5 on a window: it happens for the whole window or not at all; over 2000
    seeds the share that happen is Binomial(2000, 0.5) within 5 sigma (112)."""
    happened = 0
    for seed in range(2000):
        inj = injector("disconnect:kteam:start_s=1,end_s=2,probability=0.5", seed=seed)
        states = {inj.disconnected("kteam", 1.0 + k * 0.1) for k in range(10)}
        assert len(states) == 1
        happened += states.pop()
    assert abs(happened - 1000) <= 5 * math.sqrt(2000 * 0.25)


# --------------------------------------------------------------------------- frame faults


def test_window_bounds() -> None:
    inj = injector("drop:can:start_s=1,end_s=2")
    assert inj.on_frame("can", 0.99, b"a", 1) == [(0.99, b"a")]
    assert inj.on_frame("can", 1.0, b"a", 1) == []
    assert inj.on_frame("kteam", 1.5, b"a") == [(1.5, b"a")]  # another bus
    assert inj.on_frame("can", 1.99, b"a", 1) == []
    assert inj.on_frame("can", 2.0, b"a", 1) == [(2.0, b"a")]


def test_duplicate_and_delay() -> None:
    assert injector("duplicate:kteam").on_frame("kteam", 1.0, b"x") == [(1.0, b"x"), (1.0, b"x")]
    d = injector("delay:can:delay_s=0.01").on_frame("can", 1.0, b"x", 5)
    assert d == [(1.01, b"x")] and d[0].can_id == 5
    inj = injector("delay:mavlink:delay_s=0.02,jitter_s=0.01")
    times = [inj.on_frame("mavlink", 1.0, b"x")[0][0] - 1.0 for _ in range(500)]
    assert all(0.02 <= t <= 0.03 for t in times)
    # U(0, 0.01): mean 0.005, sigma 0.01/sqrt(12 * 500) = 1.3e-4; bound 5 sigma
    assert abs(np.mean(times) - 0.025) <= 5 * 0.01 / math.sqrt(12 * 500)


def test_reorder_swaps_a_frame_with_the_next() -> None:
    inj = injector("reorder:can:end_s=3")
    assert inj.on_frame("can", 1.0, b"a", 1) == []
    out = inj.on_frame("can", 1.1, b"b", 2)
    assert out == [(1.1, b"b"), (1.1, b"a")]
    assert [d.can_id for d in out] == [2, 1]   # each frame keeps its id
    assert inj.on_frame("can", 1.2, b"c", 3) == []
    # the held frame leaves after the next one even when the window has closed meanwhile
    assert inj.on_frame("can", 5.0, b"d", 4) == [(5.0, b"d"), (5.0, b"c")]
    assert inj.on_frame("can", 5.1, b"e", 5) == [(5.1, b"e")]


def test_faults_on_one_bus_compose_in_order() -> None:
    inj = injector("duplicate:kteam", "delay:kteam:delay_s=0.5")
    assert inj.on_frame("kteam", 1.0, b"x") == [(1.5, b"x"), (1.5, b"x")]


@pytest.mark.parametrize("bits", [1, 2, 3, 5, 17])
def test_corrupt_flips_exactly_bits_bits(bits: int) -> None:
    inj = injector(f"corrupt:rangefinders:bits={bits}")
    data = bytes(range(40))
    for i in range(50):
        (t, out), = inj.on_frame("rangefinders", i * 0.1, data)
        flipped = int.from_bytes(bytes(a ^ b for a, b in zip(data, out, strict=True)), "little")
        assert flipped.bit_count() == bits
    events = inj.events()
    assert len(events) == 50 and all(len(e.detail["bits"]) == bits for e in events)
    assert flip_bits(data, events[0].detail["bits"]) != data


@pytest.mark.parametrize("bits", [1, 2, 3])
def test_a_corrupted_range_frame_fails_at_the_client(bits: int) -> None:
    """CRC-16/CCITT-FALSE has Hamming distance 4 over frames this short (< 32 751 bits), so 1 to
    3 flipped bits are always detected (Koopman's CRC tables); a flip in the header fails the
    sync, version, kind or length check first."""
    inj = injector(f"corrupt:rangefinders:bits={bits}", seed=bits)
    frame = encode_range_frame(RangeFrame(RangeKind.IR, 7, 123456, tuple(range(0, 1600, 100))))
    assert not isinstance(decode_range_frame(frame), Reject)
    for i in range(300):
        (_, bad), = inj.on_frame("rangefinders", i * 0.01, frame)
        assert isinstance(decode_range_frame(bad), Reject)


@pytest.mark.parametrize("bits", [1, 3])
def test_a_corrupted_mavlink_packet_fails_at_the_client(bits: int) -> None:
    encoder = CompassEncoder(MavlinkIdentity(1, 1))
    packet = encoder.scaled_imu(CompassSample(1000, 20.0, -3.0, -40.0))
    good = CompassDecoder()
    assert len(good.feed_datagram(packet)) == 1
    inj = injector(f"corrupt:mavlink:bits={bits}", seed=bits)
    for i in range(300):
        (_, bad), = inj.on_frame("mavlink", i * 0.01, packet)
        decoder = CompassDecoder()
        assert decoder.feed_datagram(bad) == []
        assert decoder.rejected >= 1


def test_a_corrupted_can_frame_is_an_error_frame_then_the_frame() -> None:
    """On CAN a corrupted frame never reaches an application: the receivers' CRC check fails,
    an error frame is signalled and the sender retransmits."""
    inj = injector("corrupt:can:start_s=1")
    assert inj.on_frame("can", 1.0, b"\x01\x02", 0x101) == [(1.0, b"\x01\x02")]
    (err,) = inj.can_error_frames(1.0)
    assert err.is_error_frame and err.timestamp == 1.0 and err.dlc == 8
    assert err.arbitration_id & CAN_ERR_PROT
    assert err.data[3] == CAN_ERR_PROT_LOC_CRC_SEQ
    assert inj.can_error_frames(1.0) == []
    assert inj.events()[0].detail == {"can_id": 0x101, "error": "crc"}


def test_error_frames_every_period() -> None:
    inj = injector("error_frames:can:start_s=1,end_s=2,period_s=0.25,error=stuff")
    assert inj.can_error_frames(0.9) == []
    frames = inj.can_error_frames(1.6)
    assert [f.timestamp for f in frames] == [1.0, 1.25, 1.5]
    assert all(f.is_error_frame and f.data[2] == 0x04 for f in frames)
    assert [f.timestamp for f in inj.can_error_frames(9.0)] == [1.75]
    assert inj.counts() == {"error_frames:can#1": 4}


def test_bus_off_window_and_its_error_frames() -> None:
    inj = injector("bus_off:can:start_s=1,end_s=2")
    assert not inj.bus_off("can", 0.5)
    assert inj.bus_off("can", 1.0) and inj.bus_off("can", 1.99)
    assert not inj.bus_off("mavlink", 1.5)
    (off,) = inj.can_error_frames(1.5)
    assert off.arbitration_id == CAN_ERR_BUSOFF and off.timestamp == 1.0
    assert not inj.bus_off("can", 2.0)
    (back,) = inj.can_error_frames(2.0)
    assert back.arbitration_id == CAN_ERR_RESTARTED and back.timestamp == 2.0
    events = inj.events()
    assert [(e.t, e.detail["phase"]) for e in events] == [(1.0, "start"), (2.0, "end")]
    assert inj.counts() == {"bus_off:can#1": 1}


def test_disconnect_window() -> None:
    inj = injector("disconnect:kteam:start_s=1,end_s=2", "disconnect:mavlink:probability=0")
    assert [inj.disconnected("kteam", t) for t in (0.5, 1.0, 1.5, 2.0, 3.0)] == [
        False, True, True, False, False]
    assert not inj.disconnected("mavlink", 1.5)
    assert inj.counts() == {"disconnect:kteam#1": 1, "disconnect:mavlink#2": 0}
    with pytest.raises(ValueError, match="unknown bus"):
        inj.disconnected("kteamm", 1.0)


def test_time_never_goes_back() -> None:
    inj = injector("disconnect:kteam:start_s=1,end_s=2")
    assert inj.disconnected("kteam", 1.5)
    assert inj.disconnected("kteam", 0.2)   # taken as 1.5: the window is still open


# --------------------------------------------------------------------------- sensor faults


@pytest.fixture(scope="module")
def readings() -> list[Readings]:
    """Two simulated seconds on config/default.toml, turning (so every stream changes)."""
    sim = Simulator(load_config(DEFAULT))
    out = [sim.reset(3)]
    for _ in range(round(2.0 / sim.dt)):
        out.append(sim.step(WheelCommand(0.05, 0.15)))
    return out


def through(inj: FaultInjector, readings: list[Readings]) -> list[Readings]:
    return [inj.on_readings(r) for r in readings]


def last_before(readings: list[Readings], t: float, field: str) -> Any:
    return [getattr(r, field) for r in readings if r.t < t and getattr(r, field) is not None][-1]


def test_stuck_repeats_the_last_value_before_the_window(readings: list[Readings]) -> None:
    inj = injector("stuck:gyro:start_s=0.5,end_s=1.5", "stuck:ir:start_s=0.5,end_s=1.5,sensors=[2]",
                   "stuck:encoders:start_s=0.5,end_s=1.5", "stuck:compass:start_s=0.5,end_s=1.5")
    out = through(inj, readings)
    gyro0 = last_before(readings, 0.5, "gyro")
    ir0 = last_before(readings, 0.5, "ir")
    odo0 = last_before(readings, 0.5, "odometry")
    mag0 = last_before(readings, 0.5, "compass")
    inside = [(r, o) for r, o in zip(readings, out, strict=True) if 0.5 <= r.t < 1.5]
    for r, o in inside:
        if r.gyro is not None:
            assert o.gyro.yaw_rate == gyro0.yaw_rate
            assert o.gyro.truth_yaw_rate == r.gyro.truth_yaw_rate   # truth stays true
        if r.ir is not None:
            assert o.ir.counts[2] == ir0.counts[2]
            assert np.array_equal(np.delete(o.ir.counts, 2), np.delete(r.ir.counts, 2))
        if r.odometry is not None:
            assert (o.odometry.left_ticks, o.odometry.right_ticks) == (
                odo0.left_ticks, odo0.right_ticks)
        if r.compass is not None:
            assert np.array_equal(o.compass.field_uT, mag0.field_uT)
    assert any(r.gyro is not None and r.gyro.yaw_rate != gyro0.yaw_rate for r, _ in inside)
    after = [(r, o) for r, o in zip(readings, out, strict=True) if r.t >= 1.5]
    assert all(o is r or o == r for r, o in after)   # unchanged after the window
    assert all(r.odometry.left_ticks != odo0.left_ticks for r, _ in after if r.odometry)


def test_stuck_max_reads_nothing_in_range(readings: list[Readings]) -> None:
    inj = injector("stuck_max:ir:sensors=[0, 5]", "stuck_max:sonar")
    for r, o in zip(readings, through(inj, readings), strict=True):
        if r.ir is not None:
            assert o.ir.counts[0] == 0 and o.ir.counts[5] == 0
            assert np.array_equal(o.ir.truth_counts, r.ir.truth_counts)
            assert np.array_equal(np.delete(o.ir.counts, [0, 5]), np.delete(r.ir.counts, [0, 5]))
        if r.sonar is not None:
            assert np.isnan(o.sonar.ranges).all()


def test_gyro_bias_step(readings: list[Readings]) -> None:
    inj = injector("bias:gyro:start_s=1,bias=0.05")
    for r, o in zip(readings, through(inj, readings), strict=True):
        if r.gyro is not None:
            assert o.gyro.yaw_rate == r.gyro.yaw_rate + (0.05 if r.t >= 1 else 0.0)
            assert o.gyro.truth_yaw_rate == r.gyro.truth_yaw_rate
    (start,) = inj.events()
    assert start.to_json() == {"t": 1.0, "name": "bias:gyro#1", "kind": "bias", "target": "gyro",
                               "detail": {"phase": "start", "bias": 0.05}}


def test_glitch_outliers(readings: list[Readings]) -> None:
    """p = 0.2 per gyro reading: the number of outliers is Binomial(n, 0.2), each +-magnitude
    with the sign a fair coin (bounds 5 sigma); IR: one sensor of those listed per outlier."""
    inj = injector("glitch:gyro:probability=0.2,magnitude=0.5", "glitch:ir:magnitude=40,"
                   "sensors=[3, 4]", "glitch:compass:magnitude=10,probability=0.5")
    out = through(inj, readings)
    deltas = [o.gyro.yaw_rate - r.gyro.yaw_rate for r, o in zip(readings, out, strict=True)
              if r.gyro is not None]
    n = len(deltas)
    hits = [d for d in deltas if d != 0.0]
    assert all(abs(abs(d) - 0.5) < 1e-12 for d in hits)
    assert abs(len(hits) - 0.2 * n) <= 5 * math.sqrt(n * 0.2 * 0.8)
    assert abs(sum(d > 0 for d in hits) - len(hits) / 2) <= 5 * math.sqrt(len(hits) / 4)
    for r, o in zip(readings, out, strict=True):
        if r.ir is not None:
            changed = np.flatnonzero(o.ir.counts != r.ir.counts)
            assert len(changed) <= 1 and set(changed) <= {3, 4}
            for i in changed:
                assert o.ir.counts[i] == max(0, r.ir.counts[i] + (40 if o.ir.counts[i] >
                                                                   r.ir.counts[i] else -40))
        if r.compass is not None:
            axes = np.flatnonzero(o.compass.field_uT != r.compass.field_uT)
            assert len(axes) <= 1
            assert np.allclose(np.abs(o.compass.field_uT - r.compass.field_uT).sum(),
                               10.0 * len(axes))
    counts = inj.counts()
    assert counts["glitch:gyro#1"] == len(hits)
    assert counts["glitch:ir#2"] > 0 and counts["glitch:compass#3"] > 0


def test_glitch_keeps_no_echo(readings: list[Readings]) -> None:
    r = next(r for r in readings if r.sonar is not None)
    blind = dataclasses.replace(r, sonar=dataclasses.replace(
        r.sonar, ranges=np.full_like(r.sonar.ranges, np.nan)))
    out = injector("glitch:sonar:magnitude=0.3").on_readings(blind)
    assert np.isnan(out.sonar.ranges).all()


def test_anomaly_field() -> None:
    # zero at and beyond the radius, at the centre; peak strength near the centre; towards it
    assert anomaly_field_world(1.0, 0.0, 0.0, 0.0, 50.0, 1.0) == (0.0, 0.0, 0.0)
    assert anomaly_field_world(0.0, 0.0, 0.0, 0.0, 50.0, 1.0) == (0.0, 0.0, 0.0)
    bx, by, bz = anomaly_field_world(0.001, 0.0, 0.0, 0.0, 50.0, 1.0)
    assert bx == pytest.approx(-50.0, rel=1e-5) and by == bz == 0.0
    bx, by, _ = anomaly_field_world(0.0, -0.5, 0.0, 0.0, -40.0, 1.0)   # negative: away
    assert bx == 0.0 and by == pytest.approx(-40.0 * 0.75**2)


def test_magnetic_anomaly_adds_its_field_at_the_truth_pose(readings: list[Readings]) -> None:
    p = readings[0].pose
    cx, cy = p.x + 0.1, p.y
    inj = injector(f"magnetic_anomaly:compass:x={cx},y={cy},strength_uT=30,radius_m=0.3")
    hit = 0
    for r, o in zip(readings, through(inj, readings), strict=True):
        if r.compass is None:
            continue
        add = field_body(anomaly_field_world(r.pose.x, r.pose.y, cx, cy, 30.0, 0.3), r.pose.theta)
        assert np.allclose(o.compass.field_uT - r.compass.field_uT, add, atol=1e-12)
        assert np.array_equal(o.compass.truth_field_uT, r.compass.truth_field_uT)
        hit += any(add)
    assert hit > 0


def test_sensor_index_check() -> None:
    inj = injector("stuck:ir:sensors=[16]")
    inj.check({"ir": 17})
    with pytest.raises(ConfigError, match=r"'sensors' index 16 is out of range: the robot has 16"):
        inj.check({"ir": 16})


# --------------------------------------------------------------------------- the robot


def test_kidnap_moves_the_robot_and_the_encoders_do_not_count_it() -> None:
    sim = Simulator(load_config(IDEAL))
    r0 = sim.reset(0)
    inj = injector("kidnap:robot:start_s=0.5,x=1.5,y=1.2,theta_deg=90")
    stop = WheelCommand(0.0, 0.0)
    r = r0
    while r.t < 1.0:
        inj.apply_to_sim(sim, sim.t)
        r = sim.step(stop)
    assert (r.pose.x, r.pose.y) == (1.5, 1.2) and r.pose.theta == pytest.approx(math.pi / 2)
    assert (r.odometry.left_ticks, r.odometry.right_ticks) == (0, 0)
    (event,) = inj.events()
    assert event.kind == "kidnap" and event.t == pytest.approx(0.5)
    assert event.detail["from"] == [r0.pose.x, r0.pose.y, r0.pose.theta]
    assert inj.counts() == {"kidnap:robot#1": 1}


def test_kidnap_keeps_the_heading_without_theta() -> None:
    sim = Simulator(load_config(IDEAL))
    theta = sim.reset(0).pose.theta
    inj = injector("kidnap:robot:x=1.5,y=1.2")
    inj.apply_to_sim(sim, 0.0)
    assert sim.pose.theta == theta and (sim.pose.x, sim.pose.y) == (1.5, 1.2)


STRAIGHT = WheelCommand(0.1, 0.1)


def run(sim: Simulator, seconds: float, inj: FaultInjector | None = None) -> Readings:
    r = None
    for _ in range(round(seconds / sim.dt)):
        if inj is not None:
            inj.apply_to_sim(sim, sim.t)
        r = sim.step(STRAIGHT)
    assert r is not None
    return r


def test_wheel_slip_moves_the_body_less_than_the_encoders_count() -> None:
    """Ideal drive, straight at 0.1 m/s for 1 s with traction 0.5 on both wheels from 0.5 s:
    the body moves 0.05 + 0.025 m, the encoders count 0.1 m of wheel turn."""
    plain, slipping = Simulator(load_config(IDEAL)), Simulator(load_config(IDEAL))
    p0 = plain.reset(0).pose
    slipping.reset(0)
    a = run(plain, 1.0)
    inj = injector("wheel_slip:both:start_s=0.5,end_s=1.5,traction=0.5")
    b = run(slipping, 1.0, inj)
    assert b.odometry == a.odometry
    assert a.pose.x - p0.x == pytest.approx(0.1, abs=1e-9)
    assert b.pose.x - p0.x == pytest.approx(0.075, abs=1e-9)
    assert slipping.wheel_traction == (0.5, 0.5)
    run(slipping, 1.0, inj)
    assert slipping.wheel_traction == (1.0, 1.0)          # off again after end_s
    assert [e.detail["phase"] for e in inj.events()] == ["start", "end"]


def test_one_wheel_slipping_turns_the_robot() -> None:
    sim = Simulator(load_config(IDEAL))
    sim.reset(0)
    r = run(sim, 1.0, injector("wheel_slip:left:traction=0.0"))
    assert r.pose.theta > 0.0                         # only the right wheel pushes: CCW
    assert r.odometry.left_ticks == r.odometry.right_ticks


def test_simulator_hooks_draw_nothing() -> None:
    """Traction (1, 1) set explicitly and a teleport to where the robot is change nothing: the
    same readings bit for bit (default.toml: every error model on)."""
    a, b = Simulator(load_config(DEFAULT)), Simulator(load_config(DEFAULT))
    a.reset(5)
    b.reset(5)
    cmd = WheelCommand(0.1, 0.12)
    for k in range(300):
        if k == 100:
            b.set_wheel_traction(1.0, 1.0)
            p = b.pose
            b.teleport(p.x, p.y, p.theta)
        ra, rb = a.step(cmd), b.step(cmd)
        assert ra.pose == rb.pose
        for name in ("gyro", "odometry"):
            assert getattr(ra, name) == getattr(rb, name)
        if ra.ir is not None:
            assert np.array_equal(ra.ir.counts, rb.ir.counts)
        if ra.compass is not None:
            assert np.array_equal(ra.compass.field_uT, rb.compass.field_uT)


def test_simulator_hook_validation() -> None:
    sim = Simulator(load_config(IDEAL))
    with pytest.raises(RuntimeError):
        sim.teleport(0.0, 0.0, 0.0)
    sim.reset(0)
    with pytest.raises(ValueError, match="'left' must be in"):
        sim.set_wheel_traction(1.5, 1.0)
    with pytest.raises(ValueError, match="finite"):
        sim.teleport(math.nan, 0.0, 0.0)
    sim.set_wheel_traction(0.2, 0.3)
    sim.reset(0)
    assert sim.wheel_traction == (1.0, 1.0)


# --------------------------------------------------------------------------- events, counts, add


def test_events_drain_and_counts_accumulate() -> None:
    inj = injector("drop:can:end_s=1", "duplicate:kteam")
    assert inj.active and not FaultInjector([], 0).active
    inj.on_frame("can", 0.1, b"a", 1)
    inj.on_frame("can", 0.2, b"b", 1)
    inj.on_frame("kteam", 0.2, b"c")
    events = inj.events()
    assert [e.to_json() for e in events] == [
        {"t": 0.1, "name": "drop:can#1", "kind": "drop", "target": "can", "detail": {"can_id": 1}},
        {"t": 0.2, "name": "drop:can#1", "kind": "drop", "target": "can", "detail": {"can_id": 1}},
        {"t": 0.2, "name": "duplicate:kteam#2", "kind": "duplicate", "target": "kteam",
         "detail": {}},
    ]
    assert inj.events() == []
    assert inj.counts() == {"drop:can#1": 2, "duplicate:kteam#2": 1}
    assert isinstance(events[0], FaultEvent)


def test_add_at_run_time() -> None:
    inj = injector("drop:can:name=first")
    inj.on_frame("can", 5.0, b"x", 1)
    inj.add(spec("disconnect:mavlink:end_s=9"))      # its window opened in the past: opens now
    assert inj.disconnected("mavlink", 5.0)
    (start,) = [e for e in inj.events() if e.kind == "disconnect"]
    assert start.t == 5.0 and start.name == "disconnect:mavlink#1"
    with pytest.raises(ConfigError, match="'first' is already used"):
        inj.add(spec("drop:kteam:name=first"))
    inj.add(FaultSpec(kind="drop", target="kteam"))
    inj.add(spec("bias:gyro:end_s=2,bias=1"))         # its window is over: nothing happens
    assert not inj.events()
    assert list(inj.counts()) == ["first", "disconnect:mavlink#1", "drop:kteam#3",
                                  "bias:gyro#1"]


def test_seed_must_be_a_natural_number() -> None:
    with pytest.raises(ValueError, match="seed"):
        FaultInjector([], -1)


def test_delivery_is_a_pair() -> None:
    d = Delivery(1.0, b"x", 3)
    t, data = d
    assert (t, data, d.t, d.data, d.can_id) == (1.0, b"x", 1.0, b"x", 3)
    assert d == (1.0, b"x")
