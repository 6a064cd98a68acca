"""Directional albedo quadrature: exactness where known, stated error elsewhere."""

from __future__ import annotations

import math

import numpy as np
import pytest

import gonio.models as gm
from gonio.models.physics.albedo import QUADRATURE_ERROR

TH = np.array([0.0, 0.7, 1.2, 1.45, 1.55, math.pi / 2 - 1e-4])
WO = np.stack([np.sin(TH) * math.cos(2.0), np.sin(TH) * math.sin(2.0), np.cos(TH)], 1)

CASES = [
    ("orennayar", {}, {"sigma": 1.0, "reflectance": 1.0}),
    ("roughplastic", {}, {"alpha": 1e-4, "diffuse_reflectance": 1.0}),
    ("roughplastic", {"distribution": "ggx"}, {"alpha": 1.0, "diffuse_reflectance": 1.0}),
    ("roughplastic", {"distribution": "ggx"}, {"alpha": 0.01, "diffuse_reflectance": 0.0, "int_ior": 4.0}),
    ("roughconductor", {"distribution": "ggx"}, {"alpha": 1e-4}),
    ("roughconductor", {"distribution": "beckmann"}, {"alpha": 1.0}),
    ("roughconductor", {"distribution": "ggx", "anisotropic": True}, {"alpha_u": 1.0, "alpha_v": 0.01}),
    ("cooktorrance", {}, {"roughness": 1.0}),
    ("cooktorrance", {}, {"roughness": 1e-3}),
]


@pytest.mark.slow
@pytest.mark.parametrize("name,options,params", CASES)
def test_quadrature_error_bound(name, options, params):
    """Default albedo within QUADRATURE_ERROR (1e-3) of a 16x finer quadrature, and the
    returned error estimate is honest to within a factor 10 (plus 1e-5)."""
    m = gm.get(name, **options)
    a, e = m.albedo(WO, params, return_error=True)
    ref = m.albedo(WO, params, n_theta=512, n_phi=512, max_level=0)
    err = np.abs(a - ref)
    assert err.max() <= QUADRATURE_ERROR
    assert np.all(err <= 10 * e + 1e-5)
    # away from grazing (theta_o <= 83 deg) far better
    assert err[:4].max() <= 2e-4


def test_lambert_exact():
    a = gm.get("diffuse").albedo(WO, {"reflectance": [0.1, 0.5, 1.0]})
    np.testing.assert_allclose(a, np.broadcast_to([0.1, 0.5, 1.0], a.shape), rtol=1e-13)


def test_albedo_is_integral_of_eval():
    """Cross-check with an independent brute-force quadrature over wi (uniform grid in
    cos theta_i and phi) for a smooth configuration."""
    m = gm.get("roughconductor", distribution="ggx")
    p = {"alpha": 0.5, "eta": [0.2, 1.0, 2.0], "k": [3.0, 2.0, 0.5]}
    w = np.array([0.5, 0.2, math.sqrt(1 - 0.29)])
    n_mu, n_phi = 2000, 1000
    mu = (np.arange(n_mu) + 0.5) / n_mu
    phi = (np.arange(n_phi) + 0.5) * 2 * math.pi / n_phi
    M, P = np.meshgrid(mu, phi, indexing="ij")
    s = np.sqrt(1 - M**2)
    wi = np.stack([s * np.cos(P), s * np.sin(P), M], -1).reshape(-1, 3)
    f = m.eval(wi, np.broadcast_to(w, wi.shape), p)
    brute = (f * wi[:, 2:3]).sum(0) * (1 / n_mu) * (2 * math.pi / n_phi)
    np.testing.assert_allclose(m.albedo(w[None], p)[0], brute, atol=2e-5)


@pytest.mark.parametrize("name,options", [("roughconductor", {"distribution": "ggx"}),
                                          ("roughconductor", {"distribution": "beckmann"}),
                                          ("roughconductor", {"distribution": "ggx", "anisotropic": True}),
                                          ("cooktorrance", {}), ("tabulated", {})],
                         ids=["ggx", "beckmann", "ggx-aniso", "cooktorrance", "tabulated"])
def test_a_lobe_only_model_integrates_its_lobe_with_the_compiled_kernel(name, options, monkeypatch):
    """gonio/models/physics/albedo: roughconductor (``lobe_only``) integrates its lobe alone,
    cooktorrance and tabulated (``lambert_smooth``) their Lambertian part as rho and the lobe
    as f_r - rho / pi, in one Dr.Jit kernel a refinement level (gonio/models/engine/albedo: the nodes,
    the model's compiled f_r and every direction's sum; no numpy evaluation at all), and the
    albedo and its error estimate equal the numpy path's (GONIO_EVAL_BACKEND=numpy: the
    reference, whose smooth part the quadrature integrates at its own nodes) to 1e-12,
    grazing views included."""
    from gonio.models.physics import albedo as _albedo
    from gonio.models.engine import fast as _fast

    if not _fast.available():
        pytest.skip("Dr.Jit LLVM backend unavailable")
    m = gm.get(name, **options)
    rng = np.random.default_rng(1812)
    if name == "cooktorrance":
        p = {"roughness": 0.1, "diffuse_reflectance": rng.uniform(0, 0.5, 3), "specular_reflectance": rng.uniform(0, 0.5, 3)}
    elif name == "tabulated":       # the default tables (a GGX-like lobe) under a random body
        p = {"diffuse_reflectance": rng.uniform(0, 0.5, 3)}
    else:
        p = {"eta": rng.uniform(0.2, 3.0, 3), "k": rng.uniform(0.0, 5.0, 3)}
        p.update({"alpha_u": 0.3, "alpha_v": 0.05} if options.get("anisotropic") else {"alpha": 0.2})
    calls = {"compiled": 0, "parts": 0, "eval": 0}
    from gonio.models.engine import albedo as _albedo_jit

    real_lobe = _albedo_jit.lobe_integral
    real_parts, real_eval = type(m)._eval_parts, type(m).eval

    def spy_lobe(*args):
        calls["compiled"] += 1
        return real_lobe(*args)

    def spy_parts(self, wi, wo, params):
        calls["parts"] += 1
        return real_parts(self, wi, wo, params)

    def spy_eval(self, *args, **kw):
        calls["eval"] += 1
        return real_eval(self, *args, **kw)

    monkeypatch.setattr(_albedo_jit, "lobe_integral", spy_lobe)
    monkeypatch.setattr(type(m), "_eval_parts", spy_parts)
    monkeypatch.setattr(type(m), "eval", spy_eval)
    got, got_err = m.albedo(WO, p, return_error=True)
    # every direction still refining at a level in one call: 2 to max_level + 1 = 4 calls
    # (a call a direction and level was 12 or more for these 6 directions)
    assert 2 <= calls["compiled"] <= 4 and calls["parts"] == 0 and calls["eval"] == 0, calls
    monkeypatch.setenv("GONIO_EVAL_BACKEND", "numpy")
    monkeypatch.setattr(type(m), "lambert_smooth", None)     # the smooth part at its own nodes
    compiled = calls["compiled"]
    want, want_err = m.albedo(WO, p, return_error=True)
    assert calls["compiled"] == compiled and calls["parts"] > 0
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
    np.testing.assert_allclose(got_err, want_err, rtol=0, atol=1e-12)
    assert np.all(got > 0) and (np.all(got <= 1) or not m.energy_conserving)   # cooktorrance: > 1 near grazing


def test_the_compiled_lobe_quadrature_cuts_a_level_into_chunks_without_changing_it(monkeypatch):
    """gonio/models/engine/albedo cuts a level's directions into launches of CHUNK_NODES nodes: a
    direction per launch gives the one-launch albedo to 1e-14."""
    from gonio.models.engine import albedo as _albedo_jit
    from gonio.models.engine import fast as _fast

    if not _fast.available():
        pytest.skip("Dr.Jit LLVM backend unavailable")
    m = gm.get("roughconductor", distribution="beckmann")
    p = {"alpha": 0.15}
    whole = m.albedo(WO, p)
    monkeypatch.setattr(_albedo_jit, "CHUNK_NODES", 1)
    np.testing.assert_allclose(m.albedo(WO, p), whole, rtol=0, atol=1e-14)


@pytest.mark.parametrize("name,options,params", [("roughplastic", {}, {"alpha": 0.05}),
                                                 ("roughconductor", {"distribution": "ggx"}, {"alpha": 0.2}),
                                                 ("orennayar", {}, {"sigma": 0.5})],
                         ids=["roughplastic", "roughconductor", "orennayar"])
def test_albedo_of_many_directions_is_each_directions_albedo(name, options, params, monkeypatch):
    """The quadrature integrates every refining direction of a level in one evaluation,
    cut into chunks of CHUNK_NODES nodes: the result does not depend on the company a
    direction keeps (alone, one chunk, a chunk each) to 1e-14, directions below the horizon
    or not finite give 0 (error 0), and each direction stops refining at its own level (a
    grazing view's error estimate is its own, not its neighbours')."""
    from gonio.models.physics import albedo as _albedo

    m = gm.get(name, **options)
    rng = np.random.default_rng(77)
    th = np.arccos(rng.uniform(0.02, 1.0, 9))
    ph = rng.uniform(0.0, 2.0 * math.pi, 9)
    w = np.concatenate([np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], 1), WO,
                        [[0.0, 0.6, -0.8], [np.nan, 0.0, 1.0]]])
    together, err = m.albedo(w, params, return_error=True)
    alone = [m.albedo(w[i:i + 1], params, return_error=True) for i in range(len(w))]
    np.testing.assert_allclose(together, np.concatenate([a for a, _ in alone]), rtol=0, atol=1e-14)
    np.testing.assert_allclose(err, np.concatenate([e for _, e in alone]), rtol=0, atol=1e-14)
    monkeypatch.setattr(_albedo, "CHUNK_NODES", 1)        # every direction a chunk of its own
    np.testing.assert_allclose(m.albedo(w, params), together, rtol=0, atol=1e-14)
    assert np.all(together[-2:] == 0.0) and np.all(err[-2:] == 0.0)
    assert np.all(together[:-2] > 0.0) and np.all(np.isfinite(err[:-2]))


def test_the_compiled_lobe_quadrature_is_the_same_code_for_every_parameter_value():
    """The roughness and rho enter gonio/models/engine/albedo's kernels as opaque values: an albedo
    at new parameter values launches kernels of the code already made (their hashes), so a
    fit that checks its energy at every step compiles nothing after the first."""
    import drjit as dr

    from gonio.models.engine import fast as _fast

    if not _fast.available():
        pytest.skip("Dr.Jit LLVM backend unavailable")
    m = gm.get("cooktorrance")
    w = np.array([[0.3, 0.1, math.sqrt(0.9)], [0.0, 0.8, 0.6]])
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        hashes = []
        for p in ({"roughness": 0.12}, {"roughness": 0.21, "diffuse_reflectance": [0.1, 0.2, 0.3]}):
            dr.kernel_history()
            m.albedo(w, p)
            hashes.append({h["hash"] for h in dr.kernel_history() if h["type"] == dr.KernelType.JIT})
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert hashes[0] and hashes[1] <= hashes[0], hashes


@pytest.mark.parametrize("name,options,params,atol", [
    ("diffuse", {}, {"reflectance": [0.2, 0.5, 0.9]}, 1e-12),
    ("orennayar", {}, {"sigma": 0.6}, 1e-12),
    # the compiled f_r of roughplastic is its reference to 3.4e-9 relative (its tables), and
    # its rho = 0 part is the same f_r: the albedo's agreement follows
    ("roughplastic", {}, {"alpha": 0.08, "diffuse_reflectance": [0.3, 0.6, 0.9]}, 2e-9),
    ("roughplastic", {"distribution": "ggx", "nonlinear": True}, {"alpha": 0.3}, 2e-9),
    ("principled", {}, {"base_color": [0.8, 0.3, 0.1], "roughness": 0.2, "metallic": 0.4, "spec_tint": 0.5,
                        "sheen": 0.7, "sheen_tint": 0.3, "clearcoat": 0.8, "clearcoat_gloss": 0.6,
                        "flatness": 0.5}, 1e-12)],
    ids=["diffuse", "orennayar", "roughplastic", "roughplastic-ggx-nonlinear", "principled"])
def test_smooth_and_layered_models_integrate_on_the_compiled_kernel(name, options, params, atol, monkeypatch):
    """A model with no lobe distribution (diffuse, orennayar) integrates f_r at the smooth
    part's nodes, and roughplastic (``smooth_off``: rho = 0 leaves the specular lobe alone)
    integrates f_r - f_r(rho = 0) there and f_r(rho = 0) at the lobe's nodes, principled
    (``lobe_switch``: its kernel asked for the specular and clear-coat lobes alone) the same
    with its kernel's lobe, each a Dr.Jit kernel a level (gonio/models/engine/albedo; no numpy evaluation); the albedo and its error
    estimate equal the numpy quadrature's (GONIO_EVAL_BACKEND=numpy) to ``atol``, grazing
    views included, and Lambert's is rho to 1e-13."""
    from gonio.models.physics import albedo as _albedo
    from gonio.models.engine import fast as _fast

    if not _fast.available():
        pytest.skip("Dr.Jit LLVM backend unavailable")
    m = gm.get(name, **options)
    calls = {"lobe": 0, "smooth": 0, "parts": 0}
    from gonio.models.engine import albedo as _albedo_jit

    real_lobe, real_smooth = _albedo_jit.lobe_integral, _albedo_jit.smooth_integral
    real_parts = type(m)._eval_parts

    def spy(key, fn):
        def call(*args):
            calls[key] += 1
            return fn(*args)
        return call

    monkeypatch.setattr(_albedo_jit, "lobe_integral", spy("lobe", real_lobe))
    monkeypatch.setattr(_albedo_jit, "smooth_integral", spy("smooth", real_smooth))
    monkeypatch.setattr(type(m), "_eval_parts", lambda self, *a: spy("parts", real_parts)(self, *a))
    got, got_err = m.albedo(WO, params, return_error=True)
    levels = calls["smooth"]
    assert 2 <= levels <= 4 and calls["parts"] == 0, calls
    assert calls["lobe"] == (levels if m.smooth_off is not None or m.lobe_switch else 0), calls
    monkeypatch.setenv("GONIO_EVAL_BACKEND", "numpy")
    want, want_err = m.albedo(WO, params, return_error=True)
    assert calls["parts"] > 0 and calls["smooth"] == levels
    np.testing.assert_allclose(got, want, rtol=0, atol=atol)
    np.testing.assert_allclose(got_err, want_err, rtol=0, atol=atol)
    if name == "diffuse":
        np.testing.assert_allclose(got, np.broadcast_to([0.2, 0.5, 0.9], got.shape), rtol=1e-13)
