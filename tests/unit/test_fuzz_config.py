"""Property-based fuzzing of the config loader (issue 12, "every decoder and file loader"):
whatever bytes a config file holds, and whatever a ``--set`` says, loading and typing it ends in
a value or the project's :class:`ConfigError` -- never another exception."""

from __future__ import annotations

import tomllib
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from koala_bridge.core.errors import ConfigError
from koala_bridge.runtime.settings import (
    BridgeSettings,
    apply_override,
    load_config,
    parse_override,
)
from koala_bridge.sim.config import load_sim_config

REPO = Path(__file__).resolve().parents[2]
DEFAULT = tomllib.loads((REPO / "config" / "default.toml").read_text())
FUZZ = settings(max_examples=150, deadline=None)

#: Dotted keys of the default config, for overrides that reach real keys.
def _keys(node: object, prefix: str = "") -> list[str]:
    if not isinstance(node, dict):
        return [prefix]
    return [k for name, v in node.items() for k in _keys(v, f"{prefix}.{name}" if prefix else name)]


KEYS = sorted(_keys(DEFAULT))
TOML_VALUES = st.one_of(
    st.integers(), st.floats(allow_nan=True, allow_infinity=True), st.booleans(),
    st.text(max_size=20), st.lists(st.integers(), max_size=4),
)


def _typed(config: dict) -> None:
    """Everything a run types from a config: the bridge's sections and the simulator's."""
    BridgeSettings.from_config(config)
    load_sim_config(config)


@FUZZ
@given(st.binary(max_size=400))
def test_arbitrary_bytes_are_a_config_error(tmp_path_factory: pytest.TempPathFactory,
                                            data: bytes) -> None:
    path = tmp_path_factory.mktemp("cfg") / "c.toml"
    path.write_bytes(data)
    try:
        _typed(load_config(path))
    except ConfigError:
        pass


@FUZZ
@given(st.sampled_from(KEYS), TOML_VALUES)
def test_any_value_at_any_key_is_typed_or_refused(key: str, value: object) -> None:
    import tomli_w

    text = f"{key}={tomli_w.dumps({'v': value})[4:].strip()}"
    try:
        _typed(apply_override(DEFAULT, *parse_override(text)))
    except ConfigError:
        pass


@FUZZ
@given(st.text(max_size=60))
def test_any_set_text_is_parsed_or_refused(text: str) -> None:
    try:
        _typed(apply_override(DEFAULT, *parse_override(text)))
    except ConfigError:
        pass
