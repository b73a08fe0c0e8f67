"""Error models of the simulated Koala's drive and sensors (seeds/000 and seeds/004).

Each module holds a frozen ``*Params`` dataclass (built from a config table with ``from_dict``;
``ideal = true`` turns the model off) and pure functions of (truth, state, params, rng) that return
the measured value. The sensors of ``sim/sensors/`` compute the noise-free truth and call these.
See docs/models.md for each model's equations, sources and reconstruction.
"""

from typing import Any


def __getattr__(name: str) -> Any:
    # ERROR_MODELS (the simulator's registry) pulls in sim.sensors; import it only when asked so
    # that ``import sim.models.<model>`` stays free of the simulator (sim/config.py imports the
    # params classes lazily while it is itself being used).
    if name == "ERROR_MODELS":
        from koala_bridge.sim.models.adapters import ERROR_MODELS

        return ERROR_MODELS
    raise AttributeError(f"module 'koala_bridge.sim.models' has no attribute {name!r}")
