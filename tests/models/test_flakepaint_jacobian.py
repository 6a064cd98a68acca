"""flakepaint's exact Jacobian (issue 35): every column against central differences of eval.

The coat's roughness and index columns are the derivatives of Walter et al. 2007's D (eqs. 25,
33), Smith G1 (Mitsuba's GGX form, Beckmann's rational fit eq. 27) and the dielectric Fresnel
equations (k = 0); the lobes' as in flakepaint.half_vector_lobe. The reference is
eval_reference itself, differenced (step 1e-6 of the parameter's range scale).
"""

from __future__ import annotations

import numpy as np
import pytest

import gonio.models as gm

from models_testutil import random_hemisphere

PAINT = {"alpha": 0.3, "eta": 1.6, "haze_alpha": 0.08, "flake_alpha": 0.25, "flake_exponent": 0.4,
         "flake_widen": 0.5, "specular_reflectance": [0.9, 0.8, 0.7], "haze_reflectance": [0.02, 0.03, 0.04],
         "flake_reflectance": [0.1, 0.2, 0.3], "diffuse_reflectance": [0.05, 0.04, 0.03]}


@pytest.mark.parametrize("distribution", ["ggx", "beckmann"])
@pytest.mark.parametrize("alpha", [0.02, 0.3, 0.9])
def test_every_column_is_the_derivative(distribution, alpha):
    """Each non-colour column within 1e-6 of the column's largest value of the central difference
    (step 1e-6): the Beckmann G1 fit's two branches (b = 1 / (alpha tan) either side of 1.6: alpha
    0.9 puts most pairs below, 0.02 above), a narrow and a wide coat."""
    model = gm.get("flakepaint", distribution=distribution)
    rng = np.random.default_rng(35)
    wi, wo = random_hemisphere(rng, 400), random_hemisphere(rng, 400)
    p = model.validate({**PAINT, "alpha": alpha})
    f, J = model.jacobian_reference(wi, wo, p)
    np.testing.assert_allclose(f, model.eval_reference(wi, wo, p), rtol=1e-12)
    for name in ("alpha", "eta", "haze_alpha", "flake_alpha", "flake_exponent", "flake_widen"):
        h = 1e-6 * max(abs(p[name]), 1.0) if name != "alpha" else 1e-6 * alpha
        num = (model.eval_reference(wi, wo, {**p, name: p[name] + h})
               - model.eval_reference(wi, wo, {**p, name: p[name] - h})) / (2 * h)
        assert np.abs(num).max() > 0.0, name
        assert np.abs(num - J[name]).max() <= 1e-6 * np.abs(num).max(), (name, np.abs(num - J[name]).max())


def test_the_coat_columns_fail_when_wrong(monkeypatch):
    """The test above catches a wrong coat derivative: the Fresnel term's 1e-4 relative off."""
    import gonio.models.catalogue.flakepaint as fp

    fn = fp._dielectric_grad
    monkeypatch.setattr(fp, "_dielectric_grad", lambda c, e: (lambda F, dF: (F, dF * (1.0 + 1e-4)))(*fn(c, e)))
    model = gm.get("flakepaint", distribution="ggx")
    rng = np.random.default_rng(35)
    wi, wo = random_hemisphere(rng, 400), random_hemisphere(rng, 400)
    p = model.validate(PAINT)
    _, J = model.jacobian_reference(wi, wo, p)
    h = 1e-6 * p["eta"]
    num = (model.eval_reference(wi, wo, {**p, "eta": p["eta"] + h})
           - model.eval_reference(wi, wo, {**p, "eta": p["eta"] - h})) / (2 * h)
    assert np.abs(num - J["eta"]).max() > 1e-5 * np.abs(num).max()
