"""One ``to_xarray`` layout (issue 34): a FitResult and the FitFile of its fit document give
the same variables, coordinates and attributes (colour space, units, k, budget) and the same
numbers.

Before: ``FitResult.to_xarray`` had its own layout (value, std, lower, upper, correlation; no
u_c, U, k, colour space or budget) beside ``FitFile.to_xarray``'s.
"""

import json

import numpy as np
import pytest

import gonio.models as gm
from gonio.fitting import fit, fit_document, load_fit, write_json_atomic
from gonio.perf.fit import simulate_capture

TRUTH = {"diffuse_reflectance": np.array([0.6, 0.4, 0.2]), "alpha": 0.15, "int_ior": 1.5}


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    model = gm.get("roughplastic", distribution="ggx")
    meas, _ = simulate_capture(model, TRUTH, 150, np.random.default_rng(1))
    result = fit(meas, model, rng=np.random.default_rng(0))
    doc = fit_document(result, meas, seed=0)
    path = write_json_atomic(tmp_path_factory.mktemp("xr") / "fit.json", doc)
    return meas, result, doc, path


def test_a_result_and_its_fit_file_share_one_layout(fitted):
    meas, result, doc, path = fitted
    a, b = result.to_xarray(doc), load_fit(path).to_xarray()
    assert set(a.data_vars) == set(b.data_vars) and set(a.coords) == set(b.coords) and set(a.attrs) == set(b.attrs)
    for v in ("value", "std", "u_stat", "u_combined", "U", "ci90_low", "ci90_high", "lower", "upper", "correlation"):
        np.testing.assert_allclose(a[v].values, b[v].values, rtol=1e-12, err_msg=v)
    for v in ("at_bound", "undetermined", "flags", "unit"):
        assert list(a[v].values) == list(b[v].values), v
    for k in ("colour_space", "k", "budget", "model", "options"):
        assert a.attrs[k] == b.attrs[k], k
    assert json.loads(a.attrs["budget"]) == doc["uncertainty"]["components"]
    assert a.attrs["k"] == 2.0
    names = list(a.parameter.values)
    np.testing.assert_allclose(a.u_combined.values, [doc["parameters"][n]["u_combined"] for n in names])
    np.testing.assert_allclose(np.diag(a.correlation.values), 1.0)
    np.testing.assert_allclose(a.lower.values, result.space.lower)
    np.testing.assert_allclose(a.upper.values, result.space.upper)


def test_a_result_alone_says_its_u_c_is_statistical(fitted):
    meas, result, _, _ = fitted
    ds = result.to_xarray()
    assert set(ds.data_vars) == set(result.to_xarray(fit_document(result, meas)).data_vars)
    np.testing.assert_array_equal(ds.u_combined.values, result.std)
    assert list(json.loads(ds.attrs["budget"])) == ["statistical"]
