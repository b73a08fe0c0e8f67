"""The error models' params classes on the one config schema (:mod:`koala_bridge.core.schema`).

Each ``*ErrorParams`` class of ``sim/models/`` is a :func:`~koala_bridge.core.schema.section`:
a frozen dataclass whose fields are typed and range-checked by the schema's policy (strict
types, finite numbers, unknown keys suggest the nearest). Its keyword defaults ARE the values
``config/default.toml`` writes for those keys (``tests/unit/test_config_schema.py`` asserts it),
so a params object built in Python and one read from the shipped file agree, and a key left out
of a file means the documented value, never a different hidden one.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Annotated, Any, TypeVar

from koala_bridge.core.schema import MAX_MAGNITUDE, ConfigError, validate
from koala_bridge.sim.noise import LookupTable
from pydantic import BeforeValidator

T = TypeVar("T")


def params_from_dict(cls: type[T], d: Mapping[str, Any], section: str) -> T:
    """Build the params section ``cls`` from its keys of the table ``[section]``."""
    return validate(cls, d, section)


def _table(value: Any) -> Any:
    """``[[x, y], ...]`` or ``[[x, y, noise], ...]`` rows (numbers only) -> LookupTable."""
    if isinstance(value, LookupTable):
        return value
    if not isinstance(value, list | tuple) or not all(
        isinstance(r, list | tuple)
        and all(isinstance(v, int | float) and not isinstance(v, bool) for v in r)
        for r in value
    ):
        raise ValueError(f"must be rows of numbers [[x, y], ...] or [[x, y, noise], ...], "
                         f"got {value!r}")
    try:
        table = LookupTable.from_rows(value)
    except ConfigError as e:
        raise ValueError(str(e).removeprefix("[table] ")) from None
    if not all(map(lambda a: bool((abs(a) < float("inf")).all()), (table.x, table.y,
                                                                   table.noise_col))):
        raise ValueError(f"must hold finite numbers, got {value!r}")
    if not all(map(lambda a: bool((abs(a) <= MAX_MAGNITUDE).all()), (table.x, table.y,
                                                                     table.noise_col))):
        raise ValueError(f"must hold plausible numbers (|value| <= {MAX_MAGNITUDE:g}), "
                         f"got {value!r}")
    return table


#: A lookup table field: TOML rows in, :class:`~koala_bridge.sim.noise.LookupTable` out.
Table = Annotated[LookupTable, BeforeValidator(_table)]
