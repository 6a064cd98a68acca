"""One uncertainty statement everywhere (issue 34): the fit file's parameters, ``load_fit``'s
repr and ``to_xarray``, and the report show the same u_c, U, k and flags; the 90 % interval
is built on u_c; ``Measurements.to_xarray`` says the colour space of its values.

Before: a parameter's ``ci90`` was value +- 1.645 x the statistical std (the demo's excluded
the truth on 4 of 5 parameters), ``load_fit`` showed the statistical sigma with no u_c, U or
budget, and a fit with k[R] = 9 +- 11 (U = 22 against a range of 10) carried no flag.
"""

import dataclasses

import numpy as np
import pytest

import gonio.models as gm
from gonio.fitting import fit, fit_document, load_fit, write_json_atomic
from gonio.fitting.display import parameter_flags
from gonio.perf.fit import simulate_capture

TRUTH = {"diffuse_reflectance": np.array([0.6, 0.4, 0.2]), "alpha": 0.15, "int_ior": 1.5}
Z90 = 1.6448536269514722


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """A fit whose budget is dominated by type B: a 2 % certificate on the reference."""
    model = gm.get("roughplastic", distribution="ggx")
    meas, _ = simulate_capture(model, TRUTH, 150, np.random.default_rng(1))
    meas = dataclasses.replace(meas, attrs={**meas.attrs, "scale_rel_std": 0.02,
                                            "colour": {"space": "srgb", "variable": "brdf_srgb"}})
    result = fit(meas, model, rng=np.random.default_rng(0))
    doc = fit_document(result, meas, seed=0)
    return meas, result, doc, write_json_atomic(tmp_path_factory.mktemp("unc") / "fit.json", doc)


def test_the_parameters_state_u_c_and_the_interval_follows_it(fitted):
    _, _, doc, _ = fitted
    unc = doc["uncertainty"]["parameters"]
    for name, p in doc["parameters"].items():
        u = unc[name]
        assert (p["u_combined"], p["U"], p["k"]) == (u["u_combined"], u["U"], u["k"])
        lo, hi = p["ci90"]
        assert hi - lo == pytest.approx(2 * Z90 * p["u_combined"], rel=1e-9) or p["at_bound"]
    # the certificate dominates rho: u_c well above the statistical std
    r = doc["parameters"]["diffuse_reflectance[R]"]
    assert r["u_combined"] > 3 * r["std"]


def test_load_fit_shows_the_same_statement(fitted):
    _, _, doc, path = fitted
    loaded = load_fit(path)
    text = repr(loaded)
    assert "u_c" in text and "U" in text and "reference_certificate" in text
    from gonio.fitting.display import value_pm

    for name, p in doc["parameters"].items():
        assert value_pm(p["value"], p["u_combined"]) in text
    ds = loaded.to_xarray()
    np.testing.assert_allclose(ds.u_combined.values, [p["u_combined"] for p in doc["parameters"].values()])
    np.testing.assert_allclose(ds.U.values, [p["U"] for p in doc["parameters"].values()])
    assert ds.attrs["k"] == 2 and ds.attrs["colour_space"] == "srgb" and "reference_certificate" in ds.attrs["budget"]
    assert "u_c" in loaded._repr_html_()


def test_measurements_to_xarray_says_its_colour_space(fitted):
    meas, *_ = fitted
    ds = meas.to_xarray()
    assert ds.attrs["colour_space"] == "srgb" and ds.brdf.attrs["colour_space"] == "srgb"


@pytest.mark.parametrize("item, lower, upper, flags", [
    ({"value": 9.0, "U": 22.0}, 0.0, 10.0, ["interval_wider_than_range"]),       # k[R] = 9 +- 11 of the issue
    ({"value": 2.5, "U": 0.2, "at_bound": True}, 1.0, 2.5, ["at_bound"]),        # int_ior at its bound
    ({"value": -0.01, "U": 0.001}, 0.0, 1.0, ["outside_bounds"]),                  # a corrected value below 0
    ({"value": 0.5, "U": 0.1}, 0.0, 1.0, []),
    ({"value": 0.5, "U": 0.1}, 0.0, np.inf, []),
])
def test_flags(item, lower, upper, flags):
    assert parameter_flags(item, lower, upper) == flags


def test_the_fit_file_carries_the_flags(fitted):
    _, _, doc, _ = fitted
    assert all(isinstance(p["flags"], list) for p in doc["parameters"].values())


def test_the_report_appendix_states_z_against_u_c(fitted):
    from gonio.bench.report import fit_section
    from gonio.bench.report.inputs import Doc

    _, _, doc, _ = fitted
    truth = {"model": "roughplastic", "options": {"distribution": "ggx"},
             "params": {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in TRUTH.items()}}
    sec = fit_section(Doc(doc, "fit.json", fix="fit again"), truth)
    row = next(r for r in sec["rows"] if r["name"] == "diffuse_reflectance[R]")
    p = doc["parameters"]["diffuse_reflectance[R]"]
    assert float(row["z"]) == pytest.approx((p["value"] - 0.6) / p["u_combined"], abs=0.01)
    assert float(row["u_c"]) == pytest.approx(p["u_combined"], rel=0.05)          # two digits


def test_a_posterior_interval_carries_the_type_b_part_too(fitted):
    """With an emcee posterior the 90 % interval was the posterior's quantiles alone (the data's
    noise): the demo's excluded the truth on every parameter while u_c covered it. It is now the
    posterior's interval widened, side by side in quadrature, by 1.645 u_B (u_B^2 = u_c^2 - u_stat^2);
    the posterior's own interval stays as ``ci90_posterior``. A Gaussian posterior of the fit's
    own std stands in for emcee (same quantiles)."""
    from types import SimpleNamespace

    from scipy.stats import norm

    meas, result, doc, _ = fitted
    q = {k: result.x + norm.ppf(k / 100) * result.std for k in (5, 16, 50, 84, 95)}
    draws = np.random.default_rng(3).normal(result.x, result.std, (64, result.x.size))
    post = SimpleNamespace(converged=True, quantiles=q, samples=draws, n_walkers=8, names=list(result.space.names),
                           n_steps=8, tau=[1.0] * result.x.size, n_independent=64, acceptance=0.3, time_s=0.0,
                           advice="", surrogate_error=None)
    with_post = fit_document(result, meas, seed=0, posterior=post)
    for name, p in with_post["parameters"].items():
        if p["at_bound"] or p.get("value_fitted") is not None:
            continue
        lo, hi = p["ci90"]
        plo, phi = p["ci90_posterior"]
        assert phi - plo < hi - lo or p["u_combined"] == pytest.approx(p["std"])
        # a Gaussian posterior of the fit's std, widened by u_B: exactly value +- 1.645 u_c
        assert (lo, hi) == pytest.approx((p["value"] - Z90 * p["u_combined"], p["value"] + Z90 * p["u_combined"]),
                                         rel=1e-9, abs=1e-12), name
    r = with_post["parameters"]["diffuse_reflectance[R]"]
    assert (r["ci90"][1] - r["ci90"][0]) > 3 * (r["ci90_posterior"][1] - r["ci90_posterior"][0])
