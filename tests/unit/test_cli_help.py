"""Every subcommand's --help is plain text: its description is the module docstring, which must
not show reStructuredText markup (``literal``, :mod:`x`) to a user."""

from __future__ import annotations

import re

import pytest
from koala_bridge.cli.main import SUBCOMMANDS, build_parser

REST_MARKUP = re.compile(r"``|:[a-z]+:`")


@pytest.mark.parametrize("name", [None, *SUBCOMMANDS])
def test_help_has_no_restructuredtext_markup(name: str | None) -> None:
    parser = build_parser(name)
    if name is not None:
        parser = parser._subparsers._group_actions[0].choices[name]  # type: ignore[union-attr]
    text = parser.format_help()
    assert "example" in text
    assert not REST_MARKUP.findall(text), text


@pytest.mark.parametrize("name", SUBCOMMANDS)
def test_a_docs_file_named_in_help_is_said_to_be_in_the_source(name: str) -> None:
    """A wheel carries no docs/: a --help that names docs/X.md says where those are."""
    text = _help(name)
    if "docs/" in text:
        assert "in the koala-bridge source" in text, text


def test_calibrate_usage_shows_config_as_optional() -> None:
    """--config has a default (the shipped config): no usage line may show it as required."""
    text = _help("calibrate")
    assert "[--config MODEL.toml]" in text
    assert not re.search(r"(?<!\[)--config MODEL\.toml(?!\])", text.split("options:")[0]), text


def _help(name: str) -> str:
    parser = build_parser(name)
    return parser._subparsers._group_actions[0].choices[name].format_help()  # type: ignore[union-attr]
