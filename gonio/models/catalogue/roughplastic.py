"""Model ``roughplastic``: Mitsuba 3's rough plastic (rough dielectric coating on a
diffuse base), reproduced term by term.

Convention for the exterior medium: gonio sets ``ext_ior = 1`` exactly, so the
parameter ``int_ior`` *is* the relative index eta of the coating; :meth:`to_mitsuba`
writes ``"ext_ior": 1.0`` explicitly (Mitsuba's default would be air, 1.000277, which
changes eta by 2.8e-4 and F by about 0.1 %).
"""

from __future__ import annotations

import math

import numpy as np

from gonio.models.engine import fast as _fast
from gonio.models.base import INV_PI, Model, Parameter, register, rgb
from gonio.models.physics.fresnel import fresnel_dielectric
from gonio.core.geometry import half_vector
from gonio.models.physics.microfacet import MicrofacetDistribution, smith_g1_xyz
from gonio.models.physics.rough_tables import _interp, lerp_table, rough_tables, rough_tables_interp
from gonio.models.engine.jit import _dr, _fresnel_outside, _lerp_table, _lobe, _pairs, channels, microfacet_lobe
from gonio.models.engine.jit_tables import _cached_table_derivs, _cached_tables, _t_ext_batch, _tables
from gonio.models.structure import Affine, Structure

__all__ = ["RoughPlastic"]


@register
class RoughPlastic(Model):
    """Rough plastic BRDF (Mitsuba 3 ``roughplastic``).

    Options
    -------
    distribution : {"beckmann", "ggx"}
        Microfacet distribution (default "beckmann", Mitsuba's default).
    nonlinear : bool
        Account for the colour shift of internal scattering (Mitsuba ``nonlinear``).
    exact_tables : bool
        Keyword of the constructor, not a model option (it changes neither the model's
        definition nor ``to_mitsuba``). True (default): Mitsuba's table quadrature is
        recomputed for every new (alpha, eta) (:func:`~gonio.models.physics.rough_tables.rough_tables`,
        25-70 ms; identical to Mitsuba's tables to ~1e-7). False
        (``gm.get("roughplastic", exact_tables=False)``): the tables come from the
        precomputed grid (:func:`gonio.models.physics.rough_tables.rough_tables_interp`, ~40 us)
        in the grid cells that passed the build's check (about a third of the
        (alpha, eta) box), the exact quadrature elsewhere. Not the default: the diffuse
        term's error is typically 6e-5 but reached 2.4e-3 against Mitsuba (ggx,
        alpha 0.0036, eta 1.36) -- R_int has square-root cusps in (alpha, eta) that no
        smooth interpolant follows -- above the 1e-3 of the Mitsuba agreement.

    Parameters (``params`` keys)
    ----------------------------
    diffuse_reflectance : (3,)
        Albedo rho of the diffuse base, in [0, 1].
    alpha : float
        Roughness of the coating (GGX alpha / Beckmann RMS slope), in [1e-4, 1].
    int_ior : float
        Relative index of refraction of the coating (exterior index is 1), in [1.0001, 4].

    Notes
    -----
    With ``wm`` the half vector, F the exact dielectric Fresnel term, D the normal
    distribution and G the separable Smith term of Mitsuba (rational Beckmann G1):

    .. math:: f_r = \\frac{F(w_i\\cdot w_m)\\,D(w_m)\\,G(w_i,w_o,w_m)}
                         {4\\cos\\theta_i\\cos\\theta_o}
              + \\frac{\\rho}{1 - R}\\,\\frac{1}{\\pi\\eta^2}\\,t(\\cos\\theta_i)\\,t(\\cos\\theta_o)

    where R = R_int (``nonlinear=False``) or rho R_int (``nonlinear=True``), t is the
    tabulated rough transmittance and R_int the internal reflectance
    (:mod:`gonio.models.physics.rough_tables`); cf. Weidlich & Wilkie, "Arbitrarily layered
    micro-facet surfaces", GRAPHITE 2007, and Mitsuba 3 ``src/bsdfs/roughplastic.cpp``.
    The model is reciprocal and, for rho <= 1, conserves energy.
    """

    name = "roughplastic"
    smooth_off = {"diffuse_reflectance": 0.0}   # albedo: f_r is the specular lobe alone at rho = 0
    OPTIONS = {"distribution": ("beckmann", "ggx"), "nonlinear": (False, True)}
    energy_conserving = True

    def __init__(self, exact_tables=True, **options):
        super().__init__(**options)
        self.exact_tables = bool(exact_tables)

    def __repr__(self):
        r = super().__repr__()
        return r if self.exact_tables else r[:-1] + ", exact_tables=False)"

    @property
    def structure(self):
        """Compiled kernel (always worth it: the tables); with ``nonlinear=False`` and the
        exact tables, f_r is affine in coef = rho / q, q = 1 - R_int(alpha, eta)."""
        affine = None
        if not self.options["nonlinear"] and self.exact_tables:
            affine = Affine("diffuse_reflectance", ("alpha", "int_ior"), tables=True,
                            q_approx=self._q_approx, q_gradient=self._q_gradient, kernel=_jit_affine_parts)
        return Structure(kernel=_jit_kernel, kernel_inputs=_jit_inputs, compile_always=True, affine=affine)

    def _q_approx(self, thetas):
        """q = 1 - R_int at thetas (K, 2) from the precomputed grid's interpolation where it
        has one, else exact (:func:`gonio.models.fast.affine_q`)."""
        kind = self.options["distribution"]
        out = np.empty(thetas.shape[0])
        for k, (a, e) in enumerate(thetas):
            g = _interp(kind, a, e, tol=np.inf)
            out[k] = (1.0 - g[1]) if g is not None else _fast.affine_q(self, [[a, e]])[0]
        return out

    def _q_gradient(self, theta):
        """dq/d(alpha, eta): the grid spline where available, else central differences of the
        exact q with a 1e-3 relative step (the exact quadrature has square-root cusps where
        nodes cross the critical angle; the spline follows the physical trend)."""
        g = _interp(self.options["distribution"], theta[0], theta[1], grad=True, tol=np.inf)
        if g is not None:
            return -np.array([g[2][-1], g[3][-1]])
        out = np.empty(2)
        for j in range(2):
            h = 1e-3 * theta[j]
            tp, tm = theta.copy(), theta.copy()
            tp[j] += h
            tm[j] -= h
            qp, qm = _fast.affine_q(self, [tp, tm])
            out[j] = (qp - qm) / (2.0 * h)
        return out

    def tables(self, alpha, eta):
        """(t_ext (64,), R_int) used by :meth:`eval` for this roughness and index."""
        kind = self.options["distribution"]
        return (rough_tables if self.exact_tables else rough_tables_interp)(kind, alpha, eta)

    def _parameters(self):
        return (
            Parameter("diffuse_reflectance", 0.5, 0.0, 1.0, "1", "albedo of the diffuse base", per_channel=True),
            Parameter("alpha", 0.1, 1e-4, 1.0, "1", "roughness (GGX alpha or Beckmann RMS slope)"),
            Parameter("int_ior", 1.49, 1.0001, 4.0, "1", "relative index of refraction of the coating"),
        )

    def _lobe_distribution(self, p):
        return MicrofacetDistribution(self.options["distribution"], p["alpha"])

    def specular(self, wi, wo, p):
        """Specular (microfacet reflection) part, shape (N,), for validated ``p``."""
        kind = self.options["distribution"]
        alpha, eta = p["alpha"], p["int_ior"]
        dist = MicrofacetDistribution(kind, alpha)
        ci, co = wi[:, 2], wo[:, 2]
        wm, valid = half_vector(wi, wo)
        di = np.einsum("ij,ij->i", wi, wm)
        do = np.einsum("ij,ij->i", wo, wm)
        D = dist.D(wm)
        F = fresnel_dielectric(0.5 * (di + do), eta)[0]
        a = dist.alpha_u
        G = smith_g1_xyz(kind, a, a, wi[:, 0], wi[:, 1], ci, di) * smith_g1_xyz(kind, a, a, wo[:, 0], wo[:, 1], co, do)
        den = 4.0 * ci * co
        ok = valid & (den > 0.0)
        return np.where(ok, F * D * G / np.where(ok, den, 1.0), 0.0)

    def _eval_parts(self, wi, wo, p):
        rho, eta = p["diffuse_reflectance"], p["int_ior"]
        t_ext, r_int = self.tables(p["alpha"], eta)
        ti = lerp_table(t_ext, wi[:, 2])
        to = lerp_table(t_ext, wo[:, 2])
        denom = 1.0 - (rho * r_int if self.options["nonlinear"] else r_int)
        diff = rho / denom * (INV_PI / (eta * eta))
        return (ti * to)[:, None] * diff, self.specular(wi, wo, p)[:, None]

    def to_mitsuba(self, params):
        p = self.validate(params)
        return {
            "type": "roughplastic",
            "distribution": self.options["distribution"],
            "nonlinear": bool(self.options["nonlinear"]),
            "alpha": p["alpha"],
            "int_ior": p["int_ior"],
            "ext_ior": 1.0,
            "diffuse_reflectance": rgb(p["diffuse_reflectance"]),
        }


def _jit_inputs(model, p, P, F, grad, dtables):
    """The kernel's tables (``P["_tables"]``: t_ext and R_int, computed in float64 and cast to
    F) and, with ``dtables``, their derivatives (``P["_dtables"]``)."""
    import drjit as dr

    F64 = _dr()[1]
    kind = model.options["distribution"]
    t_paired = False  # the cached exact tables come paired already
    grid = None if getattr(model, "exact_tables", True) else _interp(kind, p["alpha"], p["int_ior"], grad=grad)
    if grid is not None:
        # the same interpolated tables as the numpy model; for gradients, their
        # first-order expansion about the current point (value unchanged: the
        # opaque alpha, eta equal p's), d/d(alpha, eta) from the spline
        if grad:
            t, r, dx, dy = grid
            da, de = P["alpha"] - p["alpha"], P["int_ior"] - p["int_ior"]
            tables = (F(t) + da * F(dx[:-1]) + de * F(dy[:-1]), F([r]) + da * dx[-1] + de * dy[-1])
        else:
            tables = (F(grid[0]), F([grid[1]]))
    elif grad:
        tables = _tables(kind, dr.maximum(F64(P["alpha"]), 1e-4), F64(P["int_ior"]))
    else:
        if dtables and grid is None:    # first: its evaluation hands _cached_tables the tables too
            P["_dtables"] = _cached_table_derivs(kind, p["alpha"], p["int_ior"], F)
        tables = _cached_tables(kind, p["alpha"], p["int_ior"], F, paired=True)
        t_paired = True
    t, r = (x if type(x) is F else F(x) for x in tables)
    P["_tables"] = (t if t_paired else _pairs(t), r)
    if dtables:
        if grid is not None:
            dx, dy = _interp(kind, p["alpha"], p["int_ior"], grad=True)[2:]
            P["_dtables"] = (_pairs(F(dx[:-1])), F([dx[-1]]), _pairs(F(dy[:-1])), F([dy[-1]]))
        elif "_dtables" not in P:
            P["_dtables"] = _cached_table_derivs(kind, p["alpha"], p["int_ior"], F)


def _jit_kernel(model, k, wi, wo, P, grad):
    """The compiled kernel: specular lobe + diffuse base through the coating's tables."""
    dr, F, U, active = k.dr, k.F, k.U, k.active
    ci, co = wi.z, wo.z
    alphas = (P["alpha"], P["alpha"])
    s, c, ds = microfacet_lobe(dr, model.options["distribution"], alphas, wi, wo, grad, False)
    J = {}
    eta = P["int_ior"]
    fres = _fresnel_outside(dr, dr.clip(c, 0.0, 1.0), eta, grad)
    spec = fres[0] * s
    t_ext, r_int = P["_tables"]
    ti = _lerp_table(dr, F, U, t_ext, ci, 64)
    to = _lerp_table(dr, F, U, t_ext, co, 64)
    k_eta = 1.0 / (math.pi * eta * eta)
    tt = dr.select(active, ti * to, 0.0)
    scale = tt * k_eta
    nonlinear = model.options["nonlinear"]
    rhos = channels(P, "diffuse_reflectance")
    inv_den = [1.0 / (1.0 - (rho * r_int if nonlinear else r_int)) for rho in rhos]
    f = [spec + rho * q * scale for rho, q in zip(rhos, inv_den)]
    if grad:
        dt_a, dr_a, dt_e, dr_e = P["_dtables"]

        def dscale(dt):
            dti = _lerp_table(dr, F, U, dt, ci, 64)
            dto = _lerp_table(dr, F, U, dt, co, 64)
            return dr.select(active, dti * to + ti * dto, 0.0) * k_eta

        ds_a = dscale(dt_a)
        ds_e = dscale(dt_e) - 2.0 * scale / eta
        # d/dx [rho / (1 - m r)] = rho m (dr/dx) / (1 - m r)^2 with m = rho or 1
        J["diffuse_reflectance"] = [scale * (q * q if nonlinear else q) for q in inv_den]
        J["alpha"] = []
        J["int_ior"] = []
        for rho, q in zip(rhos, inv_den):
            m = rho if nonlinear else 1.0
            J["alpha"].append(fres[0] * ds["alpha"] + rho * q * (ds_a + scale * m * dr_a * q))
            J["int_ior"].append(fres[2] * s + rho * q * (ds_e + scale * m * dr_e * q))
    return f, J


def _jit_affine_parts(model, ctx, cols, lanes, K, vi, vo, tables):
    """base = the specular lobe, basis = t(mu_i) t(mu_o) / (pi eta^2) (``fast.affine_parts``;
    ``nonlinear=False``)."""
    dr, F, U, active = ctx.dr, ctx.F, ctx.U, ctx.active
    k = lanes
    ci, co = vi.z, vo.z
    kind = model.options["distribution"]
    alpha = dr.maximum(cols[0], 1e-4)
    if tables is None:
        t = _t_ext_batch(kind, alpha, cols[1])
    else:  # (K * 64,), checked and loaded by fast.affine_parts
        t = tables
    al = dr.gather(F, alpha, k)
    eta = dr.gather(F, cols[1], k)
    num, den, c, ok = _lobe(dr, kind, al, al, vi, vo)
    Fr, _ = _fresnel_outside(dr, dr.clip(c, 0.0, 1.0), eta)
    base = Fr * num / den

    def lerp(x):
        x = dr.clip(x, 0.0, 1.0) * 63
        j = dr.minimum(U(x), 62)
        w1 = x - F(j)
        return dr.gather(F, t, k * 64 + j) * (1.0 - w1) + dr.gather(F, t, k * 64 + j + 1) * w1

    basis = dr.select(active, lerp(ci) * lerp(co) / (math.pi * eta * eta), 0.0)
    return base, basis
