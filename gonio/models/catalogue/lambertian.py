"""Model ``diffuse``: the Lambertian BRDF of Mitsuba 3's ``diffuse`` plugin."""

from __future__ import annotations

import math

from gonio.core.sides import sides_mask
from gonio.models.base import CHANNELS, Model, Parameter, register, rgb
from gonio.models.engine.jit import channels
from gonio.models.structure import Affine, Structure
from gonio.models.physics.diffuse import lambert

__all__ = ["Diffuse"]


@register
class Diffuse(Model):
    """Lambertian reflector, f_r = rho / pi (Mitsuba ``diffuse``; Lambert 1760).

    Parameters (``params`` keys)
    ----------------------------
    reflectance : (3,)
        Albedo rho per channel, in [0, 1].
    """

    name = "diffuse"

    @property
    def structure(self):
        return Structure(kernel=_jit_kernel, freeze=False, affine=Affine("reflectance", kernel=_jit_affine_parts),
                         geometry=_jit_geometry, body=_jit_body)
    OPTIONS = {}
    energy_conserving = True
    compiled_min_pairs = 768  # numpy's few operations beat the compiled call's ~50 us below this (measured)

    def _parameters(self):
        return (Parameter("reflectance", 0.5, 0.0, 1.0, "1", "Lambertian albedo rho", per_channel=True),)

    def _eval_parts(self, wi, wo, p):
        return lambert(p["reflectance"], wi.shape[0]), None

    def to_mitsuba(self, params):
        p = self.validate(params)
        return {"type": "diffuse", "reflectance": rgb(p["reflectance"])}


def _jit_geometry(model, dr, wi, wo):
    """The kernel's parameter-independent part: 1 / pi on the model's sides (reflection: both
    cosines > 0), 0 elsewhere."""
    return (dr.select(sides_mask(model.structure.sides, wi.z, wo.z), 1.0 / math.pi + 0.0 * wi.z, 0.0),)


def _jit_body(model, k, g, P, grad):
    """f_r = rho u, d f / d rho = u, u = :func:`_jit_geometry`'s."""
    u = g[0]
    f = [r * u for r in channels(P, "reflectance")]
    return f, ({"reflectance": [u] * CHANNELS} if grad else {})


def _jit_kernel(model, k, wi, wo, P, grad):
    """The compiled kernel (:mod:`gonio.models.fast`): f_r = rho / pi, d f / d rho = 1 / pi
    (:func:`_jit_body` after :func:`_jit_geometry`)."""
    return _jit_body(model, k, _jit_geometry(model, k.dr, wi, wo), P, grad)


def _jit_affine_parts(model, k, cols, lanes, K, vi, vo, tables):
    """base = 0, basis = 1 / pi above the horizon (``fast.affine_parts``)."""
    dr, F = k.dr, k.F
    return F(0.0) * vi.z, dr.select(k.active, F(1.0 / math.pi), F(0.0))
