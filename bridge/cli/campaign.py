"""Run a firmware test matrix (worlds x seeds x faults x overrides) and judge every run.

koala-bridge campaign CAMPAIGN.toml [--out DIR] [--workers N | --cluster tcp://HOST:PORT]

CAMPAIGN.toml names the firmware command, the base config, the axes, the limits and the checks
(docs/campaigns.md). Every run is a lockstep `koala-bridge run` beside the firmware, on ports of
its own (all port 0) in a temporary folder, so runs never clash and a case re-run with --only
gives the same run, bit for bit. Runs go to a local process pool (one per core), or with
--cluster to a Dask scheduler's workers (pip install 'koala-bridge[cluster]').

Writes DIR/results.json (one record per run), DIR/junit.xml (for CI), DIR/report.md (pass/fail
matrix; plots of failures), DIR/recordings/CASE.mcap for failures (all with --keep-all).
Exit status: 0 every run passed, 1 some run failed, 2 a bad campaign file, 130 stopped with
Ctrl-C, SIGINT or SIGTERM (what finished is kept: --resume runs the rest).
"""
# The docstring above is this subcommand's --help (cli/main.py reads it): plain text, no reST.

from __future__ import annotations

import argparse
import logging
import signal
import sys
import uuid
from pathlib import Path

from koala_bridge.cli.main import count

log = logging.getLogger(__name__)

EXAMPLE = """examples:
  koala-bridge campaign examples/campaign_coverage.toml --out out/nightly
  koala-bridge campaign my.toml --list                     # the case ids, nothing run
  koala-bridge campaign my.toml --only lab_walls_2-s3-gyro_bias-base --out out/one
  # one case again, as the campaign ran it (same outcome digest in results.json)
  koala-bridge campaign my.toml --out out/nightly --resume   # after Ctrl-C: the rest
  koala-bridge campaign my.toml --workers 2 --keep-all     # 2 at a time, keep every recording

  # on a Dask cluster (docs/campaigns.md "On a cluster"): the firmware must be on each worker
  dask scheduler --host 10.0.0.5 --port 8786 &
  # on each machine: one process per run at once, one thread each (a run is processes)
  dask worker tcp://10.0.0.5:8786 --nworkers 4 --nthreads 1 &
  koala-bridge campaign my.toml --cluster tcp://10.0.0.5:8786 --out out/cluster
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = EXAMPLE
    parser.add_argument("campaign", type=Path, metavar="CAMPAIGN.toml",
                        help="the campaign file (docs/campaigns.md)")
    parser.add_argument("--out", type=Path, default=Path("campaign-out"), metavar="DIR",
                        help="output folder (default: ./campaign-out)")
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--workers", type=count, metavar="N",
                       help="runs at once on this machine (default: one per core)")
    where.add_argument("--cluster", metavar="ADDRESS",
                       help="a Dask scheduler, tcp://HOST:PORT or its scheduler file: runs go "
                       "to its workers")
    parser.add_argument("--only", action="append", default=[], metavar="CASE_ID",
                        help="run this case only (repeatable); ids as --list prints them. "
                        "Into an --out that has this campaign's results.json, the other cases' "
                        "records are kept (merged)")
    parser.add_argument("--resume", action="store_true",
                        help="keep the runs DIR/results.json already has (same case, same "
                        "config) and run the others")
    parser.add_argument("--keep-all", action="store_true",
                        help="keep every run's recording, not only the failures'")
    parser.add_argument("--list", action="store_true",
                        help="print the case ids (with --only: those) and exit")


def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


def run(args: argparse.Namespace) -> int:
    from koala_bridge.campaign.engine import run_campaign
    from koala_bridge.campaign.executors import dask_executor, default_workers, local_executor
    from koala_bridge.campaign.results import n_runs
    from koala_bridge.campaign.spec import load_campaign
    from koala_bridge.runtime.progress import count_progress

    campaign = load_campaign(args.campaign)  # ConfigError: one line, exit 2 (cli/main.py)
    for case_id in args.only:
        campaign.case(case_id)  # an unknown id fails before anything runs
    if args.list:  # with --only: those cases only
        for case in [campaign.case(c) for c in args.only] if args.only else campaign.cases:
            print(case.case_id)
        return 0
    out: Path = args.out
    total = len(args.only) if args.only else len(campaign.cases)
    if args.cluster:
        name = f"koala-campaign-stop-{uuid.uuid4().hex}"

        def executor():  # type: ignore[no-untyped-def]
            return dask_executor(args.cluster, campaign.table.resources, name)
        where = f"the Dask cluster at {args.cluster}"
    else:
        workers = args.workers or default_workers()

        def executor():  # type: ignore[no-untyped-def]
            return local_executor(workers, out / ".stop")
        where = f"{workers} local worker{'s' if workers != 1 else ''}"
    print(f"campaign {campaign.name}: {n_runs(total)} on {where}; output in {out}",
          file=sys.stderr)
    counts = {"pass": 0, "fail": 0}
    # SIGTERM (a CI job cancelled) stops as Ctrl-C does: the runs end their processes. SIGINT
    # is installed too, whatever was inherited: a non-interactive shell starts `campaign ... &`
    # with SIGINT ignored, and Python keeps an inherited SIG_IGN (then `kill -INT` did nothing)
    previous = {sig: signal.signal(sig, _interrupt) for sig in (signal.SIGTERM, signal.SIGINT)}
    try:
        with count_progress(total, f"campaign {campaign.name}") as advance:
            def on_result(record: dict) -> None:  # type: ignore[type-arg]
                counts[record["verdict"]] = counts.get(record["verdict"], 0) + 1
                advance(f"{counts['pass']} pass, {counts['fail']} fail")
                if record["verdict"] != "pass":
                    failed = [c["name"] for c in record["checks"] if not c["passed"]]
                    log.warning("%s failed: %s", record["case_id"], ", ".join(failed))

            outcome = run_campaign(campaign, out, executor, only=args.only,
                                   resume=args.resume, keep_all=args.keep_all,
                                   on_result=on_result)
    except KeyboardInterrupt:
        print(f"campaign {campaign.name}: stopped; finished runs are in {out / 'results.json'}"
              f" (--resume runs the rest)", file=sys.stderr)
        return 130
    finally:
        for sig, handler in previous.items():
            if handler is not None:  # None: not installed from Python, nothing to restore
                signal.signal(sig, handler)
    selected = len(outcome.selected_records)
    held = ""
    if args.only:  # the other cases' earlier records were kept: say what results.json holds
        held = (f"; results.json holds {len(outcome.records)} of {len(campaign.cases)} cases"
                f"{'' if outcome.campaign_complete else ' (incomplete)'}")
    print(f"campaign {campaign.name}: {selected - outcome.failed} of {n_runs(selected)} passed "
          f"({outcome.ran} run now){held}; {outcome.results}, {outcome.junit}, "
          f"{outcome.report}")
    return 0 if outcome.failed == 0 and outcome.complete else 1
