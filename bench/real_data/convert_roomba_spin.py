"""iRobot Create 2 (Roomba) spinning clockwise in place for 25 s with an LSM9DS1 IMU on top:
the magnetometer at 64 Hz (RoombaCI-Clemson, Clemson University, spring 2021).

Upstream: github.com/mathman93/RoombaCI-Clemson, ``Data_Files/2021_Spring/IMU_Data_Clockwise.txt``
(readme ``Data_Files/2021_Spring/2021_Spring_Readme.txt``: "20 second test where IMU data is
collected while the Roomba rotates in a clockwise circle ... around a stationary Z axis"), written
by ``Python_Files/Roomba_IMU_Test.py`` (row: time, accel xyz m/s^2, gyro xyz deg/s, mag xyz gauss,
wheel speeds, encoder counts, encoder heading). No licence is stated in the repository.

Bundle: ``compass.csv`` (mx, my, mz in gauss as recorded), every row (1728). No pose
reference: the compass is held against physics (constant field magnitude). The gyro and the
Roomba's encoder counts of the same rows are not included: there is nothing to hold them
against (the compass heading after a 2-D hard/soft-iron fit departs from the integrated gyro
by up to 40 deg during the spin); the notes give how they compare with each other.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
from koala_bridge.recording.export import write_csv

from bench.real_data._upstream import read_upstream, run_converter, write_meta

NAME = "roomba_spin"
REPO = "mathman93/RoombaCI-Clemson"
COMMIT = "12997a826a0221bbd809827d381a2e2001ee128d"
PATH = "Data_Files/2021_Spring/IMU_Data_Clockwise.txt"
README = "Data_Files/2021_Spring/2021_Spring_Readme.txt"
LOGGER = "Python_Files/Roomba_IMU_Test.py"
LIBRARY = "Python_Files/RoombaCI_lib.py"


def convert(mirror: Path, out: Path) -> dict[str, int]:
    text = read_upstream(mirror, REPO, COMMIT, PATH).decode()
    rows = np.array([[float(v) for v in line.split(",")] for line in text.splitlines()
                     if line.strip()])
    t = rows[:, 0]
    n_compass = write_csv(out / "compass.csv", ["t", "mx", "my", "mz"],
                          ([f"{r[0]:.6f}", f"{r[7]:.6f}", f"{r[8]:.6f}", f"{r[9]:.6f}"]
                           for r in rows))
    dt = np.diff(t)
    gyro_turn = float(np.sum(0.5 * (rows[1:, 6] + rows[:-1, 6]) * dt))
    enc_turn = math.degrees(rows[-1, 14] - rows[0, 14])
    write_meta(out / "meta.json", {
        "name": NAME,
        "description": (
            "iRobot Create 2 spinning clockwise in place (commanded spin 75 after 2 s still, "
            "25 s) with an STMicro LSM9DS1 IMU mounted on top; its magnetometer read with the "
            "Roomba's sensor stream at 64 Hz. No pose reference."),
        "source": {
            "repository": f"https://github.com/{REPO}",
            "commit": COMMIT,
            "paths": [PATH, README, LOGGER, LIBRARY],
            "converter": "bench/real_data/convert_roomba_spin.py",
        },
        "licence": "none stated",
        "robot": {"model": "iRobot Create 2", "wheel_diameter_m": 0.072,
                  "wheel_base_m": 0.235},
        "reference": {"continuous_reference": False,
                      "field_magnitude": "constant (unknown value)"},
        "sensor": {
            "compass": {
                "type": "STMicro LSM9DS1 magnetometer, 4 gauss range",
                "declared_model": ("ideal: the logger already subtracts a hard-iron offset "
                                   "(centre of min/max over a 20 s calibration spin before the "
                                   "run) from every reading"),
            },
        },
        "units": {
            "compass.mx": "gauss (as recorded)", "compass.my": "gauss", "compass.mz": "gauss",
            "t": "s (logger clock)",
        },
        "notes": [
            f"Not included: the gyro (z integrated over the run: {gyro_turn:.1f} deg) and the "
            f"encoder heading (the Roomba's own dead reckoning, clockwise positive: "
            f"{enc_turn:.1f} deg) agree to 0.3 % with each other, but neither is a reference.",
            "The first 2 s are still (move_dict of the logger: 2 s stop, then spin).",
            "mz varies by about 0.5 gauss over the spin although the robot turns about the "
            "vertical: the IMU axes are tilted against the floor, or the motors' field moves "
            "with the wheels; either way the horizontal-plane assumption of a 2-D compass does "
            "not hold for the raw axes.",
            "The logger's CalibrateMag offset (printed to the console, not saved) is already "
            "subtracted in the recorded values, yet the horizontal field is still off-centre "
            "by about 0.1 gauss: the calibration spin ran before the recorded one, at the same "
            "commanded speed.",
            "About 29 % of consecutive rows repeat the previous magnetometer sample (the "
            "magnetometer's output rate is below the 64 Hz of the log).",
        ],
    })
    return {"compass": n_compass}


def main(argv: list[str] | None = None) -> int:
    return run_converter(NAME, convert, argv)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
