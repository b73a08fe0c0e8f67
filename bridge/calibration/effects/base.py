"""The :class:`Effect` interface and the :class:`EffectInstance` a stream's model is built from."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar, Protocol

import numpy as np
from numpy.typing import NDArray


class StreamProblem(Protocol):
    """What every effect may assume of a stream's problem: its kind. Each effect reads the
    attributes of the kinds it applies to (``calibration/streams``).

    A protocol here rather than an import of :class:`koala_bridge.calibration.problem.StreamProblem`
    (which implements it): the problem holds effect instances, so effects sit below problems and
    the two modules do not import each other.
    """

    @property
    def kind(self) -> str: ...


@dataclass(frozen=True)
class EffectInstance:
    """One effect proposed for one stream, with its parameter names and starting values.

    ``fixed`` instances carry parameters estimated when proposed (a quantisation step, a glitch
    value): least squares does not move them. ``data`` holds what ``apply`` needs beyond the
    parameters (a covariate's fit-split mean, the levels of a categorical column).
    """

    name: str
    effect: Effect
    param_names: tuple[str, ...]
    x0: tuple[float, ...]
    fixed: bool = False
    column: str | None = None
    data: Mapping[str, Any] = field(default_factory=dict)

    @property
    def n_free(self) -> int:
        return 0 if self.fixed else len(self.param_names)

    def apply(self, state: Any, params: NDArray[np.float64]) -> None:
        self.effect.apply(self, state, params)

    def config(
        self, params: Sequence[float] | NDArray[np.float64], problem: StreamProblem
    ) -> dict[str, Any]:
        return self.effect.config(self, np.asarray(params, dtype=float), problem)


class Effect(ABC):
    """A candidate effect the declared model may lack.

    Subclasses set ``kinds`` (the stream kinds they apply to: ``"scalar"``, ``"compass"``,
    ``"odometry"``) and implement :meth:`propose`, :meth:`apply` and :meth:`config`.
    ``name`` is set by ``register_effect``.
    """

    name: ClassVar[str] = ""
    kinds: ClassVar[frozenset[str]] = frozenset()
    #: the effect transforms the model's output discontinuously (rounding): with it in the
    #: model, further candidates are judged on the smooth (unrounded) residual, see
    #: :func:`koala_bridge.calibration.selection.judge`
    output_transform: ClassVar[bool] = False
    #: the effect is a second component of the likelihood (spurious readings,
    #: :mod:`koala_bridge.calibration.effects.outlier`): with it in the model the fit is EM and
    #: candidates are judged by the mixture's likelihood (:func:`calibration.selection.judge`)
    mixture: ClassVar[bool] = False

    def propose(self, problem: StreamProblem) -> list[EffectInstance]:
        """Instances of this effect that make sense for ``problem`` (empty: not applicable)."""
        if problem.kind not in self.kinds:
            return []
        return self._propose(problem)

    @abstractmethod
    def _propose(self, problem: StreamProblem) -> list[EffectInstance]: ...

    def n_tested(self, inst: EffectInstance) -> int:
        """Parameters the stopping rule counts for this instance (default: all of them)."""
        return len(inst.param_names)

    def log_density(
        self,
        inst: EffectInstance,
        params: NDArray[np.float64],
        y: NDArray[np.float64],
        r: NDArray[np.float64],
    ) -> NDArray[np.float64]:
        """A ``mixture`` effect's log density of a spurious reading, per reading ``y`` with
        residual ``r`` under the model."""
        raise NotImplementedError(f"{self.name} is not a mixture effect")

    def plausible(self, inst: EffectInstance, params: NDArray[np.float64]) -> bool:
        """Whether fitted ``params`` describe this effect at all (default: always). A fit that
        leaves the effect's physical range (a singular soft-iron matrix) is a degenerate fit of
        something else, and the candidate is rejected whatever its statistics."""
        return True

    def implausible_reason(
        self, inst: EffectInstance, params: NDArray[np.float64], problem: Any
    ) -> str | None:
        """What a fit outside :meth:`plausible`'s range says about the data, for the report's
        notes (default: nothing beyond the rejection)."""
        return None

    def estimate_bias(
        self, inst: EffectInstance, params: NDArray[np.float64], problem: Any
    ) -> tuple[float, str] | None:
        """A bound on the bias of the fitted ``params`` that their standard errors do not hold,
        with what causes it, or None (default): ``--write-config`` does not write an effect
        whose bound is more than ``WRITE_Z`` of its standard errors."""
        return None

    def not_a_sensor_error(
        self, inst: EffectInstance, params: NDArray[np.float64], problem: Any
    ) -> str | None:
        """Why fitted ``params``, however certain, describe the bundle rather than the sensor
        (a unit, a time base), so that ``--write-config`` must not write them into a sensor's
        model; None (default) when they may describe the sensor."""
        return None

    def absent(self, inst: EffectInstance) -> NDArray[np.float64]:
        """The parameter values that mean "no such effect": the declared model. Default 0 (an
        increment, a coefficient); an effect whose parameter is the quantity itself (ticks per
        metre) returns the declared value. ``|params - absent|`` is the effect's size, which
        ``--write-config`` holds against its standard error."""
        return np.zeros(len(inst.param_names))

    @abstractmethod
    def apply(self, inst: EffectInstance, state: Any, params: NDArray[np.float64]) -> None:
        """Change the stream's model state (see the stream module) by this effect."""

    @abstractmethod
    def config(
        self, inst: EffectInstance, params: NDArray[np.float64], problem: StreamProblem
    ) -> dict[str, Any]:
        """Config keys this effect writes, relative to the stream's config section.

        A key ``"calibration.x"`` goes to the ``[sensors.<stream>.calibration]`` table; a key
        starting with ``"/"`` is absolute (``"/robot.wheel_base_m"``).
        """
