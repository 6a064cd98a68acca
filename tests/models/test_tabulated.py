"""The ``tabulated`` model (issue 16): its NDF's normalisation, the Smith G1 it derives from
D against GGX's closed form, reciprocity, positivity, its energy bound, Mitsuba's eval of its
Python BSDF, and the unbiasedness of that BSDF's importance sampling."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

import gonio.models as gm
from gonio.models.catalogue import tabulated as tab
from gonio.models.physics.albedo import QUADRATURE_ERROR

from models_testutil import random_hemisphere


def ggx_ratio(theta, alpha):
    """D_GGX(theta) / D_GGX(0) (Walter et al. 2007, eq. 33)."""
    c2 = np.cos(theta) ** 2
    return 1.0 / (c2 + (1.0 - c2) / alpha**2) ** 2


def ggx_g1(theta, alpha):
    """Smith G1 of GGX (Walter et al. 2007, eq. 34; Heitz 2014, eq. 72)."""
    return 2.0 / (1.0 + np.sqrt(1.0 + alpha**2 * np.tan(theta) ** 2))


def realistic_params(model, rng):
    """A plausible parameter set: ln D of a random-width GGX plus +-1 of noise per knot,
    uniform Fresnel knots and body."""
    alpha = math.exp(rng.uniform(math.log(0.01), math.log(0.8)))
    lnd = tab.ndf_from_function(lambda t: ggx_ratio(t, alpha))
    p = {"diffuse_reflectance": rng.uniform(0, 1, 3)}
    p.update({f"ndf_tilt_{c}_{k}": math.exp(rng.uniform(-3, 3)) for c in "rb" for k in tab.TILT_KNOTS})
    p.update({f"width_{j}": math.exp(rng.uniform(-0.7, 0.7)) for j in range(1, tab.N_FRESNEL)})
    for k in range(tab.FIRST_FREE, tab.N_KNOTS):
        p[f"ndf_{k}"] = math.exp(np.clip(lnd[k] - lnd[1] + rng.uniform(-1, 1), *tab.LN_D_BOUNDS))
    for j in range(tab.N_FRESNEL):
        p[f"fresnel_{j}"] = rng.uniform(0, 1, 3)
    if model.options["body"] == "table":    # drawn last: the draws above stay those of body="lambert"
        p.update({f"body_{j}": math.exp(rng.uniform(-1.0, 0.5)) for j in range(1, tab.N_BODY)})
    if model.options["sheen"] == "ggx":     # a sheen lobe from narrow to wide, amplitudes up to 0.5
        p["sheen_alpha"] = math.exp(rng.uniform(math.log(0.05), 0.0))
        p.update({f"sheen_{j}": rng.uniform(0, 0.5, 3) for j in range(4)})
    return model.validate(p)


def ndf(ln_d, ln_z, theta):
    """The model's normalised D at polar angles theta (N,), per channel (N, C)."""
    return np.exp(tab._interp(ln_d, tab.knot_index(theta)) - ln_z[None, :])


# -- the NDF and the shadowing derived from it ---------------------------------------------


@pytest.mark.parametrize("seed", range(4))
def test_ndf_is_normalised(seed):
    """2 pi int D cos sin d theta = 1 (Walter et al. 2007, eq. 4), checked with a 2e5-point
    midpoint rule in the knot index (independent of the model's Gauss-Legendre nodes): the
    two agree to 1e-6 relative."""
    m = gm.get("tabulated")
    t = tab.tables(realistic_params(m, np.random.default_rng(seed)))
    s = (np.arange(200_000) + 0.5) * ((tab.N_KNOTS - 1) / 200_000)
    theta = 0.5 * math.pi * (s / (tab.N_KNOTS - 1)) ** 2
    dtheta = math.pi * s / (tab.N_KNOTS - 1) ** 2 * ((tab.N_KNOTS - 1) / 200_000)
    integral = 2 * math.pi * np.sum(ndf(t.ln_d, t.ln_z, theta) * (np.cos(theta) * np.sin(theta) * dtheta)[:, None], axis=0)
    np.testing.assert_allclose(integral, 1.0, rtol=1e-6)


@pytest.mark.parametrize("alpha", [0.05, 0.15, 0.5])
def test_g1_from_a_ggx_table_is_ggx_smith(alpha):
    """A table filled from GGX's D gives GGX's normalisation (D(0) = 1 / (pi alpha^2)) and
    Smith G1 (closed form, Walter et al. 2007 eq. 34) to the table's error: 200 knots of the
    same warped grid, G1 to 1e-4 and ln Z to 1e-3 (measured 5.5e-5 and 2.1e-4 at alpha
    0.05); the model's own 16 knots to 1.2e-2 and 4e-2 (measured 9.2e-3 and 3.4e-2 at alpha
    0.05, 1.6e-3 and 1.7e-3 at 0.5: the ln-linear interpolation's error)."""
    theta = tab._theta_g()
    exact = ggx_g1(theta[:-1], alpha)
    knots = 0.5 * math.pi * (np.arange(200) / 199) ** 2
    for grid, g_tol, z_tol in ((knots, 1e-4, 1e-3), (tab.THETA_KNOTS, 1.2e-2, 4e-2)):
        ln_z, g1 = tab.g1_table(tab.ndf_from_function(lambda t: ggx_ratio(t, alpha), grid)[None], grid)
        assert abs(ln_z[0] - math.log(math.pi * alpha**2)) < z_tol
        assert np.abs(g1[0, :-1] - exact).max() < g_tol
        assert g1[0, 0] == pytest.approx(1.0, abs=1e-12) and g1[0, -1] == 0.0  # normal, grazing


def test_g1_bounds_for_any_table():
    """0 <= G1 <= 1 and G1(0) = 1 (A(theta) >= cos(theta) for a normalised D: Heitz 2014,
    sec. 5.1) for tables over the whole box, including the wildest corners; non-increasing
    toward grazing for a monotone D."""
    rng = np.random.default_rng(3)
    for _ in range(20):
        ln_d = np.concatenate([np.zeros((3, 1)), rng.uniform(*tab.LN_D_BOUNDS, (3, tab.N_KNOTS - 1))], axis=1)
        _, g1 = tab.g1_table(ln_d)
        assert np.all(g1 >= 0) and np.all(g1 <= 1) and np.allclose(g1[:, 0], 1.0)
    _, g1 = tab.g1_table(-np.sort(rng.uniform(0, 20, (3, tab.N_KNOTS)), axis=1) * np.r_[0, np.ones(tab.N_KNOTS - 1)])
    assert np.all(np.diff(g1, axis=1) <= 1e-12)


# -- the BRDF -------------------------------------------------------------------------------


#: option sets: the Lambertian and the table body, and the table body with the sheen lobe
BODIES = ({"body": "lambert"}, {"body": "table"}, {"body": "table", "sheen": "ggx"})
BODY_IDS = ("lambert", "table", "table-sheen")


@pytest.mark.parametrize("body", BODIES, ids=BODY_IDS)
def test_reciprocity_and_positivity(body):
    m = gm.get("tabulated", **body)
    rng = np.random.default_rng(11)
    wi, wo = random_hemisphere(rng, 5000), random_hemisphere(rng, 5000)
    for _ in range(6):
        p = realistic_params(m, rng)
        f, g = m.eval(wi, wo, p), m.eval(wo, wi, p)
        assert np.all(np.isfinite(f)) and np.all(f >= 0)
        np.testing.assert_allclose(f, g, rtol=1e-12, atol=0)


def test_a_ggx_table_is_a_ggx_conductor():
    """With every channel's table filled from GGX (alpha 0.3) and a constant F, the lobe is
    Mitsuba's/gonio's GGX roughconductor with that F (Walter et al. 2007, eq. 20) to the
    16-knot table's error (2.5 % here; the G1 part is bounded above)."""
    alpha, F = 0.3, 0.7
    m = gm.get("tabulated")
    lnd = tab.ndf_from_function(lambda t: ggx_ratio(t, alpha))
    p = {"diffuse_reflectance": 0.0, **{f"ndf_{k}": math.exp(lnd[k] - lnd[1]) for k in range(tab.FIRST_FREE, tab.N_KNOTS)},
         **{f"fresnel_{j}": F for j in range(tab.N_FRESNEL)}}
    rng = np.random.default_rng(5)
    wi, wo = random_hemisphere(rng, 4000), random_hemisphere(rng, 4000)
    ok = (wi[:, 2] > 0.2) & (wo[:, 2] > 0.2)
    f = m.eval(wi[ok], wo[ok], p)
    # a conductor with k = 0 and eta -> big is not F = 0.7; compare D G / (4 ci co) directly
    rc = gm.get("roughconductor", distribution="ggx")
    ref = rc.eval(wi[ok], wo[ok], {"eta": 1e-2, "k": 0.0, "alpha": alpha})
    fres = gm.fresnel_conductor(np.clip(np.einsum("ij,ij->i", wi[ok], _half(wi[ok], wo[ok])), 0, 1)[:, None], 1e-2, 0.0)
    np.testing.assert_allclose(f, F * ref / fres, rtol=0.025)


def _half(a, b):
    h = a + b
    return h / np.linalg.norm(h, axis=1, keepdims=True)


def test_energy_lobe_bounded_by_fresnel_and_honest_flag():
    """With every width factor 1 (one microsurface) the lobe's albedo is at most max F
    (normalised D, Smith G1 <= 1) up to the quadrature error; with a body (or widths away from
    1) the sum can exceed 1, so the model says it does not conserve energy (and gonio's fit
    enforces albedo <= 1)."""
    m = gm.get("tabulated")
    rng = np.random.default_rng(2)
    th = np.array([0.0, 0.6, 1.2, 1.45])
    wo = np.stack([np.sin(th), 0 * th, np.cos(th)], 1)
    for _ in range(3):
        p = realistic_params(m, rng)
        p["diffuse_reflectance"] = np.zeros(3)
        p.update({f"width_{j}": 1.0 for j in range(1, tab.N_FRESNEL)})  # one microsurface: the bound is exact
        fmax = np.max([p[f"fresnel_{j}"] for j in range(tab.N_FRESNEL)], axis=0)
        a = m.albedo(wo, p, tol=3e-4)
        assert np.all(a <= fmax[None, :] + QUADRATURE_ERROR), (a, fmax)
    full = {"diffuse_reflectance": 1.0, **{f"fresnel_{j}": 1.0 for j in range(tab.N_FRESNEL)}}
    assert m.albedo(wo[:1], full).min() > 1.5
    assert m.energy_conserving is False


def test_body_table_nests_lambert_and_its_albedo():
    """body="table" with g = 1 is the Lambertian model exactly (the fallback starts it there);
    with the lobe off (F = 0) its albedo at normal view is rho g(0) int_0^{pi/2} g(theta)
    2 cos sin d(theta), g piecewise linear in theta to 80 deg and held beyond (scipy's adaptive
    quad, split at the knots, against the model's compiled quadrature: its stated 1e-3 bound);
    an unknown option value is refused."""
    from scipy.integrate import quad

    rng = np.random.default_rng(5)
    lam, table = gm.get("tabulated"), gm.get("tabulated", body="table")
    p = realistic_params(lam, rng)
    wi, wo = random_hemisphere(rng, 3000), random_hemisphere(rng, 3000)
    ones = table.validate({**p, **{f"body_{j}": 1.0 for j in range(1, tab.N_BODY)}})
    np.testing.assert_array_equal(table.eval_reference(wi, wo, ones), lam.eval_reference(wi, wo, p))
    g = np.array([1.0, 0.7, 1.3, 0.5, 0.2])
    q = table.validate({**p, **{f"body_{j}": g[j] for j in range(1, tab.N_BODY)},
                        **{f"fresnel_{j}": 0.0 for j in range(tab.N_FRESNEL)}})
    knots = np.radians(np.linspace(0.0, 80.0, tab.N_BODY))
    ref = quad(lambda t: np.interp(t, knots, g) * 2.0 * math.cos(t) * math.sin(t), 0.0, 0.5 * math.pi,
               points=knots[1:])[0]
    np.testing.assert_allclose(table.albedo(np.array([[0.0, 0.0, 1.0]]), q)[0], q["diffuse_reflectance"] * ref,
                               atol=QUADRATURE_ERROR)
    with pytest.raises(ValueError, match="body"):
        gm.get("tabulated", body="oren-nayar")
    with pytest.raises(Exception, match="body_2"):
        table.validate({**p, "body_2": -0.5})


@pytest.mark.parametrize("body", ["lambert", "table"])
def test_albedo_of_a_narrow_lobe_with_a_wide_sheen(body):
    """The albedo quadrature places its lobe nodes for one width: a narrow main lobe (GGX 0.01)
    with a wide sheen (alpha 0.8) is within QUADRATURE_ERROR of the main lobe's albedo (sheen
    off) plus the sheen's alone, integrated here on a cosine-weighted grid (Gauss-Legendre
    in sin^2 theta_i, 192 nodes, times 256 azimuths; the sheen is smooth). Measured with the
    nodes of the main lobe for both: 0.023 off at theta_o = 70 deg, 0.05 near grazing."""
    m = gm.get("tabulated", body=body, sheen="ggx")
    lnd = tab.ndf_from_function(lambda t: ggx_ratio(t, 0.01))
    p = {f"ndf_{k}": math.exp(np.clip(lnd[k] - lnd[1], *tab.LN_D_BOUNDS)) for k in range(tab.FIRST_FREE, tab.N_KNOTS)}
    p.update({"diffuse_reflectance": [0.3, 0.2, 0.1], "sheen_alpha": 0.8,
              **{f"fresnel_{j}": 0.5 for j in range(tab.N_FRESNEL)},
              **{f"sheen_{j}": [0.2, 0.4, 0.7, 1.0][j] for j in range(4)}})
    p = m.validate(p)
    th = np.radians([0.0, 40.0, 70.0, 85.0])
    wo = np.stack([np.sin(th), 0.0 * th, np.cos(th)], 1)
    main = m.albedo(wo, {**p, **{f"sheen_{j}": 0.0 for j in range(4)}})
    x, w = np.polynomial.legendre.leggauss(192)
    u, wu = 0.5 * (x + 1.0), 0.25 * w                       # cos(theta_i) d(wi) = du dphi / 2
    phi = (np.arange(256) + 0.5) * (2.0 * math.pi / 256)
    U, PHI = np.meshgrid(u, phi, indexing="ij")
    wi = np.stack([np.sqrt(U) * np.cos(PHI), np.sqrt(U) * np.sin(PHI), np.sqrt(1.0 - U)], -1).reshape(-1, 3)
    weight = np.repeat(wu, phi.size) * (2.0 * math.pi / phi.size)
    alone = m.validate({**p, "diffuse_reflectance": 0.0, **{f"fresnel_{j}": 0.0 for j in range(tab.N_FRESNEL)}})
    sheen = np.array([weight @ m.eval(wi, np.broadcast_to(v, wi.shape), alone) for v in wo])
    a = m.albedo(wo, p)
    assert np.abs(a - (main + sheen)).max() <= QUADRATURE_ERROR, (a, main + sheen)


@pytest.mark.parametrize("body", ["lambert", "table"])
def test_compiled_kernel_with_sheen_at_float32(body):
    """The compiled kernel (``backend="drjit"``; the fit's resident evaluations) in float32 agrees
    with numpy on the same directions to the float32 contract (models_testutil.F32_RTOL, 2e-5),
    the sheen alone at its narrowest (alpha 0.05: the sharpest lobe it makes) and with a main
    lobe; float64 to 1e-10. Measured before: 5.6e-5 off near theta_h = 1 deg (u = a^2 cos^2 +
    1 - cos^2 in float32)."""
    from gonio.models.engine import fast as _fast
    from models_testutil import assert_float32_agrees

    if not _fast.available():
        pytest.skip("Dr.Jit's LLVM backend is not available here")
    m = gm.get("tabulated", body=body, sheen="ggx")
    rng = np.random.default_rng(33)
    wi, wo = random_hemisphere(rng, 50001, np.float32), random_hemisphere(rng, 50001, np.float32)
    near = wo[:20000] * np.float32(0.02) + np.stack([-wi[:20000, 0], -wi[:20000, 1], wi[:20000, 2]], 1)
    wo[:20000] = near / np.linalg.norm(near, axis=1, keepdims=True)     # near the mirror direction
    for alone in (True, False):
        p = realistic_params(m, rng)
        p["sheen_alpha"] = tab.tabulated_sheen.ALPHA_BOUNDS[0]
        if alone:
            p.update({"diffuse_reflectance": 0.0, **{f"fresnel_{j}": 0.0 for j in range(tab.N_FRESNEL)}})
        p = m.validate(p)
        ref = m.eval(wi.astype(np.float64), wo.astype(np.float64), p, backend="numpy")
        assert_float32_agrees(m.eval(wi, wo, p, backend="drjit"), ref, wi)
        np.testing.assert_allclose(m.eval(wi.astype(np.float64), wo.astype(np.float64), p, backend="drjit"), ref,
                                   rtol=1e-10, atol=0)


def test_sheen_albedo_bounded_by_its_largest_amplitude():
    """The sheen alone (rho, F 0): a normalised GGX D with its own Smith G1 per direction, so its
    albedo is at most max A_c (tabulated_sheen's docstring) up to the quadrature error, from
    its narrowest (alpha 0.05: 0.997 of A at normal view, measured) to its widest."""
    m = gm.get("tabulated", sheen="ggx")
    th = np.radians([0.0, 30.0, 60.0, 80.0, 89.0])
    wo = np.stack([np.sin(th), 0.0 * th, np.cos(th)], 1)
    off = {"diffuse_reflectance": 0.0, **{f"fresnel_{j}": 0.0 for j in range(tab.N_FRESNEL)}}
    for alpha in (0.05, 0.2, 1.0):
        p = m.validate({**off, "sheen_alpha": alpha, **{f"sheen_{j}": [1.0, 0.5, 0.25] for j in range(4)}})
        a = m.albedo(wo, p)
        assert np.all(a <= np.array([1.0, 0.5, 0.25]) + QUADRATURE_ERROR), (alpha, a)
        assert a[0, 0] > (0.99 if alpha == 0.05 else 0.25), (alpha, a)


def test_start_replaces_defaults_and_is_validated():
    m0 = gm.get("tabulated")
    p = realistic_params(m0, np.random.default_rng(0))
    m = tab.Tabulated(start=p)
    d = m.defaults()
    assert all(np.array_equal(d[k], p[k]) for k in p)
    with pytest.raises(ValueError, match="ndf_3"):
        tab.Tabulated(start={**p, "ndf_3": 1e3})


# -- Mitsuba ------------------------------------------------------------------------------


mi = pytest.importorskip("mitsuba")


@pytest.mark.parametrize("body", BODIES, ids=BODY_IDS)
def test_mitsuba_eval_matches_at_float32(body):
    """gonio_tabulated's bsdf.eval equals the model at 1e-5 relative plus the float32
    allowance of tests/models/test_mitsuba_agreement.py (same comparison, 4 realistic
    parameter sets x 2e4 pairs; with the sheen, one of them the sheen alone at alpha 0.05,
    where sin^2 theta_h as 1 - cos^2 in float32 was 5e-5 off). On box-uniform tables (knot-to-knot jumps of e^20) Mitsuba's
    float32 atan2 of theta_h exceeds that allowance by ~2e-5 relative (measured): the
    steepness amplifies its few-ulp error."""
    sys.path.insert(0, str(Path(__file__).parent))
    import test_mitsuba_agreement as agreement

    m = gm.get("tabulated", **body)
    rng = np.random.default_rng(16)
    from gonio.models.mitsuba import eval_cos, mitsuba_variant

    mitsuba_variant()
    worst = -np.inf
    for k in range(4):
        p = realistic_params(m, rng)
        if m.options["sheen"] == "ggx" and k == 0:      # the sheen alone at its narrowest
            p.update({"sheen_alpha": tab.tabulated_sheen.ALPHA_BOUNDS[0], "diffuse_reflectance": 0.0,
                      **{f"fresnel_{j}": 0.0 for j in range(tab.N_FRESNEL)}})
        p = m.validate(agreement.as_float32(p))
        wi = random_hemisphere(rng, 20000, np.float32).astype(np.float64)
        wo = random_hemisphere(rng, 20000, np.float32).astype(np.float64)
        bsdf = mi.load_dict(m.to_mitsuba(p))
        ref = eval_cos(bsdf, wi, wo)
        ours = m.eval_reference(wi, wo, p) * wi[:, 2:3]
        mask = ref > agreement.THRESH
        rel = np.where(mask, np.abs(ours - ref) / np.where(mask, ref, 1.0), 0.0)
        bad = (rel > 1e-5).any(axis=1)
        if bad.any():
            noise = agreement.float32_noise(m, p, wi[bad], wo[bad], rng)
            noise_mi = agreement.mitsuba_float32_noise(bsdf, wi[bad], wo[bad], ref[bad], rng)
            worst = max(worst, float((rel[bad] - 1e-5 - agreement.K_NOISE * (noise + noise_mi)).max()))
    assert worst <= 0.0, worst


@pytest.mark.parametrize("body", BODIES, ids=BODY_IDS)
def test_mitsuba_sampling_is_unbiased(body):
    """E[bsdf.sample's weight] = the directional albedo (the sampling's pdf is the density it
    draws from): 2e5 samples per view, |z| < 4.5 per channel and view (false alarm 7e-6 each,
    9 checks: 6e-5 in all)."""
    from gonio.models.mitsuba import mitsuba_variant

    mitsuba_variant()
    m = gm.get("tabulated", **body)
    rng = np.random.default_rng(21)
    p = realistic_params(m, rng)
    p["diffuse_reflectance"] = np.array([0.05, 0.1, 0.02])
    bsdf = mi.load_dict(m.to_mitsuba(p))
    n = 200_000
    for th in (0.2, 0.8, 1.3):
        wo, w = _sample_weights(bsdf, th, n, rng)
        z = (w.mean(axis=1) - m.albedo(wo[:1], p, tol=1e-5)[0]) / (w.std(axis=1) / math.sqrt(n))
        assert np.all(np.abs(z) < 4.5), (th, z)


def _sample_weights(bsdf, th, n, rng):
    """``n`` of bsdf.sample's weights (3, n) at the view theta_o = ``th`` (rad, phi 0), and that view."""
    from gonio.models.mitsuba import interaction

    wo = np.tile([math.sin(th), 0.0, math.cos(th)], (n, 1))
    si, _ = interaction(wo, wo)
    _, w = bsdf.sample(mi.BSDFContext(), si, mi.Float(rng.random(n).astype(np.float32)),
                       mi.Point2f(rng.random((2, n)).astype(np.float32)))
    return wo, np.asarray(w, dtype=np.float64).reshape(3, n)


def test_mitsuba_sampling_draws_a_narrow_sheen_itself():
    """A narrow sheen (alpha 0.1, amplitude 0.5, a faint main lobe and body) is sampled through
    its own GGX normals, not only through the cosine-weighted part: bsdf.sample's weights are
    unbiased (|z| < 4.5 per view, false alarm 7e-6 each) and their relative spread is below 1
    at 30, 60 and 80 deg (measured 0.55 / 0.63 / 0.89; with the cosine part alone, as before
    the sheen had a part of its own, 1.55 / 1.82 / 1.96: 5-8x the variance)."""
    from gonio.models.mitsuba import mitsuba_variant

    mitsuba_variant()
    m = gm.get("tabulated", sheen="ggx")
    p = m.defaults()
    p["diffuse_reflectance"] = np.full(3, 0.05)
    p.update({f"fresnel_{j}": np.full(3, 0.02) for j in range(tab.N_FRESNEL)})
    p.update({"sheen_alpha": 0.1, **{f"sheen_{j}": np.full(3, 0.5) for j in range(4)}})
    bsdf = mi.load_dict(m.to_mitsuba(m.validate(p)))
    rng = np.random.default_rng(1)
    n = 200_000
    for th in (0.5, 1.05, 1.4):
        wo, w = _sample_weights(bsdf, th, n, rng)
        w = w[1]
        a = m.albedo(wo[:1], p, tol=1e-5)[0][1]
        assert abs(w.mean() - a) < 4.5 * w.std() / math.sqrt(n), (th, w.mean(), a)
        assert w.std() / w.mean() < 1.0, (th, w.std() / w.mean())


@pytest.mark.parametrize("body", BODIES, ids=BODY_IDS)
@pytest.mark.parametrize("seed", [0, 1])
def test_host_jacobian_matches_central_differences(seed, body):
    """``jacobian_reference``, the exact derivatives the fit uses instead of differencing 42
    columns, against central differences of the numpy reference (step 1e-6 relative: truncation
    error ~1e-12, rounding ~1e-10 of the column's scale) at realistic parameters, with a third
    of the pairs near the specular peak. A column may differ only at pairs whose table segment
    the step crosses (a kink of the piecewise-linear tables): at most 1 in 1000 pairs."""
    rng = np.random.default_rng(seed)
    model = gm.get("tabulated", **body)
    p = realistic_params(model, rng)
    n = 1200
    wi, wo = random_hemisphere(rng, n), random_hemisphere(rng, n)
    near = np.c_[-wi[:400, :2], wi[:400, 2:]] + rng.normal(0.0, 0.05, (400, 3))
    wo[:400] = near / np.linalg.norm(near, axis=1, keepdims=True)
    wo[:400, 2] = np.abs(wo[:400, 2])
    f, J = model.jacobian_reference(wi, wo, p)
    np.testing.assert_allclose(f, model.eval_reference(wi, wo, p), rtol=1e-13, atol=0.0)
    assert set(J) == {q.name for q in model.parameters}
    for q in model.parameters:
        v = np.atleast_1d(np.asarray(p[q.name], dtype=float))
        for c in (range(3) if q.per_channel else [None]):
            h = 1e-6 * abs(v[0 if c is None else c])
            up, dn = v.copy(), v.copy()
            up[slice(None) if c is None else c] += h
            dn[slice(None) if c is None else c] -= h
            shape = (lambda a: a) if q.per_channel else (lambda a: float(a[0]))
            fd = (model.eval_reference(wi, wo, {**p, q.name: shape(up)})
                  - model.eval_reference(wi, wo, {**p, q.name: shape(dn)})) / (2.0 * h)
            col = J[q.name] if c is None else np.where(np.arange(3) == c, J[q.name], 0.0)
            scale = np.max(np.abs(fd)) + 1e-300
            off = np.abs(col - fd) > 1e-5 * scale
            assert off.mean() <= 1e-3, (q.name, c, off.mean())


@pytest.mark.parametrize("body", BODIES, ids=BODY_IDS)
@pytest.mark.parametrize("seed", [0, 1])
def test_chain_rule_jacobian_matches_reference(seed, body):
    """``jacobian_host`` (the chain rule through the tables, what the fit calls) against the
    dense ``jacobian_reference``: the same derivatives summed in another order, so they agree
    to rounding (4e-16 of each column's largest value measured; bound 1e-10), on random pairs,
    pairs near the peak and degenerate ones (wo = -wi, below the horizon, grazing, normal, not
    finite: f = 0 and J = 0 there, as ``eval``)."""
    rng = np.random.default_rng(seed)
    model = gm.get("tabulated", **body)
    p = realistic_params(model, rng)
    n = 900
    wi, wo = random_hemisphere(rng, n), random_hemisphere(rng, n)
    near = np.c_[-wi[:300, :2], wi[:300, 2:]] + rng.normal(0.0, 0.05, (300, 3))
    wo[:300] = near / np.linalg.norm(near, axis=1, keepdims=True)
    wo[:300, 2] = np.abs(wo[:300, 2])
    wo[300] = -wi[300]                                   # zero half vector
    wi[301, 2] = -wi[301, 2]                             # below the horizon
    wi[302], wo[302] = (1.0, 0.0, 0.0), (0.0, 1.0, 0.0)  # grazing
    wi[303] = wo[303] = (0.0, 0.0, 1.0)                  # normal, exact specular
    wi[304, 0], wo[305, 2] = np.nan, np.inf              # not finite: 0, as eval
    f0, J0 = model.jacobian_reference(wi, wo, p)
    f1, J1 = model.jacobian_host(wi, wo, p)
    assert np.array_equal(f1, f0)
    assert set(J1) == set(J0) == {q.name for q in model.parameters}
    for name in J0:
        assert J1[name].shape == J0[name].shape == (n, 3)
        assert np.all(np.isfinite(J1[name])), name
        scale = np.max(np.abs(J0[name])) + 1e-300
        assert np.max(np.abs(J1[name] - J0[name])) <= 1e-10 * scale, name
        assert not np.any(J1[name][304:306]), name
    assert not np.any(f1[304:306])
    np.testing.assert_allclose(f1, model.eval_reference(wi, wo, p), rtol=1e-13, atol=0.0)


@pytest.mark.parametrize("body", BODIES, ids=BODY_IDS)
def test_chain_rule_jacobian_reuses_its_direction_parts(body, monkeypatch):
    """A fit asks for ``jacobian_host`` at the same directions every iteration: what depends on
    the directions alone is computed once (counted), and the results are the same, bit for bit,
    as with it computed afresh; directions changed in place (the same array, other values) are
    computed again."""
    import gonio.models.catalogue.flake_memo as flake_memo
    import gonio.models.catalogue.tabulated_jacobian as tj

    rng = np.random.default_rng(4)
    model = gm.get("tabulated", **body)
    wi, wo = random_hemisphere(rng, 700), random_hemisphere(rng, 700)
    p, q = realistic_params(model, rng), realistic_params(model, rng)
    calls, real = [], tj._pair_parts
    monkeypatch.setattr(tj, "_pair_parts", lambda *a: calls.append(1) or real(*a))
    monkeypatch.setattr(flake_memo, "_geometries", [])
    first = [model.jacobian_host(wi, wo, x) for x in (p, q, p)]
    assert len(calls) == 1
    monkeypatch.setattr(flake_memo, "_geometries", [])      # forgotten: computed afresh
    for x, (f0, J0) in zip((p, q, p), first):
        f1, J1 = model.jacobian_host(wi, wo, x)
        assert np.array_equal(f1, f0) and all(np.array_equal(J1[k], J0[k]) for k in J0)
    assert len(calls) == 2
    wo[:, :2] *= 0.5
    wo /= np.linalg.norm(wo, axis=1, keepdims=True)
    f2, _ = model.jacobian_host(wi, wo, p)
    assert len(calls) == 3 and np.array_equal(f2, model.jacobian_reference(wi, wo, p)[0])
