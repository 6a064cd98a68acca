"""Mitsuba 3 Python BSDF of the ``tabulated`` model (registered as ``gonio_tabulated`` by
:func:`gonio.models._mitsuba_plugins.ensure_registered`).

The constructor rebuilds the model's tables from the plugin's properties with the numpy
code of :mod:`._tabulated` (:func:`~gonio.models._tabulated.tables`: ln D knots, the
normalisation, the Smith G1 table derived from D, the Fresnel knots); ``eval`` interpolates
them exactly as the numpy model does (the same fractional indices, linear interpolation by
``dr.gather``), in float32. Polar angles come from ``atan2(|xy|, z)``, well conditioned near
the normal where ``acos`` is not.
"""

from __future__ import annotations

import math

import numpy as np

from ._base import CHANNELS


def make_bsdf(mi, dr, base):
    """The BSDF class for the active variant, derived from gonio's Python BSDF ``base``."""
    from . import _tabulated as tab

    model = tab.Tabulated()

    def lerp(table, n, s, c):
        """Channel ``c`` of a flattened (C, n) table at fractional indices ``s``."""
        i = dr.clip(mi.UInt32(dr.floor(s)), 0, n - 2)
        t = dr.clip(s - mi.Float(i), 0.0, 1.0)
        lo = dr.gather(mi.Float, table, c * n + i)
        hi = dr.gather(mi.Float, table, c * n + i + 1)
        return lo * (1.0 - t) + hi * t

    def polar(v):
        return dr.atan2(dr.sqrt(v.x * v.x + v.y * v.y), v.z)

    class TabulatedBSDF(base):
        def __init__(self, props):
            base.__init__(self, props)
            params = {}
            for par in model.parameters:
                params[par.name] = [float(props[f"{par.name}_{c}"]) for c in "rgb"]
            t = tab.tables(model.validate(params))
            self.rho = mi.Color3f(*[float(x) for x in t.rho / math.pi])
            self.ln_d = mi.Float(np.ascontiguousarray(t.ln_d - t.ln_z[:, None], dtype=np.float32).ravel())
            self.g1 = mi.Float(np.ascontiguousarray(t.g1, dtype=np.float32).ravel())
            self.fresnel = mi.Float(np.ascontiguousarray(t.fresnel, dtype=np.float32).ravel())
            dr.make_opaque(self.rho, self.ln_d, self.g1, self.fresnel)

        def _f(self, si, wo):
            wi_g, wo_g = wo, si.wi  # gonio: wi toward the light, wo toward the detector
            ci = mi.Frame3f.cos_theta(wi_g)
            co = mi.Frame3f.cos_theta(wo_g)
            h = wi_g + wo_g
            hn = dr.norm(h)
            up = (hn > 0) & (h.z > 0)
            cd = 0.5 * (dr.dot(wi_g, h) + dr.dot(wo_g, h)) / dr.select(up, hn, 1.0)
            up &= cd > 0
            s_h = (tab.N_KNOTS - 1) * dr.sqrt(dr.clip(polar(h) / (0.5 * math.pi), 0.0, 1.0))
            s_i = (tab.N_G - 1) * (1.0 - dr.sqrt(dr.clip(1.0 - polar(wi_g) / (0.5 * math.pi), 0.0, 1.0)))
            s_o = (tab.N_G - 1) * (1.0 - dr.sqrt(dr.clip(1.0 - polar(wo_g) / (0.5 * math.pi), 0.0, 1.0)))
            s_f = (tab.N_FRESNEL - 1) * dr.clip(1.0 - cd, 0.0, 1.0)
            den = 4.0 * dr.select(up, ci * co, 1.0)
            lobe = []
            for c in range(CHANNELS):
                D = dr.exp(lerp(self.ln_d, tab.N_KNOTS, s_h, c))
                G = lerp(self.g1, tab.N_G, s_i, c) * lerp(self.g1, tab.N_G, s_o, c)
                F = lerp(self.fresnel, tab.N_FRESNEL, s_f, c)
                lobe.append(dr.select(up, F * D * G / den, 0.0))
            return self.rho + mi.Color3f(*lobe)

        def to_string(self):
            return "GonioTabulated[]"

    return TabulatedBSDF
