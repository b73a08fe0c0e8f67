"""Raw 3-axis magnetometer samples turned through many orientations: the example input of
aleksandrbazhin/ellipsoid_fit_python (347 samples, integer sensor counts).

Upstream: github.com/aleksandrbazhin/ellipsoid_fit_python, ``mag_out.txt`` (added 2016-01-11,
"Example data added"; README: "Used for 3-axis magnetometer calibration", rows of three numbers);
LICENSE: MIT, copyright 2016 aleksandrbazhin. The sensor model and the sample rate are not
stated upstream.

Bundle: ``compass.csv`` (mx, my, mz in the recorded counts, every sample); ``t`` is synthetic
(0.1 s per sample in file order): only the order is real.
"""

from __future__ import annotations

import sys
from pathlib import Path

from koala_bridge.recording.export import write_csv

from bench.real_data._upstream import read_upstream, run_converter, write_meta

NAME = "mag_ellipsoid_bazhin"
REPO = "aleksandrbazhin/ellipsoid_fit_python"
COMMIT = "bfab4ce68244529640496f466a4374ef15748275"
PATH = "mag_out.txt"


def convert(mirror: Path, out: Path) -> dict[str, int]:
    text = read_upstream(mirror, REPO, COMMIT, PATH).decode()
    samples = [line.split() for line in text.splitlines() if line.strip()]
    n = write_csv(out / "compass.csv", ["t", "mx", "my", "mz"],
                  ([f"{0.1 * i:.1f}", *(str(int(v)) for v in s)]
                   for i, s in enumerate(samples)))
    write_meta(out / "meta.json", {
        "name": NAME,
        "description": (
            "Raw readings of a 3-axis magnetometer turned by hand through many orientations: "
            "the example input of an ellipsoid-fit calibration tool, 347 samples in sensor "
            "counts. No attitude reference: the physical fact to hold the data against is that "
            "the Earth field magnitude |m| is the same in every orientation."),
        "source": {
            "repository": f"https://github.com/{REPO}",
            "commit": COMMIT,
            "paths": [PATH, "README.md", "LICENSE"],
            "converter": "bench/real_data/convert_mag_ellipsoid_bazhin.py",
        },
        "licence": "MIT (LICENSE of the repository, copyright 2016 aleksandrbazhin)",
        "reference": {"field_magnitude": "constant (unknown value)",
                      "continuous_reference": False},
        "sensor": {
            "type": "not stated upstream",
            "declared_model": "ideal: m = R^T b_earth (no offset, equal gains, orthogonal axes)",
        },
        "units": {
            "compass.mx": "counts (raw sensor output as recorded; scale not stated)",
            "compass.my": "counts", "compass.mz": "counts",
            "t": "s (synthetic: 0.1 s per sample; only the order is real)",
        },
        "notes": [
            "Every sample of mag_out.txt, in file order; values are integers as recorded.",
            "The centre of the readings is far from zero (about (-84, 79, -99) counts against "
            "a spread of about +-170): a large hard-iron offset is plain in the raw data.",
        ],
    })
    return {"compass": n}


def main(argv: list[str] | None = None) -> int:
    return run_converter(NAME, convert, argv)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
