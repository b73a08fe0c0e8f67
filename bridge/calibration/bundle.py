"""Measurement bundles (docs/bundle-format.md): load a directory of CSV files.

A bundle is read into plain numpy columns, one :class:`Table` per CSV file, plus the free-form
``meta.json``. Recordings (MCAP) are converted to a bundle first by the recording package's
exporter, so every later stage sees one format.
"""

from __future__ import annotations

import csv
import io
import json
import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from koala_bridge.calibration.errors import BundleError
from numpy.typing import NDArray

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

#: Files of the bundle format and the columns each one requires.
REQUIRED_COLUMNS: Mapping[str, tuple[str, ...]] = {
    "truth_pose": ("t", "x", "y"),
    "odometry": ("t",),
    "gyro": ("t", "yaw_rate"),
    "compass": ("t", "mx", "my"),
    "range": ("t", "sensor", "measured", "true_range"),
    "landmarks": ("t", "landmark_id"),
    "landmark_map": ("id", "x", "y"),
}

#: The fault log a recording of koala-bridge exports beside its readings (``faults.csv``,
#: docs/faults.md): no measurement, but which readings were faulted on purpose
#: (:mod:`koala_bridge.calibration.fault_log`); its columns.
FAULT_LOG = "faults"
FAULT_LOG_COLUMNS = ("t", "name", "kind", "target", "detail")

#: Optional columns of the format that hold numbers when present: a text cell in one is an
#: error naming its line (kept as text, the column looked absent: "no theta column").
OPTIONAL_NUMERIC: Mapping[str, tuple[str, ...]] = {
    "truth_pose": ("theta",),
    "odometry": ("left_ticks", "right_ticks", "v", "omega", "x", "y", "theta"),
    "gyro": ("rate_x", "rate_y", "acc_x", "acc_y", "acc_z"),
    "compass": ("mz",),
}

#: Files that need at least one of these columns (a range beacon gives no bearing, a
#: bearing-only camera no range).
ONE_OF_COLUMNS: Mapping[str, tuple[str, ...]] = {"landmarks": ("range", "bearing")}

#: Files with one sample per time: at least two rows, no time twice. (``range`` and
#: ``landmarks`` hold several sensors / observations per time.)
SAMPLED_STREAMS = ("truth_pose", "odometry", "gyro", "compass")

#: The largest magnitude a numeric cell may hold. Nothing a bundle holds in SI units (seconds,
#: metres, counts) comes near; ``inf`` or ``1e308`` is a corrupt cell, and squaring it overflows.
MAX_ABS_VALUE = 1e12

#: ``meta.json`` ``robot`` numbers: each, when given, a finite number > 0.
META_ROBOT_POSITIVE = (
    "ticks_per_metre",
    "tick_size_m",
    "wheel_base_m",
    "wheel_diameter_m",
    "wheel_diameter_ratio",
)


@dataclass(frozen=True)
class Table:
    """One CSV file as named float columns of equal length (non-numeric cells become NaN).

    Text columns (for example ``kind``) are kept separately in :attr:`text`.
    """

    name: str
    columns: Mapping[str, FloatArray]
    text: Mapping[str, NDArray[np.str_]] = field(default_factory=dict)
    #: the file line of each row (1 = the header), for messages; None for a table not read
    #: from a file
    lines: NDArray[np.int64] | None = None
    #: series derived from the columns once and reused (the unwrapped heading of
    #: ``truth_pose``: several stream builders ask for it); not part of the table's value
    derived: dict[str, Any] = field(default_factory=dict, compare=False, repr=False)

    def __len__(self) -> int:
        return len(next(iter(self.columns.values()))) if self.columns else 0

    def __contains__(self, column: object) -> bool:
        return column in self.columns or column in self.text

    def __getitem__(self, column: str) -> FloatArray:
        return self.columns[column]

    def select(self, mask: NDArray[np.bool_]) -> Table:
        """Rows where ``mask`` is true; the table itself where it is true everywhere (the
        usual case of a builder keeping the rows with its columns filled: a copy of an hour's
        1.44 M sonar rows cost 0.11 s). Tables are read, never written in place."""
        if mask.size == len(self) and bool(np.all(mask)):
            return self
        return Table(
            self.name,
            {k: v[mask] for k, v in self.columns.items()},
            {k: v[mask] for k, v in self.text.items()},
            None if self.lines is None else self.lines[mask],
        )


@dataclass(frozen=True)
class Bundle:
    """A loaded measurement bundle: tables by file stem and the parsed ``meta.json``."""

    path: Path
    tables: Mapping[str, Table]
    meta: Mapping[str, Any]
    #: ``*.csv`` files of the directory that are no file of the format (not read; the report
    #: names them, so data under another name does not vanish silently)
    unknown_files: tuple[str, ...] = ()
    #: the whole bundle this one is a decimated subset of (``pipeline.decimate_bundle``), for
    #: what must be taken from consecutive samples (a gyro's means over its reference's
    #: intervals); None: this is the whole bundle
    whole: Bundle | None = field(default=None, compare=False, repr=False)
    #: the recording's fault log (:data:`FAULT_LOG`), None when the bundle has none
    faults: Table | None = None
    #: spans ``(start, end)`` (s) where the odometry is set aside because of an injected fault
    #: (a kidnap, a wheel slip, stuck encoders: :mod:`koala_bridge.calibration.fault_log`)
    odometry_faulted: tuple[tuple[float, float], ...] = ()

    def get(self, name: str) -> Table | None:
        return self.tables.get(name)


def read_csv_table(path: Path) -> Table:
    """Read one bundle CSV: a header row, comma separated; numeric columns as float64.

    A column whose cells do not all parse as numbers (and are not empty) is kept as text; an
    empty numeric cell is NaN. Blank lines and lines starting with ``#`` are skipped. Raises
    :class:`BundleError`, naming the file and the line (1 = the header), for what is not a
    table: bytes that are not UTF-8 text, a NUL byte, no header, a header naming a column twice,
    a row with another number of cells than the header, and a number beyond
    ±:data:`MAX_ABS_VALUE` (``inf``, ``1e308``).
    """
    try:
        raw = path.read_bytes()
    except OSError as e:
        raise BundleError(f"cannot read {path}: {e.strerror or e}") from e
    nul = raw.find(b"\x00")
    if nul < 0:
        fast = _read_numeric_fast(path, raw)
        if fast is not None:
            return fast
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        line = raw.count(b"\n", 0, e.start) + 1
        raise BundleError(
            f"{path} line {line}: not UTF-8 text (byte 0x{raw[e.start]:02x} at offset "
            f"{e.start}): a bundle CSV is UTF-8 text"
        ) from e
    if nul >= 0:
        line = raw.count(b"\n", 0, nul) + 1
        raise BundleError(f"{path} line {line}: a NUL byte: binary data, not CSV text")
    try:
        rows = [
            (n, [c.strip() for c in row])
            for n, row in enumerate(csv.reader(io.StringIO(text, newline="")), start=1)
            if row and any(c.strip() for c in row) and not row[0].lstrip().startswith("#")
        ]
    except csv.Error as e:
        raise BundleError(f"{path}: not readable as CSV: {e}") from e
    if not rows:
        raise BundleError(f"{path} has no header row")
    header_line, header = rows[0]
    seen: set[str] = set()
    for h in header:
        if h in seen:
            raise BundleError(f"{path} line {header_line}: the header names column {h!r} twice")
        seen.add(h)
    body = rows[1:]
    for line, row in body:
        if len(row) != len(header):
            raise BundleError(
                f"{path} line {line}: {len(row)} cell(s), but the header has {len(header)} "
                f"({','.join(header)!r})"
            )
    lines = np.array([line for line, _ in body], dtype=np.int64)
    cols: dict[str, FloatArray] = {}
    text_cols: dict[str, NDArray[np.str_]] = {}
    for i, h in enumerate(header):
        cells = [row[i] for _, row in body]
        try:
            values = np.array([float(c) if c != "" else np.nan for c in cells], dtype=np.float64)
        except ValueError:
            text_cols[h] = np.array(cells, dtype=np.str_)
            continue
        bad = np.flatnonzero(np.abs(values) > MAX_ABS_VALUE)
        if bad.size:
            k = int(bad[0])
            raise BundleError(
                f"{path} line {lines[k]}, column {h!r}: {cells[k]} is beyond ±1e12 "
                "(no measurement in SI units is; a corrupt cell?)"
            )
        cols[h] = values
    return Table(path.stem, cols, text_cols, lines)


def _read_numeric_fast(path: Path, raw: bytes) -> Table | None:
    """The common case at C speed: a header and rows of numbers only, every cell filled, no
    blank, comment or quoted line (Arrow's CSV reader). A 1-hour 100 Hz bundle's 2.9 M rows took
    10 s in the csv module, 0.67 s in numpy's ``loadtxt`` and 0.40 s here, all on one core;
    Arrow also parses on every core the process may use (0.23 s on two). None for anything
    else -- the general reader then reads it and names the line of any defect.

    Every column is read as float64 with no null value and no quoting, and blank lines are
    rows, so Arrow refuses (``ArrowInvalid``) an empty cell, a blank or comment line, a quoted
    cell, a cell of text and a row of another width: the line numbers are the file's. Arrow
    parses a number as the csv module's ``float`` does, correctly rounded: both paths give the
    same bits (tests/unit/test_bundle_csv_reader.py). The file's bytes are neither decoded nor
    copied here: what is not UTF-8 fails Arrow's parse of a number, and the general reader
    names its line."""
    import pyarrow as pa  # here, not at the top: the bridge's run never reads a bundle
    import pyarrow.csv as pa_csv

    eol = raw.find(b"\n")
    if eol < 0:
        return None
    try:
        head = raw[:eol].decode("utf-8-sig")
    except UnicodeDecodeError:
        return None
    if head.lstrip().startswith("#") or '"' in head:
        return None  # a comment, or a quoted header (csv.QUOTE_NONNUMERIC): the csv module's
    head = head.removesuffix("\r")
    if "\r" in head:
        return None  # a lone CR ends Arrow's first line, not this header's: the csv module's
    header = [h.strip() for h in head.split(",")]
    if len(set(header)) != len(header) or not all(header):
        return None
    end = len(raw)
    while end and raw[end - 1] in b"\r\n":
        end -= 1  # trailing blank lines aside
    if end <= eol:
        return None  # no row
    names = [f"c{i}" for i in range(len(header))]  # the header as read above, BOM and spaces off
    try:
        table = pa_csv.read_csv(
            pa.py_buffer(memoryview(raw)[:end]),
            read_options=pa_csv.ReadOptions(column_names=names, skip_rows=1),
            # a blank line is a row of one empty cell, which no float column takes
            parse_options=pa_csv.ParseOptions(quote_char=False, ignore_empty_lines=False),
            convert_options=pa_csv.ConvertOptions(
                column_types=dict.fromkeys(names, pa.float64()),
                null_values=[],
                strings_can_be_null=False,
            ),
        )
    except (pa.ArrowInvalid, pa.ArrowNotImplementedError):
        return None
    # Arrow's buffer of a one-block column is lent read-only; a column of several is joined
    # into a new array. Each is the Table's own, as the general reader's are.
    cols = {}
    for i, h in enumerate(header):
        v = table.column(i).to_numpy()
        cols[h] = v if v.flags.writeable else v.copy()
    # max/min propagate NaN (then both comparisons fail): no |values| temporary.
    if not all(v.max() <= MAX_ABS_VALUE and v.min() >= -MAX_ABS_VALUE for v in cols.values()):
        return None
    lines = np.arange(2, table.num_rows + 2, dtype=np.int64)
    return Table(path.stem, cols, {}, lines)


def _is_number(cell: str) -> bool:
    try:
        float(cell)
    except ValueError:
        return cell == ""
    return True


def load_bundle(directory: Path) -> Bundle:
    """Load every known CSV of a bundle directory and its ``meta.json``.

    Raises :class:`BundleError`, one line naming the file (and the line and column where there
    is one), when the directory does not exist or holds no known file, a file is not a table
    (:func:`read_csv_table`), lacks a column its stream requires or holds text in one, a time
    ``t`` is missing or goes backwards, a file of :data:`SAMPLED_STREAMS` has fewer than two
    rows with every required column filled or a time twice, or ``meta.json`` is not a JSON
    object with meaningful known numbers (:func:`read_meta`). Unknown files and extra columns
    are ignored / kept.
    """
    directory = Path(directory)
    if not directory.is_dir():
        raise BundleError(f"{directory} is not a bundle directory")
    tables: dict[str, Table] = {}
    for name, required in REQUIRED_COLUMNS.items():
        csv_path = directory / f"{name}.csv"
        if not csv_path.exists():
            continue
        table = read_csv_table(csv_path)
        missing = [c for c in required if c not in table]
        if missing:
            named = [*table.columns, *table.text]
            hint = ""
            if len(named) == 1 and any(sep in named[0] for sep in (";", "\t", "|")):
                hint = ": a bundle CSV is comma separated"
            elif any(c.lower() == m for c in named for m in missing):
                hint = ": column names are lower case"
            raise BundleError(
                f"{csv_path} lacks required column(s) {', '.join(missing)} (its header: "
                f"{', '.join(repr(c) for c in named)[:200]}){hint}"
            )
        either = ONE_OF_COLUMNS.get(name, ())
        if either and not any(c in table for c in either):
            raise BundleError(f"{csv_path} lacks a {' or '.join(either)} column")
        required = required + tuple(c for c in either if c in table)
        for c in required + tuple(c for c in OPTIONAL_NUMERIC.get(name, ()) if c in table):
            if c in table.text:
                cells = table.text[c]
                row = next(i for i, v in enumerate(cells) if not _is_number(v))
                raise BundleError(
                    f"{csv_path}{_line(table, row)}, column {c!r}: must be numeric (ids too), "
                    f"but holds {str(cells[row])!r}"
                )
        _check_rows(csv_path, table)
        tables[name] = table
    meta = read_meta(directory / "meta.json")
    faults = None
    if (directory / f"{FAULT_LOG}.csv").exists():
        faults = read_csv_table(directory / f"{FAULT_LOG}.csv")
        missing = [c for c in ("t", "name", "kind", "target") if c not in faults]
        if missing:
            raise BundleError(
                f"{directory / f'{FAULT_LOG}.csv'} lacks required column(s) "
                f"{', '.join(missing)}: a fault log has the columns "
                f"{','.join(FAULT_LOG_COLUMNS)} (docs/faults.md)"
            )
        if "t" in faults.text:
            raise BundleError(f"{directory / f'{FAULT_LOG}.csv'}: the time t is not numeric")
        bad = np.flatnonzero(~np.isfinite(faults["t"]))
        if bad.size:
            raise BundleError(
                f"{directory / f'{FAULT_LOG}.csv'}{_line(faults, int(bad[0]))}: the time t is "
                "empty or not a number"
            )
    unknown = tuple(
        sorted(p.name for p in directory.glob("*.csv")
               if p.stem not in REQUIRED_COLUMNS and p.stem != FAULT_LOG)
    )
    if not tables:
        found = f"; it has {', '.join(unknown)}, which the format does not know" if unknown else ""
        raise BundleError(
            f"{directory} holds no bundle CSV file ({', '.join(REQUIRED_COLUMNS)}){found}: "
            "see docs/bundle-format.md"
        )
    log.info(
        "loaded bundle %s: %s", directory, ", ".join(f"{k}[{len(v)}]" for k, v in tables.items())
    )
    return Bundle(directory, tables, meta, unknown, faults=faults)


def _line(table: Table, row: int) -> str:
    """`` line N`` of a data row, for a message."""
    return "" if table.lines is None else f" line {int(table.lines[row])}"


def _check_rows(path: Path, table: Table) -> None:
    """Row count and time of one stream file (see :func:`load_bundle`)."""
    n = len(table)
    if n == 0:
        raise BundleError(f"{path} has a header but no data row")
    if table.name in SAMPLED_STREAMS and n < 2:
        raise BundleError(f"{path} has 1 data row: a stream needs at least two samples")
    if "t" not in table.columns:
        return
    t = table["t"]
    missing = np.flatnonzero(~np.isfinite(t))
    if missing.size:
        raise BundleError(
            f"{path}{_line(table, int(missing[0]))}, column 't': empty or not a number: every "
            "row needs its time"
        )
    dt = np.diff(t)
    back = np.flatnonzero(dt < 0)
    if back.size:
        k = int(back[0]) + 1
        raise BundleError(
            f"{path}{_line(table, k)}, column 't': {t[k]:.9g} is before the previous row's "
            f"{t[k - 1]:.9g}: rows must be in time order"
        )
    if table.name in SAMPLED_STREAMS:
        required = REQUIRED_COLUMNS[table.name]
        whole = np.logical_and.reduce([np.isfinite(table[c]) for c in required])
        if int(whole.sum()) < 2:
            raise BundleError(
                f"{path}: {int(whole.sum())} row(s) with a number in every one of "
                f"{', '.join(required)}: a stream needs at least two samples"
            )
        same = np.flatnonzero(dt == 0)
        if same.size:
            k = int(same[0]) + 1
            raise BundleError(
                f"{path}{_line(table, k)}, column 't': {t[k]:.9g} repeats the previous row's "
                "time: one sample per time in this file"
            )


def read_meta(path: Path) -> dict[str, Any]:
    """``meta.json`` parsed (``{}`` when there is none); the known numbers checked.

    Raises :class:`BundleError` naming the file and the key when the file is not UTF-8 JSON
    (``NaN``, ``Infinity`` and numbers that overflow a float are not), is not an object, a
    known section (``robot``, ``sensor``, ``units``, ``reference``, ``robot.start_pose``)
    is not an object, or a known number is not a finite number (a ``robot``
    length or scale of :data:`META_ROBOT_POSITIVE` also > 0: ``ticks_per_metre: 0`` has no
    meaning).
    """
    if not path.exists():
        return {}
    try:
        text = path.read_bytes().decode("utf-8-sig")
        meta = json.loads(text, parse_constant=_no_constant, parse_float=_finite_float)
    except OSError as e:
        raise BundleError(f"cannot read {path}: {e.strerror or e}") from e
    except UnicodeDecodeError as e:
        raise BundleError(f"{path}: not UTF-8 text (byte offset {e.start})") from e
    except json.JSONDecodeError as e:
        raise BundleError(f"{path} line {e.lineno}, column {e.colno}: not JSON: {e.msg}") from e
    except ValueError as e:  # _no_constant, _finite_float
        raise BundleError(f"{path}: {e}") from e
    except RecursionError as e:
        raise BundleError(f"{path}: nested too deeply to read") from e
    if not isinstance(meta, dict):
        raise BundleError(
            f"{path} must hold a JSON object ({{...}}), not {_json_kind(meta)}"
        )
    for key in ("robot", "sensor", "units", "reference"):
        _object_or_absent(path, meta, key)
    robot = meta.get("robot") or {}
    for key in META_ROBOT_POSITIVE:
        if key in robot:
            value = _number(path, f"robot.{key}", robot[key])
            if not value > 0:
                raise BundleError(f"{path}: robot.{key} must be > 0, got {robot[key]!r}")
    start = _object_or_absent(path, robot, "start_pose", "robot.")
    if start is not None:
        for key in ("x", "y", "theta", "theta_deg"):
            if key in start and (start[key] is not None or key in ("x", "y")):
                _number(path, f"robot.start_pose.{key}", start[key])
    gyro = (meta.get("sensor") or {}).get("gyro")
    if isinstance(gyro, dict):  # sensor.gyro may be a description
        _numbers(path, gyro, "sensor.gyro.", ("bias_rad_s", "scale_factor_error"))
    reference = meta.get("reference") or {}
    _numbers(path, reference, "reference.", ("from_t", "to_t", "total_rotation_rad"))
    return meta


def _no_constant(name: str) -> Any:
    raise ValueError(f"{name} is not a JSON number (write a finite number, or leave the key out)")


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f"the number {text} is out of range")
    return value


def _json_kind(value: object) -> str:
    if value is None:
        return "null"
    if isinstance(value, list):
        return "an array"
    if isinstance(value, str):
        return "a string"
    return "a number" if isinstance(value, int | float) else f"a {type(value).__name__}"


def _object_or_absent(
    path: Path, parent: Mapping[str, Any], key: str, where: str = ""
) -> Mapping[str, Any] | None:
    value = parent.get(key)
    if value is None and key not in parent:
        return None
    if not isinstance(value, dict):
        raise BundleError(f"{path}: {where}{key} must be a JSON object, not {_json_kind(value)}")
    return value


def _numbers(path: Path, section: Mapping[str, Any], where: str, keys: tuple[str, ...]) -> None:
    """Each of ``keys`` present in ``section`` must be a finite number (:func:`_number`)."""
    for key in keys:
        if key in section:
            _number(path, f"{where}{key}", section[key])


def _number(path: Path, key: str, value: object) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise BundleError(f"{path}: {key} must be a number, got {json.dumps(value)[:40]}")
    if not math.isfinite(value) or abs(value) > MAX_ABS_VALUE:
        raise BundleError(f"{path}: {key} must be a finite number, got {value!r}")
    return float(value)


def load_input(path: Path, workdir: Path) -> Bundle:
    """Load a bundle directory, or export an MCAP recording into ``workdir`` and load that
    (``koala-bridge export``'s :func:`koala_bridge.recording.export.export_bundle`)."""
    path = Path(path)
    if path.suffix.lower() == ".mcap":
        from koala_bridge.core.errors import RecordingError
        from koala_bridge.recording.export import export_bundle

        if not path.is_file():
            raise BundleError(f"{path}: no such recording")
        out = workdir / "bundle"
        out.mkdir(parents=True, exist_ok=True)
        try:
            export_bundle(path, out)
        except (RecordingError, OSError) as e:
            raise BundleError(str(e)) from e
        return load_bundle(out)
    return load_bundle(path)
