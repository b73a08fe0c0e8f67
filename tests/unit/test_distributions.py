"""``core.distributions`` gives scipy.stats' values (it avoids importing scipy.stats)."""

from __future__ import annotations

import pytest
from koala_bridge.core import distributions as d
from scipy import stats


@pytest.mark.parametrize("q", [1e-6, 0.025, 0.5, 0.95, 0.975, 1 - 1e-4, 1 - 0.01 / 7])
@pytest.mark.parametrize("dof", [1, 2, 3, 5, 3600])
def test_chi2_ppf(q: float, dof: int) -> None:
    assert d.chi2_ppf(q, dof) == pytest.approx(stats.chi2.ppf(q, dof), rel=1e-12)


@pytest.mark.parametrize("q", [1e-9, 0.005, 0.5, 0.995])
def test_norm_ppf(q: float) -> None:
    assert d.norm_ppf(q) == pytest.approx(stats.norm.ppf(q), rel=1e-12)


@pytest.mark.parametrize("q", [0.01, 0.5, 0.99, 1 - 0.01 / 7])
@pytest.mark.parametrize("dof", [1, 2, 7, 28, 1000])
def test_t_ppf(q: float, dof: int) -> None:
    assert d.t_ppf(q, dof) == pytest.approx(stats.t.ppf(q, dof), rel=1e-12)


@pytest.mark.parametrize("z", [-2.0, 0.0, 3.0, 8.0])
def test_norm_sf(z: float) -> None:
    assert d.norm_sf(z) == pytest.approx(stats.norm.sf(z), rel=1e-12)


@pytest.mark.parametrize(("k", "n", "p"), [(-1, 10, 0.3), (0, 10, 0.3), (4, 100, 0.02),
                                          (9, 10, 0.3), (10, 10, 0.3), (50, 1000, 0.05)])
def test_binom_sf(k: int, n: int, p: float) -> None:
    assert d.binom_sf(k, n, p) == pytest.approx(stats.binom.sf(k, n, p), rel=1e-12, abs=1e-300)


def test_importing_the_product_does_not_import_scipy_stats() -> None:
    """The point of the module: checked in a fresh interpreter."""
    import subprocess
    import sys

    code = ("import sys, koala_bridge.cli.calibrate, koala_bridge.runtime.localisation; "
            "print('scipy.stats' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    assert out.stdout.strip() == "False"


@pytest.mark.parametrize(("x", "dfn", "dfd"), [(0.5, 3, 10), (2.0, 19, 19980), (40.0, 1, 5)])
def test_f_sf(x: float, dfn: int, dfd: int) -> None:
    assert d.f_sf(x, dfn, dfd) == pytest.approx(stats.f.sf(x, dfn, dfd), rel=1e-12)
