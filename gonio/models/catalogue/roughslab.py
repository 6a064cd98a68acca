"""Model ``roughslab``: a plate with a frosted front face and a polished back face (frosted
glass, an anti-glare film on its substrate), both faces in air, to first order.

Convention: ``wi`` points to the light, ``wo`` to the detector, both outside the slab in air
(index 1); the frosted face is +z, the polished back -z. Light on the front: reflection is the
front face's (Walter et al. 2007), transmission enters through the front into the glass along
wg and leaves the back along ``wo`` (Snell), with the exit's Fresnel transmittance, the 1/eta^2
of radiance leaving glass into air, and the internal transmittance along the path. Both ends in
air, so reciprocity is plain: f(wi, wo) = f(wo, wi) (Veach 1997 eq. 5.15 with n_i = n_o = 1),
tested against light entering the polished back (:func:`slab_f`). The slab is not symmetric:
seen from the back its reflection is the polished face's mirror, not the frosted lobe. The
model's domain (``eval``) is light on the frosted face; the Mitsuba twin (a Python BSDF over
Mitsuba's own ``roughdielectric``) also takes light on the back, by reciprocity. numpy
reference only (no compiled kernel).
"""

# References
# B. Walter, S. R. Marschner, H. Li, K. E. Torrance, "Microfacet Models for Refraction through
#   Rough Surfaces", EGSR 2007, eqs. (20)-(21) (the front face).
# F. E. Nicodemus, "Radiance", Am. J. Phys. 31 (1963) 368: L / n^2 is kept across an interface.
# E. Veach, PhD thesis, Stanford 1997: eq. 5.9 (radiance scaling), eq. 5.15 (generalised
#   reciprocity f / eta_o^2).
# The same first-order formula as the simulator's sample truth (gonio.sim.physics.sample.slab_exit).
# Left out (first order): the back face's reflection (F ~ 4 % at eta 1.5) sent back through
# the front, multiple bounces between the faces, the exit spot's lateral shift d tan theta_g;
# light the rough face sends past the back face's critical angle counts as lost (in a real
# plate it bounces and leaves later: most of T at grazing incidence, docs/performance.md).

from __future__ import annotations

import numpy as np

from gonio.core.channels import CHANNELS
from gonio.models.base import Model, Parameter, register
from gonio.models.catalogue.roughdielectric import BOTH_SIDES, facet_nodes, facet_refract, rough_dielectric_f
from gonio.models.physics.fresnel import fresnel_dielectric
from gonio.models.structure import Structure

__all__ = ["RoughSlab", "slab_f", "exit_direction", "slab_reflectance_transmittance"]


def exit_direction(wo, eta, tau=1.0):
    """The polished back face for a direction ``wo`` below it (in air, ``wo[:, 2] < 0``).

    Returns ``wg`` (N, 3), the direction inside the slab (toward the back face) that leaves
    along ``wo`` (sin theta_g = sin theta_o / eta, same azimuth), and ``factor`` (N,),
    (1 - F(|cos theta_o|, eta)) / eta^2 * tau^(1 / cos theta_g): Fresnel's transmittance (the
    same from either side), radiance leaving glass into air scaled by 1 / eta^2 (Nicodemus
    1963), Beer's law along the path (tau = exp(-kappa d) at normal incidence). 0 where
    ``wo`` is not below the face or no ray leaves (eta < 1 past the critical angle)."""
    wo = np.atleast_2d(np.asarray(wo, dtype=np.float64))
    with np.errstate(all="ignore"):
        s2 = (wo[:, 0] ** 2 + wo[:, 1] ** 2) / (eta * eta)
        ok = (wo[:, 2] < 0.0) & (s2 < 1.0)
        c_g = np.sqrt(np.where(ok, 1.0 - s2, 1.0))
        wg = np.stack([wo[:, 0] / eta, wo[:, 1] / eta, -c_g], axis=1)
        F = fresnel_dielectric(np.abs(wo[:, 2]), eta)[0]
        path = np.where(tau > 0.0, np.power(float(tau), 1.0 / c_g), 0.0)
        factor = np.where(ok, (1.0 - F) / (eta * eta) * path, 0.0)
    return np.where(ok[:, None], wg, 0.0), np.where(np.isfinite(factor), factor, 0.0)


def slab_f(kind, alpha, eta, tau, wi, wo):
    """f(wi -> wo) of the slab, sr^-1, (N,), for light and detector anywhere outside it.

    Parameters
    ----------
    kind : {"beckmann", "ggx"}
        The front face's microfacet distribution.
    alpha : float
        The front face's roughness, floored at 1e-4 (:func:`rough_dielectric_f`).
    eta : float
        The slab's index relative to the air around it.
    tau : float
        Internal transmittance at normal incidence, exp(-kappa d), in [0, 1].
    wi, wo : ndarray (N, 3)
        Toward the light and toward the detector, either side of the slab each.

    Notes
    -----
    With f_1 the rough interface (:func:`rough_dielectric_f`, radiance mode) and
    (wg, X) = :func:`exit_direction`:

    * light on the front, detector on the front: f_1(wi, wo);
    * light on the front, detector behind: f_1(wi, wg(wo)) X(wo);
    * light behind, detector on the front: the light enters the polished back (Fresnel,
      radiance times eta^2, solid angle cos theta_g d(w_g) = cos theta_i d(w_i) / eta^2) and
      meets the frosted face from inside: f_1(wg(wi), wo) (1 - F(|cos theta_i|)) tau^(1/cos theta_g);
    * both behind: 0 (the polished face's mirror is a delta; the rest is second order).

    The third is computed along its own path, so ``slab_f(wo, wi) == slab_f(wi, wo)`` is a
    test of the first two against the physics (f_1's generalised reciprocity does the rest).
    """
    wi = np.atleast_2d(np.asarray(wi, dtype=np.float64))
    wo = np.atleast_2d(np.asarray(wo, dtype=np.float64))
    ci, co = wi[:, 2], wo[:, 2]
    out = np.zeros(wi.shape[0])
    front = ci > 0.0
    r = front & (co > 0.0)
    if r.any():
        out[r] = rough_dielectric_f(kind, alpha, eta, wi[r], wo[r])
    t = front & (co < 0.0)
    if t.any():
        wg, x = exit_direction(wo[t], eta, tau)
        out[t] = rough_dielectric_f(kind, alpha, eta, wi[t], wg) * x
    b = (ci < 0.0) & (co > 0.0)
    if b.any():
        wg, x = exit_direction(wi[b], eta, tau)
        # x holds 1 / eta^2; light entering glass gains eta^2 in radiance and the solid angle
        # shrinks by the same factor, so f loses neither
        out[b] = rough_dielectric_f(kind, alpha, eta, wg, wo[b]) * x * (eta * eta)
    return np.where(np.isfinite(out), out, 0.0)


@register
class RoughSlab(Model):
    """A slab: frosted front face (Walter et al. 2007), polished back, internal absorption.

    Options
    -------
    distribution : {"beckmann", "ggx"}
        The front face's microfacet distribution (default "beckmann").

    Parameters (``params`` keys)
    ----------------------------
    alpha : float
        The front face's roughness, in [1e-4, 1].
    int_ior : float
        The slab's index relative to air, in [1, 4] (1: a matched plate, finite; no twin).
    tau : float
        Internal transmittance at normal incidence, exp(-kappa d), in [0, 1].

    Notes
    -----
    :func:`slab_f` and the module docstring (convention, what is left out). Light on the
    front face: R is the front face's, T at most the front face's transmittance (the exit
    loses F, the 1 / eta^2 is the solid angle's widening), so R + T <= 1 wherever the front
    face's does.
    """

    name = "roughslab"
    auto_candidate = False   # selection offers it for data with transmitted points, not for a BRDF
    OPTIONS = {"distribution": ("beckmann", "ggx")}
    energy_conserving = True

    @property
    def structure(self):
        return Structure(sides=BOTH_SIDES)

    def _parameters(self):
        return (
            Parameter("alpha", 0.1, 1e-4, 1.0, "1", "front face roughness (GGX alpha or Beckmann RMS slope)"),
            Parameter("int_ior", 1.5, 1.0, 4.0, "1", "slab index relative to the air around it"),
            Parameter("tau", 1.0, 0.0, 1.0, "1", "internal transmittance at normal incidence, exp(-kappa d)"),
        )

    def _eval(self, wi, wo, p):
        f = slab_f(self.options["distribution"], p["alpha"], p["int_ior"], p["tau"], wi, wo)
        return np.repeat(f[:, None], CHANNELS, axis=1)

    def _eval_parts(self, wi, wo, p):
        return np.zeros((wi.shape[0], CHANNELS)), self._eval(wi, wo, p)

    def to_mitsuba(self, params):
        from gonio.models.mitsuba.plugins import add_plugin, ensure_registered

        p = self.validate(params)
        if p["int_ior"] == 1.0:
            raise ValueError("roughslab: Mitsuba needs int_ior != 1 (a front face that is there)")
        add_plugin(self.name, _make_bsdf)
        return {"type": ensure_registered(self.name), "distribution": self.options["distribution"],
                "alpha": p["alpha"], "int_ior": p["int_ior"], "tau": p["tau"]}


def slab_reflectance_transmittance(kind, alpha, eta, tau, wi, n_theta=128, n_phi=128):
    """R and T (N,) each of :func:`slab_f` for light on the front face from ``wi``: the
    integral of f |cos theta_o| over each side of the slab.

    Over microfacet normals wm of the front face, as
    :func:`~gonio.models.catalogue.roughdielectric.reflectance_transmittance` (Walter et al.
    2007 eqs. 14, 17), each refracted wg taken out through the back to wo with
    d(wo) = eta^2 cos theta_g / |cos theta_o| d(wg) (the invariance of n^2 cos theta d(w),
    Nicodemus 1963); f is evaluated at every (wi, wo), so the sums test the model.
    """
    wi = np.atleast_2d(np.asarray(wi, dtype=np.float64))
    a, m, dm = facet_nodes(alpha, n_theta, n_phi)
    R, T = np.zeros(len(wi)), np.zeros(len(wi))
    with np.errstate(all="ignore"):
        for k, w_i in enumerate(wi):
            c = m @ w_i
            vis = c > 0.0
            w_b = np.broadcast_to(w_i, m.shape)
            wr = 2.0 * c[:, None] * m - w_i
            fr = slab_f(kind, a, eta, tau, w_b, wr)
            jac_r = 4.0 * np.abs(np.einsum("ij,ij->i", wr, m))
            R[k] = np.sum(np.where(vis & (wr[:, 2] > 0.0), fr * np.abs(wr[:, 2]) * jac_r * dm, 0.0))
            wg, ok = facet_refract(w_i, m, c, eta)
            dt = np.einsum("ij,ij->i", wg, m)
            s_o2 = eta * eta * (wg[:, 0] ** 2 + wg[:, 1] ** 2)
            out = ok & (wg[:, 2] < 0.0) & (dt != 0.0) & (s_o2 < 1.0)
            c_o = np.sqrt(np.where(out, 1.0 - s_o2, 1.0))
            wo = np.stack([eta * wg[:, 0], eta * wg[:, 1], -c_o], axis=1)
            ft = slab_f(kind, a, eta, tau, w_b, wo)
            jac = (c + eta * dt) ** 2 / (eta * eta * np.abs(dt)) * eta * eta * np.abs(wg[:, 2]) / c_o
            T[k] = np.sum(np.where(out, ft * c_o * jac * dm, 0.0))
    return R, T


def _make_bsdf(mi, dr, base):
    """The Mitsuba twin: Mitsuba's own ``roughdielectric`` (radiance mode) as the front face,
    the back face as :func:`exit_direction` in Dr.Jit. Mitsuba's ``si.wi`` is gonio's wo (the
    camera), its ``wo`` gonio's wi (the light); light behind the slab by reciprocity
    (f(wi, wo) = f(wo, wi), tested on :func:`slab_f`). Sampling: the front face's own, the
    back face mapped through Snell's law with its Jacobian."""

    class RoughSlabBSDF(base):
        def __init__(self, props):
            base.__init__(self, props)
            self.eta = float(props["int_ior"])
            self.log_tau = float(np.log(float(props["tau"]))) if float(props["tau"]) > 0.0 else -np.inf
            self.inner = mi.load_dict({"type": "roughdielectric", "distribution": props["distribution"],
                                       "alpha": float(props["alpha"]), "int_ior": self.eta, "ext_ior": 1.0})
            flags = mi.BSDFFlags.FrontSide | mi.BSDFFlags.BackSide
            self.m_components = [mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide,
                                 mi.BSDFFlags.GlossyTransmission | flags]
            self.m_flags = self.m_components[0] | self.m_components[1]

        def _inside(self, v):
            """(wg, factor, cos theta_g) of a direction v below the slab (exit_direction)."""
            e = self.eta
            s2 = (v.x * v.x + v.y * v.y) / (e * e)
            c_g = dr.safe_sqrt(1.0 - s2)
            wg = mi.Vector3f(v.x / e, v.y / e, -c_g)
            F = mi.fresnel(dr.abs(mi.Frame3f.cos_theta(v)), e)[0]
            path = dr.exp(self.log_tau / dr.maximum(c_g, 1e-12)) if np.isfinite(self.log_tau) else 0.0
            return wg, (1.0 - F) / (e * e) * path, c_g

        def _radiance(self, ctx):
            """The inner face in radiance mode whatever the caller's: both ends of the slab are
            in air, so f is reciprocal and the adjoint (importance mode: a light tracer's) is
            the same function; the inner roughdielectric's importance mode would drop its
            1 / eta^2 at the entry and count the slab eta^2 too dim."""
            return mi.BSDFContext(mi.TransportMode.Radiance, ctx.type_mask, ctx.component)

        def _with_wi(self, si, w):
            s = mi.SurfaceInteraction3f(si)
            s.wi = w
            return s

        def eval(self, ctx, si, wo, active=True):
            ctx = self._radiance(ctx)
            cl, cc = mi.Frame3f.cos_theta(wo), mi.Frame3f.cos_theta(si.wi)
            refl = active & (cl > 0) & (cc > 0)
            trans = active & (cl * cc < 0)
            up = dr.select(cl > 0, wo, si.wi)          # the direction on the frosted side
            down = dr.select(cl > 0, si.wi, wo)        # the one behind the slab
            wg, x, _ = self._inside(down)
            v_t = self.inner.eval(ctx, self._with_wi(si, wg), up, trans)
            scale = x * dr.abs(cl) / dr.maximum(dr.abs(mi.Frame3f.cos_theta(up)), 1e-30)
            v_r = self.inner.eval(ctx, si, wo, refl)
            return dr.select(refl, v_r, dr.select(trans, v_t * scale, 0.0))

        def pdf(self, ctx, si, wo, active=True):
            ctx = self._radiance(ctx)
            cl, cc = mi.Frame3f.cos_theta(wo), mi.Frame3f.cos_theta(si.wi)
            wg_l, _, c_gl = self._inside(wo)
            wg_c, _, _ = self._inside(si.wi)
            p_r = self.inner.pdf(ctx, si, wo, active & (cl > 0) & (cc > 0))
            p_up = self.inner.pdf(ctx, si, wg_l, active & (cc > 0) & (cl < 0))
            p_up = p_up * dr.abs(cl) / (self.eta * self.eta * dr.maximum(c_gl, 1e-30))
            p_dn = self.inner.pdf(ctx, self._with_wi(si, wg_c), wo, active & (cc < 0) & (cl > 0))
            return dr.select(active & (cl > 0) & (cc > 0), p_r,
                             dr.select(active & (cc > 0) & (cl < 0), p_up,
                                       dr.select(active & (cc < 0) & (cl > 0), p_dn, 0.0)))

        def sample(self, ctx, si, sample1, sample2, active=True):
            ctx = self._radiance(ctx)
            cc = mi.Frame3f.cos_theta(si.wi)
            wg_c, _, _ = self._inside(si.wi)
            s = self._with_wi(si, dr.select(cc > 0, si.wi, wg_c))
            bs, _ = self.inner.sample(ctx, s, sample1, sample2, active)
            g = bs.wo
            # a sample on the other side than its lobe's (a steep facet's reflection that crosses
            # the surface) is one pdf() and eval() read as the other lobe's: refused, so that
            # the accepted directions have the density pdf() gives
            refracted = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Transmission)
            side = mi.Frame3f.cos_theta(g) * mi.Frame3f.cos_theta(s.wi)
            crossed, kept = side < 0, side >= 0        # comparisons, not ~: scalar variants hold bools
            # a camera in front whose sampled ray went into the glass: out through the back
            s_o2 = self.eta * self.eta * (g.x * g.x + g.y * g.y)
            out = mi.Vector3f(self.eta * g.x, self.eta * g.y, -dr.safe_sqrt(1.0 - s_o2))
            through = (cc > 0) & crossed
            light = dr.select(through, out, g)
            ok = active & (refracted == crossed) & (bs.pdf > 0)
            ok = ok & dr.select(cc > 0, kept | (s_o2 < 1.0), crossed)
            bs.wo = light
            bs.pdf = self.pdf(ctx, si, light, ok)
            bs.eta = 1.0
            refl = (cc > 0) & kept
            bs.sampled_type = dr.select(refl, mi.UInt32(+mi.BSDFFlags.GlossyReflection),
                                        mi.UInt32(+mi.BSDFFlags.GlossyTransmission))
            bs.sampled_component = dr.select(refl, mi.UInt32(0), mi.UInt32(1))
            ok = ok & (bs.pdf > 0)
            value = self.eval(ctx, si, light, ok) / dr.select(ok, bs.pdf, 1.0)
            return bs, dr.select(ok, value, 0.0)

        def to_string(self):
            return f"GonioRoughSlab[eta={self.eta}]"

    return RoughSlabBSDF
