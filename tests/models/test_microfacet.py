"""Microfacet distributions: reference values, normalisation, Smith identities and a
chi^2 test of visible-normal sampling against its pdf."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from gonio.models import MicrofacetDistribution

KINDS = ["beckmann", "ggx"]
ALPHAS = [(0.05, 0.05), (0.3, 0.3), (1.0, 1.0), (0.1, 0.5), (0.6, 0.08)]


def slope_grid(alpha_u, alpha_v, n_u=200, n_phi=256):
    """Quadrature over microfacet normals: slope = alpha t (cos phi, sin phi) with
    t^2 = u / (1 - u) and u = 1 - (1 - v)^2 (removes the (1 - u)^-1/2 growth of
    slope-linear integrands), Gauss-Legendre in v, midpoint in phi. Returns wm (M, 3)
    and solid-angle weights (M,):
    d wm = cos^3 alpha_u alpha_v / (2 (1 - u)^2) du dphi, du = 2 (1 - v) dv."""
    x, w = np.polynomial.legendre.leggauss(n_u)
    v, wv = 0.5 * x + 0.5, 0.5 * w
    phi = (np.arange(n_phi) + 0.5) * 2 * math.pi / n_phi
    V, P = np.meshgrid(v, phi, indexing="ij")
    wm, jac = _slope_map(alpha_u, alpha_v, V, P)
    dw = (jac * wv[:, None] * (2 * math.pi / n_phi)).ravel()
    return wm.reshape(-1, 3), dw


def _slope_map(alpha_u, alpha_v, V, P):
    """wm(v, phi) and |d wm / (dv dphi)| for the map of :func:`slope_grid`."""
    U = 1 - (1 - V) ** 2
    t = np.sqrt(U) / (1 - V)
    sx, sy = alpha_u * t * np.cos(P), alpha_v * t * np.sin(P)
    inv = 1 / np.sqrt(1 + sx**2 + sy**2)
    wm = np.stack(np.broadcast_arrays(-sx * inv, -sy * inv, inv), -1)
    jac = inv**3 * alpha_u * alpha_v / (2 * (1 - U) ** 2) * 2 * (1 - V)
    return wm, jac


@pytest.mark.parametrize("kind", KINDS)
def test_D_at_normal(kind):
    # Walter et al. 2007 eqs. 25 and 33 at theta_m = 0: D = 1 / (pi alpha^2)
    for a in (1e-3, 0.1, 0.5, 1.0):
        d = MicrofacetDistribution(kind, a).D(np.array([[0.0, 0.0, 1.0]]))
        assert d[0] == pytest.approx(1 / (math.pi * a * a), rel=1e-14)
    d = MicrofacetDistribution(kind, 0.2, 0.5).D(np.array([[0.0, 0.0, 1.0]]))
    assert d[0] == pytest.approx(1 / (math.pi * 0.1), rel=1e-14)


def test_D_reference_off_normal():
    # Beckmann: exp(-tan^2 / a^2) / (pi a^2 cos^4); GGX: a^2 / (pi cos^4 (a^2 + tan^2)^2)
    th, a = math.radians(20.0), 0.3
    wm = np.array([[math.sin(th), 0.0, math.cos(th)]])
    t2, c4 = math.tan(th) ** 2, math.cos(th) ** 4
    assert MicrofacetDistribution("beckmann", a).D(wm)[0] == pytest.approx(
        math.exp(-t2 / a**2) / (math.pi * a**2 * c4), rel=1e-13
    )
    assert MicrofacetDistribution("ggx", a).D(wm)[0] == pytest.approx(a**2 / (math.pi * c4 * (a**2 + t2) ** 2), rel=1e-13)


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("au,av", ALPHAS)
def test_D_projected_area_normalised(kind, au, av):
    # integral of D(wm) cos(theta_m) d wm = 1 (Walter et al. 2007 eq. 4)
    d = MicrofacetDistribution(kind, au, av)
    wm, dw = slope_grid(au, av)
    assert np.sum(d.D(wm) * wm[:, 2] * dw) == pytest.approx(1.0, abs=2e-6)


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("au,av", ALPHAS)
def test_smith_projected_area_identity(kind, au, av):
    # integral of G1(w, wm) max(0, w.wm) D(wm) d wm = cos(theta) (Heitz 2014 eq. 7),
    # which holds for the exact Lambda only
    d = MicrofacetDistribution(kind, au, av)
    wm, dw = slope_grid(au, av, n_u=400, n_phi=512)
    for th, ph in [(0.0, 0.0), (0.6, 0.3), (1.2, 2.0), (1.5, -1.0)]:
        w = np.array([math.sin(th) * math.cos(ph), math.sin(th) * math.sin(ph), math.cos(th)])
        wb = np.broadcast_to(w, wm.shape)
        val = np.sum(d.G1(wb, wm, exact=True) * np.maximum(wm @ w, 0) * d.D(wm) * dw)
        assert val == pytest.approx(math.cos(th), abs=2e-5)


def test_beckmann_rational_G1_close_to_exact():
    # Walter et al. 2007 eq. 27: the rational fit is within 0.35 % of 1 / (1 + Lambda)
    d = MicrofacetDistribution("beckmann", 0.4)
    th = np.linspace(0.0, math.pi / 2 - 1e-4, 2000)
    w = np.stack([np.sin(th), 0 * th, np.cos(th)], 1)
    m = np.broadcast_to([0.0, 0.0, 1.0], w.shape)
    approx, exact = d.G1(w, m), d.G1(w, m, exact=True)
    rel = np.abs(approx - exact) / exact
    assert rel[exact > 1e-3].max() < 0.0035
    ggx = MicrofacetDistribution("ggx", 0.4)
    np.testing.assert_allclose(ggx.G1(w, m), ggx.G1(w, m, exact=True), rtol=1e-14)


def test_G1_lambda_reference():
    # GGX: Lambda = (-1 + sqrt(1 + a^2 tan^2)) / 2 (Heitz 2014 eq. 86); tan = 1, a = 1
    d = MicrofacetDistribution("ggx", 1.0)
    w = np.array([[math.sqrt(0.5), 0.0, math.sqrt(0.5)]])
    assert d.lambda_(w)[0] == pytest.approx((math.sqrt(2) - 1) / 2, rel=1e-14)
    # Beckmann with a = 1 / (alpha tan) = 1: Lambda = (erf(1) - 1) / 2 + exp(-1) / (2 sqrt(pi))
    b = MicrofacetDistribution("beckmann", 1.0)
    ref = (math.erf(1) - 1) / 2 + math.exp(-1) / (2 * math.sqrt(math.pi))
    assert b.lambda_(w)[0] == pytest.approx(ref, rel=1e-14)


@pytest.mark.parametrize("kind", KINDS)
def test_G_forms(kind):
    rng = np.random.default_rng(3)
    d = MicrofacetDistribution(kind, 0.2, 0.6)
    wi = rng.normal(size=(1000, 3))
    wi[:, 2] = np.abs(wi[:, 2])
    wi /= np.linalg.norm(wi, axis=1)[:, None]
    wo = rng.normal(size=(1000, 3))
    wo[:, 2] = np.abs(wo[:, 2])
    wo /= np.linalg.norm(wo, axis=1)[:, None]
    wm = wi + wo
    wm /= np.linalg.norm(wm, axis=1)[:, None]
    sep = d.G(wi, wo, wm, exact=True)
    hc = d.G(wi, wo, wm, form="height_correlated")
    # 1 / (1 + Li + Lo) >= 1 / ((1 + Li)(1 + Lo)), both symmetric, both in [0, 1]
    assert np.all(hc >= sep - 1e-15) and np.all((hc >= 0) & (hc <= 1))
    np.testing.assert_array_equal(d.G(wo, wi, wm), d.G(wi, wo, wm))
    # back-facing microfacet gives 0
    assert d.G1(np.array([[0.0, 0.0, 1.0]]), np.array([[0.0, 0.0, -1.0]]))[0] == 0.0


def _chi2_sampling(kind, au, av, wi, n=100_000, n_u=16, n_phi=16, seed=0, sampler=None):
    """p-value of the chi^2 test of ``sampler`` (default: the distribution's own
    sample_visible) against ``pdf_visible`` of (kind, au, av)."""
    d = MicrofacetDistribution(kind, au, av)
    rng = np.random.default_rng(seed)
    wm = (sampler or d).sample_visible(np.broadcast_to(wi, (n, 3)), rng.random((n, 2)))
    # bins in (v, phi) of the slope map of slope_grid: v = 1 - sqrt(1 - u),
    # u = t^2 / (1 + t^2), t = |slope| / alpha (alpha = sqrt(alpha_u alpha_v))
    ag = math.sqrt(au * av)
    t2 = (wm[:, 0] ** 2 + wm[:, 1] ** 2) / wm[:, 2] ** 2 / ag**2
    v = 1 - np.sqrt(1 / (1 + t2))
    phi = np.mod(np.arctan2(-wm[:, 1], -wm[:, 0]), 2 * math.pi)
    obs, _, _ = np.histogram2d(v, phi, bins=[n_u, n_phi], range=[[0, 1], [0, 2 * math.pi]])
    # expected counts: 8 x 8 Gauss-Legendre per bin of pdf(wm) |d wm / (dv dphi)|
    x, w = np.polynomial.legendre.leggauss(8)
    ve = (np.arange(n_u)[:, None] + 0.5 * x + 0.5) / n_u  # (n_u, 8)
    pe = (np.arange(n_phi)[:, None] + 0.5 * x + 0.5) * 2 * math.pi / n_phi
    m, jac = _slope_map(ag, ag, ve[:, None, :, None], pe[None, :, None, :])
    pdf = d.pdf_visible(np.broadcast_to(wi, (m.size // 3, 3)), m.reshape(-1, 3)).reshape(jac.shape)
    cell = (1 / n_u) * (2 * math.pi / n_phi) / 4
    exp = n * np.einsum("abij,i,j->ab", pdf * jac, w, w) * cell
    assert exp.sum() == pytest.approx(n, rel=2e-3)  # pdf integrates to 1
    # pool cells with expected count < 5 (pbrt-v4 bsdfs_test.cpp does the same)
    o, e = obs.ravel(), exp.ravel()
    order = np.argsort(e)
    o, e = o[order], e[order]
    small = e < 5
    o = np.concatenate([[o[small].sum()], o[~small]]) if small.any() else o
    e = np.concatenate([[e[small].sum()], e[~small]]) if small.any() else e
    keep = e > 0
    chi2 = np.sum((o[keep] - e[keep]) ** 2 / e[keep])
    return stats.chi2.sf(chi2, keep.sum() - 1)


CASES = [
    ("beckmann", 0.3, 0.3, 0.0),
    ("beckmann", 0.1, 0.4, 1.0),
    ("beckmann", 0.8, 0.8, 1.45),
    ("ggx", 0.3, 0.3, 0.0),
    ("ggx", 0.1, 0.4, 1.0),
    ("ggx", 0.8, 0.8, 1.45),
]


@pytest.mark.parametrize("kind,au,av,theta", CASES)
def test_visible_normal_sampling_chi2(kind, au, av, theta):
    """Samples of sample_visible follow pdf_visible (chi^2, Sidak-corrected 1 % level)."""
    wi = np.array([math.sin(theta) * math.cos(0.7), math.sin(theta) * math.sin(0.7), math.cos(theta)])
    p = _chi2_sampling(kind, au, av, wi)
    alpha = 1 - (1 - 0.01) ** (1 / len(CASES))
    assert p > alpha


def test_chi2_detects_a_wrong_pdf():
    """The chi^2 machinery rejects samples drawn with a 10 % different roughness."""
    wi = np.array([0.5, 0.0, math.sqrt(0.75)])
    assert _chi2_sampling("ggx", 0.3, 0.3, wi, sampler=MicrofacetDistribution("ggx", 0.33)) < 1e-6
    assert _chi2_sampling("beckmann", 0.3, 0.3, wi, sampler=MicrofacetDistribution("ggx", 0.3)) < 1e-6


def test_hostile_roughness():
    for bad in (0.0, -0.1, float("nan"), float("inf")):
        with pytest.raises(ValueError):
            MicrofacetDistribution("ggx", bad)
    with pytest.raises(ValueError):
        MicrofacetDistribution("phong", 0.1)
    assert MicrofacetDistribution("ggx", 1e-6).alpha_u == 1e-4  # floored like Mitsuba
