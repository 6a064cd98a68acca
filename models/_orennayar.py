"""Model ``orennayar``: rough diffuse reflection (Oren & Nayar 1994, qualitative model)."""

from __future__ import annotations

import math


from ._base import Model, Parameter, register
from ._structure import Affine, Structure
from ._diffuse import oren_nayar

__all__ = ["OrenNayar"]


@register
class OrenNayar(Model):
    """Oren-Nayar rough diffuse BRDF (see :func:`gonio.models.oren_nayar`).

    Parameters (``params`` keys)
    ----------------------------
    reflectance : (3,)
        Facet albedo rho in [0, 1].
    sigma : float
        Standard deviation of facet slope angles, radians, in [0, pi/2] (0 is Lambert).

    Notes
    -----
    Energy-conserving for rho <= 1 (the qualitative model's albedo stays below rho;
    checked by the albedo tests). Mitsuba 3 has no native plugin: ``to_mitsuba`` uses a
    registered Python BSDF (``gonio_orennayar``) with the same formula.
    """

    name = "orennayar"

    @property
    def structure(self):
        return Structure(kernel=True, affine=Affine("reflectance", ("sigma",)))
    OPTIONS = {}
    energy_conserving = True

    def _parameters(self):
        return (
            Parameter("reflectance", 0.5, 0.0, 1.0, "1", "facet albedo rho", per_channel=True),
            Parameter("sigma", 0.3, 0.0, math.pi / 2, "rad", "standard deviation of facet slope angle"),
        )

    def _eval_parts(self, wi, wo, p):
        return oren_nayar(wi, wo, p["reflectance"], p["sigma"]), None

    def to_mitsuba(self, params):
        from ._mitsuba_plugins import ensure_registered

        p = self.validate(params)
        d = {"type": ensure_registered("orennayar"), "sigma": p["sigma"]}
        for c, v in zip("rgb", p["reflectance"]):
            d[f"reflectance_{c}"] = float(v)
        return d
