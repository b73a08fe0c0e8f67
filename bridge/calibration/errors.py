"""Errors of the calibration package: one tree, rooted at :class:`CalibrationError`."""

from __future__ import annotations

from koala_bridge.core.errors import CalibrationError

__all__ = ["BundleError", "CalibrationError", "EffectRegistryError", "ModelConfigError"]


class BundleError(CalibrationError):
    """A measurement bundle is missing, unreadable or lacks a required column."""


class ModelConfigError(CalibrationError):
    """The model TOML cannot be read or a value in it has the wrong type."""


class EffectRegistryError(CalibrationError):
    """An effect name is registered twice or asked for but not registered."""
