"""Which config keys the simulator reads (:data:`SIMULATED_KEYS`): an effect whose key is one
of them goes into the TOML ``--write-config`` writes, any other into a comment block
(:mod:`.config_update`); the report and the written model's error (``StreamResult.
after_written``) tell the two apart with :func:`is_simulated`. Kept apart from
``config_update`` so that the pipeline, which that module builds on, can ask too."""

from __future__ import annotations

from collections.abc import Mapping

#: Keys the simulator reads, per section: written into the config.
SIMULATED_KEYS: Mapping[str, frozenset[str]] = {
    "robot": frozenset({"ticks_per_metre", "wheel_base_m", "wheel_diameter_ratio"}),
    "sensors.gyro": frozenset({"bias_rad_s", "scale_factor_error", "gyroscope_noise_density"}),
    "sensors.compass": frozenset({"hard_iron_uT", "soft_iron", "noise_sigma_uT"}),
    "sensors.ir": frozenset(
        {"response_range_m", "response_counts", "per_sensor_offset_counts", "count_noise_sigma"}
    ),
}


def section_and_key(dotted: str) -> tuple[str, str]:
    """``"sensors.gyro.bias_rad_s"`` -> ``("sensors.gyro", "bias_rad_s")``."""
    section, _, key = dotted.rpartition(".")
    return section, key


def is_simulated(dotted: str) -> bool:
    section, key = section_and_key(dotted)
    return key in SIMULATED_KEYS.get(section, frozenset())


def config_path(section: str, key: str) -> str:
    """The dotted path of an effect's config key (:mod:`.config_update`'s docstring):
    ``"/a.b"`` is absolute, a ``"+"`` prefix (per-element increments) is not part of the name,
    the rest is relative to the stream's ``section``."""
    key = key.removeprefix("+")
    return key[1:] if key.startswith("/") else f"{section}.{key}"
