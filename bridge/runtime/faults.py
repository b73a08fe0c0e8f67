"""Fault injection: what a firmware must survive, drawn from the run's seed (docs/faults.md).

A fault is one ``[[faults]]`` table of the configuration or one ``--fault KIND:TARGET[:k=v,...]``
option (:data:`FAULT_HELP`), validated into a :class:`FaultSpec`: a kind, a target (a bus of
:data:`FRAME_BUSES`, a sensor stream of :data:`SENSOR_STREAMS`, a wheel, the robot), a window
``start_s <= t < end_s`` in simulated seconds, a probability and the kind's parameters.

:class:`FaultInjector` applies them. The simulation loop (bridge/runtime/sim_source.py) hands it
every outbound frame (:meth:`FaultInjector.on_frame`), every step's readings
(:meth:`~FaultInjector.on_readings`) and the simulator (:meth:`~FaultInjector.apply_to_sim`), asks
which buses are gone (:meth:`~FaultInjector.disconnected`, :meth:`~FaultInjector.bus_off`) and
which CAN error frames to send (:meth:`~FaultInjector.can_error_frames`). Every injected fault is
a :class:`FaultEvent` (:meth:`~FaultInjector.events`) and is counted per fault name
(:meth:`~FaultInjector.counts`).

Randomness: fault ``i`` (its position in the list, config tables first, then ``--fault``
options, then faults added at run time) draws from its own
``numpy.random.default_rng([seed, 0x0FA1, i])``, so its decisions depend on the run's seed and on
its own calls only -- not on the other faults, nor on the simulator's streams (which this module
never touches). Frame faults draw one uniform per frame on their bus inside their window (the
frame is hit when it is below ``probability``) plus what the hit needs (bit positions, jitter);
``glitch`` likewise per reading of its stream (plus the sign and the sensor of a hit); windowed
faults (``disconnect``, ``bus_off``, ``stuck``, ``stuck_max``, ``bias``,
``magnetic_anomaly``, ``wheel_slip``) draw once, when their window opens, whether they happen at
all; ``error_frames`` draws once per period; ``kidnap`` once. Draws are made in call order, in
simulated time, so the same config, seed and call sequence give the same faults.

Every method takes the simulated time ``t``; calls must not go back in time (a call with an
earlier ``t`` than the last one is treated as happening at the last one). The methods are
thread-safe (one lock), since the K-Team replies are written from a reader thread.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import threading
import tomllib
from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Annotated, Any, Self, cast

import can
import numpy as np
from koala_bridge.core.schema import (
    ConfigError,
    Finite,
    FloatOrInf,
    NonNegative,
    NonNegativeInt,
    Positive,
    Str,
    one_of,
    section,
    tuples,
    validate,
)
from koala_bridge.sim.sensors.compass import field_body
from koala_bridge.sim.types import (
    CompassReading,
    GyroReading,
    IrReading,
    OdometryReading,
    Readings,
    SonarReading,
)
from pydantic import AfterValidator, BeforeValidator, Field, Strict

if TYPE_CHECKING:
    from koala_bridge.sim.simulator import Simulator

__all__ = [
    "CAN_ERRORS",
    "FAULT_HELP",
    "FAULT_KINDS",
    "FRAME_BUSES",
    "SENSOR_STREAMS",
    "Delivery",
    "FaultEvent",
    "FaultInjector",
    "FaultSpec",
    "anomaly_field_world",
    "can_error_frame",
    "fault_spec",
    "faults_from_config",
    "flip_bits",
    "parse_fault_option",
]

#: Outbound (robot -> firmware) frame buses: the K-Team serial replies and pushed lines, the binary
#: range frames, CAN (every CAN interface), MAVLink.
FRAME_BUSES = ("kteam", "rangefinders", "can", "mavlink")
#: Sensor streams of :class:`koala_bridge.sim.types.Readings` a sensor fault can hit.
SENSOR_STREAMS = ("ir", "sonar", "gyro", "compass", "encoders")
#: Targets of ``wheel_slip``.
WHEELS = ("left", "right", "both")
#: The CAN bus errors an ``error_frames`` fault signals (:func:`can_error_frame`).
CAN_ERRORS = ("crc", "stuff", "form", "bit", "ack")

# linux/can/error.h (SocketCAN): error classes in the error frame's can_id, and the protocol error
# type (data[2]) and location (data[3]). python-can carries the class in ``arbitration_id`` with
# ``is_error_frame`` set, as its socketcan interface does (``can_id & CAN_ERR_MASK``).
CAN_ERR_DLC = 8
CAN_ERR_CRTL = 0x004
CAN_ERR_PROT = 0x008
CAN_ERR_ACK = 0x020
CAN_ERR_BUSOFF = 0x040
CAN_ERR_BUSERROR = 0x080
CAN_ERR_RESTARTED = 0x100
CAN_ERR_PROT_BIT = 0x01
CAN_ERR_PROT_FORM = 0x02
CAN_ERR_PROT_STUFF = 0x04
CAN_ERR_PROT_LOC_CRC_SEQ = 0x08
CAN_ERR_PROT_LOC_ACK = 0x19

#: (class, data[2] type, data[3] location) of each bus error of :data:`CAN_ERRORS`.
_BUS_ERRORS: dict[str, tuple[int, int, int]] = {
    "crc": (CAN_ERR_PROT | CAN_ERR_BUSERROR, 0x00, CAN_ERR_PROT_LOC_CRC_SEQ),
    "stuff": (CAN_ERR_PROT | CAN_ERR_BUSERROR, CAN_ERR_PROT_STUFF, 0x00),
    "form": (CAN_ERR_PROT | CAN_ERR_BUSERROR, CAN_ERR_PROT_FORM, 0x00),
    "bit": (CAN_ERR_PROT | CAN_ERR_BUSERROR, CAN_ERR_PROT_BIT, 0x00),
    "ack": (CAN_ERR_ACK | CAN_ERR_PROT | CAN_ERR_BUSERROR, 0x00, CAN_ERR_PROT_LOC_ACK),
}

#: How a fault's probability is used (module docstring).
_FRAME, _SAMPLE, _WINDOW, _PERIODIC, _ONCE = "frame", "sample", "window", "periodic", "once"


@dataclass(frozen=True)
class _KindInfo:
    mode: str                   # _FRAME | _SAMPLE | _WINDOW | _PERIODIC | _ONCE
    targets: tuple[str, ...]
    params: tuple[str, ...] = ()      # its own keys besides the common ones
    required: tuple[str, ...] = ()    # of params, the keys that have no default


_KINDS: dict[str, _KindInfo] = {
    "drop": _KindInfo(_FRAME, FRAME_BUSES),
    "corrupt": _KindInfo(_FRAME, FRAME_BUSES, ("bits",)),
    "delay": _KindInfo(_FRAME, FRAME_BUSES, ("delay_s", "jitter_s")),
    "duplicate": _KindInfo(_FRAME, FRAME_BUSES),
    "reorder": _KindInfo(_FRAME, FRAME_BUSES),
    "disconnect": _KindInfo(_WINDOW, FRAME_BUSES),
    "error_frames": _KindInfo(_PERIODIC, ("can",), ("period_s", "error")),
    "bus_off": _KindInfo(_WINDOW, ("can",)),
    "stuck": _KindInfo(_WINDOW, SENSOR_STREAMS, ("sensors",)),
    "stuck_max": _KindInfo(_WINDOW, ("ir", "sonar"), ("sensors",)),
    "glitch": _KindInfo(_SAMPLE, ("ir", "sonar", "gyro", "compass"), ("magnitude", "sensors"),
                        ("magnitude",)),
    "bias": _KindInfo(_WINDOW, ("gyro",), ("bias",), ("bias",)),
    "magnetic_anomaly": _KindInfo(_WINDOW, ("compass",), ("x", "y", "strength_uT", "radius_m"),
                                  ("x", "y", "strength_uT")),
    "wheel_slip": _KindInfo(_WINDOW, WHEELS, ("traction",)),
    "kidnap": _KindInfo(_ONCE, ("robot",), ("x", "y", "theta_deg"), ("x", "y")),
}

#: Every fault kind (docs/faults.md has the table).
FAULT_KINDS: tuple[str, ...] = tuple(_KINDS)
#: The keys every fault has.
_COMMON = ("kind", "target", "start_s", "end_s", "probability", "name")
#: Every kind-specific key.
_PARAMS = tuple(dict.fromkeys(p for k in _KINDS.values() for p in k.params))


def _probability(v: float) -> float:
    if not 0.0 <= v <= 1.0:
        raise ValueError(f"must be in [0, 1], got {v!r}")
    return v


def _not_negative(v: float) -> float:
    if v < 0:
        raise ValueError(f"must be >= 0, got {v!r}")
    return v


def _traction(v: float) -> float:
    if not 0.0 <= v <= 1.0:
        raise ValueError(f"must be a traction in [0, 1] (0: the wheel spins in place, 1: no "
                         f"slip), got {v!r}")
    return v


@section
class FaultSpec:
    """One fault, validated (a ``[[faults]]`` table or a ``--fault`` option).

    Common keys: ``kind`` (:data:`FAULT_KINDS`), ``target`` (depends on the kind), ``start_s`` /
    ``end_s`` (simulated seconds; the fault is active for ``start_s <= t < end_s``; ``end_s`` inf
    = until the run ends), ``probability`` (per frame, per window or per period: module
    docstring), ``name`` (in events and ``status``; "" = ``KIND:TARGET#N``, N its 1-based position).
    The other fields are the kinds' parameters; a kind accepts only its own (docs/faults.md).
    Construction validates; :func:`fault_spec` turns a table into one with one-line
    :class:`ConfigError` messages.
    """

    kind: Annotated[Str, one_of(FAULT_KINDS)]
    target: Str
    start_s: NonNegative = 0.0
    end_s: Annotated[FloatOrInf, AfterValidator(_not_negative)] = math.inf
    probability: Annotated[Finite, AfterValidator(_probability)] = 1.0
    name: Str = ""
    # corrupt: bits flipped per frame (distinct positions)
    bits: Annotated[int, Strict(), Field(ge=1, le=64)] = 1
    # delay: every hit frame is delivered delay_s + U(0, jitter_s) later
    delay_s: NonNegative = 0.0
    jitter_s: NonNegative = 0.0
    # error_frames: one opportunity every period_s from start_s; the bus error signalled
    period_s: Positive = 0.1
    error: Annotated[Str, one_of(CAN_ERRORS)] = "crc"
    # stuck, stuck_max, glitch: sensor indices (IR / sonar: 0-based sensor; encoders: 0 left,
    # 1 right; compass (glitch): axis 0 x, 1 y, 2 z); empty = every sensor of the stream
    sensors: Annotated[tuple[NonNegativeInt, ...], BeforeValidator(tuples)] = ()
    # bias: gyro yaw-rate step, rad/s
    bias: Finite | None = None
    # glitch: the size of one outlier, in the stream's unit (IR counts, sonar m, gyro rad/s,
    # compass uT), added with a random sign
    magnitude: Annotated[Finite, Field(gt=0)] | None = None
    # magnetic_anomaly: centre (x, y) m in the world frame, peak strength_uT, radius_m;
    # kidnap: where the robot is put, x, y m and theta_deg (no theta_deg: keeps its heading)
    x: Finite | None = None
    y: Finite | None = None
    strength_uT: Finite | None = None
    radius_m: Positive = 0.5
    theta_deg: Finite | None = None
    # wheel_slip: traction of the target wheel(s) while active
    traction: Annotated[Finite, AfterValidator(_traction)] = 0.5

    def __post_init__(self) -> None:
        info = _KINDS[self.kind]
        if self.target not in info.targets:
            raise ValueError(_unknown_target(self.kind, self.target))
        if self.end_s <= self.start_s:
            raise ValueError(
                f"'end_s' must be > 'start_s' ({self.start_s:g}), got {self.end_s:g}")
        if info.mode == _ONCE and self.end_s != math.inf:
            raise ValueError(f"'end_s' does not apply to {self.kind} (it happens once, at "
                             "start_s)")
        for key in info.required:
            if getattr(self, key) is None:
                raise ValueError(f"missing required key '{key}' (a {self.kind} fault needs "
                                 f"{', '.join(repr(k) for k in info.required)})")
        defaults = _param_defaults()
        for key in _PARAMS:
            if key not in info.params and getattr(self, key) != defaults[key]:
                raise ValueError(_foreign_key(self.kind, key))

    @property
    def mode(self) -> str:
        """How the probability is used: ``frame``, ``window``, ``periodic`` or ``once``."""
        return _KINDS[self.kind].mode

    def params(self) -> dict[str, Any]:
        """The kind's own parameters, JSON-ready (for events and ``status``)."""
        return {k: _jsonable(getattr(self, k)) for k in _KINDS[self.kind].params}


def _param_defaults() -> dict[str, Any]:
    fields = dataclasses.fields(cast(Any, FaultSpec))
    return {f.name: f.default for f in fields if f.name in _PARAMS}


def _renamed(spec: FaultSpec, name: str) -> FaultSpec:
    """``spec`` named ``name`` (validated again)."""
    return cast(FaultSpec, dataclasses.replace(cast(Any, spec), name=name))


def _jsonable(v: Any) -> Any:
    return list(v) if isinstance(v, tuple) else v


def _unknown_target(kind: str, target: str) -> str:
    targets = _KINDS[kind].targets
    near = difflib.get_close_matches(target, targets, n=1)
    if near:
        return f"unknown target {target!r}; did you mean {near[0]!r}?"
    return f"unknown target {target!r} for {kind} (targets: {', '.join(targets)})"


def _foreign_key(kind: str, key: str) -> str:
    owners = [k for k, info in _KINDS.items() if key in info.params]
    return f"'{key}' does not apply to {kind} (a parameter of {', '.join(owners)})"


# --------------------------------------------------------------------------- parsing

FAULT_HELP = """\
inject a fault (repeatable; docs/faults.md): KIND:TARGET[:key=value,key=value...], values are TOML
values (a bare word is a string). Kinds and targets: drop, corrupt (bits), delay (delay_s,
jitter_s), duplicate, reorder, disconnect -- on kteam, rangefinders, can, mavlink; error_frames
(period_s, error), bus_off -- on can; stuck (sensors) on ir, sonar, gyro, compass, encoders;
stuck_max (sensors) on ir, sonar; glitch (magnitude, sensors) on ir, sonar, gyro, compass; bias
(bias) on gyro; magnetic_anomaly (x, y, strength_uT,
radius_m) on compass; wheel_slip (traction) on left, right, both; kidnap (x, y, theta_deg) on
robot. Every fault takes start_s, end_s, probability, name. E.g.
--fault drop:can:start_s=5,end_s=10,probability=0.3
--fault kidnap:robot:start_s=20,x=1.0,y=0.5,theta_deg=90"""

_OPEN = {"[": "]", "{": "}"}


def parse_fault_option(text: str) -> dict[str, Any]:
    """One ``--fault`` option as a table: ``KIND:TARGET[:key=value,key=value...]``.

    Values are TOML values (``sensors=[0, 3]``, ``error="stuff"``); a value that is not TOML is a
    plain string (``error=stuff``), as with ``--set``. Commas inside ``[...]``, ``{...}`` or
    quotes do not split. Only the syntax is checked here; :func:`faults_from_config` validates.
    """
    label = f"--fault {text!r}"
    parts = text.split(":", 2)
    if len(parts) < 2 or not parts[0].strip() or not parts[1].strip():
        raise ConfigError(f"{label}: must look like KIND:TARGET[:key=value,...], e.g. "
                          "drop:can:start_s=5,end_s=10,probability=0.3")
    table: dict[str, Any] = {"kind": parts[0].strip(), "target": parts[1].strip()}
    for item in _split_items(parts[2] if len(parts) == 3 else "", label):
        key, sep, raw = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise ConfigError(f"{label}: {item.strip()!r} must look like key=value")
        if key in ("kind", "target"):
            raise ConfigError(f"{label}: give the {key} as KIND:TARGET, not as {key}=")
        if key in table:
            raise ConfigError(f"{label}: '{key}' is given twice")
        table[key] = _option_value(key, raw.strip(), label)
    return table


def _split_items(text: str, label: str) -> list[str]:
    """``text`` split at the commas outside brackets and quotes; empty items dropped."""
    items, depth, quote, start = [], [], "", 0
    for i, c in enumerate(text):
        if quote:
            if c == quote:
                quote = ""
        elif c in "\"'":
            quote = c
        elif c in _OPEN:
            depth.append(_OPEN[c])
        elif c in "]}":
            if not depth or depth.pop() != c:
                raise ConfigError(f"{label}: unbalanced {c!r}")
        elif c == "," and not depth:
            items.append(text[start:i])
            start = i + 1
    if depth or quote:
        raise ConfigError(f"{label}: unclosed {(depth[-1:] or [quote])[0]!r}")
    items.append(text[start:])
    return [item for item in items if item.strip()]


def _option_value(key: str, raw: str, label: str) -> Any:
    try:
        parsed = tomllib.loads(f"v = {raw}")
    except (tomllib.TOMLDecodeError, RecursionError) as e:
        if raw[:1] in ("[", "{", '"', "'") or not raw:
            reason = str(e).splitlines()[0] if str(e) else "invalid value"
            raise ConfigError(f"{label}: '{key}' = {raw!r} is not a TOML value ({reason})"
                              ) from None
        return raw
    if set(parsed) != {"v"}:
        raise ConfigError(f"{label}: '{key}' = {raw!r} is more than one value")
    return parsed["v"]


def fault_spec(table: Mapping[str, Any], where: str, index: int) -> FaultSpec:
    """Validate one fault table; ``where`` labels errors (``[[faults]] #2``, ``--fault '...'``)
    and ``index`` (1-based) makes the default name ``KIND:TARGET#index``.

    Raises :class:`ConfigError`, one line naming the fault and the field: unknown kind or target
    (with did-you-mean), a key the kind does not take, a missing required key, a bad value.
    """
    if not isinstance(table, Mapping):
        raise ConfigError(f"{where} must be a table, got {table!r:.60}")
    kind = table.get("kind")
    if kind is None:
        raise ConfigError(f"{where} missing required key 'kind' (one of {', '.join(FAULT_KINDS)})")
    if kind not in _KINDS:
        near = difflib.get_close_matches(str(kind), FAULT_KINDS, n=1)
        hint = f"did you mean {near[0]!r}?" if near else f"kinds: {', '.join(FAULT_KINDS)}"
        raise ConfigError(f"{where}: unknown kind {kind!r}; {hint}")
    info = _KINDS[kind]
    if "target" not in table:
        raise ConfigError(f"{where} missing required key 'target' (for {kind}: "
                          f"{', '.join(info.targets)})")
    if not isinstance(table["target"], str) or table["target"] not in info.targets:
        raise ConfigError(f"{where}: {_unknown_target(kind, str(table['target']))}")
    allowed = [*_COMMON, *info.params]
    if info.mode == _ONCE:
        allowed.remove("end_s")
    for key in table:
        if key in allowed:
            continue
        if key in _PARAMS or key == "end_s":
            raise ConfigError(f"{where}: " + (_foreign_key(kind, key) if key != "end_s" else
                              f"'end_s' does not apply to {kind} (it happens once, at start_s)"))
        near = difflib.get_close_matches(str(key), allowed, n=1)
        hint = f"did you mean '{near[0]}'?" if near else f"{kind} takes: {', '.join(allowed)}"
        raise ConfigError(f"{where}: unknown key '{key}'; {hint}")
    try:
        spec = validate(FaultSpec, dict(table), "faults")
        if not spec.name:
            spec = _renamed(spec, f"{kind}:{spec.target}#{index}")
    except ConfigError as e:
        raise _relabel(e, where) from None
    return spec


def _relabel(e: ConfigError, where: str) -> ConfigError:
    """``[faults] 'key' ...`` -> ``WHERE 'key' ...``; ``[faults] text`` -> ``WHERE: text``."""
    text = str(e).removeprefix("[faults]").lstrip()
    return ConfigError(f"{where} {text}" if text.startswith("'") else f"{where}: {text}")


def faults_from_config(config: Mapping[str, Any], cli: Sequence[str] = ()) -> list[FaultSpec]:
    """Every fault of a run: ``config["faults"]`` (the ``[[faults]]`` tables, in file order),
    then the ``--fault`` options ``cli`` (:func:`parse_fault_option`). Names must be unique.
    Raises :class:`ConfigError` naming the fault and the field."""
    tables = config.get("faults", [])
    if isinstance(tables, Mapping):
        raise ConfigError("[faults] must be an array of tables: write [[faults]] (two brackets) "
                          "for each fault")
    if not isinstance(tables, list):
        raise ConfigError(f"[[faults]] must be an array of tables, got {tables!r:.60}")
    specs = [fault_spec(t, f"[[faults]] #{i}", i) for i, t in enumerate(tables, 1)]
    for i, text in enumerate(cli, len(specs) + 1):
        specs.append(fault_spec(parse_fault_option(text), f"--fault {text!r}", i))
    seen: dict[str, int] = {}
    for i, spec in enumerate(specs, 1):
        if spec.name in seen:
            where = (f"[[faults]] #{i}" if i <= len(tables)
                     else f"--fault {cli[i - len(tables) - 1]!r}")
            raise ConfigError(f"{where} 'name' {spec.name!r} is already the name of fault "
                              f"#{seen[spec.name]}")
        seen[spec.name] = i
    return specs


# --------------------------------------------------------------------------- pure helpers


def flip_bits(data: bytes, positions: Iterable[int]) -> bytes:
    """``data`` with the bits at ``positions`` inverted (bit ``p`` = bit ``p % 8`` of byte
    ``p // 8``, LSB first)."""
    out = bytearray(data)
    for p in positions:
        out[p >> 3] ^= 1 << (p & 7)
    return bytes(out)


def can_error_frame(t: float, error_class: int, prot_type: int = 0, location: int = 0
                    ) -> can.Message:
    """A SocketCAN error frame (linux/can/error.h): the class bits in ``arbitration_id``,
    ``data[2]`` the protocol error type, ``data[3]`` its location, DLC ``CAN_ERR_DLC`` (8)."""
    data = bytes([0, 0, prot_type, location, 0, 0, 0, 0])
    return can.Message(timestamp=t, arbitration_id=error_class, is_extended_id=False,
                       is_error_frame=True, dlc=CAN_ERR_DLC, data=data)


def anomaly_field_world(x: float, y: float, cx: float, cy: float, strength_uT: float,
                        radius_m: float) -> tuple[float, float, float]:
    """World-frame field (uT, x east, y north, z up) a magnetic anomaly at ``(cx, cy)`` adds at
    ``(x, y)``: horizontal, pointing from the robot towards the centre (away for a negative
    strength) like a local source of sim/sensors/compass.py (seeds/000 eq. 16-18), with
    magnitude ``strength_uT * (1 - (d/R)^2)^2`` -- its peak at the centre, falling smoothly to 0
    at ``d = radius_m`` and 0 beyond (a compactly supported bump, so the anomaly is local and
    the field continuous). At the centre itself the direction is undefined: 0."""
    vx, vy = cx - x, cy - y
    d = math.hypot(vx, vy)
    if d == 0.0 or d >= radius_m:
        return (0.0, 0.0, 0.0)
    q = 1.0 - (d / radius_m) ** 2
    k = strength_uT * q * q / d
    return (k * vx, k * vy, 0.0)


# --------------------------------------------------------------------------- events


@dataclass(frozen=True)
class FaultEvent:
    """One injected occurrence: a frame hit, a window opening (``detail["phase"] = "start"``)
    or closing (``"end"``), an error frame, a kidnap. ``t`` is simulated time."""

    t: float
    name: str
    kind: str
    target: str
    detail: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {"t": self.t, "name": self.name, "kind": self.kind, "target": self.target,
                "detail": dict(self.detail)}


class Delivery(tuple[float, bytes]):
    """A ``(t, data)`` pair of :meth:`FaultInjector.on_frame`: write ``data`` at simulated time
    ``t``. ``can_id`` is the CAN id the bytes belong to (a reorder releases another frame's
    bytes; None off CAN)."""

    can_id: int | None

    def __new__(cls, t: float, data: bytes, can_id: int | None = None) -> Self:
        self = super().__new__(cls, (t, data))
        self.can_id = can_id
        return self

    @property
    def t(self) -> float:
        return self[0]

    @property
    def data(self) -> bytes:
        return self[1]

    def __repr__(self) -> str:
        return f"Delivery(t={self[0]!r}, data={self[1]!r}, can_id={self.can_id!r})"


# --------------------------------------------------------------------------- the injector

_PENDING, _ACTIVE, _SKIPPED, _DONE = "pending", "active", "skipped", "done"


class _Fault:
    """The run-time state of one spec."""

    def __init__(self, spec: FaultSpec, index: int, seed: int, now: float) -> None:
        self.spec = spec
        self.index = index
        self.rng = np.random.default_rng([seed, 0x0FA1, index])
        self.state = _PENDING
        self.begin = max(spec.start_s, now)   # added at run time: not before then
        if self.begin >= spec.end_s:          # added after its window: nothing to do
            self.state = _DONE
        self.held: Delivery | None = None     # reorder
        self.stuck: Any = None                # stuck: the reading repeated
        self.next_tick = 0                    # error_frames: the next period index

    def in_window(self, t: float) -> bool:
        return self.begin <= t < self.spec.end_s


class FaultInjector:
    """Applies :class:`FaultSpec` s (module docstring). ``active`` is False without any fault:
    then the caller may skip every call."""

    def __init__(self, specs: Sequence[FaultSpec], seed: int) -> None:
        if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
            raise ValueError(f"seed must be an integer >= 0, got {seed!r}")
        self._seed = int(seed)
        self._lock = threading.Lock()
        self._faults: list[_Fault] = []
        self._events: list[FaultEvent] = []
        self._counts: Counter[str] = Counter()
        self._error_frames: list[can.Message] = []
        self._last_raw: dict[str, Any] = {}
        self._now = 0.0
        for spec in specs:
            self.add(spec)

    @property
    def active(self) -> bool:
        return bool(self._faults)

    @property
    def specs(self) -> list[FaultSpec]:
        """Every fault, in index order."""
        return [f.spec for f in self._faults]

    def add(self, spec: FaultSpec) -> None:
        """Schedule ``spec`` (also at run time: a window that opened in the past opens now).
        A name already used is a :class:`ConfigError`; "" becomes ``KIND:TARGET#N``."""
        with self._lock:
            index = len(self._faults)
            if not spec.name:
                spec = _renamed(spec, f"{spec.kind}:{spec.target}#{index + 1}")
            if any(f.spec.name == spec.name for f in self._faults):
                raise ConfigError(f"fault 'name' {spec.name!r} is already used")
            self._faults.append(_Fault(spec, index, self._seed, self._now))

    def check(self, sensor_counts: Mapping[str, int]) -> None:
        """Raise :class:`ConfigError` if a ``sensors`` index is out of range for the robot,
        e.g. ``check({"ir": 16, "sonar": 8, "encoders": 2})``. (Out-of-range indices are
        otherwise ignored.)"""
        for f in self._faults:
            n = sensor_counts.get(f.spec.target)
            bad = [s for s in f.spec.sensors if n is not None and s >= n]
            if bad and n is not None:
                raise ConfigError(f"fault {f.spec.name!r}: 'sensors' index {bad[0]} is out "
                                  f"of range: the robot has {n} {f.spec.target} sensors "
                                  f"(0..{n - 1})")

    # ----------------------------------------------------------------- frames

    def on_frame(self, bus: str, t: float, data: bytes, can_id: int | None = None,
                 reply: bool = False) -> list[Delivery]:
        """The deliveries of one outbound frame on ``bus`` produced at ``t``: ``[]`` = dropped
        (or held by a reorder), else ``(t_write, bytes)`` pairs in order (:class:`Delivery`).

        The frame faults on ``bus`` apply in index order, each to what the previous returned:
        ``drop``; ``corrupt`` flips ``bits`` distinct random bits (serial and MAVLink: the
        frame's CRC then fails at the client; CAN: the frame is delivered intact after a CRC
        error frame, which :meth:`can_error_frames` returns -- call it after this and send its
        frames first); ``delay`` by ``delay_s + U(0, jitter_s)``; ``duplicate``; ``reorder``
        holds the frame and delivers it right after the next frame that reaches this fault.
        This does not look at :meth:`disconnected` or :meth:`bus_off`: ask those first.

        ``reply``: the frame answers a request (a K-Team reply). A firmware waiting for it holds
        simulated time in lockstep, so ``delay`` and ``reorder`` pass it untouched (no draw, no
        event): only ``drop``, ``corrupt`` and ``duplicate`` apply.
        """
        _check_bus(bus)
        with self._lock:
            t = self._advance(t)
            out = [Delivery(t, bytes(data), can_id)]
            for f in self._faults:
                if f.spec.target != bus or f.spec.mode != _FRAME:
                    continue
                if reply and f.spec.kind in ("delay", "reorder"):
                    continue
                if f.spec.kind == "reorder" and f.held is not None:
                    out = self._release(f, out)
                    continue
                if not f.in_window(t):
                    continue
                new: list[Delivery] = []
                for d in out:
                    new.extend(self._hit(f, d, bus))
                out = new
            return out

    def _release(self, f: _Fault, out: list[Delivery]) -> list[Delivery]:
        """A held frame goes out right after the first delivery that reaches the reorder."""
        if not out:
            return out
        held, f.held = f.held, None
        assert held is not None
        return [out[0], Delivery(out[0].t, held.data, held.can_id), *out[1:]]

    def _hit(self, f: _Fault, d: Delivery, bus: str) -> list[Delivery]:
        spec = f.spec
        if f.held is not None:  # a reorder holding a frame: this one is the next
            return self._release(f, [d])
        if not f.rng.random() < spec.probability:
            return [d]
        detail: dict[str, Any] = {} if d.can_id is None else {"can_id": d.can_id}
        kind = spec.kind
        out: list[Delivery]
        if kind == "drop":
            out = []
        elif kind == "corrupt":
            if bus == "can":
                cls, kind_bits, loc = _BUS_ERRORS["crc"]
                self._error_frames.append(can_error_frame(d.t, cls, kind_bits, loc))
                detail["error"] = "crc"
                out = [d]
            else:
                n = len(d.data) * 8
                positions = sorted(int(p) for p in f.rng.choice(n, min(spec.bits, n),
                                                                replace=False)) if n else []
                detail["bits"] = positions
                out = [Delivery(d.t, flip_bits(d.data, positions), d.can_id)]
        elif kind == "delay":
            delay = spec.delay_s + spec.jitter_s * float(f.rng.random())
            detail["delay_s"] = delay
            out = [Delivery(d.t + delay, d.data, d.can_id)]
        elif kind == "duplicate":
            out = [d, d]
        else:  # reorder
            f.held = d
            out = []
        self._record(FaultEvent(d.t, spec.name, kind, spec.target, detail))
        return out

    def can_error_frames(self, t: float) -> list[can.Message]:
        """The CAN error frames due by ``t``, to send on every CAN interface now (python-can
        ``is_error_frame`` messages, SocketCAN classes: :func:`can_error_frame`): the CRC
        errors of ``corrupt`` hits, the ``error_frames`` fault's errors (one opportunity every
        ``period_s`` from its start, each with ``probability``), ``CAN_ERR_BUSOFF`` when a
        ``bus_off`` window opens and ``CAN_ERR_RESTARTED`` when it closes."""
        with self._lock:
            t = self._advance(t)
            for f in self._faults:
                if f.spec.mode == _PERIODIC:
                    self._tick(f, t)
            out, self._error_frames = self._error_frames, []
            return out

    def _tick(self, f: _Fault, t: float) -> None:
        spec = f.spec
        cls, kind_bits, loc = _BUS_ERRORS[spec.error]
        while True:
            tick = round(f.begin + f.next_tick * spec.period_s, 9)   # no float noise in t
            if tick > t or tick >= spec.end_s:
                return
            f.next_tick += 1
            if f.rng.random() < spec.probability:
                self._error_frames.append(can_error_frame(tick, cls, kind_bits, loc))
                self._record(FaultEvent(tick, spec.name, spec.kind, spec.target,
                                        {"error": spec.error, "class": cls}))

    def bus_off(self, bus: str, t: float) -> bool:
        """Whether the robot's CAN controller is bus-off at ``t`` (a ``bus_off`` window): it
        neither sends nor receives; it recovers at ``end_s``. False off CAN."""
        return self._window_active("bus_off", bus, t)

    def disconnected(self, bus: str, t: float) -> bool:
        """Whether ``bus`` is gone at ``t`` (a ``disconnect`` window): the caller puts its
        transports offline (``set_offline(True)``) and back at the end."""
        return self._window_active("disconnect", bus, t)

    def _window_active(self, kind: str, bus: str, t: float) -> bool:
        _check_bus(bus)
        with self._lock:
            self._advance(t)
            return any(f.state == _ACTIVE and f.spec.kind == kind and f.spec.target == bus
                       for f in self._faults)

    # ----------------------------------------------------------------- sensors and the robot

    def on_readings(self, r: Readings) -> Readings:
        """``r`` with the sensor faults active at ``r.t`` applied (``dataclasses.replace``; the
        truth fields stay true): ``stuck`` repeats the stream's last reading before the window
        (for ``sensors`` only, if given), ``stuck_max`` reads nothing in range (IR 0 counts,
        the response table's value beyond its last range; sonar no echo, nan -> 0xFFFF on the
        wire), ``glitch`` puts a single outlier into a reading now and then (:meth:`_glitch`),
        ``bias`` adds a yaw-rate step to the gyro, ``magnetic_anomaly`` adds its field
        (:func:`anomaly_field_world`, at the truth pose, rotated into the body frame)."""
        with self._lock:
            self._advance(r.t)
            raw = {s: getattr(r, _FIELD[s]) for s in SENSOR_STREAMS}
            out = r
            for f in self._faults:
                if f.spec.mode == _SAMPLE:
                    if not f.in_window(r.t):
                        continue
                elif f.state != _ACTIVE or f.spec.mode != _WINDOW:
                    continue
                stream = f.spec.target
                if stream not in SENSOR_STREAMS:
                    continue
                reading = getattr(out, _FIELD[stream])
                if reading is None:
                    continue
                if f.spec.kind == "stuck":
                    if f.stuck is None:
                        f.stuck = self._last_raw.get(stream) or raw[stream]
                    new = _stuck(stream, reading, f.stuck, f.spec.sensors)
                elif f.spec.kind == "stuck_max":
                    new = _stuck_max(stream, reading, f.spec.sensors)
                elif f.spec.kind == "glitch":
                    new = self._glitch(f, reading, r.t)
                elif f.spec.kind == "bias":
                    assert isinstance(reading, GyroReading) and f.spec.bias is not None
                    new = dataclasses.replace(reading, yaw_rate=reading.yaw_rate + f.spec.bias)
                else:  # magnetic_anomaly
                    new = _with_anomaly(reading, out, f.spec)
                out = dataclasses.replace(out, **{_FIELD[stream]: new})
            for s, reading in raw.items():
                if reading is not None:
                    self._last_raw[s] = reading
            return out

    def _glitch(self, f: _Fault, reading: Any, t: float) -> Any:
        """One reading of a ``glitch`` fault: with ``probability``, one sensor (IR / sonar:
        among ``sensors``; compass: one axis) is off by ``magnitude`` with a random sign."""
        spec = f.spec
        if not f.rng.random() < spec.probability:
            return reading
        assert spec.magnitude is not None
        delta = spec.magnitude if f.rng.random() < 0.5 else -spec.magnitude
        if isinstance(reading, GyroReading):
            self._record(FaultEvent(t, spec.name, spec.kind, spec.target, {"delta": delta}))
            return dataclasses.replace(reading, yaw_rate=reading.yaw_rate + delta)
        values = _values(reading)
        candidates = [i for i in (spec.sensors or range(len(values))) if i < len(values)]
        if not candidates:
            return reading
        i = candidates[int(f.rng.integers(len(candidates)))]
        self._record(FaultEvent(t, spec.name, spec.kind, spec.target,
                                {"sensor": i, "delta": delta}))
        if isinstance(reading, IrReading):    # counts are >= 0 (the bus clips to 0..1023)
            values[i] = max(0, int(values[i]) + round(delta))
            return dataclasses.replace(reading, counts=values)
        if isinstance(reading, SonarReading):  # no echo (nan) stays no echo
            if math.isfinite(values[i]):
                values[i] = max(0.0, float(values[i]) + delta)
            return dataclasses.replace(reading, ranges=values)
        values[i] += delta
        return dataclasses.replace(reading, field_uT=values)

    def apply_to_sim(self, sim: Simulator, t: float) -> None:
        """Act on the simulator before its step at ``t``: a ``kidnap`` teleports the robot once
        (:meth:`Simulator.teleport`, at its ``start_s``); ``wheel_slip`` sets the wheels'
        traction while active (the product of the active slips of each wheel) and (1, 1)
        again after ``end_s`` (:meth:`Simulator.set_wheel_traction`)."""
        with self._lock:
            t = self._advance(t)
            left = right = 1.0
            for f in self._faults:
                spec = f.spec
                if spec.kind == "kidnap" and f.state == _ACTIVE:
                    f.state = _DONE
                    before = sim.pose
                    assert spec.x is not None and spec.y is not None
                    theta = before.theta if spec.theta_deg is None else math.radians(
                        spec.theta_deg)
                    sim.teleport(spec.x, spec.y, theta)
                    self._record(FaultEvent(t, spec.name, spec.kind, spec.target, {
                        "from": [before.x, before.y, before.theta],
                        "to": [spec.x, spec.y, sim.pose.theta]}))
                elif spec.kind == "wheel_slip" and f.state == _ACTIVE:
                    if spec.target in ("left", "both"):
                        left *= spec.traction
                    if spec.target in ("right", "both"):
                        right *= spec.traction
            if sim.wheel_traction != (left, right):
                sim.set_wheel_traction(left, right)

    # ----------------------------------------------------------------- events

    def events(self) -> list[FaultEvent]:
        """What happened since the last call, in order (then forgotten)."""
        with self._lock:
            out, self._events = self._events, []
            return out

    def counts(self) -> dict[str, int]:
        """Injections per fault name, every fault listed (0 if none yet): frames hit, windows
        opened, error frames signalled, kidnaps."""
        with self._lock:
            return {f.spec.name: self._counts[f.spec.name] for f in self._faults}

    # ----------------------------------------------------------------- internals

    def _record(self, event: FaultEvent, counted: bool = True) -> None:
        self._events.append(event)
        if counted:
            self._counts[event.name] += 1

    def _advance(self, t: float) -> float:
        """Move to simulated time ``t`` (never back): open and close windows, decide once-only
        faults. Returns the time used."""
        t = max(float(t), self._now)
        self._now = t
        for f in self._faults:
            mode = f.spec.mode
            if mode in (_FRAME, _SAMPLE, _PERIODIC):
                continue
            if f.state == _PENDING and t >= f.begin:
                happens = bool(f.rng.random() < f.spec.probability)
                f.state = _ACTIVE if happens else _SKIPPED
                if happens and mode == _WINDOW:
                    self._open(f)
            if mode == _WINDOW and f.state == _ACTIVE and t >= f.spec.end_s:
                f.state = _DONE
                self._close(f)
        return t

    def _open(self, f: _Fault) -> None:
        spec = f.spec
        self._record(FaultEvent(f.begin, spec.name, spec.kind, spec.target,
                                {"phase": "start", **spec.params()}))
        if spec.kind == "bus_off":
            self._error_frames.append(can_error_frame(f.begin, CAN_ERR_BUSOFF))

    def _close(self, f: _Fault) -> None:
        spec = f.spec
        self._record(FaultEvent(spec.end_s, spec.name, spec.kind, spec.target,
                                {"phase": "end"}), counted=False)
        if spec.kind == "bus_off":
            self._error_frames.append(can_error_frame(spec.end_s, CAN_ERR_RESTARTED))
        f.stuck = None


#: The :class:`Readings` field of each sensor stream.
_FIELD = {"ir": "ir", "sonar": "sonar", "gyro": "gyro", "compass": "compass",
          "encoders": "odometry"}


def _check_bus(bus: str) -> None:
    if bus not in FRAME_BUSES:
        raise ValueError(f"unknown bus {bus!r} (buses: {', '.join(FRAME_BUSES)})")


def _mask(n: int, sensors: tuple[int, ...]) -> np.ndarray:
    """Boolean mask of the ``sensors`` indices among ``n`` (all if empty; out of range ignored)."""
    if not sensors:
        return np.ones(n, dtype=bool)
    m = np.zeros(n, dtype=bool)
    m[[s for s in sensors if s < n]] = True
    return m


def _stuck(stream: str, reading: Any, held: Any, sensors: tuple[int, ...]) -> Any:
    if isinstance(reading, IrReading):
        m = _mask(len(reading.counts), sensors)
        return dataclasses.replace(reading, counts=np.where(m, held.counts, reading.counts))
    if isinstance(reading, SonarReading):
        m = _mask(len(reading.ranges), sensors)
        return dataclasses.replace(reading, ranges=np.where(m, held.ranges, reading.ranges))
    if isinstance(reading, OdometryReading):
        m = _mask(2, sensors)
        return OdometryReading(held.left_ticks if m[0] else reading.left_ticks,
                               held.right_ticks if m[1] else reading.right_ticks)
    if isinstance(reading, GyroReading):
        return dataclasses.replace(reading, yaw_rate=held.yaw_rate)
    assert isinstance(reading, CompassReading), stream
    return dataclasses.replace(reading, field_uT=np.array(held.field_uT, copy=True))


def _values(reading: IrReading | SonarReading | CompassReading) -> np.ndarray:
    """The measured array of a reading (a copy)."""
    if isinstance(reading, IrReading):
        return np.array(reading.counts, copy=True)
    if isinstance(reading, SonarReading):
        return np.array(reading.ranges, dtype=float, copy=True)
    return np.array(reading.field_uT, dtype=float, copy=True)


def _stuck_max(stream: str, reading: Any, sensors: tuple[int, ...]) -> Any:
    if isinstance(reading, IrReading):
        m = _mask(len(reading.counts), sensors)
        return dataclasses.replace(reading, counts=np.where(m, 0, reading.counts))
    assert isinstance(reading, SonarReading), stream
    m = _mask(len(reading.ranges), sensors)
    return dataclasses.replace(reading, ranges=np.where(m, np.nan, reading.ranges))


def _with_anomaly(reading: Any, r: Readings, spec: FaultSpec) -> CompassReading:
    assert isinstance(reading, CompassReading)
    assert spec.x is not None and spec.y is not None and spec.strength_uT is not None
    bw = anomaly_field_world(r.pose.x, r.pose.y, spec.x, spec.y, spec.strength_uT,
                             spec.radius_m)
    return dataclasses.replace(
        reading, field_uT=np.asarray(reading.field_uT, dtype=float) + np.array(
            field_body(bw, r.pose.theta)))

