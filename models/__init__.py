"""gonio.models: physically based BRDF models that agree with Mitsuba 3.

Conventions (everywhere in this package)
----------------------------------------
* Local shading frame, +z along the surface normal.
* ``wi`` points from the surface to the **light**, ``wo`` from the surface to the
  **detector**; both are unit vectors, arrays of shape (N, 3). ``eval`` returns the
  directions' precision: float32 ``wi`` and ``wo`` run the compiled float32 kernel and give
  float32 (the fast path), anything else gives float64. ``wm`` is a microfacet normal (the half vector for reflection).
* ``eval`` returns f_r in sr^-1 per colour channel, shape (N, 3), *without* the cosine
  factor; 0 where either direction is at or below the horizon.
* Mitsuba's ``bsdf.eval(ctx, si, wo_mi)`` has ``si.wi`` = our ``wo`` (camera) and
  ``wo_mi`` = our ``wi`` (light), and returns f_r * cos(theta of our wi).
* Dielectric models use an exterior index of exactly 1: ``int_ior`` is the relative
  index eta, and ``to_mitsuba`` passes ``ext_ior = 1.0``.

Public API
----------
``get(name, **options)``, ``names()``, ``Parameter``, ``Model`` (base class),
``eval_dtype(wi, wo)`` (the precision ``Model.eval`` gives these directions),
``mitsuba_variant()``; ``mitsuba`` (the one boundary to Mitsuba: variant, direction
convention, batched ``eval_cos``); ``geometry`` (directions from angles and back); ``fast`` (compiled Dr.Jit path: ``fast.available()``,
``fast.eval(model, wi, wo, params)``, ``fast.value_and_grad(model, wi, wo, params,
cotangent)``; on resident batches ``fast.Directions(wi, wo, dtype)`` (float32 or float64,
loaded once), ``fast.Bound(model, params, dtype).eval(dirs)``, ``fast.eval_resident``,
``fast.jacobian`` (f_r and d f_r / d every parameter, one kernel) and ``fast.chi2_grad``
(chi^2 and its gradient, reduced in the kernel)); ``gonio.models.speed.run()``
(throughput benchmark); the pieces ``fresnel_dielectric``, ``fresnel_conductor``,
``fresnel_schlick``, ``MicrofacetDistribution``, ``lambert``, ``oren_nayar``.

Example
-------
>>> import gonio.models as gm
>>> m = gm.get("roughplastic", distribution="ggx")
>>> f = m.eval(wi, wo, {"diffuse_reflectance": [0.5, 0.4, 0.3], "alpha": 0.2})
"""

from __future__ import annotations

from . import _cooktorrance, _lambertian, _orennayar, _principled, _roughconductor, _roughconductor2, _roughplastic, _roughplastic2, _tabulated  # noqa: F401  (register models)
from . import _albedo, _albedo_jit
from . import _fast as fast
from ._base import CHANNELS, Model, Parameter, eval_dtype, get, install_compiled, names
from ._diffuse import lambert, oren_nayar
from ._fresnel import fresnel_conductor, fresnel_dielectric, fresnel_schlick
from ._microfacet import DISTRIBUTIONS, MicrofacetDistribution
from ._structure import Affine, Structure
from . import _tabulated as tabulated  # the tabulated model's tables and grids (for fitting's data-driven start)
from .mitsuba import mitsuba_variant

install_compiled(fast._eval_checked, fast.available)  # Model.eval's compiled path, on what it has checked (models/_base cannot import it)
_albedo.install_compiled(_albedo_jit.applies, _albedo_jit.lobe_integral, _albedo_jit.smooth_integral)  # albedo's compiled quadratures (likewise)
del install_compiled

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
