"""Turn found effects into config keys, merge them into MODEL.toml, and diff the two.

Each effect's ``config`` gives keys relative to its stream's section (``[sensors.gyro]`` ...):
``"bias_rad_s"`` sets a key the simulator reads, ``"calibration.<name>"`` goes to the stream's
``[sensors.<stream>.calibration]`` table, and ``"/robot.wheel_base_m"`` is absolute.
"""

from __future__ import annotations

import copy
import difflib
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import tomli_w

from bridge.calibration.pipeline import StreamResult
from bridge.calibration.problem import split_params


def _set(doc: dict[str, Any], dotted: str, value: Any) -> None:
    *head, last = dotted.split(".")
    node = doc
    for key in head:
        nxt = node.get(key)
        if not isinstance(nxt, dict):
            nxt = {}
            node[key] = nxt
        node = nxt
    node[last] = value


def found_keys(results: Sequence[StreamResult]) -> dict[str, Any]:
    """``{dotted.key: value}`` for every found effect (and fitted declared parts, e.g. a curve)."""
    out: dict[str, Any] = {}
    for res in results:
        problem, after = res.problem, res.selection.after
        entries: dict[str, Any] = dict(problem.config_values(after.insts, after.x))
        params = split_params(problem, after.insts, after.x)
        for inst in res.effects:
            entries.update(inst.config(params[after.insts.index(inst)], problem))
        for key, value in entries.items():
            path = key[1:] if key.startswith("/") else f"{problem.section}.{key}"
            out[path] = value
    return out


def updated_config(base: Mapping[str, Any], keys: Mapping[str, Any]) -> dict[str, Any]:
    """A deep copy of ``base`` with ``keys`` set (an ``ideal = true`` flag is cleared)."""
    doc = copy.deepcopy(dict(base))
    for dotted, value in keys.items():
        _set(doc, dotted, value)
        section = dotted.split(".calibration.")[0].rsplit(".", 1)[0]
        node: Any = doc
        for k in section.split("."):
            node = node.get(k, {}) if isinstance(node, dict) else {}
        if isinstance(node, dict) and node.get("ideal") is True:
            node["ideal"] = False
    return doc


def dumps(doc: Mapping[str, Any]) -> str:
    return tomli_w.dumps(dict(doc))


def config_diff(base: Mapping[str, Any], new: Mapping[str, Any], name: str = "MODEL.toml") -> str:
    """Unified diff of the two configs as TOML (comments of the original are not kept)."""
    return "".join(
        difflib.unified_diff(
            dumps(base).splitlines(keepends=True),
            dumps(new).splitlines(keepends=True),
            fromfile=f"a/{name}",
            tofile=f"b/{name}",
        )
    )


def write_config(path: Path, doc: Mapping[str, Any]) -> None:
    header = (
        "# Written by `koala-bridge calibrate --write-config`: the declared model with the\n"
        "# effects found in measured data added (see the report's config diff).\n"
    )
    Path(path).write_text(header + dumps(doc), encoding="utf-8")
