"""The fitter's batched kernel (gonio.models.engine.fast.affine_parts) against the reference
model.eval: f_r = base + coef * basis with coef = rho / q, at several parameter sets in one
call, including directions below the horizon and non-finite ones (f_r = 0 there)."""

import numpy as np
import pytest

import gonio.models as gm
from gonio.models.engine import fast as _fast

pytestmark = pytest.mark.skipif(not _fast.available(), reason="Dr.Jit LLVM backend unavailable")

CASES = [
    ("diffuse", {}, np.zeros((2, 0))),
    ("orennayar", {}, [[0.0], [0.3], [1.5]]),
    ("roughplastic", {"distribution": "ggx"}, [[0.15, 1.6], [0.003, 1.05], [0.9, 3.5]]),
    ("roughplastic", {"distribution": "beckmann"}, [[0.15, 1.6], [0.02, 1.3], [0.8, 2.5]]),
]


def _dirs(rng, n):
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1)[:, None]


@pytest.mark.parametrize("name,options,thetas", CASES)
def test_affine_parts_equal_model_eval(name, options, thetas):
    rng = np.random.default_rng(4)
    wi, wo = _dirs(rng, 3000), _dirs(rng, 3000)
    wi[:3] = [np.nan, 0, 1]
    model = gm.get(name, **options)
    coef_name, theta_names = _fast.affine_spec(model)
    prep = _fast.prepare(wi, wo)
    base, basis = _fast.affine_parts(model, prep, thetas)
    q = _fast.affine_q(model, thetas)
    rho = np.array([0.7, 0.35, 0.05])
    for k, th in enumerate(np.atleast_2d(thetas)):
        f = model.eval(wi, wo, {coef_name: rho, **dict(zip(theta_names, th))})
        g = base[k][:, None] + basis[k][:, None] * (rho / q[k])[None, :]
        # Beckmann's visible-normal inversion (erfinv + Newton) differs from numpy's by ~1e-8
        tol = 1e-7 if options.get("distribution") == "beckmann" else 1e-12
        np.testing.assert_allclose(g, f, rtol=tol, atol=1e-12 * np.max(f))
        assert np.all(g[:3] == 0.0) and np.all(np.isfinite(g))


def test_affine_parts_rejects_bad_thetas_and_models():
    model = gm.get("roughplastic")
    prep = _fast.prepare(_dirs(np.random.default_rng(0), 4), _dirs(np.random.default_rng(1), 4))
    with pytest.raises(ValueError, match="NaN"):
        _fast.affine_parts(model, prep, [[np.nan, 1.5]])
    with pytest.raises(ValueError, match="shape"):
        _fast.affine_parts(model, prep, [[0.1, 1.5, 3.0]])
    assert _fast.affine_spec(gm.get("roughplastic", nonlinear=True)) is None
    assert _fast.affine_spec(gm.get("roughconductor")) is None
