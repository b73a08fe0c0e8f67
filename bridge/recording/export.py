"""Export a recording as a measurement bundle (docs/bundle-format.md).

One CSV row per recorded reading, so a bundle holds exactly what the recording holds:

==================  =========================================================================
``truth_pose.csv``  ``t,x,y,theta`` — one row per ``/truth/pose`` message
``odometry.csv``    ``t,left_ticks,right_ticks`` — one row per ``/sensors/odometry`` message
``gyro.csv``        ``t,yaw_rate`` (rad/s) — one row per ``/sensors/gyro`` message
``compass.csv``     ``t,mx,my,mz`` (uT, body FLU) — one row per ``/sensors/compass`` message
``range.csv``       ``t,kind,sensor,measured,true_range,incidence_angle`` — one row per sensor of
                    each ``/sensors/sonar`` (``measured`` m, empty = no echo) and ``/sensors/ir``
                    (``measured`` counts) message; ``true_range`` m from the message's ``truth``
                    companion (empty where the truth has none: nothing in range, or a bridge
                    that does not publish it), ``incidence_angle`` rad between beam and surface
                    normal where known
``landmarks.csv``   ``t,landmark_id,range,bearing`` — one row per camera observation
``landmark_map.csv`` ``id,x,y,colour`` — from the recording's world
``meta.json``       recording, seed, config, ``robot`` (declared geometry), ``sensor`` (declared
                    sensor parameters from the world answer), ``units``
==================  =========================================================================

A file is written only when the recording has its stream. The columns of the per-message tables
are the scalar fields of the topic's typed message (:meth:`core.topics.TopicMessage.csv_columns`),
and every message is read with that class's parser: a message of another shape is an error.
"""

from __future__ import annotations

import csv
import glob
import json
import logging
import math
import os
import shutil
import tempfile
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any, TypeVar

from koala_bridge.core.topics import (
    CameraMessage,
    CompassMessage,
    FaultEventMessage,
    GyroMessage,
    IrMessage,
    OdometryMessage,
    SonarMessage,
    TopicError,
    TopicMessage,
    TruthPose,
)
from koala_bridge.recording.mcap_file import (
    META_NAME,
    RecordedMessage,
    Recording,
    RecordingError,
    open_recording,
    topic_name,
)

log = logging.getLogger(__name__)

M = TypeVar("M", bound=TopicMessage)

#: One row per message: file name -> the message class whose scalar fields are the columns.
TABLES: dict[str, type[TopicMessage]] = {
    "truth_pose.csv": TruthPose,
    "odometry.csv": OdometryMessage,
    "gyro.csv": GyroMessage,
    "compass.csv": CompassMessage,
}
RANGE_KINDS: dict[str, type[IrMessage] | type[SonarMessage]] = {
    "sonar": SonarMessage,
    "ir": IrMessage,
}
RANGE_COLUMNS = ("t", "kind", "sensor", "measured", "true_range", "incidence_angle")
LANDMARK_COLUMNS = ("t", "landmark_id", "range", "bearing")


def _cell(v: Any) -> str:
    """A CSV cell: empty for None/NaN/inf, repr-exact for floats (round-trips bit for bit)."""
    if v is None:
        return ""
    if isinstance(v, bool):
        return str(int(v))
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else ""
    return str(v)


def write_csv(path: Path, header: Sequence[str], rows: Iterable[Sequence[Any]]) -> int:
    """Write one bundle CSV (a header row, then ``rows``, cells as :func:`_cell` writes them:
    strings as given, floats repr-exact, None/NaN empty); returns the number of rows."""
    n = 0
    with path.open("w", newline="", encoding="utf-8") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(header)
        for row in rows:
            w.writerow([_cell(v) for v in row])
            n += 1
    return n


def _parsed(rec: Recording, cls: type[M]) -> list[tuple[RecordedMessage, M]]:
    """The messages of ``cls``'s topic, parsed; a message of another shape is an error."""
    out = []
    for m in rec.topic(cls.TOPIC):
        try:
            out.append((m, cls.parse(m.data)))
        except TopicError as e:
            raise RecordingError(
                f"{rec.path}: message {m.sequence} of {m.topic} is not a {cls.TOPIC} "
                f"message: {e}"
            ) from e
    return out


def _range_rows(rec: Recording) -> list[tuple[Any, ...]]:
    rows: list[tuple[Any, ...]] = []
    messages = [
        (m.log_time_ns, kind, msg)
        for kind, cls in RANGE_KINDS.items()
        for m, msg in _parsed(rec, cls)
    ]
    messages.sort(key=lambda x: x[0])  # stable: same-time sonar before IR
    for _, kind, msg in messages:
        for i, value, true_range, incidence in msg.sensor_rows():
            rows.append((msg.t, kind, i, value, true_range, incidence))
    return rows


def _meta(rec: Recording, counts: dict[str, int]) -> dict[str, Any]:
    run = rec.metadata.get(META_NAME, {})
    world = rec.world or {}
    robot_answer = world.get("robot") or {}
    robot: dict[str, Any] = {
        k: robot_answer[k]
        for k in ("ticks_per_metre", "wheel_base_m", "wheel_diameter_m")
        if k in robot_answer
    }
    start = world.get("start")
    if isinstance(start, dict) and {"x", "y"} <= start.keys():
        theta = start.get("theta")
        if theta is None and "theta_deg" in start:
            theta = math.radians(float(start["theta_deg"]))
        robot["start_pose"] = {"x": start["x"], "y": start["y"], "theta": theta or 0.0}
    sensor = {k: v for k, v in robot_answer.items() if k not in robot}
    seed: Any = run.get("seed")
    if isinstance(seed, str) and seed.lstrip("-").isdigit():
        seed = int(seed)
    fleet_robot = run.get("robot")  # a robot of a [[robots]] recording (Recording.robot)
    return {
        "source": f"koala-bridge recording ({run.get('source', 'sim')})"
                  + (f", robot {fleet_robot}" if fleet_robot else ""),
        "recording": str(rec.path.resolve()),
        "recording_complete": rec.complete,
        "recording_lost": rec.lost,
        "format_version": rec.format_version,
        "seed": seed,
        "config_path": run.get("config_path"),
        "config": run.get("config"),
        "robot": robot,
        "sensor": sensor,
        "units": {
            "t": "s (simulation time)",
            "range.measured": {"sonar": "m", "ir": "counts"},
            "range.true_range": "m",
            "range.incidence_angle": "rad",
            "compass": "uT",
            "gyro.yaw_rate": "rad/s",
            "odometry": "encoder ticks (cumulative)",
        },
        "rows": counts,
        "notes": [
            "One row per recorded message; range.csv and landmarks.csv: per sensor/observation.",
            "range.csv: empty measured = no echo; empty true_range = nothing within range.",
        ],
    }


#: What a bundle directory written by :func:`export_bundle` may hold: the only directory
#: contents an export replaces.
BUNDLE_FILES = frozenset(
    [*TABLES, "range.csv", "landmarks.csv", "landmark_map.csv", "meta.json"]
)


def export_bundle(
    mcap_path: str | os.PathLike[str], out_dir: str | os.PathLike[str],
    robot: str | None = None,
) -> Path:
    """Write the measurement bundle of the recording ``mcap_path`` into ``out_dir``.

    A recording of ``[[robots]]`` is exported one robot at a time: ``robot`` names it, and its
    channels are read as a one-robot recording's (:meth:`Recording.robot`); without ``robot``
    such a recording is refused with a line naming its robots.

    The bundle is written into a temporary sibling directory and renamed to ``out_dir`` when
    complete, so an export that fails or is killed never leaves a partial bundle that
    ``calibrate`` would accept. An existing ``out_dir`` is replaced if it is empty or holds
    only bundle files (:data:`BUNDLE_FILES`: a previous export), and refused otherwise. A
    recording cut short (SIGKILL) exports what it holds, with a warning (its ``meta.json``
    says ``recording_complete: false`` and what was lost). Raises
    :class:`recording.mcap_file.RecordingError` if the file is not a recording, is damaged, or
    holds no reading at all; OSError if the directory cannot be written.
    """
    rec = open_recording(mcap_path).robot(robot)
    out = Path(out_dir)
    if out.exists():
        if not out.is_dir():
            raise RecordingError(f"{out} exists and is not a directory")
        foreign = sorted(p.name for p in out.iterdir() if p.name not in BUNDLE_FILES)
        if foreign:
            raise RecordingError(
                f"{out} holds files that are not a bundle's ({', '.join(foreign[:3])}): "
                "choose a new or empty directory"
            )
    out.parent.mkdir(parents=True, exist_ok=True)
    _remove_stale_siblings(out)
    pid = os.getpid()
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.partial-{pid}-", dir=out.parent))
    try:
        _write_bundle(rec, mcap_path, tmp)
        if out.exists():
            # The old bundle moves aside first; between the two renames there is no bundle
            # at ``out`` at all, never a mixed or partial one.
            old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-{pid}-", dir=out.parent))
            os.rename(out, old / "bundle")
            os.rename(tmp, out)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.rename(tmp, out)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return out


def _remove_stale_siblings(out: Path) -> None:
    """Remove the ``.NAME.partial-PID-*`` and ``.NAME.old-PID-*`` folders beside ``out`` that an
    export killed mid-way left (its process PID is gone); a running export's are left alone."""
    for kind in ("partial", "old"):
        for stale in out.parent.glob(f".{glob.escape(out.name)}.{kind}-*"):
            pid = stale.name[len(f".{out.name}.{kind}-") :].split("-", 1)[0]
            if stale.is_dir() and pid.isdigit() and not _process_exists(int(pid)):
                log.info("removing %s, left by an export (process %s) that did not finish",
                         stale, pid)
                shutil.rmtree(stale, ignore_errors=True)


def _process_exists(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)  # signal 0: only checks that the process exists
    except ProcessLookupError:
        return False
    except PermissionError:  # it exists, owned by another user
        return True
    except OSError:
        return True  # when in doubt, keep the folder
    return True


def _write_bundle(rec: Recording, mcap_path: str | os.PathLike[str], out: Path) -> None:
    """The bundle's files, written into the (new, empty) directory ``out``."""
    counts: dict[str, int] = {}

    for name, cls in TABLES.items():
        msgs = _parsed(rec, cls)
        if msgs:
            rows = (msg.csv_row() for _, msg in msgs)
            counts[name] = write_csv(out / name, cls.csv_columns(), rows)

    ranges = _range_rows(rec)
    if ranges:
        counts["range.csv"] = write_csv(out / "range.csv", RANGE_COLUMNS, ranges)

    # (a camera that saw no landmark all run has messages but no observation: no file, as
    # for a stream with no message -- a header alone is no table, calibrate refuses one)
    observations = [(msg.t, o.id, o.range, o.bearing)
                    for _, msg in _parsed(rec, CameraMessage) for o in msg.observations]
    if observations:
        counts["landmarks.csv"] = write_csv(out / "landmarks.csv", LANDMARK_COLUMNS,
                                            observations)

    landmarks = (rec.world or {}).get("landmarks") or []
    if landmarks:
        rows = ((lm.get("id"), lm.get("x"), lm.get("y"), lm.get("colour", "")) for lm in landmarks)
        counts["landmark_map.csv"] = write_csv(
            out / "landmark_map.csv", ("id", "x", "y", "colour"), rows
        )

    # Injected faults (docs/faults.md): an analyst must see that a reading was faulted on
    # purpose (a kidnap is not an odometry error). Not a bundle file calibrate reads.
    faults = rec.topic(topic_name(FaultEventMessage.TOPIC))
    if faults:
        rows = ((m.json()["t"], m.json()["name"], m.json()["kind"], m.json()["target"],
                 json.dumps(m.json()["detail"], separators=(",", ":"))) for m in faults)
        counts["faults.csv"] = write_csv(out / "faults.csv",
                                          ("t", "name", "kind", "target", "detail"), rows)

    if not set(counts) - {"landmark_map.csv", "faults.csv"}:  # the map alone is no reading
        raise RecordingError(f"{mcap_path} holds no reading to export")
    (out / "meta.json").write_text(json.dumps(_meta(rec, counts), indent=2) + "\n", "utf-8")
