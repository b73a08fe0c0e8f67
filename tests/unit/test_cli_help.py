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
