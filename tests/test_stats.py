"""selfcal.core.stats: the chi-square quantile without scipy, and the tabulated Wishart quantiles."""
import math

import pytest
from scipy.special import chdtri

from selfcal.core.stats import (WISHART_TABLE, chi2_survival, chi2_upper_quantile, wishart_lambda_max_quantile,
                                wishart_lambda_min_quantile, wishart_quantiles_drawn)


@pytest.mark.parametrize("dof", [1, 2, 3, 4, 5, 10, 29, 58, 200])
def test_chi2_upper_quantile_matches_scipy(dof):
    """The closed-form survival function, inverted by bisection, gives scipy's chdtri to ~1e-13 (both are exact
    to rounding; the bisection stops at adjacent floats)."""
    for alpha in (0.9, 0.5, 0.2, 0.01, 1e-4, 1e-9):
        assert chi2_upper_quantile(dof, alpha) == pytest.approx(float(chdtri(dof, alpha)), rel=1e-12)


def test_chi2_survival_known_values():
    """dof 2 is the exponential: P(chi2(2) > x) = exp(-x/2); dof 1 is |N(0,1)|^2: P(> 1) = erfc(1/sqrt 2)."""
    assert chi2_survival(2, 3.0) == pytest.approx(math.exp(-1.5), rel=1e-15)
    assert chi2_survival(1, 1.0) == pytest.approx(math.erfc(1 / math.sqrt(2)), rel=1e-15)
    assert chi2_survival(5, 0.0) == 1.0


def test_chi2_upper_quantile_refuses_a_fractional_dof():
    with pytest.raises(ValueError):
        chi2_upper_quantile(2.5, 0.01)


def test_wishart_table_is_the_monte_carlo():
    """Every tabulated entry is what the seeded Monte Carlo draws (the table only saves start-up time), and the
    public quantile functions return it."""
    for (m, n, alpha, draws, seed), (upper, lower) in WISHART_TABLE.items():
        drawn = wishart_quantiles_drawn(m, n, alpha, draws, seed)
        assert drawn == pytest.approx((upper, lower), rel=1e-12)
        assert wishart_lambda_max_quantile(m, n, alpha, draws, seed) == upper
        assert wishart_lambda_min_quantile(m, n, alpha, draws, seed) == lower
