"""Model ``roughdielectric``: a rough interface between two dielectrics (Walter et al. 2007),
reflection and transmission, as Mitsuba 3's ``roughdielectric`` evaluates it in radiance mode.

Convention: ``wi`` points to the light, ``wo`` to the detector (camera); the light is on the
lit face (+z, the exterior, index 1), ``wo`` on either side. ``int_ior`` is the relative index
eta = n_interior / n_exterior (eta < 1: the light is in the denser medium). The eta^2 of
radiance transport sits in the transmitted f: f_t carries n_o^2 of the detector's medium
(Walter's eq. 21), so f(wi -> wo) / n_o^2 = f(wo -> wi) / n_i^2 and the integral of
f |cos theta_o| over wo is the power reflected plus transmitted, <= 1.
Mitsuba's ``si.wi`` is gonio's ``wo``; its radiance-mode factor 1/eta_camera^2 times its
eta_camera^2 leaves the form below. numpy reference only (no compiled kernel: ``eval`` uses
the reference at every size); the fitter's albedo constraint covers the reflected side.
"""

# References
# B. Walter, S. R. Marschner, H. Li, K. E. Torrance, "Microfacet Models for Refraction through
#   Rough Surfaces", EGSR 2007: generalized half vector eq. (16), BRDF eq. (20), BTDF eq. (21).
# E. Veach, "Robust Monte Carlo Methods for Light Transport Simulation", PhD thesis, Stanford
#   1997, ch. 5 (non-symmetric scattering, generalized reciprocity f/eta_o^2 eq. 5.15).

from __future__ import annotations

import numpy as np

from gonio.core.channels import CHANNELS
from gonio.core.sides import Side
from gonio.models.base import Model, Parameter, register, weighted_sample
from gonio.models.physics.fresnel import fresnel_dielectric
from gonio.models.physics.microfacet import MicrofacetDistribution, smith_g1_xyz
from gonio.models.structure import Structure

__all__ = ["RoughDielectric", "BOTH_SIDES", "rough_dielectric_f", "reflectance_transmittance", "facet_nodes",
           "facet_refract"]

#: Reflection and transmission: what the dielectric models scatter into.
BOTH_SIDES = (Side.REFLECT, Side.TRANSMIT)
#: data_start's grid: roughnesses, and indices beside the ones the brightest transmitted values give
START_ALPHAS = np.geomspace(0.005, 0.8, 15)
START_IORS = np.geomspace(0.3, 3.5, 24)
#: data_start: the transmitted values whose Snell index joins the grid (the brightest)
START_PEAKS = 6


def rough_dielectric_f(kind, alpha, eta, wi, wo):
    """f(wi -> wo) of a rough dielectric interface in radiance mode, (N,), sr^-1.

    Parameters
    ----------
    kind : {"beckmann", "ggx"}
    alpha : float
        Roughness (GGX alpha / Beckmann RMS slope), floored at 1e-4.
    eta : float
        n(-z side) / n(+z side).
    wi, wo : ndarray, shape (N, 3)
        Toward the light and toward the detector, either hemisphere each.

    Notes
    -----
    With e the index across the interface from the detector relative to the detector's side
    (eta if ``wo`` is on +z, 1/eta otherwise), the microfacet normal is
    wm = +-normalize(wo + e wi) in transmission (wo + wi in reflection), F = F(wo . wm), and

    .. math:: f_r = \\frac{F D G}{4 |\\cos\\theta_i \\cos\\theta_o|},\\qquad
              f_t = \\frac{(1 - F) D G\\, |w_i\\cdot w_m|\\,|w_o\\cdot w_m|}
                         {|\\cos\\theta_i \\cos\\theta_o|\\,(w_o\\cdot w_m + e\\, w_i\\cdot w_m)^2}

    (Walter et al. 2007 eqs. 20-21 with n_o^2 / (n_o o.m + n_i i.m)^2 = 1 / (o.m + e i.m)^2).
    Degenerate geometry (a direction in the surface plane, a zero half vector) gives 0.
    """
    with np.errstate(all="ignore"):
        return _f(kind, alpha, eta, wi, wo)


def _f(kind, alpha, eta, wi, wo):
    ci, co = wi[:, 2], wo[:, 2]
    reflect = ci * co > 0.0
    e = np.where(co > 0.0, eta, 1.0 / eta)
    m = wo + wi * np.where(reflect, 1.0, e)[:, None]
    norm = np.linalg.norm(m, axis=1)
    ok = (norm > 0.0) & (ci != 0.0) & (co != 0.0)
    m = m / np.where(ok, norm, 1.0)[:, None]
    m = m * np.where(m[:, 2] < 0.0, -1.0, 1.0)[:, None]
    dist = MicrofacetDistribution(kind, alpha)
    a = dist.alpha_u
    di = np.einsum("ij,ij->i", wi, m)
    do = np.einsum("ij,ij->i", wo, m)
    D = dist.D(m)
    G = smith_g1_xyz(kind, a, a, wi[:, 0], wi[:, 1], ci, di) * smith_g1_xyz(kind, a, a, wo[:, 0], wo[:, 1], co, do)
    F = fresnel_dielectric(do, eta)[0]
    cc = np.abs(ci * co)
    cc = np.where(ok, cc, 1.0)
    f_r = F * D * G / (4.0 * cc)
    den = do + e * di
    den2 = np.where(den != 0.0, den * den, 1.0)
    f_t = (1.0 - F) * D * G * np.abs(di * do) / (cc * den2)
    f = np.where(reflect, f_r, np.where(den != 0.0, f_t, 0.0))
    return np.where(ok & np.isfinite(f), f, 0.0)


@register
class RoughDielectric(Model):
    """Rough dielectric BSDF (Mitsuba 3 ``roughdielectric``, radiance mode).

    Options
    -------
    distribution : {"beckmann", "ggx"}
        Microfacet distribution (default "beckmann", Mitsuba's default).

    Parameters (``params`` keys)
    ----------------------------
    alpha : float
        Roughness (GGX alpha / Beckmann RMS slope), in [1e-4, 1].
    int_ior : float
        Relative index eta = n_interior / n_exterior, in [0.25, 4]; eta == 1 is finite
        (no reflection, a lobe around straight through) but has no Mitsuba twin.

    Notes
    -----
    See :func:`rough_dielectric_f` and the module docstring (which direction is which, where
    the eta^2 goes). The exterior index is 1 (``to_mitsuba`` writes ``ext_ior = 1``): f depends
    on the ratio only, so a second index would be a parameter no data can fix. Single
    scattering: R + T < 1, the missing part grows with alpha (Walter et al. 2007, sec. 5).
    """

    name = "roughdielectric"
    auto_candidate = False   # selection offers it for data with transmitted points, not for a BRDF
    OPTIONS = {"distribution": ("beckmann", "ggx")}
    energy_conserving = True

    @property
    def structure(self):
        return Structure(sides=BOTH_SIDES)

    def _parameters(self):
        return (
            Parameter("alpha", 0.1, 1e-4, 1.0, "1", "roughness (GGX alpha or Beckmann RMS slope)"),
            Parameter("int_ior", 1.5, 0.25, 4.0, "1", "relative index of refraction n_interior / n_exterior"),
        )

    def data_start(self, meas, fixed=None):
        """A start read from the data (:func:`gonio.fitting.optimise.mle.fit` asks) where it holds
        transmitted values (``wo`` below the surface; None otherwise, and the global stage
        starts the fit): the (alpha, int_ior) of least chi2 (each value over its sigma, at most
        3000 samples, evenly picked) on a grid of :data:`START_ALPHAS` and of
        :data:`START_IORS` with the index that puts each of the :data:`START_PEAKS` brightest
        transmitted pairs' refraction half-vector on the normal (wi_xy + eta wo_xy = 0: Snell's
        law; Walter et al. 2007 eq. 16). A narrow transmitted lobe is a needle in (alpha, eta):
        the stratified starts missed it on half the seeds of an anti-glare film (alpha 0.06).
        ``fixed``: the fit's held parameters; a held alpha or int_ior is the grid's only value."""
        wi, wo, y, w, use = weighted_sample(meas)
        through = (wo[:, 2] < 0.0) & use.any(axis=1)
        if np.count_nonzero(through) < 3:
            return None
        bright = np.where(through, np.where(use, y / np.where(use, w, 1.0), 0.0).max(axis=1), -np.inf)
        top = np.argsort(-bright)[:START_PEAKS]
        top = top[np.isfinite(bright[top])]
        oxy, ixy = wo[top, :2], wi[top, :2]
        den = np.sum(oxy * oxy, axis=1)
        snell = -np.sum(ixy * oxy, axis=1) / np.where(den > 1e-6, den, np.nan)
        lo, hi = next((q.lower, q.upper) for q in self.parameters if q.name == "int_ior")
        etas = np.concatenate([START_IORS, snell[np.isfinite(snell) & (snell >= lo) & (snell <= hi) & (snell != 1.0)]])
        alphas = START_ALPHAS
        fixed = dict(fixed or {})
        if "int_ior" in fixed:
            etas = np.array([float(fixed["int_ior"])])
        if "alpha" in fixed:
            alphas = np.array([float(fixed["alpha"])])
        best, start = np.inf, None
        for a in alphas:
            for e in etas:
                with np.errstate(all="ignore"):
                    g = rough_dielectric_f(self.options["distribution"], a, e, wi, wo)[:, None]
                cost = float(np.sum((g * w - y) ** 2))
                if np.isfinite(cost) and cost < best:
                    best, start = cost, {"alpha": float(a), "int_ior": float(e)}
        return start

    def _eval(self, wi, wo, p):
        f = rough_dielectric_f(self.options["distribution"], p["alpha"], p["int_ior"], wi, wo)
        return np.repeat(f[:, None], CHANNELS, axis=1)

    def _eval_parts(self, wi, wo, p):
        return np.zeros((wi.shape[0], CHANNELS)), self._eval(wi, wo, p)

    def to_mitsuba(self, params):
        p = self.validate(params)
        if p["int_ior"] == 1.0:
            raise ValueError("roughdielectric: Mitsuba needs int_ior != 1 (an interface that is there)")
        return {
            "type": "roughdielectric",
            "distribution": self.options["distribution"],
            "alpha": p["alpha"],
            "int_ior": p["int_ior"],
            "ext_ior": 1.0,
        }


def facet_nodes(alpha, n_theta=128, n_phi=128):
    """``(a, m, dm)``: alpha floored at 1e-4 and the microfacet normals (n_theta n_phi, 3) with
    their solid-angle weights of :func:`reflectance_transmittance`'s quadrature: tan(theta_m) =
    a tan(pi v / 2), v on Gauss-Legendre nodes, phi_m on midpoints."""
    a = max(float(alpha), 1e-4)
    x, w = np.polynomial.legendre.leggauss(n_theta)
    v = 0.5 * (x + 1.0)
    s = np.tan(0.5 * np.pi * v)
    theta = np.arctan(a * s)
    dtheta = 0.5 * w * a * 0.5 * np.pi / np.cos(0.5 * np.pi * v) ** 2 / (1.0 + (a * s) ** 2)
    phi = (np.arange(n_phi) + 0.5) * (2.0 * np.pi / n_phi)
    T_, P_ = np.meshgrid(theta, phi, indexing="ij")
    m = np.stack([np.sin(T_) * np.cos(P_), np.sin(T_) * np.sin(P_), np.cos(T_)], axis=-1).reshape(-1, 3)
    dm = (np.sin(theta) * dtheta)[:, None].repeat(n_phi, axis=1).reshape(-1) * (2.0 * np.pi / n_phi)
    return a, m, dm


def facet_refract(w_i, m, c, eta):
    """``(wt, ok)``: ``w_i`` refracted into the medium (relative index ``eta``) through each facet
    normal ``m`` with c = m . w_i, and where it is (visible, no total internal reflection)."""
    k2 = 1.0 - (1.0 - c * c) / (eta * eta)
    ok = (c > 0.0) & (k2 > 0.0)
    return -w_i / eta + m * (c / eta - np.sqrt(np.where(ok, k2, 0.0)))[:, None], ok


def reflectance_transmittance(kind, alpha, eta, wi, n_theta=128, n_phi=128):
    """Directional reflectance and transmittance of :func:`rough_dielectric_f` for light from
    ``wi`` (upper hemisphere): R, T = integral of f |cos theta_o| over each side, (N,) each.

    The integral runs over microfacet normals wm, where the integrand is smooth whatever
    alpha and the incidence: wo = reflect(wi, wm) with d(wo) = 4 |wo . wm| d(wm), and
    wo = refract(wi, wm) with d(wo) = (wi . wm + eta wo . wm)^2 / (eta^2 |wo . wm|) d(wm)
    (Walter et al. 2007 eqs. 14, 17); tan(theta_m) = alpha tan(pi v / 2) with v on
    ``n_theta`` Gauss-Legendre nodes, ``n_phi`` midpoints in phi_m. f itself is evaluated at
    each wo, so the sums test the model, not a second formula. R + T = 1 - (the energy single
    scattering loses), -> 1 as alpha -> 0.
    """
    wi = np.atleast_2d(np.asarray(wi, dtype=np.float64))
    a, m, dm = facet_nodes(alpha, n_theta, n_phi)
    R, T = np.zeros(len(wi)), np.zeros(len(wi))
    with np.errstate(all="ignore"):
        for k, w_i in enumerate(wi):
            c = m @ w_i
            vis = c > 0.0
            wr = 2.0 * c[:, None] * m - w_i
            do = np.einsum("ij,ij->i", wr, m)
            fr = rough_dielectric_f(kind, a, eta, np.broadcast_to(w_i, m.shape), wr)
            R[k] = np.sum(np.where(vis & (wr[:, 2] > 0.0), fr * np.abs(wr[:, 2]) * 4.0 * np.abs(do) * dm, 0.0))
            wt, ok = facet_refract(w_i, m, c, eta)
            dt = np.einsum("ij,ij->i", wt, m)
            ft = rough_dielectric_f(kind, a, eta, np.broadcast_to(w_i, m.shape), wt)
            jac = (c + eta * dt) ** 2 / (eta * eta * np.abs(dt))
            T[k] = np.sum(np.where(ok & (wt[:, 2] < 0.0) & (dt != 0.0), ft * np.abs(wt[:, 2]) * jac * dm, 0.0))
    return R, T
