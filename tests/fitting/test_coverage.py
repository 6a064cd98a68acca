"""Calibration of the uncertainty (issue 6, "the test that matters most").

Over 50 seeded simulated captures of known samples (f_r from the model itself, Gaussian
noise sigma = rel f_r + floor, directions from the seeded rng), the Laplace 1-sigma interval
must contain the truth about 68 % of the time and the emcee 90 % credible interval between
85 % and 95 % of the time, for every parameter.

Binomial noise of a coverage over 50 captures: sqrt(p (1 - p) / 50) = 6.6 % at p = 0.68 and
4.2 % at p = 0.90; the Laplace band [0.54, 0.82] is +-2.1 sigma. The emcee band [0.85, 0.95]
is the issue's and only +-1.2 sigma wide at 50 captures, so it is applied to the coverage
pooled over parameters, and each parameter is held to 2.5 binomial sigma of 0.90.
Figures measured (printed with -s) are in the fitting note.
"""

import numpy as np
import pytest

import gonio.models as gm
from gonio.fitting import fit, sample_posterior

from _simdata import simulate

ROUGHPLASTIC = (gm.get("roughplastic", distribution="ggx"),
                {"diffuse_reflectance": np.array([0.5, 0.35, 0.2]), "alpha": 0.2, "int_ior": 1.5})
ORENNAYAR = (gm.get("orennayar"), {"reflectance": np.array([0.5, 0.4, 0.3]), "sigma": 0.5})


def _laplace_coverage(model, truth, n_sets, n, seed0, **sim):
    hits = []
    for s in range(n_sets):
        meas = simulate(model, truth, np.random.default_rng(seed0 + s), n=n, **sim)
        r = fit(meas, model, rng=np.random.default_rng(s))
        x_true = r.space.from_params(truth)
        hits.append(np.abs(r.x - x_true) <= r.std)
    return r.space.names, np.mean(hits, axis=0)


@pytest.mark.slow
@pytest.mark.parametrize("case", ["roughplastic", "orennayar"])
def test_laplace_one_sigma_covers_68_percent(case):
    model, truth = {"roughplastic": ROUGHPLASTIC, "orennayar": ORENNAYAR}[case]
    sim = {"specular_fraction": 0.0} if case == "orennayar" else {}
    names, cov = _laplace_coverage(model, truth, 50, 300 if case == "roughplastic" else 100, 1000, rel=0.03, **sim)
    print(f"\nLaplace 1-sigma coverage, {case}:", dict(zip(names, np.round(cov, 2))))
    assert np.all((cov >= 0.54) & (cov <= 0.82)), dict(zip(names, cov))


def _emcee_coverage(model, truth, n_sets, seed0, n, rel, **sim):
    hits, taus, conv = [], [], []
    for s in range(n_sets):
        meas = simulate(model, truth, np.random.default_rng(seed0 + s), n=n, rel=rel, **sim)
        r = fit(meas, model, rng=np.random.default_rng(s))
        post = sample_posterior(meas, r, rng=np.random.default_rng(s), n_walkers=8, chunk=200, max_steps=1400,
                                tau_multiple=30)
        lo, hi = post.interval(90).T
        x_true = r.space.from_params(truth)
        hits.append((lo <= x_true) & (x_true <= hi))
        taus.append(np.max(post.tau))
        conv.append(post.converged)
    return r.space.names, np.mean(hits, axis=0), np.median(taus), np.mean(conv)


@pytest.mark.slow
@pytest.mark.parametrize("case", ["roughplastic", "orennayar"])
def test_emcee_90_percent_intervals_cover_85_to_95_percent(case):
    """The issue's band [0.85, 0.95] on the coverage pooled over parameters and captures, and
    every parameter within 2.5 binomial sigma of 0.90 (60 captures: sd 3.9 %, so the band
    per parameter alone would fail by chance in most runs)."""
    if case == "roughplastic":
        model, truth = ROUGHPLASTIC
        n_sets = 60
        names, cov, tau, conv = _emcee_coverage(model, truth, n_sets, 3000, n=1000, rel=0.02)
    else:
        model, truth = ORENNAYAR
        n_sets = 60
        names, cov, tau, conv = _emcee_coverage(model, truth, n_sets, 2000, n=40, rel=0.05, specular_fraction=0.0)
    print(f"\nemcee 90% coverage, {case}:", dict(zip(names, np.round(cov, 3))), "pooled", round(float(np.mean(cov)), 3),
          "median tau", tau, "converged fraction", conv)
    assert conv >= 0.9
    assert 0.85 <= np.mean(cov) <= 0.95, dict(zip(names, cov))
    sd = np.sqrt(0.9 * 0.1 / n_sets)
    assert np.all(np.abs(cov - 0.9) <= 2.5 * sd), dict(zip(names, cov))
