"""Measurement bundles (docs/bundle-format.md): load a directory of CSV files.

A bundle is read into plain numpy columns, one :class:`Table` per CSV file, plus the free-form
``meta.json``. Recordings (MCAP) are converted to a bundle first by the recording package's
exporter, so every later stage sees one format.
"""

from __future__ import annotations

import json
import logging
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
    "landmarks": ("t", "landmark_id", "range", "bearing"),
    "landmark_map": ("id", "x", "y"),
}


@dataclass(frozen=True)
class Table:
    """One CSV file as named float columns of equal length (non-numeric cells become NaN).

    Text columns (for example ``kind``) are kept separately in :attr:`text`.
    """

    name: str
    columns: Mapping[str, FloatArray]
    text: Mapping[str, NDArray[np.str_]] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(next(iter(self.columns.values()))) if self.columns else 0

    def __contains__(self, column: object) -> bool:
        return column in self.columns or column in self.text

    def __getitem__(self, column: str) -> FloatArray:
        return self.columns[column]

    def select(self, mask: NDArray[np.bool_]) -> Table:
        """Rows where ``mask`` is true."""
        return Table(
            self.name,
            {k: v[mask] for k, v in self.columns.items()},
            {k: v[mask] for k, v in self.text.items()},
        )


@dataclass(frozen=True)
class Bundle:
    """A loaded measurement bundle: tables by file stem and the parsed ``meta.json``."""

    path: Path
    tables: Mapping[str, Table]
    meta: Mapping[str, Any]

    def get(self, name: str) -> Table | None:
        return self.tables.get(name)


def read_csv_table(path: Path) -> Table:
    """Read one bundle CSV: a header row, comma separated; numeric columns as float64.

    A column whose cells do not all parse as numbers (and are not empty) is kept as text.
    """
    try:
        with path.open(encoding="utf-8") as fh:
            header = [h.strip() for h in fh.readline().strip().split(",")]
            body = fh.read()
    except OSError as e:
        raise BundleError(f"cannot read {path}: {e}") from e
    if not header or header == [""]:
        raise BundleError(f"{path} has no header row")
    if not body.strip():
        return Table(path.stem, {h: np.empty(0) for h in header})
    try:
        # The fast path: every cell numeric (the C parser of numpy >= 1.23).
        data = np.loadtxt(
            path, delimiter=",", skiprows=1, ndmin=2, dtype=np.float64, encoding="utf-8"
        )
        return Table(path.stem, {h: np.ascontiguousarray(data[:, i]) for i, h in enumerate(header)})
    except ValueError:
        pass
    raw = np.genfromtxt(
        path, delimiter=",", skip_header=1, dtype=str, encoding="utf-8", ndmin=2, autostrip=True
    )
    cols: dict[str, FloatArray] = {}
    text: dict[str, NDArray[np.str_]] = {}
    for i, h in enumerate(header):
        cells = raw[:, i]
        try:
            cols[h] = np.array([float(c) if c != "" else np.nan for c in cells], dtype=np.float64)
        except ValueError:
            text[h] = cells.astype(np.str_)
    return Table(path.stem, cols, text)


def _is_number(cell: str) -> bool:
    try:
        float(cell)
    except ValueError:
        return cell == ""
    return True


def load_bundle(directory: Path) -> Bundle:
    """Load every known CSV of a bundle directory and its ``meta.json``.

    Raises :class:`BundleError` when the directory does not exist, holds no known file, or a file
    lacks a column its stream requires. Unknown files and extra columns are ignored / kept.
    """
    directory = Path(directory)
    if not directory.is_dir():
        raise BundleError(f"{directory} is not a bundle directory")
    tables: dict[str, Table] = {}
    for name, required in REQUIRED_COLUMNS.items():
        csv = directory / f"{name}.csv"
        if not csv.exists():
            continue
        table = read_csv_table(csv)
        missing = [c for c in required if c not in table]
        if missing:
            raise BundleError(f"{csv} lacks required column(s) {', '.join(missing)}")
        for c in required:
            if c in table.text:
                cells = table.text[c]
                row = next(i for i, v in enumerate(cells) if not _is_number(v))
                raise BundleError(
                    f"{csv}: column {c!r} must be numeric (ids too), but data row {row + 1} "
                    f"holds {str(cells[row])!r}"
                )
        if "t" in table.columns:
            order = np.argsort(table["t"], kind="stable")
            if np.any(order != np.arange(len(order))):
                table = table.select(order)  # type: ignore[arg-type]
        tables[name] = table
    meta: dict[str, Any] = {}
    meta_path = directory / "meta.json"
    if meta_path.exists():
        try:
            meta = json.loads(meta_path.read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError) as e:
            raise BundleError(f"cannot parse {meta_path}: {e}") from e
    if not tables:
        raise BundleError(f"{directory} holds no bundle CSV file ({', '.join(REQUIRED_COLUMNS)})")
    log.info(
        "loaded bundle %s: %s", directory, ", ".join(f"{k}[{len(v)}]" for k, v in tables.items())
    )
    return Bundle(directory, tables, meta)


def load_input(path: Path, workdir: Path) -> Bundle:
    """Load a bundle directory, or export an MCAP recording into ``workdir`` and load that
    (``koala-bridge export``'s :func:`koala_bridge.recording.export.export_bundle`)."""
    path = Path(path)
    if path.suffix.lower() == ".mcap":
        from koala_bridge.recording.export import export_bundle
        from koala_bridge.recording.mcap_file import RecordingError

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
