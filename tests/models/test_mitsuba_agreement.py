"""gonio.models against Mitsuba 3's own ``bsdf.eval`` (issue 3, "Accuracy"; issue 12).

Mitsuba's ``bsdf.eval`` returns f_r * cos(theta) of the light direction and its
``si.wi`` is our ``wo`` (conversion in ``gonio.models.mitsuba.eval_cos``).
For each model and option set: 20 random parameter sets, 1e5 random direction pairs
each, compared wherever f_r cos > 1e-6.

Mitsuba evaluates in float32, so directions and parameters are rounded to float32 before
both evaluations. Most pairs agree within ``tol`` itself. Some pairs are ill-conditioned
in float32 (a half vector from a strong cancellation, wi nearly opposite to wo at grazing
angles; a narrow Beckmann lobe whose exponent amplifies that; the Fresnel amplitudes at
eta -> 1): there Mitsuba's own rounding exceeds ``tol``.

The float32 error model (issue 12). For each such pair the allowance is

    tol + K * (s_ours + s_mitsuba),   K = 2,

where ``s_ours`` is the relative change of our float64 f_r cos when every direction
component moves by one float32 ulp at 1 (2^-23) and every parameter by one relative
float32 ulp (the pair's conditioning), and ``s_mitsuba`` is the relative change of
*Mitsuba's own float32 result* under the same direction perturbations, measured on the
CPU the test runs on. ``s_mitsuba`` holds the rounding noise of Mitsuba's float32 kernel
as this machine's code generation makes it (vector width, FMA contraction, rcp/rsqrt
refinements), so the bound follows the CPU instead of one machine's observation: on
15e620e the bound used ``s_ours`` alone with K = 8 and failed on two AVX-512 machines
(cooktorrance: our float64 sensitivity understates the rounding of Mitsuba's float32
kernel there). Measured on 2026-12-01 (Intel AVX-512), largest (rel - tol) / (s_ours + s_mi)
over every pair above ``tol`` of every configuration: 0.18 with Dr.Jit's native 16-wide
target and 0.14 with the 8-wide AVX2 target (``GONIO_LLVM_TARGET=avx2``), against
17.5 for (rel - tol) / s_ours alone under AVX2. K = 2 leaves a factor 11.

A wrong formula still fails: ``test_a_1e-4_error_is_detected`` changes Schlick's Fresnel
term of cooktorrance or one Smith G1 factor of roughconductor by 1e-4 relative and
asserts the comparison fails (a 1e-4 change moves nearly every well-conditioned pair,
whose allowance is tol + ~1e-7).
"""

from __future__ import annotations

import numpy as np
import pytest

import gonio.models as gm
from gonio.models.catalogue.roughconductor import to_tangent_frame

from models_testutil import random_hemisphere, random_params

mi = pytest.importorskip("mitsuba")
from gonio.models.mitsuba import eval_cos as mitsuba_eval_cos, mitsuba_variant  # noqa: E402

pytestmark = pytest.mark.codegen  # run again under a second code generation (issue 12)

N_SETS = 20
THRESH = 1e-6  # compare where f_r cos > 1e-6 (issue 3)
K_NOISE = 2.0  # allowance per unit of measured float32 sensitivity (module docstring)


@pytest.fixture(scope="module")
def variant():
    return mitsuba_variant()


@pytest.fixture(scope="module")
def n_pairs(variant):
    # 1e5 pairs in the vectorised llvm variant; the scalar fallback loops in Python.
    return 100_000 if variant.startswith("llvm") else 1_000


def float32_noise(model, p, wi, wo, rng):
    """Relative change of our f_r cos when each direction component moves by one
    float32 ulp at 1 (2^-23, absolute) and each parameter by one relative float32 ulp:
    the rounding-noise floor of a float32 evaluation of the same pair (it covers e.g.
    the cancellation in the Fresnel amplitudes at eta -> 1)."""
    eps = 2.0**-23
    base = model.eval_reference(wi, wo, p) * wi[:, 2:3]
    worst = np.zeros_like(base)
    for _ in range(4):
        a = wi + eps * rng.choice([-1.0, 1.0], size=wi.shape)
        b = wo + eps * rng.choice([-1.0, 1.0], size=wo.shape)
        q = {k: np.asarray(v) * (1.0 + eps * rng.choice([-1.0, 1.0], size=np.shape(v))) for k, v in p.items()}
        q = {k: float(v) if v.ndim == 0 else v for k, v in q.items()}
        try:
            q = model.validate(q)
        except ValueError:  # a bound was crossed: keep the parameters
            q = p
        f = model.eval_reference(a, b, q) * a[:, 2:3]
        worst = np.maximum(worst, np.abs(f - base) / np.where(base > 0, base, 1.0))
    return worst


def as_float32(p):
    """Parameters rounded to float32, as Mitsuba stores them."""
    return {k: np.asarray(v, dtype=np.float32).astype(np.float64) for k, v in p.items()}


def mitsuba_float32_noise(bsdf, wi, wo, ref, rng, draws=8):
    """Relative change of Mitsuba's own float32 f_r cos when each direction component
    moves by one float32 ulp at 1 (2^-23): the rounding noise of Mitsuba's kernel as this
    CPU's code generation makes it (module docstring)."""
    eps = 2.0**-23
    worst = np.zeros_like(ref)
    for _ in range(draws):
        a = wi + eps * rng.choice([-1.0, 1.0], size=wi.shape)
        b = wo + eps * rng.choice([-1.0, 1.0], size=wo.shape)
        f = mitsuba_eval_cos(bsdf, a, b)
        worst = np.maximum(worst, np.abs(f - ref) / np.where(ref > 0, ref, 1.0))
    return worst


def compare(model, rng, n_pairs, tol, override=None, n_sets=N_SETS):
    """Run the comparison; return the largest relative error seen, the fraction of
    compared values above ``tol`` and the largest excess over the float32 allowance
    (<= 0 when every pair is within it), with the parameters where it occurred."""
    worst, n_over, n_cmp = 0.0, 0, 0
    max_excess, where = -np.inf, None
    for _ in range(n_sets):
        p = random_params(model, rng)
        p.update(override or {})
        p = model.validate(as_float32(p))
        wi = random_hemisphere(rng, n_pairs, np.float32).astype(np.float64)
        wo = random_hemisphere(rng, n_pairs, np.float32).astype(np.float64)
        bsdf = mi.load_dict(model.to_mitsuba(p))
        # Mitsuba's BSDF sees the directions in its tangent frame (the shape's dp/du; a
        # scene turns the shape: tests/models/test_tangent.py), gonio's in the holder's
        t = model.tangent_deg(p) if hasattr(model, "tangent_deg") else 0.0
        wi_m, wo_m = (to_tangent_frame(wi, t), to_tangent_frame(wo, t)) if t else (wi, wo)
        ref = mitsuba_eval_cos(bsdf, wi_m, wo_m)
        ours = model.eval_reference(wi, wo, p) * wi[:, 2:3]
        mask = ref > THRESH
        rel = np.where(mask, np.abs(ours - ref) / np.where(mask, ref, 1.0), 0.0)
        # below the comparison threshold both are tiny
        assert np.all(np.abs(ours[~mask]) <= 2 * THRESH), p
        if mask.any():
            bad = (rel > tol).any(axis=1)
            n_over += int((rel > tol).sum())
            n_cmp += int(mask.sum())
            if bad.any():
                noise = float32_noise(model, p, wi[bad], wo[bad], rng)
                noise_mi = mitsuba_float32_noise(bsdf, wi_m[bad], wo_m[bad], ref[bad], rng)
                excess = float((rel[bad] - tol - K_NOISE * (noise + noise_mi)).max())
                if excess > max_excess:
                    max_excess, where = excess, (p, float(rel.max()), float(noise.max()), float(noise_mi.max()))
            worst = max(worst, float(rel.max()))
    return worst, n_over / max(n_cmp, 1), max_excess, where


CONFIGS = [
    ("diffuse", {}, 1e-5),
    ("roughplastic", {"distribution": "beckmann"}, 1e-3),
    ("roughplastic", {"distribution": "ggx"}, 1e-3),
    ("roughplastic", {"distribution": "beckmann", "nonlinear": True}, 1e-3),
    ("roughplastic", {"distribution": "ggx", "nonlinear": True}, 1e-3),
    ("roughconductor", {"distribution": "beckmann"}, 1e-5),
    ("roughconductor", {"distribution": "ggx"}, 1e-5),
    ("roughconductor", {"distribution": "beckmann", "anisotropic": True}, 1e-5),
    ("roughconductor", {"distribution": "ggx", "anisotropic": True}, 1e-5),
    ("cooktorrance", {}, 1e-5),  # registered Python BSDF (Dr.Jit formula)
    ("orennayar", {}, 1e-5),  # registered Python BSDF
    ("roughplastic2", {"distribution": "beckmann"}, 1e-3),  # blendbsdf of two roughplastics
    ("roughplastic2", {"distribution": "ggx"}, 1e-3),
    ("roughconductor2", {"distribution": "beckmann"}, 1e-5),  # blendbsdf of two roughconductors
    ("roughconductor2", {"distribution": "ggx"}, 1e-5),
]


def _id(c):
    return "-".join([c[0]] + [f"{k}={v}" for k, v in c[1].items()])


@pytest.mark.slow
@pytest.mark.parametrize("name,options,tol", CONFIGS, ids=[_id(c) for c in CONFIGS])
def test_eval_matches_mitsuba(name, options, tol, variant, n_pairs):
    """Overall f_r cos: 1e-5 relative (diffuse, roughconductor), 1e-3 (roughplastic,
    whose diffuse part uses tabulated transmittance; measured: ~6e-6)."""
    model = gm.get(name, **options)
    rng = np.random.default_rng(sum(map(ord, _id((name, options)))))
    worst, frac, excess, where = compare(model, rng, n_pairs, tol)
    print(f"{_id((name, options))}: max relative error {worst:.2e}, fraction above {tol:g}: {frac:.1e}")
    assert excess <= 0.0, where


@pytest.mark.slow
@pytest.mark.parametrize("distribution", ["beckmann", "ggx"])
def test_roughplastic_specular_matches_mitsuba(distribution, variant, n_pairs):
    """Specular part alone (diffuse_reflectance = 0) to 1e-5 relative."""
    model = gm.get("roughplastic", distribution=distribution)
    rng = np.random.default_rng(7 if distribution == "ggx" else 8)
    worst, frac, excess, where = compare(model, rng, n_pairs, 1e-5, override={"diffuse_reflectance": 0.0})
    assert excess <= 0.0, where
    print(f"roughplastic {distribution} specular: max relative error {worst:.2e}, fraction above 1e-5: {frac:.1e}")


def _scaled(fn, factor):
    def wrapped(*args, **kwargs):
        return fn(*args, **kwargs) * factor
    return wrapped


MUTANTS = [
    # (config, module attribute, factor): Schlick's F in cooktorrance; one Smith G1 factor
    # of roughconductor (f_r carries G1(wi) G1(wo), so sqrt(1 + 1e-4) on each is 1e-4 on G)
    (("cooktorrance", {}, 1e-5), "gonio.models.catalogue.cooktorrance.fresnel_schlick", 1.0 + 1e-4),
    (("roughconductor", {"distribution": "ggx"}, 1e-5), "gonio.models.catalogue.roughconductor.smith_g1_xyz",
     float(np.sqrt(1.0 + 1e-4))),
    (("roughconductor", {"distribution": "beckmann"}, 1e-5), "gonio.models.catalogue.roughconductor.fresnel_conductor",
     1.0 - 1e-4),
]


@pytest.mark.slow
@pytest.mark.parametrize("config,target,factor", MUTANTS, ids=[m[1].rsplit(".", 1)[1] + "-" + _id(m[0]) for m in MUTANTS])
def test_a_1e_4_error_is_detected(config, target, factor, variant, n_pairs, monkeypatch):
    """The float32 allowance is not so wide that a wrong formula passes: the same
    comparison on a model whose Fresnel or G term is off by 1e-4 relative must fail."""
    name, options, tol = config
    module, attr = target.rsplit(".", 1)
    import importlib

    mod = importlib.import_module(module)
    monkeypatch.setattr(mod, attr, _scaled(getattr(mod, attr), factor))
    model = gm.get(name, **options)
    rng = np.random.default_rng(sum(map(ord, _id((name, options)))))
    worst, frac, excess, where = compare(model, rng, n_pairs, tol, n_sets=2)
    print(f"{target} x {factor}: max relative error {worst:.2e}, excess over the allowance {excess:.1e}")
    assert excess > 0.5e-4, where


@pytest.mark.parametrize("name", [n for n in gm.names() if getattr(type(gm.get(n)), "mitsuba_twin", True)])
def test_every_model_renders(name, variant):
    """A flat sample under a directional lamp seen by a radiance meter renders
    L = f_r E cos(theta_i) (direct integrator; E = 1) for every registered model."""
    model = gm.get(name)
    p = model.defaults()
    ti, to = np.radians(30.0), np.radians(20.0)
    wi = np.array([np.sin(ti), 0.0, np.cos(ti)])
    wo = np.array([-0.5 * np.sin(to), np.sqrt(0.75) * np.sin(to), np.cos(to)])
    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "direct"},
        "sample": {"type": "rectangle", "bsdf": model.to_mitsuba(p)},
        "lamp": {"type": "directional", "direction": (-wi).tolist(), "irradiance": {"type": "rgb", "value": 1.0}},
        "meter": {
            "type": "radiancemeter",
            "origin": (5.0 * wo).tolist(),
            "direction": (-wo).tolist(),
            "film": {"type": "hdrfilm", "width": 1, "height": 1, "rfilter": {"type": "box"}, "pixel_format": "rgb"},
        },
    })
    radiance = np.array(mi.render(scene, spp=4), dtype=np.float64).ravel()[:3]
    expected = model.eval(wi[None], wo[None], p)[0] * wi[2]
    np.testing.assert_allclose(radiance, expected, rtol=1e-5)


def test_ext_ior_convention(variant):
    """to_mitsuba pins ext_ior = 1: Mitsuba's default (air, 1.000277) would shift F."""
    model = gm.get("roughplastic")
    d = model.to_mitsuba({"int_ior": 1.5})
    assert d["ext_ior"] == 1.0 and d["int_ior"] == 1.5
    eta = mi.traverse(mi.load_dict(d))["eta"]
    assert abs(float(np.array(eta).ravel()[0]) - 1.5) < 1e-6


def test_variant_helper_is_idempotent(variant):
    assert mitsuba_variant() == variant == mi.variant()
    mi.set_variant("scalar_rgb" if variant != "scalar_rgb" else "scalar_spectral")
    assert mitsuba_variant() == variant  # re-selected after someone else changed it
