"""The configuration schema's one policy, implemented once (pydantic v2).

Every table of a configuration file is typed by a frozen dataclass declared with
:func:`section` and built from the parsed TOML table by :func:`validate`. The policy:

* **Every key comes from the file, or from one documented default.** A field without a default
  is required: a missing key is an error naming it. A field with a default may be left out, and
  its default is the value ``config/default.toml`` shows for that key (the file documents every
  key; ``tests/unit/test_config_schema.py`` asserts that the file holds every field of every
  section, that it holds no other key, and that each default equals the file's value).
* **Unknown keys are errors** that name the section and suggest the nearest valid key, with its
  full dotted name.
* **Types are strict**: a number key takes a TOML number, never a string (``"0.285"``) or a
  boolean (``true``); an integer key never takes a float; a boolean key only ``true``/``false``.
* **Numbers are finite and in range**: nan is refused everywhere; ``inf`` only where a field
  says so (:data:`FloatOrInf`); and no magnitude beyond :data:`MAX_MAGNITUDE` (a ``1e300`` is a
  typo, not a measurement). Fields that are meaningless at zero or below use :data:`Positive`
  or :data:`NonNegative`.
* **Errors are one line**: :class:`ConfigError` ``[section] 'key' must be ..., got ...``.

Neutral lowest layer: stdlib, pydantic and numpy only; no file I/O (loaders in ``bridge/`` read
TOML and hand plain dicts to the ``from_dict`` constructors).
"""

from __future__ import annotations

import dataclasses
import difflib
import math
from collections.abc import Callable, Iterable, Mapping
from typing import Annotated, Any, TypeVar, dataclass_transform, overload

from koala_bridge.core.errors import ConfigError  # re-exported: its old home
from pydantic import (
    AfterValidator,
    BeforeValidator,
    ConfigDict,
    Field,
    Strict,
    TypeAdapter,
    ValidationError,
)
from pydantic.dataclasses import dataclass as _pydantic_dataclass

__all__ = [
    "one_of",
    "MAX_MAGNITUDE",
    "Bool",
    "ConfigError",
    "Finite",
    "FloatOrInf",
    "FloatTuple",
    "Int",
    "NestedFloats",
    "NonNegative",
    "NonNegativeInt",
    "Port",
    "Positive",
    "PositiveInt",
    "Probability",
    "Str",
    "field_names",
    "section",
    "tuples",
    "validate",
    "number",
    "positive",
    "reject_unknown",
    "require",
    "value_of",
]

T = TypeVar("T")

#: The largest magnitude a number key may have: no quantity of this robot, in the units its keys
#: name, comes near it, so a larger value is a typo (``1e300``) that would only overflow later.
MAX_MAGNITUDE = 1e9

#: The pydantic configuration of every section: strict types, no unknown keys, no nan/inf.
SECTION_CONFIG = ConfigDict(
    strict=True, extra="forbid", allow_inf_nan=False, arbitrary_types_allowed=True,
)


@overload
def section(cls: type[T], /) -> type[T]: ...


@overload
def section(*, eq: bool = True) -> Callable[[type[T]], type[T]]: ...


@dataclass_transform(frozen_default=True, field_specifiers=(dataclasses.field, Field))
def section(cls: type[T] | None = None, /, *, eq: bool = True) -> Any:
    """Declare a config section: a frozen dataclass validated by :data:`SECTION_CONFIG`.

    Construction validates (``cls(**table)`` raises pydantic's ``ValidationError``); build one
    from a TOML table with :func:`validate`, which turns errors into one-line
    :class:`ConfigError`. ``__post_init__`` runs after field validation, for checks that
    involve several keys (raise :class:`ConfigError` or ``ValueError`` there).
    """
    def wrap(c: type[T]) -> type[T]:
        return _pydantic_dataclass(frozen=True, eq=eq, config=SECTION_CONFIG)(c)  # type: ignore[return-value]

    return wrap if cls is None else wrap(cls)


# ------------------------------------------------------------------------------ field types


def _bounded(v: float) -> float:
    if math.isnan(v):
        raise ValueError("must be a number, not nan")
    if math.isfinite(v) and abs(v) > MAX_MAGNITUDE:
        raise ValueError(f"must be a plausible number (|value| <= {MAX_MAGNITUDE:g}), got {v!r}")
    return v


def tuples(value: Any) -> Any:
    """TOML arrays (lists) as tuples, nested, so that frozen sections stay hashable."""
    if isinstance(value, list):
        return tuple(tuples(v) for v in value)
    return value


#: A finite float (an int is accepted and converted), |value| <= :data:`MAX_MAGNITUDE`.
Finite = Annotated[float, Strict(), Field(allow_inf_nan=False), AfterValidator(_bounded)]
#: A float that may be ``inf`` (a field whose meaning has an "infinitely long"), never nan.
FloatOrInf = Annotated[float, Strict(), Field(allow_inf_nan=True), AfterValidator(_bounded)]
Positive = Annotated[Finite, Field(gt=0)]
NonNegative = Annotated[Finite, Field(ge=0)]
Probability = Annotated[Finite, Field(ge=0, le=1)]
Bool = Annotated[bool, Strict()]
Str = Annotated[str, Strict()]
Int = Annotated[int, Strict(), Field(ge=-int(MAX_MAGNITUDE), le=int(MAX_MAGNITUDE))]
PositiveInt = Annotated[int, Strict(), Field(ge=1, le=int(MAX_MAGNITUDE))]
NonNegativeInt = Annotated[int, Strict(), Field(ge=0, le=int(MAX_MAGNITUDE))]


def one_of(choices: tuple[str, ...]) -> Any:
    """A validator for ``Annotated[Str, one_of(...)]``: the value is one of ``choices``."""

    def check(value: str) -> str:
        if value not in choices:
            raise ValueError(f"must be one of {', '.join(choices)}, got {value!r}")
        return value

    return AfterValidator(check)


#: A TCP/UDP port; 0 asks the system for a free one where the section allows it.
Port = Annotated[int, Strict(), Field(ge=0, le=65535)]
#: A TOML array of numbers, as a tuple of floats.
FloatTuple = Annotated[tuple[Finite, ...], BeforeValidator(tuples)]
#: A TOML array of arrays of numbers (a matrix, or groups of indices), as nested tuples.
NestedFloats = Annotated[tuple[tuple[Finite, ...], ...], BeforeValidator(tuples)]


# ------------------------------------------------------------------------------ validation


def validate(cls: Callable[..., T], table: Any, where: str) -> T:
    """Build the section ``cls`` from the TOML table ``table`` (named ``where`` in errors).

    Raises :class:`ConfigError` with one line naming the section and key: unknown keys first
    (with the nearest valid key), then missing keys, then the first bad value.
    """
    if not isinstance(table, Mapping):
        raise ConfigError(f"[{where}] must be a table, got {table!r}")
    bad = [k for k in table if not isinstance(k, str)]
    if bad:  # pragma: no cover - TOML keys are strings
        raise ConfigError(f"[{where}] keys must be strings, got {bad[0]!r}")
    try:
        return cls(**table)
    except ValidationError as e:
        raise config_error(e, cls, where) from None
    except (TypeError, ValueError) as e:  # a __post_init__ check outside pydantic's wrapping
        raise _as_config_error(e, where) from None


def field_names(cls: Any) -> list[str]:
    """The keys of the section ``cls`` (its init fields)."""
    if dataclasses.is_dataclass(cls):
        return [f.name for f in dataclasses.fields(cls) if f.init]
    return list(getattr(cls, "model_fields", {}))


def _as_config_error(e: BaseException, where: str) -> ConfigError:
    """``e`` as a :class:`ConfigError` whose message starts with the section."""
    text = str(e)
    if text.startswith("["):
        return e if isinstance(e, ConfigError) else ConfigError(text)
    return ConfigError(f"[{where}] {text}")


_PRIORITY = {"unexpected_keyword_argument": 0, "extra_forbidden": 0, "missing": 1,
             "missing_argument": 1}


def config_error(e: ValidationError, cls: Any, where: str) -> ConfigError:
    """The first of pydantic's errors (unknown keys, then missing, then values) as one line."""
    errors = sorted(e.errors(), key=lambda x: _PRIORITY.get(x["type"], 2))
    err = errors[0]
    kind, loc = err["type"], err["loc"]
    key = str(loc[0]) if loc else ""
    index = "".join(f"[{p}]" for p in loc[1:])
    if kind in ("unexpected_keyword_argument", "extra_forbidden"):
        return unknown_key_error(key, field_names(cls), where)
    if kind in ("missing", "missing_argument"):
        return ConfigError(f"[{where}] missing required key '{key}'")
    if kind == "value_error" and isinstance((err.get("ctx") or {}).get("error"), ConfigError):
        return _as_config_error(err["ctx"]["error"], where)
    what = _describe(err)
    if not loc:  # a check across keys (__post_init__)
        return _as_config_error(ValueError(what), where)
    if kind != "value_error":  # a validator of ours writes its own "got ..."
        what += f", got {err.get('input')!r}"
    return ConfigError(f"[{where}] '{key}'{index} {what}")


def _describe(err: Mapping[str, Any]) -> str:
    kind = err["type"]
    ctx = err.get("ctx") or {}
    simple = {
        "bool_type": "must be bool (true or false)",
        "float_type": "must be a number",
        "int_type": "must be an integer",
        "string_type": "must be a string",
        "finite_number": "must be a finite number",
        "tuple_type": "must be a list",
        "list_type": "must be a list",
        "dict_type": "must be a table",
    }
    if kind in simple:
        return simple[kind]
    bounds = {"greater_than": ">", "greater_than_equal": ">=", "less_than": "<",
              "less_than_equal": "<="}
    if kind in bounds:
        limit = next(iter(ctx.values()))
        return f"must be {bounds[kind]} {limit:g}" if isinstance(limit, float) else (
            f"must be {bounds[kind]} {limit}")
    msg = str(err.get("msg", kind))
    if kind == "value_error":
        msg = msg.removeprefix("Value error, ")
    return msg


def unknown_key_error(key: str, allowed: Iterable[str], where: str) -> ConfigError:
    """``[where] unknown key 'key'; did you mean 'near' (where.near)?``"""
    allowed = list(allowed)
    near = difflib.get_close_matches(key, allowed, n=1)
    if near:
        hint = f"; did you mean '{near[0]}' ({where}.{near[0]})?"
    else:
        hint = f"; valid keys: {', '.join(allowed)}"
    return ConfigError(f"[{where}] unknown key '{key}'{hint}")


# ------------------------------------------------------------------------------ small helpers


def reject_unknown(d: Mapping[str, Any], allowed: Iterable[str], section: str) -> None:
    """Raise :class:`ConfigError` for any key of ``d`` not in ``allowed``, suggesting the
    nearest (for tables that are not a :func:`section`, such as ``[world]``)."""
    allowed = list(allowed)
    for key in d:
        if key not in allowed:
            raise unknown_key_error(key, allowed, section)


def require(d: Mapping[str, Any], key: str, section: str) -> Any:
    """Return ``d[key]`` or raise :class:`ConfigError` naming the missing key."""
    if key not in d:
        raise ConfigError(f"[{section}] missing required key '{key}'")
    return d[key]


def value_of(kind: Any, value: Any, key: str, section: str) -> Any:
    """``value`` checked as the field type ``kind`` (e.g. :data:`Finite`), for a table that is
    not a :func:`section`; the same rules and messages as a section's field."""
    adapter = _ADAPTERS.get(kind)
    if adapter is None:
        adapter = _ADAPTERS[kind] = TypeAdapter(kind)
    try:
        return adapter.validate_python(value)
    except ValidationError as e:
        err = e.errors()[0]
        what = _describe(err)
        if err["type"] != "value_error":
            what += f", got {value!r}"
        raise ConfigError(f"[{section}] '{key}' {what}") from None


_ADAPTERS: dict[Any, TypeAdapter[Any]] = {}


def number(value: Any, key: str, section: str) -> float:
    """``value`` as a :data:`Finite` float (not a string, a boolean, nan or inf)."""
    return float(value_of(Finite, value, key, section))


def positive(value: Any, key: str, section: str) -> float:
    """``value`` as a :data:`Positive` float."""
    return float(value_of(Positive, value, key, section))
