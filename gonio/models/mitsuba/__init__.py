"""gonio's one boundary to Mitsuba 3: the variant, the direction convention, batched eval.

Everything in gonio that talks to Mitsuba goes through here (Mitsuba is imported lazily):

* :func:`mitsuba_variant` chooses the process-global variant once (``llvm_ad_rgb`` when LLVM
  works, else ``scalar_rgb`` with one line on stderr saying so; ``GONIO_MITSUBA_VARIANT``
  forces one); :func:`select_variant` is the same for callers that may name a variant;
  :data:`SCENE_VARIANT` is the variant of the one-ray-per-pose scenes (scalar).
* :func:`interaction` is the one place the direction convention is converted: Mitsuba's
  ``si.wi`` points to the sensor (gonio's ``wo``) and the direction ``bsdf.eval`` is asked
  about is gonio's ``wi`` (toward the light); ``bsdf.eval`` returns f_r * cos(theta_i).
* :func:`eval_cos`: a BSDF dict or object on a batch in gonio's convention, :func:`divide_cos`
  its f_r; :func:`bsdf_base`, :func:`ensure_registered`: gonio's Python BSDF plugins.
* :func:`tangent_to_world`, :func:`tangent_square`, :func:`in_tangent_frame`: a model's tangent
  frame; :func:`quarter_turns`, :func:`turn`: an isotropic ``measured`` BSDF's pairs turned.
"""

# SCENE_VARIANT is scalar: a single ray renders faster there than a kernel launch. eval_cos runs
# one kernel per chunk in LLVM, a loop in scalar.

from __future__ import annotations

import numpy as np

from gonio.core.channels import CHANNELS
from gonio.core.geometry import finite_directions
from gonio.core.sides import REFLECTION_ONLY, sides_mask
from gonio.models.mitsuba.plugins import bsdf_base, ensure_registered
from gonio.models.mitsuba.variant import FALLBACK, PREFERRED, SCENE_VARIANT, mitsuba_variant

__all__ = ["mitsuba_variant", "select_variant", "tangent_to_world", "tangent_square", "in_tangent_frame",
           "plugin_kind", "interaction", "eval_cos", "divide_cos", "bsdf_base",
           "ensure_registered", "quarter_turns", "turn", "PREFERRED", "FALLBACK", "SCENE_VARIANT"]


def select_variant(variant=None):
    """The variant to use (gonio's process choice when None); makes sure one is set globally."""
    import mitsuba as mi

    if variant is None:
        variant = mitsuba_variant()
    if mi.variant() is None:  # scoped_set_variant cannot restore "no variant"
        mi.set_variant(variant)
    return variant


def interaction(wi, wo):
    """A wavefront ``SurfaceInteraction3f`` and the direction to evaluate, gonio -> Mitsuba.

    ``wi``, ``wo`` (N, 3) in gonio's convention (toward the light, toward the detector);
    returns ``(si, w)`` for ``bsdf.eval(ctx, si, w)`` in the active (vectorised) variant:
    ``si.wi`` = gonio's ``wo`` (Mitsuba's points to the sensor), ``w`` = gonio's ``wi``,
    identity shading frame (the flat sample's). Directions are rounded to float32.
    """
    import drjit as dr
    import mitsuba as mi

    si = dr.zeros(mi.SurfaceInteraction3f, wi.shape[0])
    si.wi = mi.Vector3f(np.ascontiguousarray(wo.T, dtype=np.float32))
    si.sh_frame = mi.Frame3f(mi.Normal3f(0.0, 0.0, 1.0))
    si.n = mi.Normal3f(0.0, 0.0, 1.0)
    return si, mi.Vector3f(np.ascontiguousarray(wi.T, dtype=np.float32))


def quarter_turns(wo) -> np.ndarray:
    """Quarter turns (0-3, counter-clockwise about the normal) that give gonio's ``wo``
    (Mitsuba's ``si.wi``) the sign bit of both x and y. Mitsuba's ``measured`` BSDF (3.9.1)
    mirrors its inputs by those signs or not depending on a member it leaves uninitialised
    for isotropic files (``m_reduction``): one loaded copy of a file would sample and evaluate
    differently from another. With both sign bits set its mirroring is the identity. Turning
    both directions of a pair by the same quarter turns is exact (swaps and negations) and,
    for an isotropic BSDF, the same pair."""
    neg = np.signbit(np.asarray(wo)[:, :2])
    return np.select([neg[:, 0] & neg[:, 1], ~neg[:, 0] & ~neg[:, 1], ~neg[:, 0]], [0, 2, 3], 1)


def turn(w, k) -> np.ndarray:
    """``w`` (N, 3) turned by ``k`` (N,) quarter turns counter-clockwise about the normal."""
    w = np.asarray(w, dtype=np.float64)
    x, y = w[:, 0], w[:, 1]
    k = np.asarray(k) % 4
    out = w.copy()
    out[:, 0] = np.select([k == 1, k == 2, k == 3], [-y, -x, y], x)
    out[:, 1] = np.select([k == 1, k == 2, k == 3], [x, -y, -x], y)
    return out


def tangent_to_world(model, params, to_world=None):
    """The ``to_world`` of a flat shape (a ``rectangle``: normal +z, tangent dp/du along +x)
    carrying ``model.to_mitsuba(params)`` so that its BSDF's tangent frame is the model's:
    ``to_world @ rotate(z, tangent_deg)`` (the shape turned about its own normal; a Mitsuba
    BSDF dict holds no frame, the shading frame's tangent is the shape's dp/du). ``to_world``:
    a ``mitsuba.ScalarTransform4f`` (identity when None); the current variant's types."""
    import mitsuba as mi

    T = mi.ScalarTransform4f
    base = T() if to_world is None else to_world
    t = float(getattr(model, "tangent_deg", lambda p: 0.0)(params))
    return base if t == 0.0 else base @ T().rotate([0.0, 0.0, 1.0], t)


def in_tangent_frame(model, params, w):
    """Directions ``w`` (N, 3) of the holder frame as ``model.to_mitsuba(params)`` sees them:
    turned by -``model.tangent_deg(params)`` about the normal (``w`` itself where that is 0)."""
    t = float(getattr(model, "tangent_deg", lambda p: 0.0)(params))
    if t == 0.0:
        return w
    w = np.asarray(w, dtype=np.float64)
    c, s = np.cos(np.radians(t)), np.sin(np.radians(t))
    return np.stack([c * w[..., 0] + s * w[..., 1], c * w[..., 1] - s * w[..., 0], w[..., 2]], axis=-1)


def tangent_square(bsdf: dict, to_world, tangent_deg: float):
    """A ``rectangle``'s square ([-1, 1]^2 at z = 0 under ``to_world``) carrying ``bsdf``
    with its tangent frame turned by ``tangent_deg`` about the normal: the rectangle's dict
    itself at 0, else a two-triangle ``mitsuba.Mesh`` (a scene dict takes it as a value) whose
    texture coordinates are the square's turned by -tangent_deg, so that dp/du, the shading
    frame's tangent, lies at tangent_deg from to_world's x axis while the square covers what
    the rectangle covers (Mitsuba's mesh takes dp/du from its uv). Current variant."""
    import mitsuba as mi

    t = float(tangent_deg)
    if t == 0.0:
        return {"type": "rectangle", "to_world": to_world, "bsdf": bsdf}
    xy = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])
    c, s = np.cos(np.radians(t)), np.sin(np.radians(t))
    uv = np.c_[c * xy[:, 0] + s * xy[:, 1], c * xy[:, 1] - s * xy[:, 0]]
    mesh = mi.Mesh("sample", 4, 2, has_vertex_texcoords=True)
    params = mi.traverse(mesh)
    params["vertex_positions"] = np.array([list(to_world @ mi.ScalarPoint3f(x, y, 0.0)) for x, y in xy],
                                          dtype=np.float32).ravel()
    params["faces"] = np.array([0, 1, 2, 0, 2, 3], dtype=np.uint32)
    params["vertex_texcoords"] = uv.astype(np.float32).ravel()
    params.update()
    mesh.set_bsdf(mi.load_dict(bsdf))
    return mesh


def eval_cos(bsdf, wi, wo, variant: str | None = None, chunk: int = 1 << 20) -> np.ndarray:
    """Mitsuba's ``bsdf.eval`` in gonio's convention, batched.

    Parameters
    ----------
    bsdf : dict or mitsuba.BSDF
        A ``mitsuba.load_dict`` dict (loaded in ``variant``) or a BSDF already loaded in it.
    wi, wo : array_like, shape (N, 3)
        Toward the light and toward the detector (local frame, +z the normal).
    variant : str, optional
        Mitsuba variant; gonio's choice (:func:`mitsuba_variant`) when None.

    Returns
    -------
    ndarray, shape (N, 3), float64
        f_r(wi, wo) * cos(theta_i) as Mitsuba computes it (float32 inside); 0 below the
        horizon.
    """
    import drjit as dr
    import mitsuba as mi

    variant = select_variant(variant)
    wi = finite_directions(wi, "wi")
    wo = finite_directions(wo, "wo")
    if wi.shape != wo.shape:
        raise ValueError(f"wi and wo must have the same shape, got {wi.shape} and {wo.shape}")
    n = wi.shape[0]
    out = np.zeros((n, CHANNELS))
    if n == 0:
        return out
    with mi.scoped_set_variant(variant):
        if isinstance(bsdf, dict):
            bsdf = mi.load_dict(bsdf)
        ctx = mi.BSDFContext()
        if variant.startswith(("llvm", "cuda")):
            for start in range(0, n, chunk):
                stop = min(n, start + chunk)
                si, w = interaction(wi[start:stop], wo[start:stop])
                value = bsdf.eval(ctx, si, w)
                out[start:stop] = np.array(value, dtype=np.float64).reshape(CHANNELS, stop - start).T
        else:
            si = dr.zeros(mi.SurfaceInteraction3f)
            si.sh_frame = mi.Frame3f(mi.Normal3f(0.0, 0.0, 1.0))
            si.n = mi.Normal3f(0.0, 0.0, 1.0)
            wi32 = wi.astype(np.float32).tolist()
            wo32 = wo.astype(np.float32).tolist()
            for j in range(n):
                si.wi = mi.Vector3f(*wo32[j])  # Mitsuba's si.wi points to the sensor: gonio's wo
                value = bsdf.eval(ctx, si, mi.Vector3f(*wi32[j]))
                out[j] = (value[0], value[1], value[2])
    return out


def divide_cos(values, wi, wo, sides=REFLECTION_ONLY):
    """f_r from f_r * cos(theta_i); 0 for pairs on none of ``sides`` (reflection: either direction
    at or below the horizon)."""
    cos_i = wi[:, 2].astype(np.float32).astype(np.float64)  # the cosine Mitsuba multiplied by
    ok = sides_mask(sides, wi[:, 2], wo[:, 2], 1e-9)
    fr = np.zeros_like(values)
    fr[ok] = values[ok] / cos_i[ok, None]
    return fr


def plugin_kind(name: str) -> str:
    """What Mitsuba's plugin ``name`` makes, as its XML tag: ``"bsdf"``, ``"texture"``,
    ``"emitter"`` and so on (gonio's own plugins registered first); ``"texture"`` for a name
    Mitsuba does not know, which is how a scene refers to a texture."""
    import mitsuba as mi

    select_variant()
    if str(name).startswith("gonio_"):
        ensure_registered(str(name)[len("gonio_"):])
    try:
        kind = mi.PluginManager.instance().plugin_type(str(name))
    except Exception:
        return "texture"
    return str(kind).rsplit(".", 1)[-1].lower()
