"""gonio.models: physically based BRDF models that agree with Mitsuba 3.

Conventions: local shading frame, +z along the normal; ``wi`` points from the surface to the
**light**, ``wo`` to the **detector** (unit vectors, shape (N, 3)); ``wm`` a microfacet normal.
``eval`` returns f_r in sr^-1 per colour channel, shape (N, 3), *without* the cosine factor, 0
where either direction is at or below the horizon; float32 ``wi`` and ``wo`` give float32 (the
compiled float32 kernel), anything else float64 (``eval_dtype``). Mitsuba's ``si.wi`` is our
``wo``, its ``bsdf.eval`` gives f_r * cos(theta of our wi); dielectrics: exterior index 1.

API: ``get(name, **options)``, ``names()``, ``Model``, ``Parameter``, ``eval_dtype(wi, wo)``,
``mitsuba_variant()``; ``mitsuba`` (the one boundary to Mitsuba), ``geometry``, ``fast`` (the
compiled Dr.Jit path); ``fresnel_*``, ``MicrofacetDistribution``, ``lambert``, ``oren_nayar``.

>>> m = gonio.models.get("roughplastic", distribution="ggx")
>>> f = m.eval(wi, wo, {"diffuse_reflectance": [0.5, 0.4, 0.3], "alpha": 0.2})
"""

# Dielectric models' ``int_ior`` is the relative index eta; ``to_mitsuba`` passes
# ``ext_ior = 1.0``. ``gonio.perf.models.run()`` is the throughput benchmark.

from __future__ import annotations

from gonio.core import atomic, geometry  # noqa: F401  (public as gonio.models.geometry, .atomic)
# the catalogue registers its models on import
from gonio.models.catalogue import cooktorrance as _cooktorrance  # noqa: F401
from gonio.models.catalogue import flakepaint as _flakepaint  # noqa: F401
from gonio.models.catalogue import gratingpaint as _gratingpaint  # noqa: F401
from gonio.models.catalogue import lambertian as _lambertian
from gonio.models.catalogue import orennayar as _orennayar
from gonio.models.catalogue import principled as _principled
from gonio.models.catalogue import roughconductor as _roughconductor
from gonio.models.catalogue import roughconductor2 as _roughconductor2
from gonio.models.catalogue import roughplastic as _roughplastic
from gonio.models.catalogue import roughplastic2 as _roughplastic2
from gonio.models.catalogue import tabulated as _tabulated  # noqa: F401  (register models)
from gonio.models.engine import fast
from gonio.models.base import CHANNELS, Model, Parameter, eval_dtype, get, names
from gonio.models.physics.diffuse import lambert, oren_nayar
from gonio.models.physics.fresnel import fresnel_conductor, fresnel_dielectric, fresnel_schlick
from gonio.models.physics.microfacet import DISTRIBUTIONS, MicrofacetDistribution
from gonio.models.structure import Affine, Structure
from gonio.models.catalogue import tabulated  # the tabulated model's tables and grids (for fitting's data-driven start)
from gonio.models.mitsuba import mitsuba_variant


__all__ = [
    "get",
    "names",
    "Parameter",
    "Model",
    "Structure",
    "Affine",
    "CHANNELS",
    "eval_dtype",
    "mitsuba_variant",
    "fast",
    "geometry",
    "mitsuba",
    "fresnel_dielectric",
    "fresnel_conductor",
    "fresnel_schlick",
    "MicrofacetDistribution",
    "DISTRIBUTIONS",
    "lambert",
    "oren_nayar",
    "tabulated",
]
