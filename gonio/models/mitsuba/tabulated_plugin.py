"""Mitsuba 3 Python BSDF of the ``tabulated`` model (registered as ``gonio_tabulated``).

Registered by :func:`gonio.models.mitsuba.plugins.ensure_registered`. The constructor rebuilds
the model's tables from the plugin's properties with the numpy code of
:func:`gonio.models.catalogue.tabulated.tables`; ``eval`` interpolates them exactly as the numpy
model does (the same fractional indices, ``dr.gather``), in float32, with the table body
(``body_j``) and the sheen lobe (``sheen_alpha``) where the properties give them. ``sample``
draws from a mixture of the lobe's normals, cosine-weighted directions and the sheen's normals,
and ``pdf`` is exactly that mixture's density (the notes below).
"""

# Sampling: reflections about microfacet normals m drawn from the channels' mean D (normalised,
# so D cos(theta_m) is a density of m), piecewise constant on SAMPLING_BINS rings of the warped
# theta grid (uniform in solid angle within a ring); pdf(wo) = q p_m(h) / (4 wo . h) + (1 - q)
# cos(theta_o) / pi, q the mean Fresnel factor's share of (mean F + mean rho + mean sheen
# amplitude), clipped to [Q_MIN, Q_MAX]. With the sheen, a third part draws m from its GGX
# D cos(theta_m) (Walter et al. 2007, eqs. 35 and 36); its share of the rest is the sheen's share
# of (mean rho + mean sheen amplitude), at most SHEEN_MAX.

from __future__ import annotations

import math

import numpy as np

from gonio.core.channels import CHANNELS

#: rings of the sampled microfacet normal (warped like the knots: dense at the core)
SAMPLING_BINS = 1024
#: bounds of the probability of sampling the lobe (the rest: cosine-weighted)
Q_MIN, Q_MAX = 0.2, 0.9
#: the most of the non-lobe share that samples the sheen (the rest: cosine-weighted, which
#: covers every direction)
SHEEN_MAX = 0.5


def make_bsdf(mi, dr, base, tab):
    """The BSDF class for the active variant, derived from gonio's Python BSDF ``base``;
    ``tab`` is the model's module (:mod:`gonio.models.catalogue.tabulated`, passed in: no import cycle)."""
    models = {(b, s): tab.Tabulated(body=b, sheen=s) for b in ("lambert", "table") for s in ("none", "ggx")}

    def lerp(table, n, s, c):
        """Channel ``c`` of a flattened (C, n) table at fractional indices ``s``."""
        i = dr.clip(mi.UInt32(dr.floor(s)), 0, n - 2)
        t = dr.clip(s - mi.Float(i), 0.0, 1.0)
        lo = dr.gather(mi.Float, table, c * n + i)
        hi = dr.gather(mi.Float, table, c * n + i + 1)
        return lo * (1.0 - t) + hi * t

    F64 = dr.float64_array_t(mi.Float)

    def polar(v):
        return dr.atan2(dr.sqrt(v.x * v.x + v.y * v.y), v.z)

    def polar64(x, y, z):
        """Polar angle in float64 (float32's atan2 is off by a few ulp, which a steep ln D
        table turns into 1e-5 relative; measured)."""
        return dr.atan2(dr.sqrt(x * x + y * y), z)

    class TabulatedBSDF(base):
        def __init__(self, props):
            base.__init__(self, props)
            params = {}
            model = models[("table" if "body_1" in props else "lambert", "ggx" if "sheen_alpha" in props else "none")]
            for par in model.parameters:
                params[par.name] = ([float(props[f"{par.name}_{c}"]) for c in "rgb"] if par.per_channel
                                    else float(props[par.name]))
            t = tab.tables(model.validate(params))
            self.rho = mi.Color3f(*[float(x) for x in t.rho / math.pi])
            self.ln_d = mi.Float(np.ascontiguousarray(t.ln_d - t.ln_z[:, None], dtype=np.float32).ravel())
            self.g1 = mi.Float(np.ascontiguousarray(t.g1, dtype=np.float32).ravel())
            self.fresnel = mi.Float(np.ascontiguousarray(t.fresnel, dtype=np.float32).ravel())
            self.width = mi.Float(np.ascontiguousarray(t.width, dtype=np.float32).ravel())
            self.body = mi.Float(np.ascontiguousarray(t.body, dtype=np.float32).ravel())
            self.table = model.options["body"] == "table"
            self.sheen = t.sheen is not None
            amp = tab.tabulated_sheen.amplitudes(t.sheen) if self.sheen else np.zeros((CHANNELS, tab.N_FRESNEL))
            self.sheen_amp = mi.Float(np.ascontiguousarray(amp, dtype=np.float32).ravel())
            self.sheen_a2 = mi.Float(float(t.sheen["sheen_alpha"]) ** 2 if self.sheen else 0.0)
            dr.make_opaque(self.rho, self.ln_d, self.g1, self.fresnel, self.width, self.body, self.sheen_amp,
                           self.sheen_a2)
            # importance sampling (module notes): the channels' mean D on SAMPLING_BINS rings
            edges = 0.5 * math.pi * (np.linspace(0.0, 1.0, SAMPLING_BINS + 1)) ** 2
            cos_e = np.cos(edges)
            cos_e[-1] = 0.0
            mid = tab.knot_index(0.5 * (edges[:-1] + edges[1:]))
            d_mid = np.exp(tab._interp(t.ln_d, mid) - t.ln_z[None, :]).mean(axis=1)
            ring = 2.0 * math.pi * (cos_e[:-1] - cos_e[1:])  # solid angle of each ring
            mass = d_mid * 0.5 * (cos_e[:-1] + cos_e[1:]) * ring  # int D cos dm over the ring
            self.dist = mi.DiscreteDistribution(mi.Float(mass.astype(np.float32)))
            self.density = mi.Float((mass / mass.sum() / ring).astype(np.float32))  # pdf of m per sr
            self.cos_lo = mi.Float(cos_e[1:].astype(np.float32))
            self.cos_hi = mi.Float(cos_e[:-1].astype(np.float32))
            spec = float(np.mean(t.fresnel))
            rest = float(np.mean(t.rho)) + float(np.mean(amp))      # sampled by the cosine-weighted part
            q = float(np.clip(spec / max(spec + rest, 1e-12), Q_MIN, Q_MAX))
            share = float(np.mean(amp)) / max(rest, 1e-12) if self.sheen else 0.0
            self.q = mi.Float(q)
            self.q_sheen = mi.Float((1.0 - q) * min(share, SHEEN_MAX))
            dr.make_opaque(self.density, self.cos_lo, self.cos_hi, self.q, self.q_sheen)

        def _pdf_m(self, m):
            """pdf of the sampled microfacet normal m per steradian (piecewise constant)."""
            b = mi.UInt32(dr.clip(dr.floor(SAMPLING_BINS * dr.sqrt(dr.clip(polar(m) / (0.5 * math.pi), 0.0, 1.0))),
                                  0, SAMPLING_BINS - 1))
            return dr.gather(mi.Float, self.density, b)

        def pdf(self, ctx, si, wo, active=True):
            ok = active & (mi.Frame3f.cos_theta(si.wi) > 0) & (mi.Frame3f.cos_theta(wo) > 0)
            h = dr.normalize(si.wi + wo)
            dh = dr.dot(wo, h)
            p_spec = dr.select(dh > 0, self._pdf_m(h) / (4.0 * dr.select(dh > 0, dh, 1.0)), 0.0)
            p_cos = mi.warp.square_to_cosine_hemisphere_pdf(wo)
            p = self.q * p_spec + (1.0 - self.q - self.q_sheen) * p_cos
            if self.sheen:      # GGX D(h) cos(theta_h) / (4 wo . h)
                a2 = self.sheen_a2
                ch2 = dr.clip(h.z, 0.0, 1.0) ** 2
                u = a2 * ch2 + (1.0 - ch2)
                p_sheen = a2 / (math.pi * u * u) * dr.clip(h.z, 0.0, 1.0) / (4.0 * dr.select(dh > 0, dh, 1.0))
                p = p + self.q_sheen * dr.select(dh > 0, p_sheen, 0.0)
            return dr.select(ok, p, 0.0)

        def sample(self, ctx, si, sample1, sample2, active=True):
            spec = sample1 < self.q
            b, u = self.dist.sample_reuse(sample2.x)
            lo, hi = dr.gather(mi.Float, self.cos_lo, b), dr.gather(mi.Float, self.cos_hi, b)
            cos_m = lo + (hi - lo) * u  # uniform in solid angle within the ring
            sin_m = dr.sqrt(dr.maximum(0.0, 1.0 - cos_m * cos_m))
            phi = 2.0 * math.pi * sample2.y
            m = mi.Vector3f(sin_m * dr.cos(phi), sin_m * dr.sin(phi), cos_m)
            w_spec = 2.0 * dr.dot(si.wi, m) * m - si.wi
            bs = mi.BSDFSample3f()
            bs.wo = dr.select(spec, w_spec, mi.warp.square_to_cosine_hemisphere(sample2))
            if self.sheen:      # the sheen's GGX normals: tan^2(theta_m) = a^2 v / (1 - v)
                sheen = ~spec & (sample1 < self.q + self.q_sheen)
                v = dr.clip(sample2.x, 0.0, 1.0 - 1e-7)
                cos_s = dr.rsqrt(1.0 + self.sheen_a2 * v / (1.0 - v))
                sin_s = dr.sqrt(dr.maximum(0.0, 1.0 - cos_s * cos_s))
                m_s = mi.Vector3f(sin_s * dr.cos(phi), sin_s * dr.sin(phi), cos_s)
                bs.wo = dr.select(sheen, 2.0 * dr.dot(si.wi, m_s) * m_s - si.wi, bs.wo)
            bs.pdf = self.pdf(ctx, si, bs.wo, active)
            bs.eta = 1.0
            bs.sampled_type = mi.UInt32(+mi.BSDFFlags.GlossyReflection)
            bs.sampled_component = mi.UInt32(0)
            ok = active & (mi.Frame3f.cos_theta(si.wi) > 0) & (mi.Frame3f.cos_theta(bs.wo) > 0) & (bs.pdf > 0)
            value = self.eval(ctx, si, bs.wo, ok) / dr.select(ok, bs.pdf, 1.0)
            return bs, dr.select(ok, value, 0.0)

        def eval_pdf(self, ctx, si, wo, active=True):
            return self.eval(ctx, si, wo, active), self.pdf(ctx, si, wo, active)

        def _f(self, si, wo):
            wi_g, wo_g = wo, si.wi  # gonio: wi toward the light, wo toward the detector
            ci = mi.Frame3f.cos_theta(wi_g)
            co = mi.Frame3f.cos_theta(wo_g)
            # the geometry of the table indices in float64 (the directions are float32)
            ix, iy, iz = F64(wi_g.x), F64(wi_g.y), F64(wi_g.z)
            ox, oy, oz = F64(wo_g.x), F64(wo_g.y), F64(wo_g.z)
            hx, hy, hz = ix + ox, iy + oy, iz + oz
            hn = dr.sqrt(hx * hx + hy * hy + hz * hz)
            up64 = (hn > 0) & (hz > 0)
            cd = 0.5 * (ix * hx + iy * hy + iz * hz + ox * hx + oy * hy + oz * hz) / dr.select(up64, hn, 1.0)
            up = mi.Bool(up64 & (cd > 0))
            half_pi = 0.5 * math.pi
            s_f = mi.Float((tab.N_FRESNEL - 1) * dr.clip(1.0 - cd, 0.0, 1.0))
            w = lerp(self.width, tab.N_FRESNEL, s_f, 0)
            s_h = mi.Float((tab.N_KNOTS - 1) * dr.sqrt(dr.clip(polar64(hx, hy, hz) / (F64(w) * half_pi), 0.0, 1.0)))
            s_i = mi.Float((tab.N_G - 1) * (1.0 - dr.sqrt(dr.clip(1.0 - polar64(ix, iy, iz) / half_pi, 0.0, 1.0))))
            s_o = mi.Float((tab.N_G - 1) * (1.0 - dr.sqrt(dr.clip(1.0 - polar64(ox, oy, oz) / half_pi, 0.0, 1.0))))
            den = 4.0 * dr.select(up, ci * co, 1.0) * w * w
            lobe, body = [], []
            if self.sheen:      # tabulated_sheen.shape: D / ((ci + q_i)(co + q_o)), GGX of sheen_alpha
                a2 = self.sheen_a2
                r2 = dr.select(up64, hn * hn, 1.0)     # u in float64: sin^2 from |h_xy|^2, not 1 - cos^2
                u = mi.Float(dr.select(up64, F64(a2) * dr.minimum(hz * hz / r2, 1.0) + (hx * hx + hy * hy) / r2, 1.0))
                ci_, co_ = dr.select(up, ci, 1.0), dr.select(up, co, 1.0)
                qi = dr.sqrt(ci_ * ci_ + a2 * (1.0 - ci_ * ci_))
                qo = dr.sqrt(co_ * co_ + a2 * (1.0 - co_ * co_))
                unit = a2 / (math.pi * u * u) / ((ci_ + qi) * (co_ + qo))
            b_i, b_o = (mi.Float((tab.N_BODY - 1) * dr.minimum(dr.acos(dr.clip(z, -1.0, 1.0)) / tab.BODY_MAX, 1.0))
                        for z in (iz, oz))
            for c in range(CHANNELS):
                body.append(lerp(self.body, tab.N_BODY, b_i, 0) * lerp(self.body, tab.N_BODY, b_o, 0) if self.table
                            else mi.Float(1.0))
                D = dr.exp(lerp(self.ln_d, tab.N_KNOTS, s_h, c))
                G = lerp(self.g1, tab.N_G, s_i, c) * lerp(self.g1, tab.N_G, s_o, c)
                F = lerp(self.fresnel, tab.N_FRESNEL, s_f, c)
                value = F * D * G / den
                if self.sheen:
                    value = value + lerp(self.sheen_amp, tab.N_FRESNEL, s_f, c) * unit
                lobe.append(dr.select(up, value, 0.0))
            return self.rho * mi.Color3f(*body) + mi.Color3f(*lobe)

        def to_string(self):
            return "GonioTabulated[]"

    return TabulatedBSDF
