"""core.topics: one typed message per Zenoh topic, from which the published JSON, the recording's
JSON Schemas, the export's CSV columns and the parsers all come.

For every topic the JSON a message produces must validate against the schema derived from the
same class and recorded on its MCAP channel, and parse back to the same message; the export's
columns are the class's scalar fields. The real robot's ``sensors/ir`` message once lacked the
``ambient`` member its schema requires (issue 11): it is checked through the real source's own
reader.
"""

from __future__ import annotations

import ast
import csv
import json
import math
import sys
import threading
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import DEFAULT_CONFIG, REPO
from koala_bridge.core import topics
from koala_bridge.core.topics import (
    IrMessage,
    StatusMessage,
    TopicError,
    TopicMessage,
    TruthPose,
    WorldMessage,
)
from koala_bridge.drivers.messages import RangeFrame, RangeKind
from koala_bridge.drivers.rangeframes import NO_ECHO, encode_range_frame
from koala_bridge.drivers.transports.loop import LoopbackTransport
from koala_bridge.estimation import messages as estimation
from koala_bridge.recording.export import LANDMARK_COLUMNS, RANGE_COLUMNS, TABLES, export_bundle
from koala_bridge.recording.mcap_file import Recorder, open_recording
from koala_bridge.runtime.settings import BridgeSettings, load_config
from koala_bridge.runtime.zenoh_io import sensor_topics, status_message, truth_pose
from koala_bridge.sim.simulator import Simulator
from koala_bridge.sim.types import (
    CameraReading,
    CompassReading,
    GyroReading,
    IrReading,
    LandmarkObservation,
    OdometryReading,
    Pose,
    Readings,
    SonarReading,
    WheelCommand,
)
from koala_bridge.sim.world import World

# -- a small JSON Schema validator (draft 2020-12, the keywords the schemas use) ---------------

ANNOTATIONS = {"$schema", "title", "description", "contentEncoding"}
ASSERTIONS = {"type", "properties", "required", "items", "prefixItems", "minItems", "maxItems",
              "const", "enum", "additionalProperties", "anyOf"}
JSON_TYPES = {
    "object": lambda v: isinstance(v, dict),
    "array": lambda v: isinstance(v, list),
    "string": lambda v: isinstance(v, str),
    "integer": lambda v: isinstance(v, int) and not isinstance(v, bool),
    "number": lambda v: isinstance(v, int | float) and not isinstance(v, bool),
    "boolean": lambda v: isinstance(v, bool),
    "null": lambda v: v is None,
}


def errors(value: Any, schema: dict[str, Any], where: str = "$") -> list[str]:
    """Why ``value`` does not validate against ``schema`` (empty: it does). A keyword this
    validator does not know is an error, so that it never passes by ignoring one."""
    unknown = set(schema) - ANNOTATIONS - ASSERTIONS
    if unknown:
        return [f"{where}: unknown schema keywords {sorted(unknown)}"]
    out: list[str] = []
    if "type" in schema:
        kinds = schema["type"] if isinstance(schema["type"], list) else [schema["type"]]
        if not any(JSON_TYPES[k](value) for k in kinds):
            return [f"{where}: {json.dumps(value)[:40]} is not {kinds}"]
    if "const" in schema and value != schema["const"]:
        out.append(f"{where}: not {schema['const']!r}")
    if "enum" in schema and value not in schema["enum"]:
        out.append(f"{where}: not one of {schema['enum']}")
    if "anyOf" in schema and all(errors(value, s, where) for s in schema["anyOf"]):
        out.append(f"{where}: matches none of anyOf")
    if isinstance(value, dict):
        out += [f"{where}: no {k!r}" for k in schema.get("required", []) if k not in value]
        props = schema.get("properties", {})
        for k, v in value.items():
            if k in props:
                out += errors(v, props[k], f"{where}.{k}")
            elif isinstance(schema.get("additionalProperties"), dict):
                out += errors(v, schema["additionalProperties"], f"{where}.{k}")
    if isinstance(value, list):
        prefix = schema.get("prefixItems", [])
        if "minItems" in schema and len(value) < schema["minItems"]:
            out.append(f"{where}: fewer than {schema['minItems']} items")
        if "maxItems" in schema and len(value) > schema["maxItems"]:
            out.append(f"{where}: more than {schema['maxItems']} items")
        for i, v in enumerate(value):
            if i < len(prefix):
                out += errors(v, prefix[i], f"{where}[{i}]")
            elif "items" in schema:
                out += errors(v, schema["items"], f"{where}[{i}]")
    return out


def test_the_validator_is_not_vacuous() -> None:
    schema = IrMessage.json_schema()
    good = {"t": 0.0, "counts": [1, 2], "ambient": [3, None]}
    assert errors(good, schema) == []
    assert errors({"t": 0.0, "counts": [1, 2]}, schema) == ["$: no 'ambient'"]
    assert errors({**good, "counts": [1.5]}, schema)
    assert errors({**good, "t": None}, schema)
    assert errors({**good, "truth": {"counts": [], "ranges": ["x"], "incidence": []}}, schema)
    assert errors(1, {"type": "integer", "format": "x"})  # an unknown keyword is no pass


# -- one message of every topic -------------------------------------------------------------------

def readings(t: float = 1.25) -> Readings:
    """One simulator step with every sensor due, no echo and nothing in range included."""
    obs = (LandmarkObservation(2, 1.5, -0.25), LandmarkObservation(4, np.inf, 0.5))
    return Readings(
        t=t,
        pose=Pose(1.0, 2.0, 0.5),
        wheel_speeds=WheelCommand(0.1, 0.1),
        ir=IrReading(np.full(16, 7), np.full(16, 450), np.full(16, 6), np.full(16, np.inf)),
        sonar=SonarReading(np.array([0.5, np.nan]), np.array([0.49, np.nan]),
                           np.array([0.1, np.nan])),
        odometry=OdometryReading(100, -20),
        gyro=GyroReading(0.25, 0.2),
        compass=CompassReading(np.array([20.0, -1.0, -43.0]), np.array([19.0, 0.0, -43.0])),
        camera=CameraReading(obs, obs[:1]),
    )


def world_message() -> WorldMessage:
    config = load_config(DEFAULT_CONFIG)
    sim = Simulator(config)
    return WorldMessage.of(sim.world, sim.robot_description())


def every_message() -> list[tuple[str, dict[str, Any]]]:
    """``(topic, JSON)`` of every topic, as the bridge's own builders make them."""
    r = readings()
    incidence = np.linspace(0.0, 1.0, 16)
    incidence[3] = np.nan
    out: list[tuple[str, dict[str, Any]]] = [("truth/pose", truth_pose(r).to_json())]
    out += [(k, m.to_json()) for k, m in sensor_topics(r, incidence).items()]
    out += [(k, m.to_json()) for k, m in sensor_topics(r).items()]
    out.append(("status", status_message(2.0, math.nan, {"kteam": {"sent": 1, "received": 2,
                                                                   "rejected": 3}})))
    out.append(("status", StatusMessage(
        3.0, 0.99, {"can.virtual": {"sent": 4, "received": 0, "rejected": 0, "dropped": 1}},
        motor_command_source="", leds=(0, 1), localisation={"frames": {"ir": 3}},
    ).to_json()))
    out.append(("status", StatusMessage(
        4.0, None, {}, lockstep={"engaged": True, "cycles": 5, "explicit": 0, "misses": 1},
        faults={"drop:can#0": 3}, bus_load={"can": 0.25},
    ).to_json()))
    out.append(("events/fault", topics.FaultEventMessage(
        5.0, "drop:can#0", "drop", "can", {"can_id": 0x101}).to_json()))
    rng = np.random.default_rng(3)
    out.append(("estimate/pose", estimation.pose_message(1.0, 0.5, 0.25, -0.1, np.eye(3))))
    out.append(("estimate/health", estimation.health_message(
        1.0, "uncertain", ["wheel_slip", "wall_contact"], 0.02, 1.5, 12, 1, 0)))
    out.append(("estimate/cell", estimation.cell_message(1.0, (2, 3), 0.5)))
    out.append(("estimate/grid", estimation.grid_message(1.0, rng.uniform(size=(4, 6)), 0.5)))
    out.append(("map/occupancy", estimation.occupancy_message(
        1.0, rng.normal(size=(5, 7)), 0.05, 4.0)))
    out.append(("world", world_message().to_json()))
    return out


def test_every_topic_has_a_message_here() -> None:
    assert {topic for topic, _ in every_message()} == set(topics.TOPICS)


@pytest.mark.parametrize("topic, message", every_message(), ids=lambda v: str(v)[:20])
def test_message_validates_against_its_schema_and_parses_back(
    topic: str, message: dict[str, Any]
) -> None:
    cls = topics.TOPICS[topic]
    payload = cls.parse(message).to_bytes()
    assert json.loads(payload) == message  # strict JSON, nothing lost or added
    assert errors(json.loads(payload), cls.json_schema()) == []
    assert topics.parse(topic, payload) == cls.from_json(message)


def test_the_sim_ir_and_sonar_carry_null_for_nothing_in_range() -> None:
    m = {k: v.to_json() for k, v in sensor_topics(readings()).items()}
    assert m["sensors/ir"]["ambient"] == [450] * 16
    assert m["sensors/ir"]["truth"]["ranges"] == [None] * 16
    assert m["sensors/sonar"]["ranges"] == [0.5, None]
    assert m["sensors/camera"]["observations"][1] == {"id": 4, "range": None, "bearing": 0.5}


def test_a_payload_of_another_shape_is_a_topic_error() -> None:
    with pytest.raises(TopicError, match="no member 'counts'"):
        IrMessage.from_json({"t": 1.0})
    with pytest.raises(TopicError, match="counts: expected an array"):
        IrMessage.from_json({"t": 1.0, "counts": "x"})
    with pytest.raises(TopicError, match="yaw_rate"):
        topics.parse("sensors/gyro", b'{"t": 1.0, "yaw_rate": "fast"}')
    with pytest.raises(TopicError, match="not JSON"):
        topics.parse("truth/pose", b"{")
    with pytest.raises(TopicError, match="not a koala-bridge topic"):
        topics.parse("sensors/lidar", b"{}")


def test_an_older_real_recording_ir_without_ambient_reads_as_not_measured() -> None:
    msg = IrMessage.from_json({"t": 1.0, "counts": [5, 6]})
    assert msg.ambient == (None, None) and msg.truth is None


def test_optional_members_are_left_out_and_order_is_field_order() -> None:
    sim_status = StatusMessage(1.0, 1.0, {}, motor_command_source="kteam", leds=(1, 0),
                               localisation={})
    assert list(sim_status.to_json()) == ["t", "real_time_factor", "buses",
                                          "motor_command_source", "leds", "localisation"]
    real_status = StatusMessage(1.0, 1.0, {}, source="real")
    assert list(real_status.to_json()) == ["t", "real_time_factor", "buses", "source"]
    assert real_status.to_bytes() == b'{"t":1.0,"real_time_factor":1.0,"buses":{},"source":"real"}'
    assert StatusMessage(1.0, math.inf, {}).to_json()["real_time_factor"] is None


# -- the real robot's sensors/ir (the regression of issue 11) -----------------------------------

class _Tap:
    def __init__(self) -> None:
        self.records: list[tuple[str, float, Any]] = []

    def declare(self, keys: Any = (), buses: Any = ()) -> None:
        pass

    def record(self, channel: str, t: float, payload: Any) -> None:
        self.records.append((channel, t, payload))

    def record_frame(self, *args: Any, **fields: Any) -> None:
        pass


def real_source(real: dict[str, Any], tap: _Tap) -> Any:
    """A real-robot source on ``[real]`` ports (none opened), recording into ``tap``."""
    from koala_bridge.runtime.real_source import RealRobotSource

    config = load_config(DEFAULT_CONFIG)
    config["real"] = real
    config["localisation"] = {**config.get("localisation", {}), "enabled": False}
    return RealRobotSource(config, BridgeSettings.from_config(config), dict, tap=tap)


def real_source_messages(frames: list[RangeFrame]) -> list[tuple[str, dict[str, Any]]]:
    """What the real source publishes (and records) for range frames read from the robot."""
    tap = _Tap()
    source = real_source({"rangefinders": "loop://"}, tap)
    robot, port = LoopbackTransport.pair()  # the robot's end writes, the source's end reads
    try:
        robot.write(b"".join(encode_range_frame(f) for f in frames))
        source._range_reader(port)()
    finally:
        robot.close()
        port.close()
    return [(channel, payload) for channel, _, payload in tap.records]


def test_the_real_robot_ir_from_kteam_polls_validates_too() -> None:
    tap = _Tap()
    source = real_source({"kteam": "loop://", "kteam_poll": ["N"]}, tap)
    counts = list(range(16))
    robot, port = LoopbackTransport.pair()
    source._kteam = port
    try:
        # The robot's reply is waiting before the poll: the poll drops what the port holds
        # first, so the reply goes in from a thread once the command has arrived.
        def robot_replies() -> None:
            robot.wait(5.0)
            robot.read()
            robot.write(("n," + ",".join(map(str, counts)) + "\r\n").encode())

        replier = threading.Thread(target=robot_replies)
        replier.start()
        source._poll_kteam("N")
        replier.join()
    finally:
        robot.close()
        port.close()
    [(topic, _, ir)] = tap.records
    assert topic == "sensors/ir"
    assert errors(ir, IrMessage.json_schema()) == []
    assert ir["counts"] == counts and ir["ambient"] == [None] * 16


def test_the_real_robot_ir_message_validates_against_the_recording_schema() -> None:
    counts = tuple(range(100, 116))
    sonar = (250, NO_ECHO, 1200, 0, 300, 400, 500, 600, 700)
    got = real_source_messages([RangeFrame(RangeKind.IR, 0, 0, counts),
                                RangeFrame(RangeKind.SONAR, 0, 0, sonar)])
    assert [topic for topic, _ in got] == ["sensors/ir", "sensors/sonar"]
    ir = got[0][1]
    assert errors(ir, IrMessage.json_schema()) == []
    assert ir == {"t": ir["t"], "counts": list(counts), "ambient": [None] * 16}  # not measured
    sonar_msg = got[1][1]
    assert errors(sonar_msg, topics.SonarMessage.json_schema()) == []
    assert sonar_msg["ranges"][:3] == [0.25, None, 1.2]


# -- the recording declares the derived schemas; the export's columns are the classes' ----------

def test_recorded_channels_declare_the_derived_schemas_and_export_uses_the_columns(
    tmp_path: Path,
) -> None:
    path = tmp_path / "all.mcap"
    world = world_message().to_json()
    published = [(t, m) for t, m in every_message() if t != "world"]
    with Recorder(path, world=world) as rec:
        for topic, message in published:
            rec.record(topic, message["t"], message)
    recording = open_recording(path)
    for topic in {t for t, _ in published}:
        schema = json.loads(recording.schemas["/" + topic])
        assert schema == topics.TOPICS[topic].json_schema()
        for m in recording.topic(topic):
            assert errors(m.json(), schema) == [], topic
    assert WorldMessage.parse(json.dumps(recording.world)).to_json() == world

    out = export_bundle(path, tmp_path / "bundle")
    expected_columns = {
        "truth_pose.csv": ("t", "x", "y", "theta"),
        "odometry.csv": ("t", "left_ticks", "right_ticks"),
        "gyro.csv": ("t", "yaw_rate"),
        "compass.csv": ("t", "mx", "my", "mz"),
    }
    assert {name: cls.csv_columns() for name, cls in TABLES.items()} == expected_columns
    for name, cls in TABLES.items():
        with (out / name).open(newline="") as f:
            rows = list(csv.reader(f))
        assert tuple(rows[0]) == cls.csv_columns()
        messages = [cls.from_json(m.json()) for m in recording.topic(cls.TOPIC)]
        assert [[float(v) for v in row] for row in rows[1:]] == [
            [float(v) for v in m.csv_row()] for m in messages
        ]
    with (out / "range.csv").open(newline="") as f:
        rows = list(csv.reader(f))
    assert tuple(rows[0]) == RANGE_COLUMNS
    assert len(rows) - 1 == 2 * (16 + 2)  # two IR and two sonar messages, one row per sensor
    with (out / "landmarks.csv").open(newline="") as f:
        assert tuple(next(csv.reader(f))) == LANDMARK_COLUMNS


def test_a_real_recording_exports_without_truth(tmp_path: Path) -> None:
    path = tmp_path / "real.mcap"
    ir = IrMessage(0.5, (3,) * 16, (None,) * 16)
    with Recorder(path) as rec:
        rec.record("sensors/ir", 0.5, ir.to_json())
        rec.record("sensors/ir", 0.6, {"t": 0.6, "counts": [4] * 16})  # before ambient
    out = export_bundle(path, tmp_path / "bundle")
    with (out / "range.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 32 and {r["true_range"] for r in rows} == {""}


# -- the world answer -----------------------------------------------------------------------------

def test_world_answer_is_built_from_the_world_and_validates() -> None:
    with DEFAULT_CONFIG.open("rb") as f:
        world = World.from_dict(tomllib.load(f)["world"])
    msg = WorldMessage.of(world, {"name": "koala"}).to_json()
    assert errors(msg, WorldMessage.json_schema()) == []
    assert list(msg) == ["name", "cols", "rows", "cell_m", "walls", "segments", "blocked",
                         "landmarks", "magnetic_sources", "earth_field", "start", "robot"]
    assert msg["walls"] == [list(w) for w in world.walled_sides()]
    assert msg["segments"] == world.segments.tolist()
    assert msg["landmarks"][0] == vars(world.landmarks[0])
    assert msg["start"] == (None if world.start is None else vars(world.start))


def test_sim_does_not_build_the_world_json() -> None:
    source = (REPO / "sim" / "world.py").read_text()
    assert "def to_dict" not in source


# -- layering --------------------------------------------------------------------------------------

def test_topics_is_the_lowest_layer() -> None:
    """core/topics.py imports the standard library only (and other core modules)."""
    tree = ast.parse((REPO / "bridge" / "core" / "topics.py").read_text())
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module)
    outside = {n for n in names if n.split(".")[0] not in sys.stdlib_module_names
               and not n.startswith("koala_bridge.core")}
    assert outside <= {"numpy"}, outside


def test_topic_message_classes_are_frozen() -> None:
    msg = TruthPose(0.0, 1.0, 2.0, 3.0)
    with pytest.raises(AttributeError):
        msg.x = 5.0  # type: ignore[misc]
    assert issubclass(WorldMessage, TopicMessage)
