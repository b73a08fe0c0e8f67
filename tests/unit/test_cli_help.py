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


@pytest.mark.parametrize("name", [None, *SUBCOMMANDS])
def test_a_docs_or_examples_file_named_in_help_is_said_to_be_in_the_source(
        name: str | None) -> None:
    """A wheel carries no docs/ and no examples/: the top-level --help, and a subcommand's that
    names docs/X.md or examples/X, say where those are."""
    text = build_parser(None).format_help() if name is None else _help(name)
    if name is None or "docs/" in text or "examples/" in text:
        note = " ".join(text.split())  # argparse may wrap the note
        assert "in the koala-bridge source repository" in note, text
        for named in ("docs/*.md", "docs/foxglove-layout.json", "examples/", "two_robots.toml",
                      "campaign_coverage.toml", "coverage_firmware.py"):
            assert named in note, (named, text)


def test_calibrate_usage_shows_config_as_optional() -> None:
    """--config has a default (the shipped config): no usage line may show it as required."""
    text = _help("calibrate")
    assert "[--config MODEL.toml]" in text
    assert not re.search(r"(?<!\[)--config MODEL\.toml(?!\])", text.split("options:")[0]), text


def _help(name: str) -> str:
    parser = build_parser(name)
    return parser._subparsers._group_actions[0].choices[name].format_help()  # type: ignore[union-attr]


def test_campaign_help_and_docs_give_the_same_dask_worker_line() -> None:
    """One worker process per run at once, one thread each: --help and docs/campaigns.md agree."""
    from pathlib import Path

    line = re.compile(r"dask worker tcp://\S+ (--[a-z]+ \d+ --[a-z]+ \d+)")
    (in_help,) = line.findall(_help("campaign"))
    docs = Path(__file__).resolve().parents[2] / "docs" / "campaigns.md"
    assert line.findall(docs.read_text()) == [in_help]
    assert in_help == "--nworkers 4 --nthreads 1"
