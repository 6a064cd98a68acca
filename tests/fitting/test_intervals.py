"""Coverage intervals of a non-normal parameter distribution (gonio/fitting/uncertainty/intervals.py).

References: JCGM 101:2008 7.7 (probabilistically symmetric coverage interval from the
distribution's quantiles) and 8.2 (when ±k u_c is good enough); the quadratic form of a standard
normal, (h/2) e^2, is (h/2) chi^2_1, whose quantiles scipy gives exactly.
"""

import numpy as np
import pytest
from scipy import stats

from gonio.fitting.uncertainty.intervals import LEVELS, MC_DRAWS, error_quantiles, gaussian_adequate


def _tol(u, p, draws=MC_DRAWS, pdf=None):
    # the Monte Carlo quantile's standard error sqrt(p (1 - p) / M) / pdf at the quantile, times 5
    return 5.0 * np.sqrt(p * (1 - p) / draws) / pdf


def test_normal_errors_give_plus_minus_z_u():
    """H = 0: the error is normal with variance |L|^2 + var_rest, its intervals ±z u."""
    L = np.array([[0.3, 0.4], [0.0, 0.0]])
    var_rest = np.array([0.0, 4.0])
    q = error_quantiles(L, np.zeros((2, 2, 2)), np.zeros(2), var_rest)
    u = np.array([0.5, 2.0])
    for lev in LEVELS:
        z = stats.norm.isf((1 - lev) / 2)
        tol = _tol(1.0, (1 - lev) / 2, pdf=stats.norm.pdf(z))
        np.testing.assert_allclose(q[lev][:, 1] / u, z, atol=tol)
        np.testing.assert_allclose(q[lev][:, 0] / u, -z, atol=tol)


def test_a_quadratic_term_gives_the_chi_square_quantiles():
    """err = (h/2) e^2 - h/2 (the mean corrected): quantiles (h/2)(chi2_1 quantile - 1); ±u
    (u = h / sqrt(2), its standard deviation) covers P(chi2_1 < 1 + sqrt(2)) = 0.880, not 0.683."""
    h = 0.02
    q = error_quantiles(np.zeros((1, 1)), np.full((1, 1, 1), h), np.array([h / 2]), np.zeros(1))
    for lev in LEVELS:
        lo_p, hi_p = (1 - lev) / 2, (1 + lev) / 2
        want = 0.5 * h * (stats.chi2.ppf([lo_p, hi_p], 1) - 1.0)
        pdf = stats.chi2.pdf(stats.chi2.ppf([lo_p, hi_p], 1), 1) * 2 / h
        tol = np.array([_tol(1, lo_p, pdf=pdf[0]), _tol(1, hi_p, pdf=pdf[1])])
        for got, w, t in zip(q[lev][0], want, tol):
            assert abs(got - w) <= max(t, 1e-4 * h), (lev, got, w, t)
    u = h / np.sqrt(2)
    assert stats.chi2.cdf(1 + np.sqrt(2), 1) == pytest.approx(0.880, abs=5e-4)
    assert not gaussian_adequate(q[0.9545][0], u)


def test_gaussian_adequate_accepts_a_normal_interval():
    z = stats.norm.isf(0.02275)
    assert gaussian_adequate(np.array([-z * 0.0133, z * 0.0133]), 0.0133)
    assert not gaussian_adequate(np.array([-1.5 * 0.0133, 2.6 * 0.0133]), 0.0133)


def test_intervals_are_deterministic_and_refuse_non_finite_terms():
    L, H = np.array([[1.0, 2.0]]), np.array([[[0.5, 0.1], [0.1, -0.2]]])
    a = error_quantiles(L, H, np.array([0.15]), np.array([0.3]))
    b = error_quantiles(L, H, np.array([0.15]), np.array([0.3]))
    for lev in LEVELS:
        np.testing.assert_array_equal(a[lev], b[lev])
    with pytest.raises(ValueError, match="non-finite"):
        error_quantiles(np.array([[np.nan, 0.0]]), H, np.array([0.0]), np.array([0.0]))
