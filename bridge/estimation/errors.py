"""The estimation package's error tree.

Estimation functions raise for inputs that have no answer (three collinear landmarks, too few
observations); a measurement that merely disagrees with the estimate is a value (gated, counted),
never an exception.
"""

from __future__ import annotations

from koala_bridge.core.errors import EstimationError

__all__ = ["DegenerateGeometryError", "EstimationError"]


class DegenerateGeometryError(EstimationError):
    """The observations cannot determine the quantity asked for (e.g. collinear landmarks)."""
