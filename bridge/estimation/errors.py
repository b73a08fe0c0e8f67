"""The estimation package's error tree.

Estimation functions raise for inputs that have no answer (three collinear landmarks, too few
observations); a measurement that merely disagrees with the estimate is a value (gated, counted),
never an exception.
"""

from __future__ import annotations


class EstimationError(ValueError):
    """Root of every exception raised by :mod:`koala_bridge.estimation`."""


class DegenerateGeometryError(EstimationError):
    """The observations cannot determine the quantity asked for (e.g. collinear landmarks)."""
