"""Rewrite a recording cut short (kill -9, a full disk) into a complete, indexed MCAP file.

A recorder killed with SIGKILL leaves its complete chunks on disk but no summary, index or
footer, so indexed MCAP readers (Foxglove, `mcap` CLI, mcap.reader.make_reader) refuse the file.
`recover` reads every complete chunk (CRCs checked; a damaged record ends the readable part as
a cut does), says what was lost, and writes OUT.mcap with the summary and index: a file every
MCAP tool opens. `export`, `calibrate` and `replay` read a cut recording without this step.

example:
  koala-bridge run --clock fast --duration 600 --record /tmp/run.mcap   # killed with kill -9
  koala-bridge recover /tmp/run.mcap /tmp/run-recovered.mcap
  mcap info /tmp/run-recovered.mcap                                      # any MCAP tool
"""

from __future__ import annotations

import argparse
from pathlib import Path

from koala_bridge.recording.recover import recover


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("recording", type=Path, metavar="IN.mcap", help="the recording to read")
    parser.add_argument(
        "output", type=Path, metavar="OUT.mcap", help="the complete file to write (must not exist)"
    )


def run(args: argparse.Namespace) -> int:
    recover(args.recording, args.output)  # a RecordingError is reported by cli/main.py
    return 0
