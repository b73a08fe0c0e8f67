"""``koala-bridge``: one entry point, one module per subcommand.

A :class:`~koala_bridge.core.errors.KoalaBridgeError` that a subcommand raises is caught here,
once, and printed as one line ``koala-bridge <subcommand>: <message>`` (exit 2).

Subcommands are listed in :data:`SUBCOMMANDS` (name -> module). Only the subcommand being run
is imported; the others' one-line help is read from their source (``ast``), so
``koala-bridge run`` does not pay for the imports of ``calibrate`` and a broken subcommand cannot
break the others. Each module exposes ``add_arguments(parser)`` and ``run(args) -> int``; the
first line of its docstring is its one-line help, the rest its description.
"""

from __future__ import annotations

import argparse
import ast
import importlib
import importlib.util
import logging
import math
import sys
from collections.abc import Sequence
from pathlib import Path
from types import ModuleType
from typing import NoReturn

from koala_bridge.core.errors import ConfigError, KoalaBridgeError

log = logging.getLogger(__name__)

SUBCOMMANDS: dict[str, str] = {
    "run": "koala_bridge.cli.run",
    "calibrate": "koala_bridge.cli.calibrate",
    "export": "koala_bridge.cli.export",
    "recover": "koala_bridge.cli.recover",
    "replay": "koala_bridge.cli.replay",
    "monitor": "koala_bridge.cli.monitor",
    "snapshot": "koala_bridge.cli.snapshot",
    "config": "koala_bridge.cli.config",
    "campaign": "koala_bridge.cli.campaign",
}

EPILOG = """\
examples:
  koala-bridge run                                # real time, the shipped default.toml
  koala-bridge run --clock fast --duration 10 --seed 3
  koala-bridge run --endpoints-file /tmp/koala.json --set buses.mavlink.port=14551
  koala-bridge config init my-koala               # an editable copy of the shipped config
  koala-bridge run --config my-koala/ideal.toml   # every error model off
  koala-bridge monitor                            # in another terminal: the live streams
  koala-bridge run --clock fast --duration 60 --record /tmp/run.mcap
  koala-bridge export /tmp/run.mcap --bundle /tmp/run-bundle
  koala-bridge replay /tmp/run.mcap
  koala-bridge <subcommand> --help                # what each subcommand does
"""

#: Below the top-level --help and a subcommand's that names docs/ or examples/: a wheel installs
#: neither folder.
DOCS_NOTE = (
    "docs/*.md, docs/foxglove-layout.json and examples/ (two_robots.toml,\n"
    "campaign_coverage.toml, coverage_firmware.py, ...) are in the koala-bridge source\n"
    "repository (get them with a git clone of it); they are not installed with the\n"
    "package."
)


def seconds(text: str) -> float:
    """Argument type: a finite number of seconds >= 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected seconds, got {text!r}") from None
    if not math.isfinite(value) or value < 0:
        raise argparse.ArgumentTypeError(f"must be a finite number of seconds >= 0, got {text!r}")
    return value


def positive(text: str) -> float:
    """Argument type: a finite number > 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text!r}")
    return value


def count(text: str) -> int:
    """Argument type: a whole number >= 1."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {text}")
    return value


class OneLineErrorParser(argparse.ArgumentParser):
    """An argument error is one line on stderr (exit 2) that points at ``--help``, instead of
    the usage block followed by the error."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _summary(module_name: str) -> tuple[str, str] | None:
    """The module's docstring as (first line, rest), read from its source without importing it
    (some subcommands import heavy libraries); None if the module does not exist (yet)."""
    try:
        spec = importlib.util.find_spec(module_name)
    except ModuleNotFoundError:
        return None
    if spec is None or spec.origin is None:
        return None
    try:
        source = Path(spec.origin).read_text(encoding="utf-8")
        doc = ast.get_docstring(ast.parse(source)) or ""
    except (OSError, SyntaxError, UnicodeDecodeError):
        doc = ""
    summary, _, rest = doc.strip().partition("\n")
    return summary, rest


def _load(module_name: str) -> ModuleType | None:
    """Import a subcommand module; None only if that very module does not exist (yet)."""
    try:
        return importlib.import_module(module_name)
    except ModuleNotFoundError as e:
        if e.name == module_name:
            return None
        raise


def build_parser(chosen: str | None = None) -> argparse.ArgumentParser:
    """The parser; only the ``chosen`` subcommand's module is imported to add its arguments."""
    parser = OneLineErrorParser(
        prog="koala-bridge",
        description=(
            "Hardware-in-the-loop bridge for the K-Team Koala: a simulated robot served on its "
            "real buses (serial, CAN, MAVLink) and published over Zenoh."
        ),
        epilog=f"{EPILOG}\n{DOCS_NOTE}",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    common = OneLineErrorParser(add_help=False)
    common.add_argument(
        "--log-level",
        default="INFO",
        choices=("DEBUG", "INFO", "WARNING", "ERROR"),
        help="logging threshold, to stderr (default: INFO)",
    )
    sub = parser.add_subparsers(dest="command", metavar="SUBCOMMAND", required=True)
    for name, module_name in SUBCOMMANDS.items():
        summary = _summary(module_name)
        if summary is None:
            continue
        p = sub.add_parser(
            name,
            help=summary[0],
            description=f"{summary[0]}\n{summary[1]}".strip(),
            formatter_class=argparse.RawDescriptionHelpFormatter,
            parents=[common],
        )
        if name == chosen:
            module = _load(module_name)
            if module is None:
                continue
            module.add_arguments(p)
            p.set_defaults(_module=module, _parser=p)
        if "docs/" in p.format_help() or "examples/" in p.format_help():
            p.epilog = f"{p.epilog.rstrip()}\n\n{DOCS_NOTE}" if p.epilog else DOCS_NOTE
    return parser


def parse_arguments(parser: argparse.ArgumentParser, argv: Sequence[str]) -> argparse.Namespace:
    """``parser.parse_args(argv)``, except that arguments the subcommand does not know are
    reported by the subcommand's parser (``koala-bridge run: error: …``), not the top-level one
    (argparse hands a subparser's leftovers back up to ``koala-bridge``)."""
    args, unknown = parser.parse_known_args(argv)
    if unknown:
        owner = getattr(args, "_parser", parser)
        owner.error(f"unrecognized arguments: {' '.join(unknown)}")
    return args


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    chosen = next((a for a in argv if not a.startswith("-")), None)
    parser = build_parser(chosen if chosen in SUBCOMMANDS else None)
    args = parse_arguments(parser, argv)
    logging.basicConfig(
        level=getattr(logging, args.log_level),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    try:
        return int(args._module.run(args))
    except KoalaBridgeError as e:
        # The one place a project error becomes a line on stderr (core/errors.py); the cause,
        # if any, is in the traceback that --log-level DEBUG shows.
        log.debug("%s failed", args.command, exc_info=True)
        print(f"koala-bridge {args.command}: {error_line(e)}", file=sys.stderr)
        return 2


def error_line(e: KoalaBridgeError) -> str:
    """The line a user reads for ``e``: a configuration error says so, and a config that lacks
    keys says where a complete one comes from."""
    if not isinstance(e, ConfigError):
        return str(e)
    hint = ""
    # (a fault's required key is the fault's, not the config file's)
    if "missing required key" in str(e) and not str(e).startswith(
            ("--fault", "[[faults]]", "faults/")):
        hint = (" (a bridge config sets every key: start from a copy of config/default.toml,"
                " e.g. `koala-bridge config init DIR`)")
    return f"configuration error: {e}{hint}"


if __name__ == "__main__":
    sys.exit(main())
