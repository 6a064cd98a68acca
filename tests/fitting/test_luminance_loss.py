"""The ``luminance`` loss: a colour error relative to the pair's measured luminance.

Its residual is (f_model - f_meas) cos_i / (a + Y cos_i), Y the pair's Rec. 709 luminance and
a = LUMINANCE_FLOOR times Y cos_i's solid-angle mean: checked against that formula written out
here, on the used values only, its derivative against differences, and a fit that recovers a
simulated truth through it (its compiled normal equations: tests/fitting/test_normal_equations.py).
"""

import numpy as np
import pytest

import gonio.models as gm
from gonio.fitting.likelihood import loss as _loss
from gonio.fitting.optimise.mle import fit
from _simdata import simulate

TRUTH = {"diffuse_reflectance": np.array([0.4, 0.2, 0.02]), "alpha": 0.15, "int_ior": 1.5}


def _data(seed=3, n=400, weighted=True):
    model = gm.get("roughplastic", distribution="ggx")
    meas = simulate(model, TRUTH, np.random.default_rng(seed), n=n)
    if weighted:
        meas.weight = np.random.default_rng(seed + 1).uniform(0.5, 2.0, meas.n_points)
    return model, meas


def test_the_residual_is_the_formula():
    model, meas = _data()
    f = model.eval(meas.wi, meas.wo, {**TRUTH, "alpha": 0.2})
    ci = np.clip(meas.wi[:, 2], 0.0, 1.0)
    y = np.maximum(meas.brdf @ np.array([0.2126, 0.7152, 0.0722]), 0.0)
    w = meas.weight
    a = 0.3 * np.sum(w * y * ci) / np.sum(w)
    expect = (f - meas.brdf) * (ci / (a + y * ci))[:, None] * np.sqrt(w / w.mean())[:, None]
    got = _loss.residuals("luminance", f, meas)
    assert np.allclose(got, expect[meas.use], rtol=1e-12, atol=0.0)


def test_values_the_fit_does_not_use_do_not_weigh():
    """Unused values (saturated ones are kept but unused) enter neither a pair's Y nor the
    floor a: the used pairs' weights are those of the data without the unused ones."""
    model, meas = _data()
    keep = np.ones(meas.n_points, bool)
    keep[::8] = False
    junk = meas.subset(np.arange(meas.n_points))
    junk.use[~keep] = False
    junk.brdf[~keep] = 1e3
    np.testing.assert_allclose(_loss.fixed_weight("luminance", junk)[keep],
                               _loss.fixed_weight("luminance", meas.subset(np.flatnonzero(keep))), rtol=1e-12)
    # one channel of a pair unused: its Y from the other two, their weights renormalised
    v = np.array([[0.2, 0.4, 9.0]])
    y = _loss.luminance(v, np.array([[True, True, False]]))[0, 0]
    assert y == pytest.approx((0.2126 * 0.2 + 0.7152 * 0.4) / (0.2126 + 0.7152), rel=1e-12)


def test_y_follows_the_colour_space():
    v = np.array([[0.2, 1.0, 0.3]])
    assert _loss.luminance(v, space="xyz")[0, 0] == 1.0
    assert _loss.luminance(v)[0, 0] == pytest.approx(0.2126 * 0.2 + 0.7152 + 0.0722 * 0.3, rel=1e-12)


def test_derivative_matches_differences():
    model, meas = _data()
    f = model.eval(meas.wi, meas.wo, TRUTH)
    d = _loss.residual_derivative("luminance", f, meas)[meas.use]
    h = 1e-6
    num = (_loss.residuals("luminance", f + h, meas) - _loss.residuals("luminance", f - h, meas)) / (2 * h)
    assert np.allclose(d, num, rtol=1e-7, atol=1e-12)


def test_a_dark_dataset_is_refused_in_one_line():
    model, meas = _data()
    meas.brdf = -np.abs(meas.brdf)
    with pytest.raises(ValueError, match="positive mean luminance"):
        _loss.residuals("luminance", meas.brdf, meas)


@pytest.mark.parametrize("use_fast", [False, True])
def test_a_fit_through_it_recovers_the_truth(use_fast):
    """Noise-free data: the truth is the loss's minimum, whichever path steps."""
    model, meas = _data(seed=5, n=600)
    meas.brdf = model.eval(meas.wi, meas.wo, TRUTH)
    r = fit(meas, model, loss="luminance", rng=np.random.default_rng(0), use_fast=use_fast,
            start={**TRUTH, "alpha": 0.3, "int_ior": 1.3}, n_starts=0, n_local=1)
    assert r.loss == "luminance"
    assert r.params["alpha"] == pytest.approx(0.15, rel=1e-4)
    assert r.params["int_ior"] == pytest.approx(1.5, rel=1e-4)
    assert np.allclose(r.params["diffuse_reflectance"], TRUTH["diffuse_reflectance"], rtol=1e-4)
    assert r.k_criterion == r.space.size + 1       # its scale profiled, as cosine's and log's
    assert np.all(np.isfinite(r.std))
