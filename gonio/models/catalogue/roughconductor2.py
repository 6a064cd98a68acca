"""Model ``roughconductor2``: a rough conductor with a second specular lobe.

Metallic paints and brushed or bead-blasted metals show a sharp specular peak on a broader
glossy halo, which one microfacet lobe cannot follow (Ngan et al. 2005 fit two-lobe
Cook-Torrance models for the same reason). Here the two lobes are two Mitsuba
``roughconductor`` layers of one metal (the same complex index) that differ only in
roughness, mixed by a weight:

    f_r = (1 - w) roughconductor(eta, k, alpha) + w roughconductor(eta, k, alpha2)

which is exactly Mitsuba's ``blendbsdf`` of the two (:meth:`RoughConductor2.to_mitsuba`), so
the model renders through native plugins and matches Mitsuba wherever ``roughconductor``
does. A convex combination of two energy-conserving BRDFs conserves energy. Both lobes use
the same distribution, and each distribution is an option.
"""

from __future__ import annotations

from gonio.models.base import Parameter, register
from gonio.models.catalogue.roughconductor import RoughConductor
from gonio.models.catalogue.twolobe import TwoLobe

__all__ = ["RoughConductor2"]


@register
class RoughConductor2(TwoLobe):
    """Two-lobe rough conductor (see the module).

    Options
    -------
    distribution : {"beckmann", "ggx"}
        Microfacet distribution of both lobes.

    Parameters (``params`` keys)
    ----------------------------
    eta, k : (3,)
        Complex index per channel (as ``roughconductor``).
    alpha, alpha2 : float
        Roughness of the first and the second lobe, in [1e-4, 1].
    weight : float
        Weight of the second lobe's layer, in [0, 1].
    """

    name = "roughconductor2"
    OPTIONS = {"distribution": ("beckmann", "ggx")}
    energy_conserving = True

    LAYER = RoughConductor
    COMMON = ("eta", "k")

    def _parameters(self):
        return (
            Parameter("eta", 0.2, 0.01, 10.0, "1", "real part of the complex index of refraction", per_channel=True),
            Parameter("k", 3.0, 0.0, 10.0, "1", "extinction coefficient (imaginary part of the index)", per_channel=True),
            Parameter("alpha", 0.05, 1e-4, 1.0, "1", "roughness of the first lobe"),
            Parameter("alpha2", 0.3, 1e-4, 1.0, "1", "roughness of the second lobe"),
            Parameter("weight", 0.3, 0.0, 1.0, "1", "weight of the second lobe's layer"),
        )
