"""Find what the sensor model lacks in measured data; report the error before/after and the fix.

``koala-bridge calibrate INPUT --config MODEL.toml --out DIR [--write-config NEW.toml]``

INPUT is a measurement bundle directory (``shared/data/BUNDLE-FORMAT.md``) or an MCAP recording
(converted by ``koala-bridge export`` first). For each stream the declared model predicts the
measurements from the reference; candidate effects are added greedily while they improve the
held-out error beyond chance (see ``docs/calibration.md``). Writes ``DIR/report.json``,
``DIR/report.md`` with residual plots, and optionally the model with the found effects.
"""

from __future__ import annotations

import argparse
import logging
import sys
import tempfile
from pathlib import Path

from bridge.calibration.bundle import load_input
from bridge.calibration.config_update import (
    config_diff,
    found_keys,
    noise_keys,
    not_simulated,
    updated_config,
    write_config,
)
from bridge.calibration.errors import CalibrationError
from bridge.calibration.model import declared_model, read_config
from bridge.calibration.pipeline import Options, calibrate
from bridge.calibration.report import write_report

log = logging.getLogger(__name__)

EXAMPLE = """example:
  koala-bridge calibrate tests/data/real/lego_brenner --config config/default.toml \\
      --out out/lego --write-config out/lego/koala-calibrated.toml
  # then read out/lego/report.md; run the simulator with the written config.
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``koala-bridge calibrate``."""
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = EXAMPLE
    parser.add_argument("input", type=Path, help="measurement bundle directory or .mcap recording")
    parser.add_argument(
        "--config",
        type=Path,
        default=None,
        metavar="MODEL.toml",
        help="declared model (the bridge config); omitted: every sensor ideal",
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
        help="write MODEL.toml with the found effects added",
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
        type=float,
        default=5.0,
        help="odometry dead-reckoning window length in seconds (default 5)",
    )
    parser.add_argument(
        "--effects",
        default=None,
        help="comma-separated effect names to consider (default: all registered)",
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


def run(args: argparse.Namespace) -> int:
    """Run the calibration; 0 on success, 2 on a bad input or config."""
    try:
        config = read_config(args.config)
        with tempfile.TemporaryDirectory(prefix="koala-calibrate-") as tmp:
            bundle = load_input(args.input, Path(tmp))
            model = declared_model(config, bundle.meta)
            options = Options(
                window_s=args.window_s, effects=args.effects.split(",") if args.effects else None
            )
            with _progress_bar(not args.quiet and sys.stdout.isatty()) as bar:
                tasks: dict[str, int] = {}

                def progress(stream: str, done: int, total: int) -> None:
                    if stream not in tasks:
                        tasks[stream] = bar.add_task(stream, total=None)
                    bar.update(tasks[stream], completed=done)

                results = calibrate(bundle, model, options, progress)
        keys = found_keys(results)
        if args.write_noise:
            keys.update(noise_keys(results))
        new_config = updated_config(config, keys)
        name = args.config.name if args.config is not None else "MODEL.toml"
        diff = config_diff(config, new_config, name)
        write_report(args.out, results, str(args.input), diff, plots=not args.no_plots)
        if args.write_config is not None:
            args.write_config.parent.mkdir(parents=True, exist_ok=True)
            write_config(args.write_config, new_config, not_simulated(keys))
    except CalibrationError as e:
        log.error("%s", e)
        return 2
    for res in results:
        log.info(
            "%s %s: %.4g -> %.4g %s [%s]",
            res.problem.name,
            res.problem.metric,
            res.before,
            res.after,
            res.problem.unit,
            ", ".join(i.name for i in res.effects) or "-",
        )
    return 0


def main(argv: list[str] | None = None) -> int:
    """Stand-alone entry (``python -m bridge.cli.calibrate``) until ``koala-bridge`` dispatches."""
    parser = argparse.ArgumentParser(
        prog="koala-bridge calibrate", description=(__doc__ or "").splitlines()[0]
    )
    add_arguments(parser)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    return run(args)


if __name__ == "__main__":
    sys.exit(main())
