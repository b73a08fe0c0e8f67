"""Find what the sensor model lacks in measured data; report the error before/after and the fix.

koala-bridge calibrate INPUT [INPUT ...] --out DIR [--config MODEL.toml] [--write-config NEW.toml]

INPUT is a measurement bundle directory (docs/bundle-format.md) or an MCAP recording
(converted as `koala-bridge export` does first). Several inputs are calibrated in order, each on
the model the ones before it produced: a still recording first for the gyro bias, then one with
motion. For each stream the declared model predicts the measurements from the reference;
candidate effects are added greedily while they improve the held-out error beyond chance
(docs/calibration.md). Writes DIR/report.json, DIR/report.md with residual plots,
and optionally the model with the found effects.

Reading the report: each stream is fitted on the first 60 % of its time span and scored on the
last 40 % (held out); "before" is the declared model exactly as declared, "after" the model with
the effects found. --write-config writes an effect only when it is certain (at least 2.58
standard errors from the declared value) and when the written effects, at their values, beat the
declared model on held-out data without the ones it cannot hold (when they do not, the effect
that helps least is left out, in turn, until they do); an effect the simulator has no
key for (a time offset, a covariate, a range bias of a sonar) is written as a comment, and "the
written model" is the held-out error of what is written. Every stream, and every candidate not
tried or not kept, has a note saying why (a column that is another channel of the measured
quantity, a scale through zero: a sign convention, a time offset at the edge of its search,
+-0.5 s or 5 % of the fit part, whichever is shorter: clocks apart).
"""
# The docstring above is this subcommand's --help (cli/main.py reads it): plain text, no reST.

from __future__ import annotations

import argparse
import copy
import logging
import os
import sys
import tempfile
from pathlib import Path
from typing import Any

from koala_bridge.calibration.config_update import (
    config_diff,
    declared_parts,
    not_simulated,
    write_config,
)
from koala_bridge.calibration.effects import available_effects
from koala_bridge.calibration.errors import BundleError
from koala_bridge.calibration.model import read_config
from koala_bridge.calibration.pipeline import Options, check_effect_names
from koala_bridge.calibration.report import metric_lines, write_report
from koala_bridge.calibration.stages import all_keys, calibrate_stages
from koala_bridge.runtime.settings import map_relative_paths

log = logging.getLogger(__name__)

EXAMPLE = """examples:
  koala-bridge config init my-koala       # an editable copy of the shipped configuration
  koala-bridge run --config my-koala/default.toml --clock fast --duration 120 --record run.mcap
  koala-bridge calibrate run.mcap --config my-koala/default.toml --out out/run
  # a recording of this bridge, against the config it ran with: no effect should be found.

  # in a checkout of koala-bridge, tests/data/real holds measured data of real robots:
  koala-bridge calibrate tests/data/real/lego_brenner --config config/default.toml \\
      --out out/lego --write-config out/lego/koala-calibrated.toml
  # odometry of another robot (its meta.json declares ticks and wheel base, overriding the
  # config): read out/lego/report.md, then run the simulator with the written config.

  koala-bridge calibrate tests/data/real/mpu6050_gyro_static tests/data/real/mpu6050_turns \\
      --out out/imu --write-config out/imu/imu.toml
  # staged: the still recording gives the gyro bias, carried into the turns' model, where
  # the compass's hard iron is found against the bias-corrected gyro heading.
"""


def _positive(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
    return value


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``koala-bridge calibrate``."""
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = EXAMPLE
    parser.add_argument(
        "input",
        type=Path,
        nargs="+",
        help="measurement bundle directory or .mcap recording; several: calibrated in order, "
        "each on the model the ones before it produced (effects carried in their config keys)",
    )
    parser.add_argument(
        "--config",
        type=Path,
        default=None,
        metavar="MODEL.toml",
        help="declared model: the bridge config the data were recorded with (the shipped "
        "\"$(koala-bridge config path)/default.toml\" declares the Koala's own sensor "
        "models: turn-on gyro bias, IR curve, ...). Omitted: "
        "every sensor ideal, as for another robot's data, whose meta.json declares what it "
        "knows (meta.json values always take precedence)",
    )
    parser.add_argument(
        "--out",
        type=Path,
        required=True,
        metavar="DIR",
        help="directory for report.json, report.md and residual plots",
    )
    parser.add_argument(
        "--write-config",
        type=Path,
        default=None,
        metavar="NEW.toml",
        help="write MODEL.toml with the found effects added (of every input, when several)",
    )
    parser.add_argument(
        "--write-noise",
        action="store_true",
        help="also write each stream's residual white-noise level into the simulator's noise key "
        "(gyroscope_noise_density, noise_sigma_uT, count_noise_sigma); for references far less "
        "noisy than the sensor (robot still, motion tracker)",
    )
    parser.add_argument(
        "--window-s",
        type=_positive,
        default=5.0,
        help="odometry dead-reckoning window length in seconds (default 5)",
    )
    parser.add_argument(
        "--effects",
        default=None,
        help="comma-separated effect names to consider (default: all registered: "
        + ", ".join(available_effects()) + "; a per-column one as covariate:<column>)",
    )
    parser.add_argument("--no-plots", action="store_true", help="skip the residual PNGs")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def _progress_bar(enabled: bool):  # type: ignore[no-untyped-def]
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    console = Console(stderr=False)
    return Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        TextColumn("{task.completed}/{task.total}"),
        TimeElapsedColumn(),
        console=console,
        disable=not (enabled and console.is_terminal),
        transient=True,
    )


def _paths_for(config: dict[str, Any], source: Path, target: Path) -> dict[str, Any]:
    """``config`` with its relative file paths (the DBC, a signing key: relative to the folder of
    the file they were read from, ``source``) made relative to ``target``, where the new file
    goes: a config from ``config init`` names ``koala.dbc`` beside itself."""
    return map_relative_paths(
        copy.deepcopy(config),
        lambda value: os.path.relpath((source / value).resolve(), target.resolve()))


def run(args: argparse.Namespace) -> int:
    """Run the calibration; 0 on success, 1 when the output cannot be written. A bad input or
    config raises a CalibrationError, which cli/main.py reports in one line (exit 2)."""
    # checked before the work: a wrong path found after minutes of fitting is lost work
    blocking = next((p for p in (args.out, *args.out.parents) if p.exists() and not p.is_dir()),
                    None)
    if blocking is not None:
        print(f"koala-bridge calibrate: --out {args.out}: {blocking} is a file, not a "
              "directory; give the directory the report goes into, e.g. --out calibration",
              file=sys.stderr)
        return 2
    for each in args.input:
        if not Path(each).exists():  # (every stage's, before the first one's work)
            raise BundleError(f"{each} does not exist: give a bundle directory or an .mcap "
                              "recording")
    if args.write_config is not None:
        if args.write_config.is_dir():
            print(f"koala-bridge calibrate: --write-config {args.write_config} is a directory; "
                  f"give a file name, e.g. {args.write_config}/calibrated.toml", file=sys.stderr)
            return 2
        if args.config is not None and args.write_config.resolve() == args.config.resolve():
            print(f"koala-bridge calibrate: --write-config would overwrite --config "
                  f"{args.config} (its comments and layout would be lost); write a new file "
                  "and compare them", file=sys.stderr)
            return 2
    try:
        config = read_config(args.config)
        effects = (
            [e.strip() for e in args.effects.split(",") if e.strip()] if args.effects else None
        )
        if effects is not None:
            check_effect_names(effects)
        options = Options(window_s=args.window_s, effects=effects)
        with (
            tempfile.TemporaryDirectory(prefix="koala-calibrate-") as tmp,
            _progress_bar(not args.quiet and sys.stdout.isatty()) as bar,
        ):
            tasks: dict[str, int] = {}
            prefix = [""]

            def progress(stream: str, done: int, total: int) -> None:
                key = prefix[0] + stream
                if key not in tasks:
                    tasks[key] = bar.add_task(key, total=total)
                bar.update(tasks[key], completed=done, total=total)

            def on_stage(number: int, path: Path) -> None:
                if len(args.input) > 1:
                    prefix[0] = f"{number}:"
                    log.info("stage %d: %s", number, path)

            stages, new_config = calibrate_stages(
                args.input, config, options, Path(tmp), progress, args.write_noise, on_stage
            )
        name = args.config.name if args.config is not None else "MODEL.toml"
        # without --config, the declared model is the first input's meta.json: its geometry,
        # laid into the written file, is no change
        diff = config_diff(config if args.config is not None else stages[0].config,
                           new_config, name)
        write_report(args.out, stages, diff, plots=not args.no_plots)
        if args.write_config is not None:
            args.write_config.parent.mkdir(parents=True, exist_ok=True)
            if args.config is not None:
                new_config = _paths_for(new_config, args.config.parent, args.write_config.parent)
            write_config(
                args.write_config,
                new_config,
                not_simulated(all_keys(stages)),
                fragment=args.config is None,
                # MODEL.toml's own text, edited: its comments and layout stay
                template=None if args.config is None else (
                    args.config.read_text(encoding="utf-8"), config),
                notes=declared_parts([r for stage in stages for r in stage.results]),
            )
            log.info("model with the found effects written to %s (report.md's \"Model "
                     "change\" shows what changed)", args.write_config)
    except OSError as e:  # the report or the config cannot be written
        print(f"koala-bridge calibrate: {e}", file=sys.stderr)
        return 1
    for stage in stages:
        tag = f"{stage.number}:" if len(stages) > 1 else ""
        for res in stage.results:
            for line in metric_lines(stage, res):
                log.info("%s%s", tag, line)
            for inst, reason in zip(res.effects, res.not_written(), strict=True):
                if reason is not None:
                    log.warning(
                        "%s%s: %s not written: %s", tag, res.problem.name, inst.name, reason
                    )
        for skipped in stage.skipped:
            log.warning("%snot calibrated: %s", tag, skipped.line())
    return 0
