"""The fitter against problems whose answer is known in closed form.

For a Lambertian f_r = rho / pi measured with independent Gaussian noise sigma_k, the
maximum-likelihood rho is the weighted mean of pi * f_k, with variance
pi^2 / sum(1 / sigma_k^2) (weighted least squares; e.g. Bevington & Robinson, Data Reduction
and Error Analysis, 3rd ed., eq. 4.19-4.20). The Laplace covariance must reproduce it, and
emcee's posterior, with a flat prior inside the bounds, is that Gaussian.
"""

import json

import numpy as np
import pytest

import gonio.models as gm
from gonio.fitting import (DataError, Measurements, ParameterSpace, direction, fit, fit_document, load_fit,
                           sample_posterior, write_json_atomic)


def _lambert_data(rng, n=200, rho=(0.6, 0.35, 0.1), rel_noise=0.02):
    wi = direction(np.radians(rng.uniform(0, 80, n)), rng.uniform(-np.pi, np.pi, n))
    wo = direction(np.radians(rng.uniform(0, 80, n)), rng.uniform(-np.pi, np.pi, n))
    f = np.tile(np.asarray(rho) / np.pi, (n, 1))
    sigma = rel_noise * f * rng.uniform(0.5, 2.0, (n, 1))
    data = f + sigma * rng.standard_normal(f.shape)
    return Measurements(wi, wo, data, sigma, np.ones(f.shape, bool)), np.asarray(rho)


def test_lambert_fit_matches_weighted_least_squares():
    meas, _ = _lambert_data(np.random.default_rng(11))
    result = fit(meas, gm.get("diffuse"), rng=np.random.default_rng(0))
    w = 1.0 / meas.brdf_std ** 2
    rho_wls = np.pi * np.sum(w * meas.brdf, axis=0) / np.sum(w, axis=0)
    std_wls = np.pi / np.sqrt(np.sum(w, axis=0))
    np.testing.assert_allclose(result.x, rho_wls, rtol=1e-7)
    np.testing.assert_allclose(result.std, std_wls, rtol=1e-4)
    assert result.converged
    assert result.undetermined == [] and result.at_bound == []
    # 3 x 200 values, 3 parameters: chi^2/dof ~ 1 +- sqrt(2/597)
    assert 0.8 < result.chi2_dof < 1.2


def test_lambert_recovery_is_unbiased_over_seeds():
    """Over 40 seeded data sets the pull (fit - truth) / sigma has mean ~0 and std ~1."""
    pulls = []
    for seed in range(40):
        meas, rho = _lambert_data(np.random.default_rng(100 + seed), n=50)
        r = fit(meas, gm.get("diffuse"), rng=np.random.default_rng(seed), n_starts=4, n_local=1)
        pulls.append((r.x - rho) / r.std)
    pulls = np.concatenate(pulls)
    assert abs(pulls.mean()) < 3 / np.sqrt(pulls.size)
    assert 0.8 < pulls.std() < 1.2


def test_posterior_matches_gaussian_of_linear_problem():
    meas, _ = _lambert_data(np.random.default_rng(5), n=100)
    result = fit(meas, gm.get("diffuse"), rng=np.random.default_rng(0))
    post = sample_posterior(meas, result, rng=np.random.default_rng(1), n_walkers=16, chunk=400, max_steps=6000)
    assert post.converged, post.advice
    half_width = 0.5 * (post.quantiles[84] - post.quantiles[16])
    np.testing.assert_allclose(half_width, result.std, rtol=0.12)
    np.testing.assert_allclose(post.quantiles[50], result.x, atol=0.15 * result.std.max())


def test_short_chain_is_refused():
    meas, _ = _lambert_data(np.random.default_rng(6), n=60)
    result = fit(meas, gm.get("diffuse"), rng=np.random.default_rng(0))
    post = sample_posterior(meas, result, rng=np.random.default_rng(1), n_walkers=8, chunk=20, max_steps=20)
    assert not post.converged
    assert "run at least" in post.advice


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_nan_in_used_data_raises(bad):
    meas, _ = _lambert_data(np.random.default_rng(1), n=10)
    data = meas.brdf.copy()
    data[3, 1] = bad
    with pytest.raises(DataError, match="NaN or inf"):
        Measurements(meas.wi, meas.wo, data, meas.brdf_std, meas.use)


def test_nan_in_flagged_data_is_ignored():
    meas, _ = _lambert_data(np.random.default_rng(1), n=30)
    data, use = meas.brdf.copy(), meas.use.copy()
    data[3, 1], use[3, 1] = np.nan, False
    masked = Measurements(meas.wi, meas.wo, data, meas.brdf_std, use)
    r = fit(masked, gm.get("diffuse"), rng=np.random.default_rng(0))
    assert np.all(np.isfinite(r.x)) and r.n_used == meas.n_used - 1


def test_nonpositive_sigma_raises():
    meas, _ = _lambert_data(np.random.default_rng(1), n=10)
    std = meas.brdf_std.copy()
    std[0, 0] = 0.0
    with pytest.raises(DataError, match="brdf_std"):
        Measurements(meas.wi, meas.wo, meas.brdf, std, meas.use)


def test_fit_needs_a_generator():
    meas, _ = _lambert_data(np.random.default_rng(1), n=10)
    with pytest.raises(TypeError, match="Generator"):
        fit(meas, gm.get("diffuse"))
    with pytest.raises(ValueError, match="unknown loss"):
        fit(meas, gm.get("diffuse"), rng=np.random.default_rng(0), loss="l7")


def test_parameter_space_round_trip_and_log_mapping():
    space = ParameterSpace(gm.get("roughplastic", distribution="ggx"), 3)
    assert space.names[:3] == ["diffuse_reflectance[R]", "diffuse_reflectance[G]", "diffuse_reflectance[B]"]
    x = space.default()
    np.testing.assert_allclose(space.from_unit(space.to_unit(x)), x, rtol=1e-12)
    alpha = space.names.index("alpha")
    if space.upper[alpha] / space.lower[alpha] > 100:  # log-mapped: the box midpoint is the geometric mean
        mid = space.from_unit(np.full(space.size, 0.5))[alpha]
        assert mid == pytest.approx(np.sqrt(space.lower[alpha] * space.upper[alpha]))
    params = space.to_params(x)
    assert params["diffuse_reflectance"].shape == (3,)
    np.testing.assert_allclose(space.from_params(params), x)


def test_fit_file_round_trip(tmp_path):
    meas, _ = _lambert_data(np.random.default_rng(2), n=40)
    result = fit(meas, gm.get("diffuse"), rng=np.random.default_rng(0))
    doc = fit_document(result, meas, seed=0)
    path = write_json_atomic(tmp_path / "fit.json", doc)
    text = path.read_text()
    assert "NaN" not in text and "Infinity" not in text
    fitfile = load_fit(path)
    model, params, loaded = fitfile.model, fitfile.params, fitfile.document
    assert model.name == "diffuse"
    np.testing.assert_allclose(params["reflectance"], result.x)
    assert loaded["parameters"]["reflectance[R]"]["std"] == pytest.approx(result.std[0])
    with pytest.warns(DeprecationWarning, match="unpacking load_fit"):   # the old tuple, still readable
        old_model, old_params, old_doc = fitfile
    assert old_model is model and old_params is params and old_doc is loaded
    assert json.loads(text)["provenance"]["versions"]["numpy"] == np.__version__
    assert not list(tmp_path.glob("*.tmp"))
