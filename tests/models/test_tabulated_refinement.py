"""``tabulated``'s sheen refinement: offered for a matte fit only, started with the main
lobe's tail handed to the sheen.

A gloss meter's 60 deg reading (ASTM D523) of the fit decides matte (below 10 GU): a GGX
lobe of alpha 0.05 with a Fresnel factor of 0.1 over a dark body reads 33.6 GU, a wide lobe
(alpha 0.5, F 0.04) over a bright body 1.5 GU (this module's evaluation of
:func:`specular_gloss`; a black glass standard reads 100).
"""

import math

import numpy as np
import pytest

import gonio.models as gm
from gonio.models.catalogue import tabulated as tab
from gonio.models.catalogue import tabulated_sheen
from gonio.models.physics.gloss import MATTE_BELOW_GU, specular_gloss


def _params(alpha, rho, f0):
    model = gm.get("tabulated")
    p = dict(model.defaults())
    lnd = tab.ndf_from_function(lambda t: tab._ggx_ratio(t, alpha))
    for k in range(tab.FIRST_FREE, tab.N_KNOTS):
        p[f"ndf_{k}"] = float(np.clip(np.exp(lnd[k] - lnd[1]), *tab.D_BOUNDS))
    p["diffuse_reflectance"] = np.full(3, rho)
    for j in range(tab.N_FRESNEL):
        p[f"fresnel_{j}"] = np.full(3, f0)
    return model, model.validate(p)


def _gloss(model, p):
    return specular_gloss(lambda wi, wo: model.eval(wi, wo, p))


def test_a_glossy_fit_is_not_offered_the_sheen():
    model, p = _params(0.05, 0.05, 0.1)
    assert _gloss(model, p) > 3 * MATTE_BELOW_GU
    assert model.refinement(p) is None


def test_a_matte_fit_is_offered_the_sheen_with_its_body():
    for body in ("lambert", "table"):
        model, p = _params(0.5, 0.5, 0.04)
        if body == "table":
            model = gm.get("tabulated", body="table")
            p = model.validate({**model.defaults(), **p})
        assert _gloss(model, p) < MATTE_BELOW_GU
        refined = model.refinement(p)
        assert refined is not None and refined.options == {"body": body, "sheen": "ggx"}
        assert refined.refinement(p) is None          # nothing further to refine
        assert model.refinement(None) is None


def test_the_start_hands_the_tail_to_the_sheen_and_keeps_the_rest():
    model, p = _params(0.5, 0.5, 0.04)
    refined = model.refinement(p)
    s = refined.start_from(p)
    assert set(s) == set(refined.defaults())
    last = tabulated_sheen.N_SHEEN - 1
    alpha, grazing = tab.Tabulated.SHEEN_START
    assert float(s["sheen_alpha"]) == alpha
    assert np.all(s[f"sheen_{last}"] == grazing)
    assert all(np.all(s[f"sheen_{j}"] == 0.0) for j in range(last))
    for k in range(tab.FIRST_FREE, tab.N_KNOTS):
        cap = tab.Tabulated.TAIL_CAP[k - tab.Tabulated.TAIL_KNOT] if k >= tab.Tabulated.TAIL_KNOT else math.inf
        assert float(s[f"ndf_{k}"]) == pytest.approx(min(float(p[f"ndf_{k}"]), cap), rel=1e-12)
    assert math.degrees(tab.THETA_KNOTS[tab.Tabulated.TAIL_KNOT]) == pytest.approx(25.6, abs=0.1)
    for name in ("diffuse_reflectance", "fresnel_3", "width_2"):
        assert np.array_equal(s[name], p[name])
    # the wide part moved: at theta_h 40 deg (retro-reflection at 40 deg) the main lobe is far
    # below the plain fit's
    wi = wo = np.array([[math.sin(math.radians(40)), 0.0, math.cos(math.radians(40))]])
    off = {**s, **{f"sheen_{j}": np.zeros(3) for j in range(tabulated_sheen.N_SHEEN)}}
    assert float(refined.eval(wi, wo, off)[0, 1] - 0.5 / math.pi) < 1e-3 * float(model.eval(wi, wo, p)[0, 1] - 0.5 / math.pi)
