"""Model ``flakepaint``: a metallic-flake lacquer whose colour changes with angle.

    f_r = rho_d[c] / pi + rho_s[c] F(eta; wi . wm) D G / (4 cos_i cos_o)        (base, clear coat)
          + rho_h[c] L(alpha_h) + rho_f[c] L(alpha_f[c] (1 + w (1 - cos theta_d))),
    L(a) = D(wm; a) / (4 (cos_i cos_o)^p)

A metallic paint's colour sits in its flakes: mirror platelets under a clear coat spread the
light about the specular direction in a broad lobe of their own colour, over the coat's sharp,
nearly white reflection and its haze (Ershov, Kolchin & Myszkowski 2001; Guenther et al. 2005).
Cornell's Cayman lacquer shows the flake lobe as a function of theta_h with little of the
microfacet 1 / (cos_i cos_o) growth (hence p), widening toward grazing theta_d (w). Option
``spread="wavelength"``: one flake spread per wavelength, so the chromaticity shifts with angle.
Every colour enters f_r linearly. Offered by ``--model auto`` on spectral and goniochromic RGB
data (``spectral_candidate``). Mitsuba twin: the Python BSDF ``gonio_flakepaint``
(:func:`_make_bsdf`), each colour a Mitsuba spectrum (any variant, ``*_spectral`` included).
"""

from __future__ import annotations

import math

import numpy as np

from gonio.models.base import Model, Parameter, register
from gonio.models.catalogue.flake_memo import geometry, memo, values
from gonio.models.physics.fresnel import fresnel_conductor
from gonio.models.physics.microfacet import MicrofacetDistribution, smith_g1_xyz
from gonio.models.structure import Structure

__all__ = ["FlakePaint", "half_vector_lobe"]

#: the parameters the lobes' shapes depend on (every other one is a colour, entering f_r linearly)
_SHAPE_PARAMETERS = ("alpha", "eta", "haze_alpha", "flake_alpha", "flake_exponent", "flake_widen")


def _coat(kind, alpha, eta, wi, wo):
    """F D G / (4 cos_i cos_o) of the clear coat (Walter et al. 2007 eq. 20, Mitsuba's separable
    Smith G, the dielectric Fresnel as the conductor one with k = 0), (N,)."""
    g = geometry(wi, wo)
    D = MicrofacetDistribution(kind, alpha).D(g.wm)
    G = smith_g1_xyz(kind, alpha, alpha, g.wi[:, 0], g.wi[:, 1], g.ci, g.di) \
        * smith_g1_xyz(kind, alpha, alpha, g.wo[:, 0], g.wo[:, 1], g.co, g.do)
    ok = g.coat_ok
    F = fresnel_conductor(g.cos_d[:, None], np.full(1, eta), np.zeros(1))[:, 0]
    return np.where(ok, F * D * G / np.where(ok, g.den, 1.0), 0.0)


def _coat_grad(kind, alpha, eta, wi, wo):
    """(d coat / d alpha, d coat / d eta), (N,) each: :func:`_coat`'s exact derivatives. D:
    Walter et al. 2007 eqs. 33, 25 differentiated; G1: GGX's 2 / (1 + sqrt(1 + T)), T = alpha^2
    tan^2, and Beckmann's rational fit (eq. 27) in b = 1 / sqrt(T); F: the dielectric's (k = 0,
    eta > 1, so a = sqrt(eta^2 - sin^2)) R_s and R_p of :func:`fresnel_conductor` in eta."""
    g = geometry(wi, wo)
    a = float(alpha)
    D = MicrofacetDistribution(kind, a).D(g.wm)
    s = g.wm[:, 0] ** 2 + g.wm[:, 1] ** 2
    z2 = g.wm[:, 2] ** 2
    if kind == "ggx":
        dD = D * (-2.0 / a + 4.0 * s / (a ** 3 * (s / (a * a) + z2)))
    else:
        dD = D * (2.0 * s / (a ** 3 * np.where(z2 > 0.0, z2, 1.0)) - 2.0 / a)
    Gi, dGi = _g1_grad(kind, a, g.wi[:, 0], g.wi[:, 1], g.ci, g.di)
    Go, dGo = _g1_grad(kind, a, g.wo[:, 0], g.wo[:, 1], g.co, g.do)
    F, dF = _dielectric_grad(g.cos_d, float(eta))
    den = np.where(g.coat_ok, g.den, 1.0)
    dalpha = np.where(g.coat_ok, F * (dD * Gi * Go + D * (dGi * Go + Gi * dGo)) / den, 0.0)
    return dalpha, np.where(g.coat_ok, dF * D * Gi * Go / den, 0.0)


def _g1_grad(kind, alpha, x, y, z, dot):
    """(G1, d G1 / d alpha) of :func:`smith_g1_xyz` for an isotropic alpha."""
    G = smith_g1_xyz(kind, alpha, alpha, x, y, z, dot)
    xy = (alpha * x) ** 2 + (alpha * y) ** 2
    z2 = z * z
    t2 = xy / np.where(z2 > 0.0, z2, 1.0)
    if kind == "ggx":
        r = np.sqrt(1.0 + t2)
        dG = -2.0 * t2 / (alpha * r * (1.0 + r) ** 2)
    else:
        b = 1.0 / np.sqrt(np.where(t2 > 0.0, t2, 1.0))
        num, den = 3.535 * b + 2.181 * b * b, 1.0 + 2.276 * b + 2.577 * b * b
        dgdb = ((3.535 + 4.362 * b) * den - num * (2.276 + 5.154 * b)) / (den * den)
        dG = np.where(b >= 1.6, 0.0, dgdb * (-b / alpha))
    dG = np.where((z2 > 0.0) & (xy != 0.0) & (dot * z > 0.0), dG, 0.0)
    return G, dG


def _dielectric_grad(cos_d, eta):
    """(F, d F / d eta) of :func:`fresnel_conductor` at k = 0 and eta > 1 (its t1 = eta^2 -
    sin^2 > 0, a^2 + b^2 = t1, a = sqrt(t1)), (N,)."""
    c = np.clip(cos_d, 0.0, 1.0)
    c2 = c * c
    s2 = 1.0 - c2
    t1 = eta * eta - s2
    a = np.sqrt(t1)
    term1, term2 = t1 + c2, 2.0 * c * a
    d1, d2 = 2.0 * eta, 2.0 * c * eta / a
    rs = (term1 - term2) / (term1 + term2)
    drs = ((d1 - d2) * (term1 + term2) - (term1 - term2) * (d1 + d2)) / (term1 + term2) ** 2
    term3, term4 = t1 * c2 + s2 * s2, term2 * s2
    d3, d4 = d1 * c2, d2 * s2
    q = (term3 - term4) / (term3 + term4)
    dq = ((d3 - d4) * (term3 + term4) - (term3 - term4) * (d3 + d4)) / (term3 + term4) ** 2
    return 0.5 * (rs + rs * q), 0.5 * (drs + drs * q + rs * dq)


def half_vector_lobe(kind, alpha, p, wi, wo, grad=False, widen=0.0):
    """L = D(wm; a) / (4 (cos_i cos_o)^p), (N, K) for ``alpha`` (K,), a = alpha (1 + widen (1 -
    cos theta_d)) (the lobe widens toward grazing theta_d), with (grad) dL/dalpha, dL/dp and
    dL/dwiden. GGX: D = a^2 / (pi cos^4 (a^2 + tan^2)^2); Beckmann: D = exp(-tan^2 / a^2) /
    (pi a^2 cos^4) (Walter et al. 2007 eqs. 33, 25); 0 below the horizon."""
    g = geometry(wi, wo)      # cos theta_d symmetric in wi, wo: reciprocal
    ok, c2, t2, grazing, logcc = g.lobe_ok, g.c2, g.t2, g.grazing, g.logcc
    a0 = np.atleast_1d(np.asarray(alpha, float))[None, :]
    a = a0 * (1.0 + widen * grazing)
    a2 = a * a
    if kind == "ggx":
        D = a2 / (math.pi * c2 * c2 * (a2 + t2) ** 2)
        dlog = 2.0 / a - 4.0 * a / (a2 + t2)
    else:
        D = np.exp(-t2 / a2) / (math.pi * a2 * c2 * c2)
        dlog = 2.0 * t2 / (a2 * a) - 2.0 / a
    L = np.where(ok, D * np.exp(-p * logcc) / 4.0, 0.0)
    if not grad:
        return L
    da = L * dlog            # dL / d(the widened a)
    return L, da * (1.0 + widen * grazing), -logcc * L, da * a0 * grazing


@register
class FlakePaint(Model):
    """Base + clear coat + haze + flake lobe, each with its own colour (see the module).

    Options
    -------
    distribution : {"ggx", "beckmann"}
        Microfacet distribution of every lobe.
    spread : {"shared", "wavelength"}
        One flake spread for every channel, or one per channel.

    Parameters (``params`` keys)
    ----------------------------
    diffuse_reflectance, specular_reflectance, haze_reflectance, flake_reflectance : (C,)
        rho_d, rho_s, rho_h, rho_f in [0, 1].
    alpha : float
        Roughness of the clear coat, in [1e-4, 1].
    eta : float
        Relative index of the clear coat, in [1.0001, 4].
    haze_alpha : float
        Spread of the haze, in [1e-3, 1].
    flake_alpha : float, or (C,) with ``spread="wavelength"``
        Spread of the flakes' normals, in [1e-2, 1].
    flake_exponent : float
        p of the half-vector lobes, in [0, 1].

    Notes
    -----
    Not energy-conserving for every parameter set (four albedos up to about 1 add up); a fit
    holds albedo <= 1. Reciprocal: every term is symmetric in wi, wo.
    """

    name = "flakepaint"
    OPTIONS = {"distribution": ("ggx", "beckmann"), "spread": ("shared", "wavelength")}
    energy_conserving = False
    #: not offered on every RGB file: on spectral data, and on RGB data that shows goniochromism
    auto_candidate = False
    spectral_candidate = True
    #: its twin is gonio's Python BSDF ``gonio_flakepaint``
    mitsuba_twin = True

    def __init__(self, **options):
        super().__init__(**options)
        if self.options["spread"] == "wavelength":   # nested: started from the shared spread's fit
            self._layer = FlakePaint(distribution=self.options["distribution"], spread="shared")

    @property
    def structure(self):
        return Structure()     # numpy: four lobe shapes per evaluation, the colours outer products

    def affine_colours(self) -> tuple:
        """The per-channel parameters in which f_r is affine, jointly, whatever the others: the
        four lobes' colours (the module's formula). gonio.fitting.likelihood.problem takes them
        as declared instead of probing (tests/fitting/test_affine_declared.py checks the probe
        agrees)."""
        return ("diffuse_reflectance", "specular_reflectance", "haze_reflectance", "flake_reflectance")

    def _parameters(self):
        per = self.options["spread"] == "wavelength"
        return (
            Parameter("diffuse_reflectance", 0.05, 0.0, 1.0, "1", "albedo of the base", per_channel=True),
            Parameter("specular_reflectance", 1.0, 0.0, 1.0, "1", "weight of the clear coat", per_channel=True),
            Parameter("alpha", 0.01, 1e-4, 1.0, "1", "roughness of the clear coat"),
            Parameter("eta", 1.5, 1.0001, 4.0, "1", "relative index of the clear coat"),
            Parameter("haze_reflectance", 0.01, 0.0, 1.0, "1", "weight of the haze", per_channel=True),
            Parameter("haze_alpha", 0.03, 1e-3, 1.0, "1", "spread of the haze"),
            Parameter("flake_reflectance", 0.1, 0.0, 1.0, "1", "weight of the flake lobe", per_channel=True),
            Parameter("flake_alpha", 0.3, 1e-2, 1.0, "1", "spread of the flakes' normals", per_channel=per),
            Parameter("flake_exponent", 0.2, 0.0, 1.0, "1", "p of the half-vector lobes"),
            Parameter("flake_widen", 0.0, 0.0, 3.0, "1", "widening of the flake lobe toward grazing theta_d"),
        )

    def _terms(self, wi, wo, p, grad=False):
        """(base, coat, haze, flake): the four lobes' shapes (with ``grad`` the half-vector
        lobes' derivatives), remembered for these directions and spreads (flake_memo: a fit's
        calls that change only the colours reuse them)."""
        kind = self.options["distribution"]
        g = geometry(wi, wo)
        key = ("flakepaint", kind, bool(grad), _coat, half_vector_lobe, fresnel_conductor) + values(p, _SHAPE_PARAMETERS)

        def make():
            coat = _coat(kind, p["alpha"], p["eta"], g.wi, g.wo)[:, None]
            haze = half_vector_lobe(kind, p["haze_alpha"], p["flake_exponent"], g.wi, g.wo, grad)
            flake = half_vector_lobe(kind, p["flake_alpha"], p["flake_exponent"], g.wi, g.wo, grad, p["flake_widen"])
            return g.up / math.pi, coat, haze, flake
        return memo(g, key, make)

    def _eval_parts(self, wi, wo, p):
        g = geometry(wi, wo)        # its arrays: the calls below find it by identity
        base, coat, haze, flake = self._terms(g.wi, g.wo, p)
        lobe = coat * p["specular_reflectance"] + haze * p["haze_reflectance"] + flake * p["flake_reflectance"]
        return np.broadcast_to(base * p["diffuse_reflectance"], lobe.shape), lobe

    def jacobian_reference(self, wi, wo, params):
        """(f_r, {parameter: d f_r / d parameter (N, C)}): the colours' columns exactly (their
        lobes), the lobes' spreads and exponent and the coat's roughness and index analytically
        (:func:`_coat_grad`); a per-channel spread's column c is
        d f_r[c] / d alpha_f[c]."""
        g = geometry(wi, wo)
        wi, wo = g.wi, g.wo
        p = self.validate(params)
        base, coat, (haze, dh, ph, _), (flake, df, pf, wf) = self._terms(wi, wo, p, grad=True)
        rs, rh, rf = p["specular_reflectance"], p["haze_reflectance"], p["flake_reflectance"]
        f = base * p["diffuse_reflectance"] + coat * rs + haze * rh + flake * rf
        n = f.shape
        J = {"diffuse_reflectance": np.broadcast_to(base, n).copy(),
             "specular_reflectance": np.broadcast_to(coat, n).copy(),
             "haze_reflectance": np.broadcast_to(haze, n).copy(), "flake_reflectance": np.broadcast_to(flake, n).copy(),
             "haze_alpha": dh * rh, "flake_alpha": np.broadcast_to(df * rf, n).copy(),
             "flake_exponent": np.broadcast_to(ph * rh + pf * rf, n).copy(), "flake_widen": wf * rf}
        da, de = _coat_grad(self.options["distribution"], p["alpha"], p["eta"], wi, wo)
        J["alpha"], J["eta"] = da[:, None] * rs, de[:, None] * rs
        return f, J

    def start_from(self, layer_params):
        """The shared spread's fit (``layer_params``) as the start of the per-wavelength one."""
        p = dict(self._layer.validate(layer_params))
        p["flake_alpha"] = np.full(self.n_channels(p), float(p["flake_alpha"]))
        return p

    def _bsdf_maker(self):
        """The factory of this model's Python BSDF (a derived model derives its twin)."""
        return _make_bsdf

    def to_mitsuba(self, params):
        """The Python BSDF ``gonio_flakepaint``: each colour (and a spread per wavelength) as
        :func:`gonio.models.base.rgb` writes it (an ``rgb``, or a spectral fit's ``spectrum``)."""
        from gonio.models.base import rgb
        from gonio.models.mitsuba.plugins import add_plugin, ensure_registered

        p = self.validate(params)
        add_plugin(self.name, self._bsdf_maker())
        d = {"type": ensure_registered(self.name), "distribution": self.options["distribution"]}
        for name in ("diffuse_reflectance", "specular_reflectance", "haze_reflectance", "flake_reflectance"):
            d[name] = rgb(p[name])
        for name in ("alpha", "eta", "haze_alpha", "flake_exponent", "flake_widen"):
            d[name] = float(p[name])
        d["flake_alpha"] = rgb(p["flake_alpha"]) if self.options["spread"] == "wavelength" else float(p["flake_alpha"])
        return d


#: lower bound of the flakes' spread: the plugin's floor where a spectrum ends (Mitsuba's
#: irregular spectrum is 0 outside its wavelengths; the flake colour is 0 there too)
_FLAKE_ALPHA_MIN = 1e-2


def _scalar(x) -> float:
    """One number from a Dr.Jit value (a Python float in scalar variants, an array of one in llvm)."""
    return float(np.asarray(x, dtype=np.float64).ravel()[0])


def _make_bsdf(mi, dr, base):
    """The Mitsuba twin: :meth:`FlakePaint._eval_parts` in Dr.Jit, a Mitsuba spectrum per colour
    evaluated at ``si``'s wavelengths (the flakes' spread too with ``spread="wavelength"``); the
    coat's D and Smith G are Mitsuba's ``MicrofacetDistribution`` (the numpy model's convention),
    its Fresnel ``mitsuba.fresnel``. Mitsuba's ``si.wi`` is gonio's wo, its ``wo`` gonio's wi.
    Sampling: a mixture of the cosine hemisphere and the three lobes' D (Walter et al. 2007
    eq. 38: pdf = D cos(theta_m) / (4 |wo . wm|)), weighted by their mean colours."""
    kinds = {"ggx": mi.MicrofacetType.GGX, "beckmann": mi.MicrofacetType.Beckmann}

    class FlakePaintBSDF(base):
        def __init__(self, props):
            base.__init__(self, props)
            self.kind = str(props["distribution"])
            mtype = kinds[self.kind]
            self.rho = [props.get_texture(k) for k in
                        ("diffuse_reflectance", "specular_reflectance", "haze_reflectance", "flake_reflectance")]
            self.alpha_f = props.get_unbounded_texture("flake_alpha")
            eta, alpha_h = float(props["eta"]), float(props["haze_alpha"])
            flake_mean = max(_scalar(self.alpha_f.mean()), _FLAKE_ALPHA_MIN)
            f0 = ((eta - 1.0) / (eta + 1.0)) ** 2
            rd, rs, rh, rf = (max(_scalar(t.mean()), 0.0) for t in self.rho)
            w = [rs * max(f0, 0.04), rh, rf]           # the coat's weight: its reflectance near normal
            total = rd + sum(w)
            # at least a tenth cosine-weighted: the diffuse base and the lobes' far tails stay sampled
            lobe = 0.0 if total <= 0.0 else 0.9 * sum(w) / total
            self.weights = [1.0 - lobe] + [lobe * x / sum(w) if lobe > 0.0 else 0.0 for x in w]
            # opaque, as Mitsuba's own plugins keep their parameters: a new fit reuses the compiled
            # kernel instead of folding its values into a new one
            self.eta, self.haze_alpha, self.p, self.widen, alpha, alpha_f, *self.w = (
                mi.Float(x) for x in (eta, alpha_h, float(props["flake_exponent"]), float(props["flake_widen"]),
                                      float(props["alpha"]), flake_mean, *self.weights))
            dr.make_opaque(self.eta, self.haze_alpha, self.p, self.widen, alpha, alpha_f, *self.w)
            self.coat = mi.MicrofacetDistribution(mtype, alpha, False)
            self.lobes = [self.coat, mi.MicrofacetDistribution(mtype, self.haze_alpha, False),
                          mi.MicrofacetDistribution(mtype, alpha_f, False)]
            flags = mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.FrontSide
            self.m_components = [flags]
            self.m_flags = flags

        def _lobe_d(self, a, t2, c2):
            """D(wm; a) (Walter et al. 2007 eqs. 33, 25) from tan^2 and cos^2 of theta_m."""
            a2 = a * a
            if self.kind == "ggx":
                return a2 / (math.pi * c2 * c2 * dr.square(a2 + t2))
            return dr.exp(-t2 / a2) / (math.pi * a2 * c2 * c2)

        def _f(self, si, wo):
            wi_g, wo_g = wo, si.wi                 # gonio: wi toward the light, wo toward the detector
            ci, co = mi.Frame3f.cos_theta(wi_g), mi.Frame3f.cos_theta(wo_g)
            h = wi_g + wo_g
            n2 = dr.squared_norm(h)
            valid = n2 > 0.0
            wm = h * dr.rsqrt(dr.select(valid, n2, 1.0))
            cc = ci * co
            ok = valid & (cc > 0.0) & (wm.z > 0.0)
            di, do = dr.dot(wi_g, wm), dr.dot(wo_g, wm)
            cos_d = 0.5 * (di + do)
            F = mi.fresnel(dr.clip(cos_d, 0.0, 1.0), self.eta)[0]
            den = dr.select(ok, 4.0 * cc, 1.0)
            coat = dr.select(ok, F * self.coat.eval(wm) * self.coat.G(wi_g, wo_g, wm) / den, 0.0)
            c2 = dr.select(ok, wm.z * wm.z, 1.0)
            t2 = (wm.x * wm.x + wm.y * wm.y) / c2
            shape = dr.exp(-self.p * dr.log(dr.select(ok, cc, 1.0))) / 4.0     # 1 / (4 (cos_i cos_o)^p)
            haze = dr.select(ok, self._lobe_d(self.haze_alpha, t2, c2) * shape, 0.0)
            a = dr.maximum(self.alpha_f.eval(si), _FLAKE_ALPHA_MIN)
            a = a * (1.0 + self.widen * (1.0 - dr.clip(cos_d, 0.0, 1.0)))
            flake = self._lobe_d(a, t2, c2) * dr.select(ok, shape, 0.0)
            rd, rs, rh, rf = (t.eval(si) for t in self.rho)
            return rd / math.pi + rs * coat + rh * haze + rf * flake

        def _pdf(self, si, wo):
            m = dr.normalize(si.wi + wo)
            dot = dr.dot(wo, m)
            pdf = self.w[0] * mi.warp.square_to_cosine_hemisphere_pdf(wo)
            for weight, w, distr in zip(self.weights[1:], self.w[1:], self.lobes):
                if weight > 0.0:
                    pdf += w * distr.pdf(si.wi, m) / (4.0 * dr.select(dot > 0.0, dot, 1.0))
            ok = (mi.Frame3f.cos_theta(si.wi) > 0) & (mi.Frame3f.cos_theta(wo) > 0) & (dot > 0.0)
            return dr.select(ok, pdf, 0.0)

        def pdf(self, ctx, si, wo, active=True):
            return dr.select(active, self._pdf(si, wo), 0.0)

        def sample(self, ctx, si, sample1, sample2, active=True):
            bs = mi.BSDFSample3f()
            w = mi.warp.square_to_cosine_hemisphere(sample2)
            edge = self.w[0]
            for weight, wk, distr in zip(self.weights[1:], self.w[1:], self.lobes):
                if weight > 0.0:
                    m, _ = distr.sample(si.wi, sample2)
                    w = dr.select(sample1 >= edge, mi.reflect(si.wi, m), w)
                edge = edge + wk
            bs.wo = w
            bs.pdf = self._pdf(si, w)
            bs.eta = 1.0
            cosine = sample1 < self.w[0]
            bs.sampled_type = dr.select(cosine, mi.UInt32(+mi.BSDFFlags.DiffuseReflection),
                                        mi.UInt32(+mi.BSDFFlags.GlossyReflection))
            bs.sampled_component = mi.UInt32(0)
            ok = active & (mi.Frame3f.cos_theta(si.wi) > 0) & (bs.pdf > 0)
            value = self.eval(ctx, si, bs.wo, ok) / dr.select(ok, bs.pdf, 1.0)
            return bs, dr.select(ok, value, 0.0)

        def to_string(self):
            return f"GonioFlakePaint[{self.kind}]"

    return FlakePaintBSDF
