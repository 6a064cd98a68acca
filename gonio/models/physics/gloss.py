"""Specular gloss (ASTM D523 / ISO 2813) of a BRDF: the gloss meter's reading, computed.

A surface's 60 deg gloss in gloss units (GU) from its f_r, and the limit below which D523
counts it as matte: what ``gonio perf real`` reports of a measured file and where
``--model auto`` tries a matte surface's sheen (gonio.models.catalogue.tabulated).
"""

from __future__ import annotations

import math

import numpy as np

from gonio.core.channels import SRGB_Y
from gonio.core.geometry import directions

__all__ = ["GLOSS_APERTURE_DEG", "GLOSS_STANDARD_N", "MATTE_BELOW_GU", "specular_gloss"]

#: ASTM D523-14 / ISO 2813: the 60 deg geometry's receptor aperture (deg, in the plane of
#: incidence x across it), the black glass standard's index (100 GU), and below what 60 deg
#: gloss a surface counts as matte (D523 sends surfaces below 10 GU at 60 deg to its 85 deg
#: low-gloss geometry)
GLOSS_APERTURE_DEG, GLOSS_STANDARD_N, MATTE_BELOW_GU = (4.4, 11.7), 1.567, 10.0


def specular_gloss(f_r, theta_deg=60.0, aperture_deg=GLOSS_APERTURE_DEG, n=25) -> float:
    """Specular gloss (GU) of a BRDF ``f_r(wi, wo) -> (N, 3)`` as ASTM D523 defines it: the
    luminance-weighted (Rec. 709 Y) reflectance into the receptor's rectangular aperture
    about the mirror direction, collimated light at ``theta_deg``, over the black glass
    standard's Fresnel reflectance (n = 1.567, 100 GU); ``n`` x ``n`` midpoints. The source
    aperture's 0.75 x 2.5 deg is left out (a collimated beam)."""
    d_in, d_out = (math.radians(a) for a in aperture_deg)
    u = (np.arange(n) + 0.5) / n - 0.5
    a, b = np.meshgrid(d_in * u, d_out * u, indexing="ij")
    tho = math.radians(theta_deg) + a.ravel()
    pho = math.pi + b.ravel() / np.sin(tho)
    wo = directions(tho, pho)
    wi = directions(np.full(tho.size, math.radians(theta_deg)), np.zeros(tho.size))
    from gonio.models.physics.fresnel import fresnel_dielectric

    f = np.asarray(f_r(wi, wo), float)
    if not np.all(np.isfinite(f)):
        raise ValueError("specular gloss: the BRDF is not finite inside the gloss receptor")
    refl = float(np.sum(f * (np.cos(tho) * (d_in * d_out / n ** 2))[:, None], axis=0) @ SRGB_Y)
    return 100.0 * refl / float(fresnel_dielectric(math.cos(math.radians(theta_deg)), GLOSS_STANDARD_N)[0])
