"""Error models of the simulated Koala's drive and sensors (seeds/000 and seeds/004).

One module per sensor, named as in ``sim/sensors/`` (``sonar.py``: the sonar's truth is
``sim/sensors/sonar.py``, its error model ``sim/models/sonar.py``). Each module holds a frozen
``*Params`` dataclass (built from a config table with ``from_dict``; ``ideal = true`` turns the
model off), pure functions of (truth, state, params, rng) that return the measured value, and at
its end the stateful ``*ErrorModel`` class the simulator calls, with its factory
``error_model(config, rng)``. The numba kernels they share are in ``_kernels.py``; each module's
docstring names the ones it uses. See docs/models.md for each model's equations and sources.
"""

from collections.abc import Mapping
from types import MappingProxyType
from typing import Any

#: The sensors (and the drive) that have an error model: each is a module of this package.
MODELLED = ("drive", "ir", "sonar", "gyro", "compass", "camera")


def __getattr__(name: str) -> Any:
    # ERROR_MODELS (the simulator's registry) pulls in sim.sensors; build it only when asked so
    # that ``import sim.models`` stays light (sim/sections.py imports the params classes lazily
    # while the sensors' sections are being built).
    if name == "ERROR_MODELS":
        return error_models()
    raise AttributeError(f"module 'koala_bridge.sim.models' has no attribute {name!r}")


def error_models() -> Mapping[str, Any]:
    """Sensor name -> ``factory(config, rng)`` of its error model, called by the simulator at
    every reset (``drive``: the whole SimConfig; a sensor: its ``[sensors.<name>]`` config)."""
    from koala_bridge.sim.models import camera, compass, drive, gyro, ir, sonar

    modules = {"drive": drive, "ir": ir, "sonar": sonar, "gyro": gyro, "compass": compass,
               "camera": camera}
    return MappingProxyType({name: modules[name].error_model for name in MODELLED})
