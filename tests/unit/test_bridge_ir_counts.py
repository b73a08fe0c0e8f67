"""The bridge's IR range frames carry the counts clipped to 0..1023 exactly as
``np.clip(counts, 0, 1023).astype(int)`` did (the clip moved to Python for latency, issue 14)."""

from __future__ import annotations

import numpy as np
from koala_bridge.runtime.sim_source import _ir_counts


def numpy_clip(counts: np.ndarray) -> tuple[int, ...]:
    return tuple(int(c) for c in np.clip(np.asarray(counts), 0, 1023).astype(int))


def test_ir_counts_equal_numpy_clip_on_random_int_counts() -> None:
    rng = np.random.default_rng(14)
    for _ in range(200):
        counts = rng.integers(-2000, 3000, size=16)
        out = _ir_counts(counts)
        assert out == numpy_clip(counts)
        assert all(type(c) is int for c in out)


def test_ir_counts_edges_and_inputs() -> None:
    edges = np.array([-1, 0, 1, 1022, 1023, 1024, 2**31 - 1, -(2**31)], dtype=np.int64)
    assert _ir_counts(edges) == (0, 0, 1, 1022, 1023, 1023, 1023, 0)
    assert _ir_counts([5, 2000]) == (5, 1023)                 # a hand-built reading's list
    floats = np.array([-0.5, 0.7, 511.9, 1023.4, 5000.0])    # float counts truncate as astype
    assert _ir_counts(floats) == numpy_clip(floats)
