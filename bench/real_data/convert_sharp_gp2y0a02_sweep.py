"""Sharp GP2Y0A02YK infrared distance sensor on an Arduino UNO against tape-measured distances to
a white notebook, 5-150 cm in 5 cm steps, with the datasheet's typical curve beside it
(gonzalo-bulnes/arduino_playground, 2016).

Upstream: github.com/gonzalo-bulnes/arduino_playground, commit b624d83 ("Add GP2Y0A02YK driver
documentation / Add measurement data"), ``src/sensor_gp2y0a02yk/doc/measurement_data.csv``
(distance cm, raw 10-bit reading at 4.9 mV per unit, output voltage by multimeter, datasheet
voltage) and ``doc/README.md`` (set-up). LICENSE: GPL-3.0.

Bundle: ``range.csv`` (kind ``ir``, sensor 0, ``measured`` = the raw reading in counts,
``true_range`` in metres; ``t`` synthetic, 1 s per distance in table order) and
``declared_model.toml``: the datasheet's typical output (upstream column 4, volts / 4.9 mV) as
the ``[sensors.ir]`` response curve, the declared model a user starts from
(``koala-bridge calibrate DIR --config DIR/declared_model.toml``).
"""

from __future__ import annotations

import sys
from pathlib import Path

from koala_bridge.recording.export import write_csv

from bench.real_data._upstream import read_upstream, run_converter, write_meta

NAME = "sharp_gp2y0a02_sweep"
REPO = "gonzalo-bulnes/arduino_playground"
COMMIT = "b624d83d9392b3e4b9e0c8b6de01652af4574ea0"
PATH = "src/sensor_gp2y0a02yk/doc/measurement_data.csv"
README = "src/sensor_gp2y0a02yk/doc/README.md"
VOLTS_PER_COUNT = 0.0049  # upstream header: "raw_output (4.9mV/unit)"


def convert(mirror: Path, out: Path) -> dict[str, int]:
    text = read_upstream(mirror, REPO, COMMIT, PATH).decode()
    rows: list[list[object]] = []
    curve: list[tuple[float, float]] = []
    for line in text.splitlines():
        cells = [c.strip() for c in line.split(",")]
        if len(cells) != 4 or not cells[0].isdigit():
            continue
        d_m = int(cells[0]) / 100.0
        rows.append([f"{len(rows):.0f}", 0, "ir", cells[1], f"{d_m:.2f}"])
        if cells[3] not in ("", "-"):
            curve.append((d_m, round(float(cells[3]) / VOLTS_PER_COUNT, 1)))
    n = write_csv(out / "range.csv", ["t", "sensor", "kind", "measured", "true_range"], rows)
    (out / "declared_model.toml").write_text(
        "# Declared model of the Sharp GP2Y0A02YK of this bundle: the datasheet's typical output\n"
        "# voltage (upstream measurement_data.csv, column 'V_o (datasheet)') in Arduino counts of\n"
        f"# {VOLTS_PER_COUNT * 1000:g} mV. Written by bench/real_data/convert_{NAME}.py.\n"
        "[sensors.ir]\n"
        "ideal = false\n"
        f"response_range_m = [{', '.join(f'{d:.2f}' for d, _ in curve)}]\n"
        f"response_counts = [{', '.join(f'{c:.1f}' for _, c in curve)}]\n",
        encoding="utf-8",
    )
    write_meta(out / "meta.json", {
        "name": NAME,
        "description": (
            "Sharp GP2Y0A02YK infrared distance sensor (triangulation, analog output) read by an "
            "Arduino UNO's 10-bit ADC, facing an 18 x 13 cm white notebook at tape-measured "
            "distances of 5-150 cm in 5 cm steps (30 readings, one per distance)."),
        "source": {
            "repository": f"https://github.com/{REPO}",
            "commit": COMMIT,
            "paths": [PATH, README, "LICENSE"],
            "converter": f"bench/real_data/convert_{NAME}.py",
        },
        "licence": "GPL-3.0 (LICENSE of the repository)",
        "sensor": {
            "ir": {
                "type": "Sharp GP2Y0A02YK",
                "datasheet_range_m": [0.2, 1.5],
                "declared_model": ("the datasheet's typical output curve, in counts: "
                                   "declared_model.toml (--config)"),
                "datasheet_curve_range_m": [d for d, _ in curve],
                "datasheet_curve_counts": [c for _, c in curve],
            },
        },
        "units": {
            "range.measured": "counts (Arduino UNO 10-bit ADC, 4.9 mV per count)",
            "range.true_range": "m",
            "t": "s (synthetic: 1 s per distance in table order; only the order is real)",
        },
        "notes": [
            "The upstream README: the measured output is consistently lower than the datasheet "
            "beyond a few cm, 'maybe the small size of the target reduces the amount of light "
            "that is reflected'.",
            "Below 15 cm the sensor's output folds back (the datasheet's specified range "
            "starts at 20 cm); the 5 cm reading has no datasheet value and lies outside the "
            "declared curve.",
            "The multimeter voltage column (reference only, per upstream) is left out: it is a "
            "second reading of the same output, not a covariate.",
        ],
    })
    return {"range": n}


def main(argv: list[str] | None = None) -> int:
    return run_converter(NAME, convert, argv)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
