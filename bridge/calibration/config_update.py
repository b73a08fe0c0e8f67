"""Turn found effects into config keys, merge them into MODEL.toml, and diff the two.

Each effect's ``config`` gives keys relative to its stream's section (``[sensors.gyro]`` ...):
``"bias_rad_s"`` sets a key of that section, ``"calibration.<name>"`` names an effect without a
simulator key, and ``"/robot.wheel_base_m"`` is absolute.

The written config must still load in the simulator (``sim/config.py`` rejects unknown keys),
so only the keys of :data:`.sim_keys.SIMULATED_KEYS` go into the TOML document; every other
finding is written as a comment block at the end of the file (and is in report.json).
docs/calibration.md
"What the simulator reproduces" says which effects are which, and why.

When a sensor declared ``ideal = true`` gets a found effect, its error model is switched on;
the model's other error terms, which the calibration did not measure, are set to their
"absent" values (the params class's ``ABSENT``: no turn-on bias, no random walk, ...) rather
than to whatever the config held under ``ideal = true``.
"""

from __future__ import annotations

import copy
import difflib
import importlib
import math
import textwrap
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import tomli_w
from koala_bridge.calibration.pipeline import StreamResult
from koala_bridge.calibration.problem import split_params
from koala_bridge.calibration.sim_keys import config_path, is_simulated, section_and_key

#: Config section -> the simulator's error-model name (sim.sections.ERROR_PARAMS).
_MODEL_OF = {"sensors.gyro": "gyro", "sensors.compass": "compass", "sensors.ir": "ir"}


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


def declared_parts(results: Sequence[StreamResult]) -> list[str]:
    """What a written key holds that the data did not show, one line each: a compass fitted in
    a plane (two dimensions) writes its hard iron's z and its soft iron's vertical terms from the
    declared model (a simulator config needs all three axes), and a spin about the vertical
    cannot show them; a new user's written ``hard_iron_uT = [40.93, -89.46, 0.0]`` read as a
    measured zero where the raw z sat at 560 uT. ``results``: every stage's, in order; a part
    a full-sphere (3-D) fit of any stage measured is not said."""
    written: dict[tuple[str, int], set[str]] = {}  # (section, dims) -> iron effects written
    planar: dict[str, Any] = {}  # section -> its last planar compass problem
    for res in results:
        dims = getattr(res.problem, "dims", None)
        if dims not in (2, 3):
            continue
        names = {i.name for i, why in zip(res.effects, res.not_written(), strict=True)
                 if why is None and i.name in ("hard_iron", "soft_iron")}
        written.setdefault((res.problem.section, dims), set()).update(names)
        if dims == 2 and names:
            planar[res.problem.section] = res.problem
    out = []
    for section, problem in planar.items():
        unmeasured = written[(section, 2)] - written.get((section, 3), set())
        parts = []
        if "hard_iron" in unmeasured:
            z = float(problem.h_declared[2]) * problem.uT_per_unit
            parts.append(f"hard_iron_uT's z is the declared {z:g} uT")
        if "soft_iron" in unmeasured:
            parts.append("soft_iron's vertical terms follow from the declared matrix")
        if parts:
            out.append(
                f"{section}: {' and '.join(parts)}, not measured: the compass was fitted in "
                "its horizontal plane, which does not show the vertical"
            )
    return out


def found_keys(results: Sequence[StreamResult]) -> dict[str, Any]:
    """``{dotted.key: value}`` for every found effect (and fitted declared parts, e.g. a curve),
    except an effect whose uncertainty is larger than it (:meth:`StreamResult.not_written`):
    it is neither written nor carried into a later stage; the report says so."""
    out: dict[str, Any] = {}
    for res in results:
        problem, after = res.problem, res.selection.after
        entries: dict[str, Any] = dict(problem.config_values(after.insts, after.x))
        params = split_params(problem, after.insts, after.x)
        increments: dict[str, np.ndarray] = {}
        for inst, reason in zip(res.effects, res.not_written(), strict=True):
            if reason is not None:
                continue
            for key, value in inst.config(params[after.insts.index(inst)], problem).items():
                if key.startswith("+"):  # per-element increments of a declared list: summed
                    inc = np.asarray(value, dtype=float)
                    old = increments.get(key, np.zeros(0))
                    n = max(old.size, inc.size)
                    increments[key] = np.pad(old, (0, n - old.size)) + np.pad(
                        inc, (0, n - inc.size)
                    )
                else:
                    entries[key] = value
        for key, inc in increments.items():
            declared = np.asarray(problem.declared_values.get(key, ()), dtype=float)
            n = max(inc.size, declared.size, int(problem.declared_values.get("n_sensors", 0)))
            total = np.pad(inc, (0, n - inc.size)) + np.pad(declared, (0, n - declared.size))
            entries[key[1:]] = [float(f"{v:.6g}") for v in total]
        for key, value in entries.items():
            out[config_path(problem.section, key)] = value
    return out


def noise_keys(results: Sequence[StreamResult]) -> dict[str, Any]:
    """The white-noise level of each stream's final residual, in the simulator's noise key
    (``--write-noise``): gyro ``gyroscope_noise_density`` = sigma sqrt(mean sample interval)
    (Kalibr's discretisation, sim/models/gyro.py), compass ``noise_sigma_uT`` (heading residual
    times the horizontal field, or the magnitude residual times the field), IR
    ``count_noise_sigma`` (minus the rounding's 1/12 count^2). Right when the reference is far
    less noisy than the sensor (a robot standing still, a motion tracker)."""
    out: dict[str, Any] = {}
    for res in results:
        key, value = res.problem.noise_estimate(res.selection.after.insts, res.selection.after.x)
        if key is not None and value is not None and math.isfinite(value):
            out[f"{res.problem.section}.{key}"] = float(f"{value:.4g}")
    return out


def _absent_error_terms(section: str) -> dict[str, Any]:
    """The error-model keys of ``section`` and their values that mean 'no such error'."""
    model = _MODEL_OF.get(section)
    if model is None:
        return {}
    from koala_bridge.sim.sections import ERROR_PARAMS

    module, name = ERROR_PARAMS[model]
    cls = getattr(importlib.import_module(module), name)
    return {k: ([list(r) if isinstance(r, tuple) else r for r in v] if isinstance(v, tuple)
                else v)
            for k, v in getattr(cls, "ABSENT", {}).items()}


def updated_config(base: Mapping[str, Any], keys: Mapping[str, Any]) -> dict[str, Any]:
    """A deep copy of ``base`` with the simulated ``keys`` set; a sensor whose ``ideal = true``
    flag is cleared gets its unmeasured error terms set to 'absent' (module docstring)."""
    doc = copy.deepcopy(dict(base))
    for dotted, value in keys.items():
        if not is_simulated(dotted):
            continue
        section, _ = section_and_key(dotted)
        node: Any = doc
        for k in section.split("."):
            node = node.get(k, {}) if isinstance(node, dict) else {}
        if isinstance(node, dict) and node.get("ideal") is True:
            node["ideal"] = False
            for k, v in _absent_error_terms(section).items():
                if k in node and f"{section}.{k}" not in keys:
                    node[k] = v
        _set(doc, dotted, value)
    return doc


def not_simulated(keys: Mapping[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in keys.items() if not is_simulated(k)}


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


def _inline(value: Any) -> str:
    """``value`` as a one-line TOML value: a table inline (``{ a = 1, b = 2 }``), since the
    comment block is one ``#`` line per key (a multi-line table there would become keys)."""
    if isinstance(value, Mapping):
        return "{ " + ", ".join(f"{k} = {_inline(v)}" for k, v in value.items()) + " }"
    if isinstance(value, list | tuple):  # tomli_w spreads arrays over lines
        return "[" + ", ".join(_inline(v) for v in value) + "]"
    return tomli_w.dumps({"v": value})[4:].strip()


def _edited(template: str, base: Mapping[str, Any], doc: Mapping[str, Any]) -> str:
    """``template`` (MODEL.toml's text, which loads as ``base``) with every value that differs
    in ``doc`` set, by tomlkit: its comments, order and layout stay. A changed key's own inline
    comment, which described the old value, becomes ``calibrate: was <old>``."""
    import tomlkit
    from tomlkit.items import Item

    out = tomlkit.parse(template)

    def walk(node: Any, old: Mapping[str, Any], new: Mapping[str, Any]) -> None:
        for key, value in new.items():
            before = old.get(key) if isinstance(old, Mapping) else None
            if isinstance(value, Mapping) and isinstance(before, Mapping) and key in node:
                walk(node[key], before, value)
                continue
            if key in old and before == value:
                continue
            item = tomlkit.item(value)
            previous = node.get(key)
            if key in old and isinstance(previous, Item) and not isinstance(value, Mapping):
                kept = previous.trivia.comment.lstrip("#").strip()
                if isinstance(value, str) and kept:
                    item.comment(kept)  # a file path made relative to the new file: same key
                else:
                    item.comment(f"calibrate: was {_inline(before)}")
            node[key] = item

    walk(out, base, doc)
    return tomlkit.dumps(out)


def write_config(
    path: Path,
    doc: Mapping[str, Any],
    unsimulated: Mapping[str, Any] = {},
    fragment: bool = False,
    template: tuple[str, Mapping[str, Any]] | None = None,
    notes: Sequence[str] = (),
) -> None:
    """Write ``doc`` as TOML; ``unsimulated`` findings as a trailing comment; ``fragment``: no
    MODEL.toml was given, so the file holds only the found keys, which the header says.
    ``template``: MODEL.toml's text and what it loads as; the file is then that text with the
    changed values set (:func:`_edited`), so its comments and layout stay. ``notes``: what a
    written key holds that the data did not show (:func:`declared_parts`), in the header."""
    header = (
        "# Written by `koala-bridge calibrate --write-config`: the declared model with the\n"
        "# effects found in measured data added (see the report's config diff).\n"
    )
    for note in notes:
        header += "".join(f"# {line}\n" for line in textwrap.wrap(note, 90))
    if fragment:
        header += (
            "# No --config was given: this holds the keys found and the robot geometry\n"
            "# meta.json declared, not a whole bridge config. To simulate with them, copy\n"
            "# them into one (e.g. config/default.toml), or calibrate again with --config\n"
            "# that file.\n"
        )
    tail = ""
    if unsimulated:
        lines = [
            "",
            "# Found in the data but not written above: the simulator has no key for these",
            "# (docs/calibration.md, 'What the simulator reproduces'):",
        ]
        for k, v in unsimulated.items():
            lines.append(f"#   {k} = {_inline(v)}")
        tail = "\n".join(lines) + "\n"
    body = dumps(doc) if template is None else _edited(template[0], template[1], doc)
    Path(path).write_text(header + body + tail, encoding="utf-8")
