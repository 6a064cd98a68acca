"""Model ``cooktorrance``: Lambert + Cook-Torrance lobe in the form fitted by Ngan,
Durand & Matusik (2005), so fitted values compare with the published ones."""

from __future__ import annotations

import math

import numpy as np

from gonio.models.base import CHANNELS, Model, Parameter, register
from gonio.models.engine.jit import _floor, channels
from gonio.models.structure import Structure
from gonio.models.physics.fresnel import fresnel_schlick
from gonio.core.geometry import half_vector
from gonio.models.physics.microfacet import MicrofacetDistribution

__all__ = ["CookTorrance", "cook_torrance_lobe"]


def cook_torrance_lobe(wi, wo, m, f0):
    """Cook-Torrance specular lobe (without rho_s), sr^-1, shape (N, C).

    Parameters
    ----------
    wi, wo : ndarray, shape (N, 3)
        Toward light, toward detector (local frame).
    m : float
        Beckmann RMS slope (radians of slope, dimensionless).
    f0 : array_like, shape (C,)
        Schlick normal-incidence reflectance.

    Notes
    -----
    .. math:: f_s = \\frac{F(w_o\\cdot w_h)\\,D(\\theta_h)\\,G}{\\pi\\cos\\theta_i\\cos\\theta_o},\\quad
              D = \\frac{\\exp(-\\tan^2\\theta_h / m^2)}{m^2\\cos^4\\theta_h},\\quad
              G = \\min\\left(1, \\frac{2\\cos\\theta_h\\cos\\theta_o}{w_o\\cdot w_h},
                               \\frac{2\\cos\\theta_h\\cos\\theta_i}{w_o\\cdot w_h}\\right)

    Cook & Torrance 1982 eqs. (for R_s, D and G; note D without 1/pi and pi in the
    denominator), Schlick 1994 for F, as in Ngan, Durand & Matusik 2005. Reciprocal.
    """
    ci, co = wi[:, 2], wo[:, 2]
    wh, valid = half_vector(wi, wo)
    ch = wh[:, 2]
    vh = 0.5 * (np.einsum("ij,ij->i", wo, wh) + np.einsum("ij,ij->i", wi, wh))
    ch2 = ch * ch
    up = valid & (ch > 0.0) & (vh > 0.0) & (ci > 0.0) & (co > 0.0)
    ch2s = np.where(up, ch2, 1.0)
    m2 = m * m
    # tan^2 from the tangential components: no cancellation in 1 - cos^2 near the normal
    tan2 = (wh[:, 0] ** 2 + wh[:, 1] ** 2) / ch2s
    D = np.exp(-tan2 / m2) / (m2 * ch2s * ch2s)
    vhs = np.where(up, vh, 1.0)
    G = np.minimum(1.0, 2.0 * ch * np.minimum(ci, co) / vhs)
    den = math.pi * np.where(up, ci * co, 1.0)
    s = np.where(up, D * G / den, 0.0)
    return fresnel_schlick(vh[:, None], f0) * s[:, None]


@register
class CookTorrance(Model):
    """Lambertian + Cook-Torrance lobe (Ngan, Durand & Matusik 2005 form).

    Parameters (``params`` keys)
    ----------------------------
    diffuse_reflectance : (3,)
        rho_d, Lambertian albedo in [0, 1].
    specular_reflectance : (3,)
        rho_s, lobe weight in [0, 1].
    roughness : float
        Beckmann RMS slope m in [1e-3, 1].
    f0 : (3,)
        Schlick normal-incidence Fresnel reflectance in [0, 1].

    Notes
    -----
    ``f_r = rho_d / pi + rho_s f_s`` with ``f_s`` from :func:`cook_torrance_lobe`.

    Not energy-conserving: the lobe albedo a_s(wo) = integral of f_s cos(theta_i) is
    about 4 F (the 1/pi vs 1/4 normalisation of Cook-Torrance) at small m and normal
    view, and it grows toward grazing views, so ``rho_d + rho_s a_s`` can exceed 1
    (e.g. rho_s = 1, f0 = 1 gives an albedo near 4 at normal view). Rendering it in
    Mitsuba uses a registered Python BSDF (``gonio_cooktorrance``).

    References
    ----------
    .. [1] R. L. Cook and K. E. Torrance, "A Reflectance Model for Computer Graphics",
           ACM TOG 1(1), 7-24 (1982).
    .. [2] A. Ngan, F. Durand, W. Matusik, "Experimental Analysis of BRDF Models",
           EGSR 2005 (Cook-Torrance fits to the MERL data).
    """

    name = "cooktorrance"
    lambert_smooth = "diffuse_reflectance"   # albedo: smooth part rho_d, the lobe on the compiled kernel

    @property
    def structure(self):
        return Structure(kernel=_jit_kernel, geometry=_jit_geometry, body=_jit_body)
    OPTIONS = {}
    energy_conserving = False

    def _parameters(self):
        return (
            Parameter("diffuse_reflectance", 0.5, 0.0, 1.0, "1", "Lambertian albedo rho_d", per_channel=True),
            Parameter("specular_reflectance", 0.1, 0.0, 1.0, "1", "Cook-Torrance lobe weight rho_s", per_channel=True),
            Parameter("roughness", 0.2, 1e-3, 1.0, "1", "Beckmann RMS slope m"),
            Parameter("f0", 0.04, 0.0, 1.0, "1", "Schlick Fresnel reflectance at normal incidence", per_channel=True),
        )

    def _lobe_distribution(self, p):
        return MicrofacetDistribution("beckmann", p["roughness"])

    def _eval_parts(self, wi, wo, p):
        n = wi.shape[0]
        diffuse = np.broadcast_to(p["diffuse_reflectance"] / math.pi, (n, np.size(p["diffuse_reflectance"])))
        return diffuse, cook_torrance_lobe(wi, wo, p["roughness"], p["f0"]) * p["specular_reflectance"]

    def to_mitsuba(self, params):
        from gonio.models.mitsuba.plugins import ensure_registered, rgb_channels

        p = self.validate(params)
        d = {"type": ensure_registered("cooktorrance"), "roughness": p["roughness"]}
        for key in ("diffuse_reflectance", "specular_reflectance", "f0"):
            for c, v in rgb_channels(self.name, p[key]):
                d[f"{key}_{c}"] = float(v)
        return d


def _jit_geometry(model, dr, wi, wo):
    """The kernel's parameter-independent part, per pair: (tan^2(theta_m), the geometric
    factor sec^4(theta_m) G / (pi ci co), Schlick's (1 - cos)^5, the Lambertian 1 / pi),
    all 0 where the lobe (the first three) or the pair (the last) is below the horizon."""
    ci, co = wi.z, wo.z
    active = (ci > 0) & (co > 0)
    # Ngan et al. 2005: Beckmann D without pi, G = min(1, 2 cos_m min(cos_i, cos_o) / (wi . m)),
    # written with the unnormalised half vector h: cos_m = h_z / |h|, wi . m = (wi . h) / |h|
    h = wi + wo
    h2 = dr.squared_norm(h)
    hz = h.z
    dh = 0.5 * (dr.dot(wi, h) + dr.dot(wo, h))  # |h| (wi . m)
    up = active & (h2 > _floor(h2)) & (hz > 0) & (dh > 0)
    r_hz2 = 1.0 / dr.select(up, hz * hz, 1.0)
    tan2 = dr.select(up, (h.x * h.x + h.y * h.y) * r_hz2, 0.0)
    g_num = 2.0 * hz * dr.minimum(ci, co)
    g_den = dr.select(g_num < dh, dh, g_num)  # G = g_num / g_den = min(1, 2 hz min / dh)
    # D G / (pi ci co) = exp(-tan^2 / m^2) / m^2 * sec^4 G / (pi ci co), 1 / cos^2 = |h|^2 / hz^2
    # (ratios first: hz^4 ci co underflows float32 at grazing angles)
    sec2 = h2 * r_hz2
    geo = dr.select(up, sec2 * sec2 * g_num / (math.pi * g_den * dr.select(up, ci * co, 1.0)), 0.0)
    x = 1.0 - dr.clip(dh * dr.rsqrt(dr.select(up, h2, 1.0)), 0.0, 1.0)
    x2 = x * x
    lam = dr.select(active, 1.0 / math.pi + 0.0 * ci, 0.0)
    return tan2, geo, dr.select(up, x2 * x2 * x, 0.0), lam


def _jit_body(model, k, g, P, grad):
    """The kernel on :func:`_jit_geometry`'s quantities (value and derivatives by hand)."""
    dr = k.dr
    tan2, geo, x5, lam = g
    J = {}
    m = P["roughness"]
    rm2 = 1.0 / (m * m)
    e = tan2 * rm2  # tan^2(theta_m) / m^2
    s = dr.exp(-e) * geo * rm2
    rds, rss, f0s = (channels(P, k) for k in ("diffuse_reflectance", "specular_reflectance", "f0"))
    f = [rd * lam + rs * (f0 + (1.0 - f0) * x5) * s for rd, rs, f0 in zip(rds, rss, f0s)]
    if grad:
        ds = (2.0 * e - 2.0) * (1.0 / m) * s  # d ln s / dm = (2 e - 2) / m
        J["diffuse_reflectance"] = [lam] * CHANNELS
        J["specular_reflectance"] = [(f0 + (1.0 - f0) * x5) * s for f0 in f0s]
        J["roughness"] = [rs * (f0 + (1.0 - f0) * x5) * ds for rs, f0 in zip(rss, f0s)]
        J["f0"] = [rs * (1.0 - x5) * s for rs in rss]
    return f, J


def _jit_kernel(model, k, wi, wo, P, grad):
    """The compiled kernel: :func:`_jit_body` after :func:`_jit_geometry`, in one kernel."""
    return _jit_body(model, k, _jit_geometry(model, k.dr, wi, wo), P, grad)
