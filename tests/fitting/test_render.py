"""The Mitsuba loop closure renders exactly what gonio's models evaluate.

Reference: for a flat sample under a directional emitter of irradiance E seen by a
radiancemeter, Mitsuba's direct integrator returns L = f_r E cos(theta_i) with no Monte Carlo
noise (../shared/notes/tech-facts.md, checked there to 4e-7 relative), so the render divided
by cos(theta_i) must equal ``model.eval`` up to Mitsuba's float32 arithmetic.
"""

import numpy as np
import pytest

import gonio.models as gm
from gonio.fitting import Measurements, direction
from gonio.fitting.render import loop_closure, render_brdf

CASES = [
    ("diffuse", {}, {"reflectance": [0.7, 0.4, 0.1]}),
    ("roughplastic", {"distribution": "ggx"}, {"diffuse_reflectance": [0.5, 0.3, 0.1], "alpha": 0.15, "int_ior": 1.5}),
    ("roughplastic", {"distribution": "beckmann"}, {"diffuse_reflectance": [0.2, 0.3, 0.6], "alpha": 0.3, "int_ior": 1.8}),
    ("roughconductor", {"distribution": "ggx"}, {"eta": [0.2, 0.9, 1.1], "k": [3.9, 2.4, 2.2], "alpha": 0.2}),
    ("cooktorrance", {}, None),
    ("orennayar", {}, None),
]


def _directions(n, seed):
    rng = np.random.default_rng(seed)
    wi = direction(np.radians(rng.uniform(0, 85, n)), rng.uniform(-np.pi, np.pi, n))
    wo = direction(np.radians(rng.uniform(0, 85, n)), rng.uniform(-np.pi, np.pi, n))
    # in-plane mirror configurations, where glossy lobes peak
    th = np.radians([5.0, 30.0, 60.0, 80.0])
    return np.vstack([wi, direction(th, 0 * th)]), np.vstack([wo, direction(th, 0 * th + np.pi)])


@pytest.mark.parametrize("name,options,params", CASES, ids=[f"{c[0]}-{c[1].get('distribution', '')}" for c in CASES])
def test_render_matches_model(name, options, params):
    model = gm.get(name, **options)
    params = params or {p.name: p.default for p in model.parameters}
    wi, wo = _directions(60, 1)
    fr, seconds, variant = render_brdf(model, params, wi, wo)
    ref = model.eval(wi, wo, params)
    mask = ref * wi[:, 2:3] > 1e-6
    rel = np.abs(fr - ref)[mask] / ref[mask]
    assert rel.max() < 1e-4, (variant, rel.max())


def test_loop_closure_residuals_are_in_sigma_units():
    model = gm.get("diffuse")
    params = {"reflectance": [0.5, 0.5, 0.5]}
    wi, wo = _directions(20, 2)
    truth = model.eval(wi, wo, params)
    sigma = 0.01 * truth
    meas = Measurements(wi, wo, truth + 2.0 * sigma, sigma, np.ones(truth.shape, bool))
    out = loop_closure(model, params, meas)
    assert out["summary"]["export_max_rel"] < 1e-5
    # every measurement was displaced by exactly +2 sigma
    np.testing.assert_allclose(out["residual_sigma"], 2.0, atol=1e-4)
    assert len(out["summary"]["worst"]) == 5


def test_a_tabulated_fit_closes_the_loop_in_its_vectorised_variant():
    """tabulated's plugin gathers tables, which Dr.Jit's scalar variants cannot: `gonio render`
    of the most chosen real-material model failed at its scalar per-pose scene check. The loop
    now re-renders its poses in the batch's own variant, agrees with model.eval, and a scalar
    variant is refused in one line before anything renders."""
    from gonio.fitting.render import check_renders_in, renders_in

    model = gm.get("tabulated")
    params = {p.name: p.default for p in model.parameters}
    wi, wo = _directions(30, 3)
    truth = model.eval(wi, wo, params)
    meas = Measurements(wi, wo, truth, 0.01 * truth + 1e-4, np.ones(truth.shape, bool))
    out = loop_closure(model, params, meas)
    assert out["scene_check"]["variant"] == out["variant"] != "scalar_rgb"
    assert out["scene_check"]["max_rel"] < 1e-4 and out["summary"]["export_max_rel"] < 1e-4
    assert renders_in(gm.get("diffuse"), "scalar_rgb") and not renders_in(model, "scalar_rgb")
    for call in (lambda: check_renders_in(model, "scalar_rgb"), lambda: render_brdf(model, params, wi, wo, "scalar_rgb")):
        with pytest.raises(ValueError, match="tabulated renders in a vectorised Mitsuba variant") as err:
            call()
        assert "\n" not in str(err.value)
