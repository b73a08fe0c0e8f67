"""Error models of the simulated Koala's drive and sensors (seeds/000 and seeds/004).

Each module holds a frozen ``*Params`` dataclass (built from a config table with ``from_dict``;
``ideal = true`` turns the model off) and pure functions of (truth, state, params, rng) that return
the measured value. The sensors of ``sim/sensors/`` compute the noise-free truth and call these.
See docs/models.md for each model's equations, sources and reconstruction.
"""
