"""Model ``difftrans``: an ideal diffuse transmitter, f_t = tau / pi through the surface
(Mitsuba 0.6's and Mitsuba 3's ``difftrans``; an opal diffuser, a thin paper, a diffusing film).

Light on either face leaves from the other face with the same radiance in every direction,
nothing on its own face: the integral of f_t |cos theta_o| is tau (<= 1), and f_t is
symmetric in wi and wo (reciprocal, no eta^2: both sides are the same medium). Mitsuba 3.9
ships no ``difftrans``, so the twin is a Python BSDF (``gonio_difftrans``, registered through
gonio.models.mitsuba.plugins) with cosine-weighted sampling on the far side.
"""

from __future__ import annotations

import math

import numpy as np

from gonio.core.sides import Side
from gonio.models.base import Model, Parameter, register
from gonio.models.physics.diffuse import lambert
from gonio.models.structure import Structure

__all__ = ["DiffTrans"]


@register
class DiffTrans(Model):
    """Diffuse transmitter, f_t = tau / pi on the far side, 0 on the lit side.

    Parameters (``params`` keys)
    ----------------------------
    transmittance : (3,)
        Diffuse transmittance tau per channel, in [0, 1].
    """

    name = "difftrans"
    auto_candidate = False   # selection offers it for data with transmitted points, not for a BRDF
    OPTIONS = {}
    energy_conserving = True

    @property
    def structure(self):
        return Structure(sides=(Side.TRANSMIT,))

    def _parameters(self):
        return (Parameter("transmittance", 0.5, 0.0, 1.0, "1", "diffuse transmittance tau", per_channel=True),)

    def _eval_parts(self, wi, wo, p):
        return lambert(p["transmittance"], wi.shape[0]), None

    def to_mitsuba(self, params):
        from gonio.models.mitsuba.plugins import add_plugin, ensure_registered, rgb_channels

        p = self.validate(params)
        add_plugin("difftrans", _make_bsdf)
        d = {"type": ensure_registered("difftrans")}
        for c, v in rgb_channels(self.name, p["transmittance"]):
            d[f"transmittance_{c}"] = float(v)
        return d


def _make_bsdf(mi, dr, base):
    """The Mitsuba twin: eval = tau / pi |cos theta_light| where the light and the detector
    are on opposite faces (Mitsuba's ``si.wi`` is gonio's wo, its ``wo`` gonio's wi)."""

    class DiffTransBSDF(base):
        def __init__(self, props):
            base.__init__(self, props)
            self.tau = mi.Color3f(*(float(props.get(f"transmittance_{c}", 0.5)) for c in "rgb"))
            flags = mi.BSDFFlags.DiffuseTransmission | mi.BSDFFlags.FrontSide | mi.BSDFFlags.BackSide
            self.m_components = [flags]
            self.m_flags = flags

        def eval(self, ctx, si, wo, active=True):
            ci, co = mi.Frame3f.cos_theta(wo), mi.Frame3f.cos_theta(si.wi)
            ok = active & (ci * co < 0)
            return dr.select(ok, self.tau * (dr.abs(ci) / math.pi), 0.0)

        def pdf(self, ctx, si, wo, active=True):
            ci, co = mi.Frame3f.cos_theta(wo), mi.Frame3f.cos_theta(si.wi)
            return dr.select(active & (ci * co < 0), dr.abs(ci) / math.pi, 0.0)

        def sample(self, ctx, si, sample1, sample2, active=True):
            bs = mi.BSDFSample3f()
            w = mi.warp.square_to_cosine_hemisphere(sample2)
            flip = mi.Frame3f.cos_theta(si.wi) > 0
            bs.wo = mi.Vector3f(w.x, w.y, dr.select(flip, -w.z, w.z))
            bs.pdf = mi.warp.square_to_cosine_hemisphere_pdf(w)
            bs.eta = 1.0
            bs.sampled_type = mi.UInt32(+mi.BSDFFlags.DiffuseTransmission)
            bs.sampled_component = mi.UInt32(0)
            ok = active & (bs.pdf > 0)
            return bs, dr.select(ok, self.tau, 0.0)

    return DiffTransBSDF
