"""Hard cases of the fit (issue 6): each must converge or say plainly what the data cannot
determine, and never return NaN. Data: the model's own f_r with Gaussian noise
(tests/fitting/_simdata.py)."""

import numpy as np
import pytest

import gonio.models as gm
from gonio.fitting import Measurements, fit

from _simdata import simulate

pytestmark = pytest.mark.codegen  # run again under a second code generation (issue 12)

RP = gm.get("roughplastic", distribution="ggx")
RHO = np.array([0.5, 0.4, 0.3])


def _finite(r):
    return all(np.all(np.isfinite(a)) for a in (r.x, r.std, r.cov)) and np.isfinite(r.chi2)


def test_nearly_diffuse_data_reports_the_lobe_undetermined():
    """Lambertian data: the specular lobe of roughplastic has nothing to fit."""
    meas = simulate(gm.get("diffuse"), {"reflectance": RHO}, np.random.default_rng(1), n=200)
    r = fit(meas, RP, rng=np.random.default_rng(0))
    assert _finite(r)
    assert "alpha" in r.undetermined
    assert "int_ior" in r.at_bound  # eta -> 1: no specular reflection at all
    np.testing.assert_allclose(r.x[:3], RHO, atol=5 * r.std[:3].max() + 1e-3)
    assert 0.8 < r.chi2_dof < 1.25


def test_near_mirror_data_recovers_small_alpha():
    truth = {"diffuse_reflectance": RHO, "alpha": 1e-3, "int_ior": 1.5}
    meas = simulate(RP, truth, np.random.default_rng(2), n=300, spread=0.003)
    r = fit(meas, RP, rng=np.random.default_rng(0))
    assert _finite(r) and r.converged and not r.undetermined
    pull = (r.x - r.space.from_params(truth)) / r.std
    assert np.all(np.abs(pull) < 4), pull
    assert r.x[3] == pytest.approx(1e-3, rel=0.05)


def test_grazing_dominated_data():
    truth = {"diffuse_reflectance": RHO, "alpha": 0.2, "int_ior": 1.5}
    meas = simulate(RP, truth, np.random.default_rng(3), n=300, theta_min_deg=70, theta_max_deg=88)
    r = fit(meas, RP, rng=np.random.default_rng(0))
    assert _finite(r) and r.converged
    pull = (r.x - r.space.from_params(truth)) / r.std
    assert np.all(np.abs(pull) < 4), pull
    assert 0.8 < r.chi2_dof < 1.25


def test_saturated_and_flagged_points_are_excluded():
    truth = {"diffuse_reflectance": RHO, "alpha": 0.15, "int_ior": 1.6}
    meas = simulate(RP, truth, np.random.default_rng(4), n=200)
    brdf, use = meas.brdf.copy(), meas.use.copy()
    bad = np.zeros(meas.n_points, bool)
    bad[::7] = True
    brdf[bad] = 1e3          # clipped sensor values: absurd if used
    brdf[bad & (np.arange(meas.n_points) % 2 == 0), 1] = np.nan
    use[bad] = False
    flagged = Measurements(meas.wi, meas.wo, brdf, meas.brdf_std, use)
    clean = meas.subset(~bad)
    r1 = fit(flagged, RP, rng=np.random.default_rng(0))
    r2 = fit(clean, RP, rng=np.random.default_rng(0))
    assert r1.n_used == clean.n_used
    np.testing.assert_allclose(r1.x, r2.x, rtol=1e-6)
    assert r1.chi2 == pytest.approx(r2.chi2, rel=1e-6)


def test_correlated_parameters_are_reported():
    """Cook-Torrance seen near normal incidence only: the Schlick term (1 - f0)(1 - c)^5 is
    ~0, so the data constrains the product specular_reflectance * f0, not each (the
    eta-versus-specular-strength degeneracy)."""
    ct = gm.get("cooktorrance")
    truth = {"diffuse_reflectance": 0.5 * RHO, "specular_reflectance": np.full(3, 0.3), "roughness": 0.3,
             "f0": np.full(3, 0.2)}
    meas = simulate(ct, truth, np.random.default_rng(5), n=300, theta_max_deg=25, spread=0.2)
    r = fit(meas, ct, rng=np.random.default_rng(0))
    assert _finite(r)
    pairs = {(a, b) for a, b, _ in r.correlated}
    assert ("specular_reflectance[G]", "f0[G]") in pairs, r.correlated
    rho = dict(((a, b), c) for a, b, c in r.correlated)[("specular_reflectance[G]", "f0[G]")]
    assert rho < -0.9  # more strength, less f0
    np.testing.assert_allclose(r.correlation.diagonal(), 1.0)
    assert r.energy["holds"]
