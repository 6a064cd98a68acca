"""Model ``diffuse``: the Lambertian BRDF of Mitsuba 3's ``diffuse`` plugin."""

from __future__ import annotations

from ._base import Model, Parameter, register, rgb
from ._structure import Affine, Structure
from ._diffuse import lambert

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
        return Structure(kernel=True, affine=Affine("reflectance"))
    OPTIONS = {}
    energy_conserving = True

    def _parameters(self):
        return (Parameter("reflectance", 0.5, 0.0, 1.0, "1", "Lambertian albedo rho", per_channel=True),)

    def _eval_parts(self, wi, wo, p):
        return lambert(p["reflectance"], wi.shape[0]), None

    def to_mitsuba(self, params):
        p = self.validate(params)
        return {"type": "diffuse", "reflectance": rgb(p["reflectance"])}
