"""Model ``roughplastic2``: a rough plastic with a second specular lobe.

Real coatings (paints, lacquers, varnished papers) show a sharp specular peak on a broader
glossy halo, which one microfacet lobe cannot follow (Ngan et al. 2005 fit two-lobe
Cook-Torrance and Ward models for the same reason; Loew et al. 2012 sec. 6). Here the two
lobes are two Mitsuba ``roughplastic`` layers of one coating (the same diffuse base and
index) that differ only in roughness, mixed by a weight:

    f_r = (1 - w) roughplastic(rho, alpha, eta) + w roughplastic(rho, alpha2, eta)

which is exactly Mitsuba's ``blendbsdf`` of the two (:meth:`RoughPlastic2.to_mitsuba`), so
the model renders through native plugins and matches Mitsuba term by term wherever
``roughplastic`` does. A convex combination of two energy-conserving BRDFs conserves
energy. Both lobes use the same distribution, and each distribution is an option.
"""

from __future__ import annotations

from gonio.models.base import Parameter, register
from gonio.models.catalogue.roughplastic import RoughPlastic
from gonio.models.catalogue.twolobe import TwoLobe

__all__ = ["RoughPlastic2"]


@register
class RoughPlastic2(TwoLobe):
    """Two-lobe rough plastic (see the module).

    Options
    -------
    distribution : {"beckmann", "ggx"}
        Microfacet distribution of both lobes.

    Parameters (``params`` keys)
    ----------------------------
    diffuse_reflectance : (3,)
        Albedo of the diffuse base, in [0, 1].
    alpha : float
        Roughness of the first lobe, in [1e-4, 1].
    alpha2 : float
        Roughness of the second lobe, in [1e-4, 1].
    weight : float
        Weight of the second lobe's layer, in [0, 1].
    int_ior : float
        Relative index of refraction of the coating, in [1.0001, 4].
    """

    name = "roughplastic2"
    OPTIONS = {"distribution": ("beckmann", "ggx")}
    energy_conserving = True
    #: fitted by name (``--model roughplastic2``), not tried by ``--model auto``: every new
    #: (alpha, alpha2, eta) recomputes two sets of roughplastic's transmittance tables
    #: (measured 13-26 s for one fit of 40 points, against 0.3-0.4 s for roughconductor2 and
    #: principled), which would multiply the cost of every automatic selection
    auto_candidate = False

    LAYER = RoughPlastic
    COMMON = ("diffuse_reflectance", "int_ior")

    def _parameters(self):
        return (
            Parameter("diffuse_reflectance", 0.5, 0.0, 1.0, "1", "albedo of the diffuse base", per_channel=True),
            Parameter("alpha", 0.05, 1e-4, 1.0, "1", "roughness of the first lobe"),
            Parameter("alpha2", 0.3, 1e-4, 1.0, "1", "roughness of the second lobe"),
            Parameter("weight", 0.3, 0.0, 1.0, "1", "weight of the second lobe's layer"),
            Parameter("int_ior", 1.49, 1.0001, 4.0, "1", "relative index of refraction of the coating"),
        )
