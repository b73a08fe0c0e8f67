"""Shared noise primitives for the sensor and drive error models of ``sim/models/``.

Pure: every function takes its state, parameters and a ``numpy.random.Generator`` and returns
arrays; nothing here keeps state or touches a global RNG (docs/architecture.md "Randomness").

Contents
- :func:`random_walk_step` — one step of a Wiener process given a continuous-time density
  (Kalibr / allan-variance convention: ``sigma * sqrt(dt)``).
- :func:`gauss_markov_step` — one exactly discretised step of a first-order Gauss–Markov process
  (Gazebo's ``bias_correlation_time``), which tends to :func:`random_walk_step` as tau -> inf.
- :class:`LookupTable` — a Webots-style ``[input, output, noise]`` table, linearly interpolated.
- :func:`rate_scaled_sigma` — rescale a per-step relative error defined at a reference step rate
  so that the error accumulated over a distance (or angle) does not depend on the step rate.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from koala_bridge.core.schema import ConfigError

ArrayLike = float | np.ndarray


def random_walk_step(x: ArrayLike, density: float, dt: float, rng: np.random.Generator
                     ) -> np.ndarray:
    """One step of a random walk ``dx/dt = density * w(t)`` with unit white noise ``w``.

    ``density`` is the continuous-time noise density (e.g. Kalibr ``gyroscope_random_walk`` in
    rad/s^2/sqrt(Hz)); the discrete increment has standard deviation ``density * sqrt(dt)``, so
    after time T the walk has variance ``density^2 * T`` whatever ``dt`` is.
    """
    x_arr = np.asarray(x, dtype=float)
    return x_arr + density * math.sqrt(dt) * rng.standard_normal(x_arr.shape)


def gauss_markov_step(x: ArrayLike, sigma_ss: float, tau: float, dt: float,
                      rng: np.random.Generator) -> np.ndarray:
    """One exact step of the first-order Gauss–Markov process ``dx = -x/tau dt + q dW``.

    ``sigma_ss`` is the stationary standard deviation, ``tau`` the correlation time (s).
    Exact discretisation: ``x' = phi x + sigma_ss sqrt(1 - phi^2) n`` with ``phi = exp(-dt/tau)``.
    ``tau = inf`` is rejected: use :func:`random_walk_step` for the undamped walk.
    """
    if not (tau > 0 and math.isfinite(tau)):
        raise ValueError("gauss_markov_step needs a finite tau > 0; use random_walk_step")
    x_arr = np.asarray(x, dtype=float)
    phi = math.exp(-dt / tau)
    return phi * x_arr + sigma_ss * math.sqrt(1.0 - phi * phi) * rng.standard_normal(x_arr.shape)


def rate_scaled_sigma(sigma_ref: float, step_hz: float, reference_hz: float) -> float:
    """Per-step relative standard deviation at ``step_hz`` equivalent to ``sigma_ref`` at
    ``reference_hz``.

    A relative error ``sigma`` applied independently to each of N steps of size ``D/N`` gives an
    accumulated variance ``sigma^2 D^2 / N``; keeping it equal at another N requires
    ``sigma_step = sigma_ref * sqrt(step_hz / reference_hz)``. At ``step_hz == reference_hz`` this
    is the seed's per-step error as written (seeds/000 "Drive Control": "every time the location
    changes the error applies").
    """
    return sigma_ref * math.sqrt(step_hz / reference_hz)


@dataclass(frozen=True)
class LookupTable:
    """A piecewise-linear table ``input -> (output, noise)`` in the Webots ``lookupTable`` sense.

    Rows are ``(x, y, noise)`` with strictly increasing ``x``. :meth:`value` and :meth:`noise`
    interpolate linearly and hold the end rows' values beyond the table (``np.interp``).
    What ``noise`` means (absolute sigma, relative sigma) is the caller's to say.
    """

    x: np.ndarray
    y: np.ndarray
    noise_col: np.ndarray

    @classmethod
    def from_rows(cls, rows: Sequence[Sequence[float]], section: str = "table") -> LookupTable:
        """Build from ``[[x, y], ...]`` or ``[[x, y, noise], ...]`` rows (TOML arrays)."""
        try:
            arr = np.array([list(map(float, r)) for r in rows], dtype=float)
        except (TypeError, ValueError) as e:
            raise ConfigError(f"[{section}] table rows must be numbers, got {rows!r}") from e
        if arr.ndim != 2 or arr.shape[0] < 2 or arr.shape[1] not in (2, 3):
            raise ConfigError(f"[{section}] table needs >= 2 rows of [x, y] or [x, y, noise]")
        if np.any(np.diff(arr[:, 0]) <= 0):
            raise ConfigError(f"[{section}] table inputs must be strictly increasing")
        noise = arr[:, 2] if arr.shape[1] == 3 else np.zeros(arr.shape[0])
        if np.any(noise < 0):
            raise ConfigError(f"[{section}] table noise must be >= 0")
        for a in (arr[:, 0], arr[:, 1], noise):
            a.flags.writeable = False
        return cls(arr[:, 0].copy(), arr[:, 1].copy(), noise.copy())

    def value(self, x: ArrayLike) -> np.ndarray:
        """Interpolated output column at ``x``."""
        return np.interp(x, self.x, self.y)

    def noise(self, x: ArrayLike) -> np.ndarray:
        """Interpolated noise column at ``x``."""
        return np.interp(x, self.x, self.noise_col)

    def rows(self) -> list[list[float]]:
        return [[float(a), float(b), float(c)] for a, b, c in zip(self.x, self.y, self.noise_col,
                                                                  strict=True)]


class BlockStream:
    """One sensor's random numbers, drawn in blocks: what the simulator hands its error models.

    Per-call draws from a ``numpy.random.Generator`` cost about a microsecond each, more than the
    compiled models they feed; so the simulator draws standard normals and uniforms in blocks and
    hands them out in order. Normals and uniforms come from two child streams of the sensor's
    generator (``Generator.spawn``), each a plain sequence: the k-th normal a model uses is the
    k-th normal of its stream whatever the block size and however the model interleaves normals
    and uniforms. The streams belong to one sensor only (docs/architecture.md "Randomness"), so
    enabling one model never changes another sensor's numbers, and the same seed gives the same
    numbers.

    Compiled models take :meth:`normals` / :meth:`uniforms` (1-D views of the next ``n``
    values); scalar models :meth:`normal_list` / :meth:`uniform_list` (Python floats, cheaper in
    scalar arithmetic). :meth:`standard_normal` and :meth:`random` mirror the ``Generator``
    methods of those names, so the pure model functions accept either.
    """

    __slots__ = ("_n_rng", "_u_rng", "_block", "_n", "_n_list", "_ni", "_u", "_u_list", "_ui",
                 "_n_next", "_u_next")

    def __init__(self, rng: np.random.Generator, block: int = 4096) -> None:
        self._n_rng, self._u_rng = rng.spawn(2)
        self._block = block
        # Blocks grow from 64 to ``block`` values: a reset stays cheap for a sensor that draws
        # little (the values do not depend on the block sizes).
        self._n_next = self._u_next = min(64, block)
        self._n = self._u = np.empty(0)
        self._n_list: list[float] | None = None       # built on first scalar use of a block
        self._u_list: list[float] | None = None
        self._ni = self._ui = 0

    def _refill_normals(self, need: int) -> None:
        # Keep the values not handed out yet: the sequence stays the same whatever the block size.
        fresh = self._n_rng.standard_normal(max(self._n_next, need))
        self._n_next = min(2 * self._n_next, self._block)
        self._n = np.concatenate([self._n[self._ni:], fresh])
        self._n_list = None
        self._ni = 0

    def _refill_uniforms(self, need: int) -> None:
        fresh = self._u_rng.random(max(self._u_next, need))
        self._u_next = min(2 * self._u_next, self._block)
        self._u = np.concatenate([self._u[self._ui:], fresh])
        self._u_list = None
        self._ui = 0

    def normals(self, n: int) -> np.ndarray:
        """The next ``n`` standard normals (a view into the block: do not write to it)."""
        i = self._ni
        if i + n > self._n.shape[0]:
            self._refill_normals(n)
            i = 0
        self._ni = i + n
        return self._n[i:i + n]

    def uniforms(self, n: int) -> np.ndarray:
        """The next ``n`` uniforms on [0, 1) (a view into the block: do not write to it)."""
        i = self._ui
        if i + n > self._u.shape[0]:
            self._refill_uniforms(n)
            i = 0
        self._ui = i + n
        return self._u[i:i + n]

    def normal_list(self, n: int) -> list[float]:
        """The next ``n`` standard normals as Python floats."""
        i = self._ni
        if i + n > self._n.shape[0]:
            self._refill_normals(n)
            i = 0
        self._ni = i + n
        lst = self._n_list
        if lst is None:
            lst = self._n_list = self._n.tolist()
        return lst[i:i + n]

    def uniform_list(self, n: int) -> list[float]:
        """The next ``n`` uniforms on [0, 1) as Python floats."""
        i = self._ui
        if i + n > self._u.shape[0]:
            self._refill_uniforms(n)
            i = 0
        self._ui = i + n
        lst = self._u_list
        if lst is None:
            lst = self._u_list = self._u.tolist()
        return lst[i:i + n]

    def standard_normal(self, size: int | tuple[int, ...] | None = None) -> ArrayLike:
        """``Generator.standard_normal`` from this stream (a float when ``size`` is None)."""
        if size is None:
            return self.normal_list(1)[0]
        if isinstance(size, int):
            return self.normals(size)
        shape = tuple(size)
        return self.normals(math.prod(shape)).reshape(shape)

    def random(self, size: int | tuple[int, ...] | None = None) -> ArrayLike:
        """``Generator.random`` from this stream (a float when ``size`` is None)."""
        if size is None:
            return self.uniform_list(1)[0]
        if isinstance(size, int):
            return self.uniforms(size)
        shape = tuple(size)
        return self.uniforms(math.prod(shape)).reshape(shape)


Variates = np.random.Generator | BlockStream
"""What a model draws from: a ``Generator`` (tests, figures) or a :class:`BlockStream` (the
simulator)."""
