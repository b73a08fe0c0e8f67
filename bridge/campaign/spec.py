"""A campaign file: the firmware, the base config, the matrix of axes, the limits and the checks.

A campaign is a TOML file (docs/campaigns.md)::

    [campaign]
    name = "coverage"
    firmware = ["{python}", "coverage_firmware.py", "--endpoints-file", "{endpoints}", ...]
    config = ""                  # the base bridge config; "" = the shipped default.toml
    set = ["lockstep.period_s=0.02"]   # --set overrides for every run
    sim_duration_s = 400.0       # the firmware's budget, {duration_s}; the bridge stops 1 s later
    wall_timeout_s = 300.0       # a run still going after this many wall seconds fails

    [matrix]
    worlds = ["lab_walls_1", "worlds/my_arena.toml"]   # shipped names or files
    seeds = [0, 1, 2]
    [matrix.faults]              # named fault sets: --fault options
    none = []
    gyro_bias = ["bias:gyro:start_s=20,bias=0.02"]
    [matrix.overrides]           # named --set sets
    base = []

    [checks]
    exit_code = true
    sim_time_advanced = true     # simulated time moved past 0 (default true)
    sim_time_min_s = 300.0       # ... and reached 300 s (default: off; <= sim_duration_s)
    no_wall_contact = true
    coverage_min_percent = 100.0
    localisation_error_max_m = 0.05
    no_bus_errors = true
    user = ["my_checks.py:finished_quickly"]

Every table is typed with the config schema's policy (``core/schema.py``): unknown keys are errors
with a did-you-mean, types strict, numbers finite. Loading also builds and validates every case's
bridge configuration, so a typo in an override or a fault fails before any run starts.

Relative paths (``config``, world files, ``user`` check files, the firmware's words that name an
existing file) are relative to the campaign file's folder; each case carries its configuration
as data, so a cluster worker needs only the firmware (docs/campaigns.md, "On a cluster").
"""

from __future__ import annotations

import itertools
import re
import string
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

from koala_bridge.core.resources import config_dir, default_config_path
from koala_bridge.core.schema import (
    Bool,
    ConfigError,
    NonNegative,
    Positive,
    Str,
    reject_unknown,
    section,
    tuples,
    validate,
)
from pydantic import AfterValidator, BeforeValidator, Field

#: What a word of the firmware command may name; :func:`firmware_command` fills them in.
PLACEHOLDERS = {
    "python": "the Python running the campaign task (sys.executable on the worker)",
    "endpoints": "the bridge's endpoints file (JSON, docs/protocols.md)",
    "config": "the run's bridge configuration (TOML: the firmware's period, robot, ...)",
    "world": "the run's world file (TOML with a [world] table)",
    "seed": "the run's seed",
    "duration_s": "the campaign's sim_duration_s (the bridge stops 1 simulated s later)",
    "report": "where the firmware may write a JSON report (checks and the report read it)",
    "run_dir": "the run's own temporary folder",
    "campaign_dir": "the campaign file's folder (as seen on the machine that runs the case)",
}

#: A name in the matrix: part of a case id, a folder name and a JUnit test name.
_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.]*")


def _name(value: str) -> str:
    if not _NAME.fullmatch(value):
        raise ValueError(f"must be a name of letters, digits, '_' and '.', got {value!r}")
    return value


def _firmware(value: tuple[str, ...]) -> tuple[str, ...]:
    if not value:
        raise ValueError("must name the firmware's command, e.g. [\"./my-firmware\", "
                         "\"--endpoints-file\", \"{endpoints}\"]")
    for word in value:
        for _, name, spec, conv in string.Formatter().parse(word):
            if name is not None and (name not in PLACEHOLDERS or spec or conv):
                raise ValueError(f"{word!r}: unknown placeholder {{{name}}}; the placeholders "
                                 f"are {', '.join('{' + p + '}' for p in PLACEHOLDERS)}")
    return value


_Words = Annotated[tuple[Str, ...], BeforeValidator(tuples)]


@section
class CampaignTable:
    """``[campaign]``: what runs, on what, for how long."""

    firmware: Annotated[_Words, AfterValidator(_firmware)]
    name: Annotated[Str, AfterValidator(_name)] = "campaign"
    config: Str = ""
    set: _Words = ()
    sim_duration_s: Positive = 60.0
    wall_timeout_s: Positive = 300.0
    # a cluster worker runs at most this many cases at once per resource unit (Dask
    # resources=): workers started with --resources "simulators=N" take N at a time
    resources: dict[Str, Positive] = field(default_factory=dict)


@section
class MatrixTable:
    """``[matrix]``: the axes; the cases are their product."""

    worlds: Annotated[_Words, Field(min_length=1)]
    seeds: Annotated[tuple[Annotated[int, Field(ge=0, lt=2**32)], ...],
                     BeforeValidator(tuples), Field(min_length=1)]
    faults: dict[Annotated[Str, AfterValidator(_name)], _Words] = field(
        default_factory=lambda: {"none": ()})
    overrides: dict[Annotated[Str, AfterValidator(_name)], _Words] = field(
        default_factory=lambda: {"base": ()})


@section
class ChecksTable:
    """``[checks]``: what decides a run's verdict (every check enabled must pass)."""

    exit_code: Bool = True
    sim_time_advanced: Bool = True
    sim_time_min_s: Positive | None = None
    no_wall_contact: Bool = False
    coverage_min_percent: Annotated[float, Field(ge=0, le=100)] | None = None
    localisation_error_max_m: NonNegative | None = None
    no_bus_errors: Bool = False
    user: _Words = ()


@dataclass(frozen=True)
class Case:
    """One run of the matrix: its axes and everything a worker needs to run it."""

    case_id: str
    world: str            # the world's name (its file's stem)
    seed: int
    faults_name: str
    faults: tuple[str, ...]
    overrides_name: str
    overrides: tuple[str, ...]
    config: dict[str, Any] = field(compare=False, repr=False)  # the bridge config, resolved

    @property
    def axes(self) -> dict[str, Any]:
        return {"world": self.world, "seed": self.seed, "faults": self.faults_name,
                "overrides": self.overrides_name}


@dataclass(frozen=True)
class Campaign:
    """A campaign file, validated, with its cases in matrix order."""

    path: Path
    table: CampaignTable
    matrix: MatrixTable
    checks: ChecksTable
    cases: tuple[Case, ...]

    @property
    def name(self) -> str:
        return self.table.name

    @property
    def folder(self) -> Path:
        return self.path.parent

    def case(self, case_id: str) -> Case:
        for c in self.cases:
            if c.case_id == case_id:
                return c
        import difflib

        near = difflib.get_close_matches(case_id, [c.case_id for c in self.cases], n=1)
        hint = f"; did you mean {near[0]!r}?" if near else ""
        raise ConfigError(f"no case {case_id!r} in campaign {self.name!r}{hint}")


def case_id(world: str, seed: int, faults_name: str, overrides_name: str) -> str:
    """``WORLD-sSEED-FAULTS-OVERRIDES``, e.g. ``lab_walls_1-s3-gyro_bias-base``."""
    return f"{world}-s{seed}-{faults_name}-{overrides_name}"


def load_campaign(path: str | Path) -> Campaign:
    """Read and validate the campaign file ``path`` and build its cases (:class:`ConfigError`
    naming the table and key on any mistake)."""
    p = Path(path)
    try:
        d = tomllib.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"campaign file not found: {p}") from None
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(f"cannot read campaign file {p}: {e}") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{p}: not valid TOML: {e}") from None
    return campaign_from_dict(d, p.resolve())


def campaign_from_dict(d: Mapping[str, Any], path: Path) -> Campaign:
    reject_unknown(d, ("campaign", "matrix", "checks"), "campaign file")
    for key in ("campaign", "matrix"):
        if key not in d:
            raise ConfigError(f"[{key}] missing: a campaign names its firmware ([campaign]) and "
                              "its axes ([matrix])")
    table = validate(CampaignTable, d["campaign"], "campaign")
    matrix = validate(MatrixTable, d["matrix"], "matrix")
    checks = validate(ChecksTable, d.get("checks", {}), "checks")
    if checks.sim_time_min_s is not None and checks.sim_time_min_s > table.sim_duration_s:
        raise ConfigError(f"[checks] 'sim_time_min_s' = {checks.sim_time_min_s:g} can never be "
                          f"met: the runs last sim_duration_s = {table.sim_duration_s:g} "
                          "simulated seconds")
    if not matrix.faults or not matrix.overrides:
        raise ConfigError("[matrix] 'faults' and 'overrides' need at least one named set "
                          "(e.g. none = [])")
    folder = path.parent
    base = _base_config(table, folder)
    worlds = [_world(w, folder) for w in matrix.worlds]
    stems = [stem for stem, _ in worlds]
    if len(set(stems)) != len(stems):
        raise ConfigError(f"[matrix] 'worlds': two worlds share a name: {stems}")
    cases = []
    for (stem, world), seed, (fname, faults), (oname, overrides) in itertools.product(
            worlds, matrix.seeds, matrix.faults.items(), matrix.overrides.items()):
        cid = case_id(stem, seed, fname, oname)
        config = case_config(base, world, seed, (*table.set, *overrides), faults, cid)
        cases.append(Case(cid, stem, seed, fname, tuple(faults), oname, tuple(overrides),
                          config))
    for check in checks.user:
        _user_check_spec(check, folder)  # the form only; imported where the case runs
    return Campaign(path, table, matrix, checks, tuple(cases))


def _base_config(table: CampaignTable, folder: Path) -> dict[str, Any]:
    from koala_bridge.runtime.settings import load_config

    path = default_config_path() if not table.config else folder / table.config
    return load_config(path)


def _world(text: str, folder: Path) -> tuple[str, dict[str, Any]]:
    """A world of ``[matrix] worlds``: a shipped name (``lab_walls_1``) or a TOML file."""
    shipped = config_dir() / "worlds" / f"{text}.toml"
    path = shipped if "/" not in text and not text.endswith(".toml") else folder / text
    if not path.is_file():
        names = sorted(p.stem for p in (config_dir() / "worlds").glob("*.toml"))
        raise ConfigError(f"[matrix] 'worlds': no world {text!r} (a file, or one of the "
                          f"shipped: {', '.join(names)})")
    try:
        world = tomllib.loads(path.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"[matrix] 'worlds': {path}: not valid TOML: {e}") from None
    if "world" not in world:
        raise ConfigError(f"[matrix] 'worlds': {path} has no [world] table")
    _name(path.stem)
    return path.stem, world["world"]


def case_config(base: Mapping[str, Any], world: Mapping[str, Any], seed: int,
                overrides: tuple[str, ...], faults: tuple[str, ...], cid: str) -> dict[str, Any]:
    """The bridge configuration of one case: ``base``, its world, the overrides, the faults, and
    what isolates it -- lockstep, every port 0 (any free one; the endpoints file names them),
    no multicast scouting, its own Zenoh prefix. Validated as ``koala-bridge run`` would."""
    from koala_bridge.runtime.faults import faults_from_config, parse_fault_option
    from koala_bridge.runtime.settings import (
        BridgeSettings,
        apply_override,
        parse_override,
    )
    from koala_bridge.sim.config import load_sim_config

    config = apply_override(base, ["world"], dict(world))
    for text in overrides:
        try:
            config = apply_override(config, *parse_override(text))
        except ConfigError as e:
            raise ConfigError(f"case {cid}: --set {text!r}: {e}") from None
    isolation = {
        ("sim", "seed"): seed,
        ("run", "clock"): "lockstep",
        ("buses", "can", "socketcand_port"): 0,
        ("buses", "mavlink", "port"): 0,
        ("zenoh", "listen"): ["tcp/127.0.0.1:0"],
        ("zenoh", "connect"): [],
        ("zenoh", "multicast_scouting"): False,
        ("zenoh", "prefix"): f"campaign/{cid.replace('.', '_')}",
    }
    for key, value in isolation.items():
        config = apply_override(config, list(key), value)
    try:
        specs = faults_from_config(config, faults)
        config = {**config, "faults": [*config.get("faults", []),
                                       *(parse_fault_option(t) for t in faults)]}
        BridgeSettings.from_config(config)
        load_sim_config(config)
    except ConfigError as e:
        raise ConfigError(f"case {cid}: {e}") from None
    del specs
    return config


def _user_check_spec(text: str, folder: Path) -> tuple[str, str]:
    """``module.path:function`` or ``file.py:function`` (relative to the campaign file)."""
    where, sep, func = text.rpartition(":")
    if not sep or not where or not func.isidentifier():
        raise ConfigError(f"[checks] 'user': {text!r} is not MODULE:FUNCTION or FILE.py:FUNCTION")
    if where.endswith(".py"):
        path = folder / where
        if not path.is_file():
            raise ConfigError(f"[checks] 'user': {text!r}: no file {path}")
        return str(path.resolve()), func
    return where, func
