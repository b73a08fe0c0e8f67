"""Write an editable copy of the shipped configuration, or print where it lives.

The configuration installed with koala-bridge (default.toml, ideal.toml, koala25.toml for a
Koala 2.5, worlds/*.toml,
koala.dbc and the README that says where every number comes from) lives inside the package;
`config init DIR` copies it into DIR, to edit and run with `run --config DIR/default.toml`; the
copied default.toml, ideal.toml and koala25.toml use the koala.dbc copied beside them
(dbc = "koala.dbc", relative to the config file's folder).
Existing files are left alone unless --force is given. `config path` prints the folder of the
shipped files (read them there, do not edit them: a reinstall replaces them).

examples:
  koala-bridge config init my-koala                # *.toml, worlds/, koala.dbc, README.md
  koala-bridge run --config my-koala/default.toml --clock fast --duration 10
  koala-bridge config init my-koala --force        # overwrite with the shipped files again
  koala-bridge config path                         # where the shipped configuration lives
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterator
from importlib.resources import files
from importlib.resources.abc import Traversable
from pathlib import Path, PurePosixPath

from koala_bridge.core.resources import CONFIG_PACKAGE, config_dir

# What `config init` copies, relative to the shipped config folder (koala_bridge.config).
SHIPPED_NAMES = ("default.toml", "ideal.toml", "koala25.toml", "koala.dbc", "README.md")
SHIPPED_FOLDERS = {"worlds": ".toml"}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    init = actions.add_parser(
        "init",
        help="write an editable copy of the shipped configuration into DIR",
        description="Write default.toml, ideal.toml, koala25.toml (a Koala 2.5), worlds/*.toml,\n"
        "koala.dbc and README.md "
        "into DIR (created if needed). Existing files are not overwritten unless --force.",
        epilog="example:\n  koala-bridge config init my-koala\n"
        "  koala-bridge run --config my-koala/default.toml",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    init.add_argument("directory", type=Path, metavar="DIR", help="folder to write into")
    init.add_argument(
        "--force", action="store_true", help="overwrite files that already exist in DIR"
    )
    actions.add_parser(
        "path",
        help="print the folder of the shipped configuration",
        description="Print the folder of the configuration installed with koala-bridge (the "
        "default of `run --config` is default.toml in it).",
    )


def shipped_files() -> Iterator[tuple[PurePosixPath, Traversable]]:
    """(path relative to the config folder, resource) of every file `config init` copies,
    read through importlib.resources so that a wheel, an editable install and a checkout agree."""
    root = files(CONFIG_PACKAGE)
    for name in SHIPPED_NAMES:
        yield PurePosixPath(name), root / name
    for folder, suffix in SHIPPED_FOLDERS.items():
        entries = sorted((root / folder).iterdir(), key=lambda e: e.name)
        for entry in entries:
            if entry.is_file() and entry.name.endswith(suffix):
                yield PurePosixPath(folder, entry.name), entry


def write_copy(directory: Path, *, force: bool = False) -> list[Path]:
    """Copy the shipped configuration into ``directory``; the paths written.

    Raises FileExistsError naming every file already there (nothing is written then) unless
    ``force``; OSError if the folder cannot be written."""
    files = list(shipped_files())
    existing = [directory / rel for rel, _ in files if (directory / rel).exists()]
    if existing and not force:
        raise FileExistsError(
            f"{len(existing)} file(s) already there, nothing written (--force overwrites them): "
            + ", ".join(str(p) for p in existing)
        )
    written = []
    for rel, resource in files:
        target = directory / rel
        target.parent.mkdir(parents=True, exist_ok=True)
        data = resource.read_bytes()
        if rel.suffix == ".toml" and rel.parent == PurePosixPath("."):
            data = own_dbc(data)
        target.write_bytes(data)
        written.append(target)
    return written


#: The shipped configs' ``[buses.can] dbc = ""`` (the DBC inside the package) ...
SHIPPED_DBC = b'dbc = ""          '
#: ... and in a copy: the copied koala.dbc beside it (a config's relative paths are relative to
#: its own folder), so editing the copy's DBC takes effect. Same width: the comment stays aligned.
COPIED_DBC = b'dbc = "koala.dbc" '


def own_dbc(config_toml: bytes) -> bytes:
    """A shipped config's text, made to use the DBC copied beside it."""
    return config_toml.replace(SHIPPED_DBC, COPIED_DBC, 1)


def file_in_the_way(directory: Path) -> Path | None:
    """``directory`` or the first of its parents that exists as something other than a folder
    (a file there means the folder cannot be made), else None."""
    for path in (directory, *directory.parents):
        if path.exists():
            return None if path.is_dir() else path
    return None


def run(args: argparse.Namespace) -> int:
    if args.action == "path":
        print(config_dir())
        return 0
    blocking = file_in_the_way(args.directory)
    if blocking is not None:
        print(f"koala-bridge config init: {blocking} is a file, not a folder: "
              "DIR must be a folder (new or existing)", file=sys.stderr)
        return 2
    if args.directory.suffix.lower() == ".toml" and not args.directory.exists():
        # `config init my.toml` made a folder named my.toml, and `run --config my.toml` then
        # said "Is a directory"
        print(f"koala-bridge config init: {args.directory} looks like a config file's name, "
              "but DIR is a folder to write several files into (default.toml, koala.dbc, "
              "worlds/...): e.g. `koala-bridge config init my-koala`, then "
              "`koala-bridge run --config my-koala/default.toml`", file=sys.stderr)
        return 2
    try:
        written = write_copy(args.directory, force=args.force)
    except FileExistsError as e:
        print(f"koala-bridge config init: {e}", file=sys.stderr)
        return 1
    except OSError as e:
        print(f"koala-bridge config init: cannot write {args.directory}: {e}", file=sys.stderr)
        return 1
    print(f"Wrote the shipped configuration to {args.directory}:")
    for path in written:
        print(f"  {path}")
    default = args.directory / "default.toml"
    print(
        "Edit it and run with it:\n"
        f"  koala-bridge run --config {default}\n"
        f"  koala-bridge run --config {args.directory / 'ideal.toml'}   # every error model off\n"
        f"  koala-bridge run --config {args.directory / 'koala25.toml'}   # a Koala 2.5\n"
        f"worlds/*.toml are other [world] tables: paste one over the [world] of {default}."
    )
    return 0
