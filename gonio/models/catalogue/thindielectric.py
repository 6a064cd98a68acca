"""Model ``thindielectric``: a thin smooth slab, e.g. a window pane (Mitsuba 3 ``thindielectric``).

Both faces are smooth and parallel and the slab is thin: light leaves either mirrored or
straight through (no displacement, no refraction), with the interreflections between the two
faces summed, R' = R + T^2 R (1 + R^2 + ...) = 2R / (1 + R), T' = 1 - R' (absorption-free;
Mitsuba's form). The medium is the same on both sides, so no eta^2 enters. Two deltas:
:meth:`eval` is 0 at every pair, :meth:`ThinDielectric.specular` gives the directions and
R', T' (see :mod:`gonio.models.catalogue.dielectric` for why).
"""

from __future__ import annotations

import numpy as np

from gonio.core.geometry import as_directions
from gonio.models.base import Parameter, register
from gonio.models.catalogue.dielectric import Dielectric, SpecularLobes
from gonio.models.physics.fresnel import fresnel_dielectric

__all__ = ["ThinDielectric"]


@register
class ThinDielectric(Dielectric):
    """Thin smooth dielectric slab (Mitsuba 3 ``thindielectric``): two deltas, a
    :class:`~gonio.models.catalogue.dielectric.Dielectric` whose light leaves through the
    slab's far face instead of refracting into it.

    Parameters (``params`` keys)
    ----------------------------
    int_ior : float
        Index of the slab relative to its surroundings, in [0.25, 4].

    Notes
    -----
    R = F(|cos theta_i|; eta) of one face, R' = 2R / (1 + R) (the geometric series of
    internal reflections), T' = 1 - R'; at normal incidence for eta 1.5: R = 0.04,
    R' = 0.0769, T' = 0.923.
    """

    name = "thindielectric"

    def _parameters(self):
        return (Parameter("int_ior", 1.5, 0.25, 4.0, "1", "index of the slab relative to its surroundings"),)

    def specular(self, wi, params) -> SpecularLobes:
        """The two deltas for light from ``wi``: mirrored with R', straight through with T'."""
        eta = self.validate(params)["int_ior"]
        wi = as_directions(wi, "wi")
        r = fresnel_dielectric(np.abs(np.clip(wi[:, 2], -1.0, 1.0)), eta)[0]
        r = 2.0 * r / (1.0 + r)
        t = 1.0 - r
        return SpecularLobes(wi * [-1.0, -1.0, 1.0], r, -wi, t, t)

    def to_mitsuba(self, params):
        p = self.validate(params)
        return {"type": "thindielectric", "int_ior": p["int_ior"], "ext_ior": 1.0}
