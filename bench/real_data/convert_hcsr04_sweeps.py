"""HC-SR04 ultrasonic ranger on a Raspberry Pi against tape-measured distances to a metal
target, 2-150 cm, three sweeps on two days (vishnu10183/ccu_test, a student project, Feb 2021).

Upstream: github.com/vishnu10183/ccu_test, branch RPi4 at the commit below, markdown tables
``25FEB21/ultraS_14cm_5ms.md``, ``26FEB21/ultraS_14cm_10ms.md``, ``26FEB21/ultraS_14cm_25ms.md``
(one row per set-up: actual distance, two DHT22 temperatures, 10 or 5 readings). The readings
were computed on the Pi with a temperature-compensated speed of sound
(``26FEB21/ultraS_dht22_1.c``: ``cm = duration_us / 20000 * (331.3 + 0.606 T)``). No licence is
stated in the repository.

Bundle: ``range.csv``, one row per reading (all of them, 1395): kind ``sonar``, sensor 0,
``measured`` and ``true_range`` in metres, covariates ``temperature_c`` (mean of the row's two
readings), ``obs`` (index of the reading within its burst) and ``session`` (0-2). ``t`` is
synthetic (1 s per table row, 10 ms per reading within a row, the sweeps back to back in the
order they were recorded): only the order is real.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

from koala_bridge.recording.export import write_csv

from bench.real_data._upstream import read_upstream, run_converter, write_meta

NAME = "hcsr04_sweeps"
REPO = "vishnu10183/ccu_test"
COMMIT = "eda364e6d0a20d2dfc3d3c4a2b8fde02b9a5bd71"
SESSIONS = ["25FEB21/ultraS_14cm_5ms.md", "26FEB21/ultraS_14cm_10ms.md",
            "26FEB21/ultraS_14cm_25ms.md"]
FIRMWARE = "26FEB21/ultraS_dht22_1.c"
_ROW = re.compile(r"^\s*(\d+)cm\s*\|")


def convert(mirror: Path, out: Path) -> dict[str, int]:
    rows = []
    t_row = 0.0
    for session, path in enumerate(SESSIONS):
        text = read_upstream(mirror, REPO, COMMIT, path).decode()
        header = next(line for line in text.splitlines() if line.startswith("Actual"))
        n_obs = sum(1 for cell in header.split("|") if cell.strip().startswith("Obs."))
        for line in text.splitlines():
            if not _ROW.match(line):
                continue
            cells = [c.strip() for c in line.split("|")]
            actual_m = int(cells[0].removesuffix("cm")) / 100.0
            temps = [float(c.split("'")[0]) for c in cells[1:3]]
            temperature = sum(temps) / 2
            for k, cell in enumerate(cells[3:3 + n_obs]):
                rows.append([f"{t_row + 0.01 * k:.2f}", 0, "sonar", f"{float(cell) / 100:.5f}",
                             f"{actual_m:.2f}", f"{temperature:.2f}", k, session])
            t_row += 1.0
    n = write_csv(out / "range.csv", ["t", "sensor", "kind", "measured", "true_range",
                                      "temperature_c", "obs", "session"], rows)
    write_meta(out / "meta.json", {
        "name": NAME,
        "description": (
            "HC-SR04 ultrasonic ranger read by a Raspberry Pi (WiringPi, busy-wait echo timing), "
            "facing a metal target set at tape-measured distances of 2-150 cm, sensor 14.5 cm "
            "above the floor; three sweeps (25 and 26 Feb 2021), bursts of 10 or 5 readings per "
            "set-up, 1395 readings."),
        "source": {
            "repository": f"https://github.com/{REPO}",
            "commit": COMMIT,
            "branch": "RPi4",
            "paths": [*SESSIONS, FIRMWARE],
            "converter": "bench/real_data/convert_hcsr04_sweeps.py",
        },
        "licence": "none stated",
        "sensor": {
            "sonar": {
                "type": "HC-SR04",
                "declared_model": ("measured = true range: the firmware converts the echo time "
                                   "with c = 331.3 + 0.606 T m/s (T from a DHT22), so no further "
                                   "scale, offset or temperature term is declared"),
                "datasheet_range_m": [0.02, 4.0],
                "datasheet_resolution_m": 0.003,
            },
        },
        "units": {
            "range.measured": "m", "range.true_range": "m", "range.temperature_c": "degC",
            "range.obs": "index of the reading within its burst (covariate)",
            "range.session": "sweep index 0-2 (covariate)",
            "t": "s (synthetic: 1 s per table row, 10 ms per reading; only the order is real)",
        },
        "notes": [
            "Sweeps: 0 = 25FEB21/ultraS_14cm_5ms.md (10 readings 5 ms apart, 2-125 cm), "
            "1 = 26FEB21/ultraS_14cm_10ms.md (5 readings 10 ms apart, 2-150 cm, most distances "
            "twice or more), 2 = 26FEB21/ultraS_14cm_25ms.md (5 readings 25 ms apart, 2-150 cm).",
            "The tables' 'Repeat Count', 'Repeat Value' (the burst's mode) and 'Error Rate' "
            "columns are derived by the upstream script and left out; every raw reading is kept.",
            "At 150 cm many bursts hold readings of 70-135 cm (echoes off something nearer "
            "than the target); they are kept as recorded.",
            "The first reading of a burst is often lower than the rest by about 1 mm; obs lets "
            "a model see that.",
        ],
    })
    return {"range": n}


def main(argv: list[str] | None = None) -> int:
    return run_converter(NAME, convert, argv)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
