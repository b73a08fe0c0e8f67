"""The Zenoh topics' payloads, each defined once as a typed message.

Every key the bridge publishes below its prefix (``truth/pose``, ``sensors/*``, ``status``,
``estimate/*``, ``map/occupancy``) and the answer of the ``world`` queryable is a frozen dataclass
here. From that one definition come:

* the JSON published on Zenoh and recorded in MCAP: :meth:`TopicMessage.to_json` (a ``dict``)
  and :meth:`TopicMessage.to_bytes` (compact, strict UTF-8 JSON; a non-finite number in a field
  typed ``float | None`` becomes ``null``);
* the JSON Schema each MCAP channel declares: :meth:`TopicMessage.json_schema`;
* the CSV columns of an export: :meth:`TopicMessage.csv_columns` (the scalar fields);
* the parser the monitor, snapshot and export use: :func:`parse` and
  :meth:`TopicMessage.from_json`, which raise :class:`TopicError` on a payload of another shape.

Field order is JSON member order. A field whose default is ``None`` is left out of the JSON when
it is ``None`` (the ``truth`` companion of a real robot's readings; the status members only one
source fills in); any other ``None`` is written as ``null``. docs/protocols.md ("Zenoh") gives
every field's unit and meaning; docs/recording.md how the recording uses the schemas.

This module is the lowest layer (standard library only): the simulator's readings, the real
robot's decoded frames and the estimators' results are turned into these messages by the
runtime (``runtime/zenoh_io.py``, ``runtime/real_source.py``, ``estimation/messages.py``).
"""

from __future__ import annotations

import base64
import dataclasses
import functools
import json
import math
import types
import typing
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from json.encoder import c_make_encoder, encode_basestring_ascii  # type: ignore[attr-defined]
from typing import Any, ClassVar, Literal, Protocol, TypeVar

import numpy as np
from koala_bridge.core.errors import TopicError  # re-exported: its old home

JSON_SCHEMA_DIALECT = "https://json-schema.org/draft/2020-12/schema"

GRID_ENCODING = "float32-le"
OCCUPANCY_ENCODING = "int8-logodds"

M = TypeVar("M", bound="TopicMessage")


def _doc(description: str = "", **schema: Any) -> Any:
    """A dataclass field carrying a schema description (and extra schema keywords)."""
    return field(metadata={"description": description, "schema": schema})


def _opt(description: str = "", **schema: Any) -> Any:
    """An optional member: default ``None``, left out of the JSON when ``None``."""
    return field(default=None, metadata={"description": description, "schema": schema})


# -- conversion, schema and parsing, driven by the type annotations --------------------------

def finite_or_none(v: Any) -> float | None:
    """``float(v)``, or None when it is None or not finite (JSON has no NaN/Infinity)."""
    if v is None:
        return None
    f = float(v)
    return f if math.isfinite(f) else None


def ints(values: Iterable[Any]) -> tuple[int, ...]:
    return tuple(map(int, values))


def nums(values: Iterable[Any]) -> tuple[float | None, ...]:
    """Finite floats, ``None`` for the rest (no echo, nothing in range, unknown)."""
    return tuple(map(finite_or_none, values))


def _optional_of(tp: Any) -> Any | None:
    """``X`` for ``X | None``, else None."""
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(args) == 1 and len(typing.get_args(tp)) == 2:
            return args[0]
    return None


def _encoder(tp: Any) -> Callable[[Any], Any]:
    """The function that turns a field value of type ``tp`` into its JSON-ready value."""
    inner = _optional_of(tp)
    if inner is float:
        return finite_or_none
    if inner is not None:
        enc = _encoder(inner)
        return lambda v: None if v is None else enc(v)
    if tp is float:
        return float
    if tp is int:
        return int
    if tp is str:
        return str
    if tp is bool:
        return bool
    if tp is Any or typing.get_origin(tp) is Literal:
        return lambda v: v
    if isinstance(tp, type) and dataclasses.is_dataclass(tp):
        return lambda v: v.to_json()
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin is tuple:
        if len(args) == 2 and args[1] is Ellipsis:
            item = _encoder(args[0])
            return lambda v: list(map(item, v))
        encs = [_encoder(a) for a in args]
        return lambda v: [enc(e) for enc, e in zip(encs, v, strict=True)]
    if origin in (dict, Mapping):
        value = _encoder(args[1])
        return lambda v: {str(k): value(e) for k, e in v.items()}
    raise TypeError(f"no JSON encoding for the field type {tp!r}")


_JSON_TYPES: dict[Any, str] = {float: "number", int: "integer", str: "string", bool: "boolean"}


def _schema(tp: Any) -> dict[str, Any]:
    """The JSON Schema of a value of type ``tp``."""
    inner = _optional_of(tp)
    if inner is not None:
        s = _schema(inner)
        if isinstance(s.get("type"), str):
            return {**s, "type": [s["type"], "null"]}
        return {"anyOf": [s, {"type": "null"}]}
    if tp in _JSON_TYPES:
        return {"type": _JSON_TYPES[tp]}
    if tp is Any:
        return {}
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin is Literal:
        return {"const": args[0]} if len(args) == 1 else {"enum": list(args)}
    if isinstance(tp, type) and dataclasses.is_dataclass(tp):
        return _object_schema(tp)  # type: ignore[arg-type]
    if origin is tuple:
        if len(args) == 2 and args[1] is Ellipsis:
            return {"type": "array", "items": _schema(args[0])}
        return {
            "type": "array",
            "prefixItems": [_schema(a) for a in args],
            "minItems": len(args),
            "maxItems": len(args),
        }
    if origin in (dict, Mapping):
        value = _schema(args[1])
        return {"type": "object", "additionalProperties": value} if value else {"type": "object"}
    raise TypeError(f"no JSON Schema for the field type {tp!r}")


def _object_schema(cls: type[_Message]) -> dict[str, Any]:
    props: dict[str, Any] = {}
    for f, tp in _fields(cls):
        s = {**_schema(tp), **f.metadata.get("schema", {})}
        if f.metadata.get("description"):
            s["description"] = f.metadata["description"]
        props[f.name] = s
    required = [f.name for f, _ in _fields(cls) if not _optional_member(f)]
    return {"type": "object", "properties": props, "required": required}


def _decoder(tp: Any, where: str) -> Callable[[Any], Any]:
    """The function that checks a JSON value against ``tp`` and returns the field value
    (numbers as they were decoded: an integer in a float field stays an ``int``)."""
    inner = _optional_of(tp)
    if inner is not None:
        dec = _decoder(inner, where)
        return lambda v: None if v is None else dec(v)

    def bad(v: Any, what: str) -> TopicError:
        return TopicError(f"{where}: expected {what}, got {json.dumps(v)[:40]}")

    if tp is float:
        def number(v: Any) -> Any:
            if isinstance(v, bool) or not isinstance(v, int | float):
                raise bad(v, "a number")
            return v
        return number
    if tp in (int, str, bool):
        def scalar(v: Any) -> Any:
            if not isinstance(v, tp) or (tp is int and isinstance(v, bool)):
                raise bad(v, _JSON_TYPES[tp])
            return v
        return scalar
    if tp is Any:
        return lambda v: v
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin is Literal:
        def const(v: Any) -> Any:
            if v not in args:
                raise bad(v, " or ".join(json.dumps(a) for a in args))
            return v
        return const
    if isinstance(tp, type) and issubclass(tp, _Message):
        message: Any = tp
        return lambda v: message.from_json(v, where)
    if origin is tuple:
        if len(args) == 2 and args[1] is Ellipsis:
            item = _decoder(args[0], where)

            def array(v: Any) -> tuple[Any, ...]:
                if not isinstance(v, list):
                    raise bad(v, "an array")
                return tuple(item(e) for e in v)
            return array
        decs = [_decoder(a, where) for a in args]

        def fixed(v: Any) -> tuple[Any, ...]:
            if not isinstance(v, list) or len(v) != len(decs):
                raise bad(v, f"an array of {len(decs)}")
            return tuple(dec(e) for dec, e in zip(decs, v, strict=True))
        return fixed
    if origin in (dict, Mapping):
        value = _decoder(args[1], where)

        def obj(v: Any) -> dict[str, Any]:
            if not isinstance(v, dict):
                raise bad(v, "an object")
            return {k: value(e) for k, e in v.items()}
        return obj
    raise TypeError(f"no JSON decoding for the field type {tp!r}")


def _optional_member(f: dataclasses.Field[Any]) -> bool:
    return f.default is None


_FieldTypes = tuple[tuple[dataclasses.Field[Any], Any], ...]
_Codecs = tuple[tuple[str, bool, Callable[[Any], Any]], ...]


def _fields_of(cls: type) -> _FieldTypes:
    hints = typing.get_type_hints(cls)
    return tuple((f, hints[f.name]) for f in dataclasses.fields(cls))


def _encoders_of(cls: type) -> _Codecs:
    return tuple((f.name, _optional_member(f), _encoder(tp)) for f, tp in _fields(cls))


def _decoders_of(cls: type) -> _Codecs:
    name = getattr(cls, "TOPIC", "") or cls.__name__
    return tuple(
        (f.name, _optional_member(f), _decoder(tp, f"{name}.{f.name}")) for f, tp in _fields(cls)
    )


# Worked out once per class (the type hints are resolved and the codecs built on first use).
_fields: Callable[[type], _FieldTypes] = functools.cache(_fields_of)
_encoders: Callable[[type], _Codecs] = functools.cache(_encoders_of)
_decoders: Callable[[type], _Codecs] = functools.cache(_decoders_of)


class _Message:
    """JSON conversion shared by the messages and their nested parts (``truth``, ...)."""

    def to_json(self) -> dict[str, Any]:
        """The JSON-ready ``dict`` (members in field order)."""
        out: dict[str, Any] = {}
        for name, optional, encode in _encoders(type(self)):
            v = getattr(self, name)
            if v is None and optional:
                continue
            out[name] = encode(v)
        return out

    @classmethod
    def from_json(cls: type[Any], d: Any, where: str = "") -> Any:
        """The message of a decoded JSON payload; members it does not know are ignored.

        Raises :class:`TopicError` when a required member is missing or has the wrong type.
        """
        if not isinstance(d, Mapping):
            raise TopicError(f"{where or cls.__name__}: expected a JSON object")
        kwargs: dict[str, Any] = {}
        for name, optional, decode in _decoders(cls):
            if name in d:
                kwargs[name] = decode(d[name])
            elif not optional:
                raise TopicError(f"{where or getattr(cls, 'TOPIC', cls.__name__)}: "
                                 f"no member {name!r}")
        return cls(**kwargs)


class TopicMessage(_Message):
    """A payload published under ``<prefix>/<TOPIC>``; ``TITLE`` names its schema."""

    TOPIC: ClassVar[str]
    TITLE: ClassVar[str]

    def to_bytes(self) -> bytes:
        """Compact strict JSON (no NaN/Infinity literals) as UTF-8: the Zenoh payload."""
        return encode(self.to_json())

    @classmethod
    def json_schema(cls) -> dict[str, Any]:
        """The JSON Schema (draft 2020-12) of this topic, as its MCAP channel declares it."""
        return {"$schema": JSON_SCHEMA_DIALECT, "title": cls.TITLE, **_object_schema(cls)}

    @classmethod
    def csv_columns(cls) -> tuple[str, ...]:
        """The scalar members (numbers, integers, strings): one CSV column each."""
        return tuple(
            f.name for f, tp in _fields(cls) if (_optional_of(tp) or tp) in (float, int, str)
        )

    def csv_row(self) -> tuple[Any, ...]:
        """The values of :meth:`csv_columns`, in that order."""
        return tuple(getattr(self, c) for c in self.csv_columns())

    @classmethod
    def parse(cls: type[M], payload: bytes | str | Mapping[str, Any]) -> M:
        """The message of a payload (bytes or text as published, or decoded JSON)."""
        if isinstance(payload, bytes | str):
            try:
                payload = json.loads(payload)
            except ValueError as e:
                raise TopicError(f"{cls.TOPIC}: not JSON ({e})") from e
        return typing.cast(M, cls.from_json(payload))


# One encoder for every payload: ``json.dumps`` with options builds a new one per call.
_JSON = json.JSONEncoder(allow_nan=False, separators=(",", ":"))
# ``JSONEncoder.encode`` also builds its C scanner anew on every call (~1 us of a few-us
# payload); this is that scanner, built once with the same options (json/encoder.py,
# ``iterencode``), so the bytes are the same. No circular-reference bookkeeping: a payload is a
# tree of typed messages. None when the C accelerator is missing.
_C_JSON = None if c_make_encoder is None else c_make_encoder(
    None, _JSON.default, encode_basestring_ascii, None, ":", ",", False, False, False
)


def encode(message: Mapping[str, Any]) -> bytes:
    """Strict JSON (no NaN/Infinity literals), compact, as UTF-8."""
    if _C_JSON is None or not isinstance(message, dict):
        return _JSON.encode(message).encode()
    return "".join(_C_JSON(message, 0)).encode()


def _t() -> Any:
    """The ``t`` member (a new field object per class: dataclasses bind a field to its class)."""
    return _doc("simulation time, s (a real robot: host seconds since the start)")
_TRUTH = "noise-free companion (simulation only)"


# -- truth/pose ----------------------------------------------------------------------------------

@dataclass(frozen=True)
class TruthPose(TopicMessage):
    """``truth/pose``: the robot's true pose, world frame (m, m, rad)."""

    TOPIC: ClassVar[str] = "truth/pose"
    TITLE: ClassVar[str] = "koala.truth.Pose"

    t: float = _t()
    x: float = _doc()
    y: float = _doc()
    theta: float = _doc()


def _sensor_rows(measured: tuple[Any, ...], truth: Any) -> list[tuple[Any, Any, Any, Any]]:
    ranges = truth.ranges if truth is not None else ()
    incidence = truth.incidence if truth is not None else ()

    def at(seq: tuple[Any, ...], i: int) -> Any:
        return seq[i] if i < len(seq) else None

    return [(i, v, at(ranges, i), at(incidence, i)) for i, v in enumerate(measured)]


# -- sensors -------------------------------------------------------------------------------------

@dataclass(frozen=True)
class IrTruth(_Message):
    counts: tuple[int, ...]
    ranges: tuple[float | None, ...] = _doc("m along each axis; null: nothing in range")
    incidence: tuple[float | None, ...] = _doc("rad; null: no surface, or not known")


@dataclass(frozen=True)
class IrMessage(TopicMessage):
    """``sensors/ir``: proximity and ambient counts of the n IR sensors.

    ``ambient`` is null for a sensor whose ambient light was not measured (a real robot's range
    frames and K-Team ``N`` replies carry proximity only).
    """

    TOPIC: ClassVar[str] = "sensors/ir"
    TITLE: ClassVar[str] = "koala.sensors.Ir"

    t: float = _t()
    counts: tuple[int, ...] = _doc("proximity counts 0..1023")
    ambient: tuple[int | None, ...] = _doc("ambient-light counts 0..1023; null: not measured")
    truth: IrTruth | None = _opt(_TRUTH)

    def sensor_rows(self) -> list[tuple[int, int | None, float | None, float | None]]:
        """``(sensor, measured counts, true range m, incidence rad)`` per sensor (export's
        ``range.csv``); the truth columns are None where the message has no truth."""
        return _sensor_rows(self.counts, self.truth)

    @classmethod
    def from_json(cls, d: Any, where: str = "") -> IrMessage:
        # Recordings of a real robot made before ambient was published lack it: not measured.
        if isinstance(d, Mapping) and "ambient" not in d and isinstance(d.get("counts"), list):
            d = {**d, "ambient": [None] * len(d["counts"])}
        return typing.cast(IrMessage, super().from_json(d, where))


@dataclass(frozen=True)
class SonarTruth(_Message):
    ranges: tuple[float | None, ...]
    incidence: tuple[float | None, ...]


@dataclass(frozen=True)
class SonarMessage(TopicMessage):
    """``sensors/sonar``: first echo of each sonar, m (null: no echo; 0.0: too near)."""

    TOPIC: ClassVar[str] = "sensors/sonar"
    TITLE: ClassVar[str] = "koala.sensors.Sonar"

    t: float = _t()
    ranges: tuple[float | None, ...] = _doc("m; null: no echo")
    truth: SonarTruth | None = _opt(_TRUTH)

    def sensor_rows(self) -> list[tuple[int, float | None, float | None, float | None]]:
        """``(sensor, measured m, true range m, incidence rad)`` per sensor (export's
        ``range.csv``); None where there was no echo or the message has no truth."""
        return _sensor_rows(self.ranges, self.truth)


@dataclass(frozen=True)
class OdometryTruth(_Message):
    left_ticks: int
    right_ticks: int


@dataclass(frozen=True)
class OdometryMessage(TopicMessage):
    """``sensors/odometry``: cumulative encoder counts since the start."""

    TOPIC: ClassVar[str] = "sensors/odometry"
    TITLE: ClassVar[str] = "koala.sensors.Odometry"

    t: float = _t()
    left_ticks: int = _doc()
    right_ticks: int = _doc()
    truth: OdometryTruth | None = _opt(_TRUTH)


@dataclass(frozen=True)
class GyroTruth(_Message):
    yaw_rate: float


@dataclass(frozen=True)
class GyroMessage(TopicMessage):
    """``sensors/gyro``: yaw rate about body z, rad/s, counter-clockwise positive."""

    TOPIC: ClassVar[str] = "sensors/gyro"
    TITLE: ClassVar[str] = "koala.sensors.Gyro"

    t: float = _t()
    yaw_rate: float = _doc("rad/s")
    truth: GyroTruth | None = _opt(_TRUTH)


@dataclass(frozen=True)
class CompassTruth(_Message):
    mx: float
    my: float
    mz: float


@dataclass(frozen=True)
class CompassMessage(TopicMessage):
    """``sensors/compass``: magnetic field in the body FLU frame, uT."""

    TOPIC: ClassVar[str] = "sensors/compass"
    TITLE: ClassVar[str] = "koala.sensors.Compass"

    t: float = _t()
    mx: float = _doc("uT")
    my: float = _doc("uT")
    mz: float = _doc("uT")
    truth: CompassTruth | None = _opt(_TRUTH)


@dataclass(frozen=True)
class Observation(_Message):
    """A landmark seen by the camera: range (m) and bearing (rad, CCW from the heading)."""

    id: int
    range: float | None
    bearing: float | None


@dataclass(frozen=True)
class CameraTruth(_Message):
    observations: tuple[Observation, ...]


@dataclass(frozen=True)
class CameraMessage(TopicMessage):
    """``sensors/camera``: the landmarks the camera reports, ordered by id."""

    TOPIC: ClassVar[str] = "sensors/camera"
    TITLE: ClassVar[str] = "koala.sensors.Camera"

    t: float = _t()
    observations: tuple[Observation, ...] = _doc()
    truth: CameraTruth | None = _opt(_TRUTH)


# -- status --------------------------------------------------------------------------------------

@dataclass(frozen=True)
class StatusMessage(TopicMessage):
    """``status``: real-time factor and per-bus counters (``sent``, ``received``, ``rejected``,
    ``dropped``); the simulated service adds the motor command's source and the LEDs, the real
    source says ``source: "real"``; both add the estimator node's counters when it runs."""

    TOPIC: ClassVar[str] = "status"
    TITLE: ClassVar[str] = "koala.Status"

    t: float = _t()
    real_time_factor: float | None = _doc("simulation s per wall s; null if not finite")
    buses: dict[str, dict[str, int]] = _doc("per bus: sent, received, rejected, dropped")
    motor_command_source: str | None = _opt("the bus of the wheel command in force")
    leds: tuple[int, ...] | None = _opt("[lateral, frontal], 0 off / 1 on")
    source: str | None = _opt("\"real\" for a real robot")
    localisation: dict[str, Any] | None = _opt("the estimator node's counters")
    lockstep: dict[str, Any] | None = _opt(
        "--clock lockstep: engaged (false while held at t = 0), cycles (granted by the "
        "firmware's cycle message), explicit (by lockstep/step), misses (stepped after a "
        "quiet timeout), unpaced_steps (stepped while a disconnect fault cut the firmware's "
        "command bus)")
    faults: dict[str, int] | None = _opt("injected faults so far, per fault name")
    bus_load: dict[str, float] | None = _opt(
        "wire timing: busy fraction of each paced bus over the last status period")


@dataclass(frozen=True)
class FaultEventMessage(TopicMessage):
    """``events/fault``: one injected fault (docs/faults.md): a frame dropped, corrupted,
    delayed, ..., a window opening or closing, a kidnap."""

    TOPIC: ClassVar[str] = "events/fault"
    TITLE: ClassVar[str] = "koala.events.Fault"

    t: float = _t()
    name: str = _doc("the fault's name ([[faults]] name, or kind:target#index)")
    kind: str = _doc("drop, corrupt, delay, duplicate, reorder, stuck, ... (docs/faults.md)")
    target: str = _doc("the bus or stream")
    detail: dict[str, Any] = _doc("what happened, kind-specific")


# -- estimates (the localisation node) -----------------------------------------------------------

@dataclass(frozen=True)
class EstimatePose(TopicMessage):
    """``estimate/pose``: the pose filter's estimate and its covariance."""

    TOPIC: ClassVar[str] = "estimate/pose"
    TITLE: ClassVar[str] = "koala.estimate.Pose"

    t: float = _t()
    x: float = _doc()
    y: float = _doc()
    theta: float = _doc()
    cov: tuple[tuple[float, ...], ...] = _doc("3x3 covariance of x, y, theta")


@dataclass(frozen=True)
class EstimateHealth(TopicMessage):
    """``estimate/health``: whether the pose estimate can be trusted (docs/localisation.md
    "Health"), at ``health_rate_hz`` and at every change of state."""

    TOPIC: ClassVar[str] = "estimate/health"
    TITLE: ClassVar[str] = "koala.estimate.Health"

    t: float = _t()
    state: Literal["tracking", "uncertain", "lost", "relocalising"] = _doc()
    reasons: tuple[str, ...] = _doc(
        "why not tracking: wheel_slip, wall_contact, covariance_large, no_absolute_fix, "
        "evidence_disputed, innovations_rejected, absolute_references_rejected, "
        "estimate_in_wall")
    sigma_xy_m: float = _doc("the larger of the position standard deviations")
    sigma_theta_deg: float = _doc("heading standard deviation")
    accepted: int = _doc("informative readings (landmarks, map ranges) accepted in the window")
    rejected: int = _doc("... and gated out")
    relocalisations: int = _doc("global relocalisations completed since the start")


@dataclass(frozen=True)
class EstimateCell(TopicMessage):
    """``estimate/cell``: the grid filter's most probable cell and its probability."""

    TOPIC: ClassVar[str] = "estimate/cell"
    TITLE: ClassVar[str] = "koala.estimate.Cell"

    t: float = _t()
    cell: tuple[int, ...] = _doc("[col, row], row 0 south")
    p: float = _doc("probability of that cell")


@dataclass(frozen=True)
class EstimateGrid(TopicMessage):
    """``estimate/grid``: the whole belief as base64 little-endian float32."""

    TOPIC: ClassVar[str] = "estimate/grid"
    TITLE: ClassVar[str] = "koala.estimate.Grid"

    t: float = _t()
    cols: int = _doc()
    rows: int = _doc()
    cell_m: float = _doc()
    encoding: Literal["float32-le"] = _doc()
    data: str = _doc(
        "rows*cols float32 probabilities, row-major from SW", contentEncoding="base64"
    )
    cell: tuple[int, ...] = _doc("[col, row], row 0 south")
    p: float = _doc()

    def probabilities(self) -> np.ndarray:
        """The ``(rows, cols)`` belief as floats, row 0 south. Raises :class:`TopicError` when
        ``data`` does not hold ``rows * cols`` float32 values."""
        return _cells(self.TOPIC, self.data, "<f4", self.rows, self.cols)


@dataclass(frozen=True)
class OccupancyMap(TopicMessage):
    """``map/occupancy``: log-odds quantised to int8, base64."""

    TOPIC: ClassVar[str] = "map/occupancy"
    TITLE: ClassVar[str] = "koala.map.Occupancy"

    t: float = _t()
    cols: int = _doc()
    rows: int = _doc()
    resolution_m: float = _doc()
    origin: tuple[float, ...] = _doc()
    encoding: Literal["int8-logodds"] = _doc()
    scale: float = _doc("log-odds = q * scale; P(occ) = 1/(1+exp(-l))")
    data: str = _doc(
        "rows*cols int8 q, row-major from the SW corner, 0 unknown", contentEncoding="base64"
    )

    def log_odds(self) -> np.ndarray:
        """The ``(rows, cols)`` log-odds ``q * scale``, row 0 south (0: unknown). Raises
        :class:`TopicError` when ``data`` does not hold ``rows * cols`` int8 values."""
        return _cells(self.TOPIC, self.data, "i1", self.rows, self.cols) * self.scale

    def p_occupied(self) -> np.ndarray:
        """``P(occupied) = 1 / (1 + exp(-l))`` per cell (0.5 where unknown)."""
        return 1.0 / (1.0 + np.exp(-self.log_odds()))


def _cells(topic: str, data: str, dtype: str, rows: int, cols: int) -> np.ndarray:
    """A base64 row-major grid of ``dtype`` as a ``(rows, cols)`` float array."""
    try:
        a = np.frombuffer(base64.b64decode(data, validate=True), dtype=dtype)
    except ValueError as e:  # binascii.Error, or a length that is not a whole number of cells
        raise TopicError(f"{topic}: data is not base64 {dtype} cells ({e})") from e
    if a.size != rows * cols:
        raise TopicError(f"{topic}: data holds {a.size} cells, expected {rows}x{cols}")
    return a.reshape(rows, cols).astype(float)


# -- the world queryable -------------------------------------------------------------------------

@dataclass(frozen=True)
class LandmarkInfo(_Message):
    id: int
    colour: str
    x: float
    y: float
    facing_deg: float
    a_max_deg: float


@dataclass(frozen=True)
class MagneticSourceInfo(_Message):
    x: float
    y: float
    strength_uT: float


@dataclass(frozen=True)
class EarthFieldInfo(_Message):
    horizontal_uT: float
    vertical_uT: float
    north_deg: float


@dataclass(frozen=True)
class StartPoseInfo(_Message):
    x: float
    y: float
    theta: float


class WorldLike(Protocol):
    """What :meth:`WorldMessage.of` reads of a world (``koala_bridge.sim.world.World``)."""

    name: str
    cols: int
    rows: int
    cell_m: float

    @property
    def segments(self) -> Any: ...          # (n, 4) array of x1, y1, x2, y2
    @property
    def blocked(self) -> Iterable[tuple[int, int]]: ...
    @property
    def landmarks(self) -> Iterable[Any]: ...
    @property
    def magnetic_sources(self) -> Iterable[Any]: ...
    @property
    def earth_field(self) -> Any: ...
    @property
    def start(self) -> Any: ...

    def walled_sides(self) -> Iterable[tuple[int, int, str]]: ...


@dataclass(frozen=True)
class WorldMessage(TopicMessage):
    """The answer of the ``<prefix>/world`` queryable: the world and the robot's description."""

    TOPIC: ClassVar[str] = "world"
    TITLE: ClassVar[str] = "koala.World"

    name: str
    cols: int
    rows: int
    cell_m: float
    walls: tuple[tuple[int, int, str], ...] = _doc("[col, row, side]: every walled cell side")
    segments: tuple[tuple[float, ...], ...] = _doc("[x1, y1, x2, y2] m: every wall once")
    blocked: tuple[tuple[int, ...], ...] = _doc("[col, row]")
    landmarks: tuple[LandmarkInfo, ...] = _doc()
    magnetic_sources: tuple[MagneticSourceInfo, ...] = _doc()
    earth_field: EarthFieldInfo = _doc()
    start: StartPoseInfo | None = _doc("m, m, rad; null: the first free cell's centre")
    robot: dict[str, Any] = _doc("the robot's and its sensors' parameters")

    @classmethod
    def of(cls, world: WorldLike, robot: Mapping[str, Any]) -> WorldMessage:
        """The answer for ``world`` and the robot description ``robot`` (JSON-ready)."""
        ef, start = world.earth_field, world.start
        return cls(
            name=world.name,
            cols=world.cols,
            rows=world.rows,
            cell_m=world.cell_m,
            walls=tuple((int(c), int(r), str(s)) for c, r, s in world.walled_sides()),
            segments=tuple(tuple(float(v) for v in s) for s in world.segments),
            blocked=tuple(sorted((int(c), int(r)) for c, r in world.blocked)),
            landmarks=tuple(
                LandmarkInfo(lm.id, lm.colour, lm.x, lm.y, lm.facing_deg, lm.a_max_deg)
                for lm in world.landmarks
            ),
            magnetic_sources=tuple(
                MagneticSourceInfo(m.x, m.y, m.strength_uT) for m in world.magnetic_sources
            ),
            earth_field=EarthFieldInfo(ef.horizontal_uT, ef.vertical_uT, ef.north_deg),
            start=None if start is None else StartPoseInfo(start.x, start.y, start.theta),
            robot=dict(robot),
        )


# -- the table of topics -------------------------------------------------------------------------

#: Every published key below the prefix (and the ``world`` queryable) -> its message class.
TOPICS: dict[str, type[TopicMessage]] = {
    cls.TOPIC: cls
    for cls in (
        TruthPose, IrMessage, SonarMessage, OdometryMessage, GyroMessage, CompassMessage,
        CameraMessage, StatusMessage, EstimatePose, EstimateHealth, EstimateCell, EstimateGrid,
        OccupancyMap,
        FaultEventMessage, WorldMessage,
    )
}

#: The published keys (what a recording has channels for; ``world`` is a queryable).
PUBLISHED_TOPICS: tuple[str, ...] = tuple(k for k in TOPICS if k != WorldMessage.TOPIC)


def parse(topic: str, payload: bytes | str | Mapping[str, Any]) -> TopicMessage:
    """The message of ``payload`` published on the key ``topic`` (below the prefix).

    Raises :class:`TopicError` for a key without a message class or a payload of another shape.
    """
    cls = TOPICS.get(topic.strip("/"))
    if cls is None:
        raise TopicError(f"{topic!r} is not a koala-bridge topic")
    return cls.parse(payload)


def json_schema(topic: str) -> dict[str, Any]:
    """The JSON Schema of ``topic``; a key without a message class gets the generic one (an
    object with a time ``t``)."""
    cls = TOPICS.get(topic.strip("/"))
    if cls is not None:
        return cls.json_schema()
    return generic_schema(topic)


def generic_schema(topic: str) -> dict[str, Any]:
    """The schema of a key without a message class: an object with a time ``t``."""
    return {
        "$schema": JSON_SCHEMA_DIALECT,
        "title": "koala." + topic.strip("/").replace("/", "."),
        "type": "object",
        "properties": {"t": {"type": "number", "description": "simulation time, s"}},
        "required": ["t"],
    }


def pose_of(payload: Any) -> TruthPose | None:
    """The ``(t, x, y, theta)`` of a pose payload (``truth/pose`` or the pose part of
    ``estimate/pose``), or None when it has none."""
    try:
        return TruthPose.from_json(payload)  # type: ignore[no-any-return]
    except TopicError:
        return None
