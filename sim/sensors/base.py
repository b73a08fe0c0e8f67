"""The seam between ideal sensors and error models.

Every sensor module in :mod:`koala_bridge.sim.sensors` follows the same shape:

1. a pure function computes the sensor's *truth* -- a frozen dataclass holding the noise-free value
   and everything an error model may need (ray ranges, incidence angles, sample interval, ...);
2. a thin class ``<Name>Sensor(params, error_model=None)`` with ``measure(...) -> <Reading>``:
   with ``params.ideal`` (or no error model) it returns the ideal reading built from the truth;
   otherwise it returns ``error_model.measure(truth, rng)``.

An error model therefore only has to implement :class:`ErrorModel` for its sensor's truth type and
return the sensor's reading type of :mod:`sim.types` (filling the reading's ``truth_*`` fields from
the truth). Models may keep internal state (bias random walk, Gauss-Markov); the simulator builds
new ones on every ``reset``, so a run starts from the same state.

How the simulator finds error models: ``Simulator(config, error_models=...)`` takes a mapping
``{sensor name: factory}``; when it is None and any sensor (or ``[robot.drive_error]``) has
``ideal = false``, the simulator imports :mod:`sim.models` and uses its ``ERROR_MODELS`` mapping.
A factory is called at every ``reset`` as ``factory(config, rng)`` with the sensor's typed config
(``<Name>Config`` of its own module; its ``errors`` attribute holds the error model's validated
params object)
and the sensor's own generator (for turn-on biases); it returns the model.
The drive-error model is registered under the name ``"drive"``; its factory gets the whole
:class:`sim.config.SimConfig` (it needs the wheel base and ``dt``) and the drive stream, and
returns a :class:`koala_bridge.sim.robot.DriveErrorSeam`.

Each sensor draws only from its own ``numpy.random.Generator`` (one child stream per sensor,
:data:`koala_bridge.sim.simulator.RNG_STREAMS`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol, TypeVar

import numpy as np
from koala_bridge.sim.noise import Variates

TruthT = TypeVar("TruthT", contravariant=True)
ReadingT = TypeVar("ReadingT", covariant=True)


class ErrorModel(Protocol[TruthT, ReadingT]):
    """Turns a sensor's noise-free truth into a measurement, drawing from ``variates`` only (the
    sensor's :class:`sim.noise.BlockStream` in the simulator; any ``Generator`` in tests)."""

    def measure(self, truth: TruthT, variates: Variates) -> ReadingT: ...


ErrorModelFactory = Callable[[Any, np.random.Generator], Any]
"""``factory(sensor_config, rng) -> ErrorModel`` (``factory(sim_config, rng) -> DriveErrorSeam``
for "drive")."""


def fan_offsets(rays: int, aperture_rad: float) -> np.ndarray:
    """Angles of ``rays`` rays spread evenly over a cone of ``aperture_rad`` around its axis
    (the Webots distance-sensor convention that seeds/004 quotes: aperture + numberOfRays)."""
    if rays == 1:
        return np.zeros(1)
    return np.linspace(-0.5 * aperture_rad, 0.5 * aperture_rad, rays)
