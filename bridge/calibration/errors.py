"""Errors of the calibration package: one tree, rooted at :class:`CalibrationError`."""

from __future__ import annotations


class CalibrationError(Exception):
    """Base of every error raised by :mod:`koala_bridge.calibration`."""


class BundleError(CalibrationError):
    """A measurement bundle is missing, unreadable or lacks a required column."""


class ModelConfigError(CalibrationError):
    """The model TOML cannot be read or a value in it has the wrong type."""


class EffectRegistryError(CalibrationError):
    """An effect name is registered twice or asked for but not registered."""
