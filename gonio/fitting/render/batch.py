"""Batched Mitsuba evaluation at the measured geometry: 1e4 poses in one vectorised call.

:class:`gonio.fitting.render.VirtualGonio` renders one scene per pose (a flat sample, a
``directional`` lamp, a ``radiancemeter``, the ``direct`` integrator). For that scene the
rendered radiance is exactly ``bsdf.eval(ctx, si, wi) * E`` at the one intersection the
meter's ray makes with the sample (no Monte Carlo noise: a delta light and a single ray), so
the same numbers come out of one *wavefront* ``bsdf.eval`` over all poses: a
``SurfaceInteraction3f`` of size N with the identity shading frame (the flat sample's),
``si.wi`` = gonio's ``wo`` (Mitsuba's ``si.wi`` points to the sensor) and the evaluated
direction = gonio's ``wi`` (toward the lamp). ``bsdf.eval`` returns f_r * cos(theta_i); we
divide by cos(theta_i) (:func:`gonio.models.mitsuba.eval_cos`).
:func:`gonio.fitting.render.scene_check` re-renders a subset with the real scene to show the
two agree (tests: 1e-5 relative). In ``llvm_ad_rgb`` the evaluation is one JIT kernel; in
``scalar_rgb`` (no LLVM) a Python loop over ``bsdf.eval`` (still no scene per pose).
"""

from __future__ import annotations

import time

from gonio.core.geometry import finite_directions
from gonio.models.mitsuba import divide_cos, eval_cos, in_tangent_frame, select_variant

__all__ = ["check_renders_in", "render_brdf_batch", "renders_in"]


def renders_in(model, variant: str) -> bool:
    """Whether ``model``'s Mitsuba BSDF runs in ``variant``: every one in the vectorised variants,
    not those whose plugin gathers tables (``mitsuba_scalar = False``: tabulated) in a scalar one."""
    return getattr(type(model), "mitsuba_scalar", True) or not str(variant).startswith("scalar")


def check_renders_in(model, variant: str) -> None:
    """ValueError (one line) where ``model`` cannot render in ``variant`` (:func:`renders_in`)."""
    if not renders_in(model, variant):
        raise ValueError(f"{model.name} renders in a vectorised Mitsuba variant (llvm_ad_rgb), not {variant}: its "
                         "plugin gathers tables; give --variant llvm_ad_rgb or leave it out")


def render_brdf_batch(model, params, wi, wo, variant: str | None = None):
    """What Mitsuba renders for the exported model at each measured pose, in one batch.

    Parameters
    ----------
    model : gonio.models.Model
    params : dict
        Parameter values (``model.to_mitsuba(params)`` is what is loaded).
    wi, wo : array_like, shape (N, 3)
        Toward the light and toward the detector (gonio convention).
    variant : str, optional
        ``llvm_ad_rgb`` (one vectorised call) or ``scalar_rgb`` (a loop); gonio's process
        choice when None.

    Returns
    -------
    fr : ndarray, shape (N, 3)
        Rendered f_r in sr^-1 (the virtual gonioreflectometer's L / (E cos(theta_i))); 0 for
        pairs on none of the model's sides (a reflector: either direction at or below the horizon).
    seconds : float
        Wall time including loading the BSDF (and the JIT compilation, first call).
    variant : str
        The Mitsuba variant that ran.
    """
    t0 = time.perf_counter()
    import mitsuba as mi

    variant = select_variant(variant)
    check_renders_in(model, variant)
    wi = finite_directions(wi, "wi")
    wo = finite_directions(wo, "wo")

    with mi.scoped_set_variant(variant):  # Python plugins register for the active variant
        bsdf = model.to_mitsuba(params)
    try:    # the BSDF is written in the model's tangent frame (anisotropic roughconductor)
        values = eval_cos(bsdf, in_tangent_frame(model, params, wi), in_tangent_frame(model, params, wo), variant)
    except Exception as exc:
        kind = bsdf.get("type", "?") if isinstance(bsdf, dict) else type(bsdf).__name__
        raise RuntimeError(f"Mitsuba could not load or evaluate BSDF {kind!r} in {variant}: {exc}") from exc
    return divide_cos(values, wi, wo, model.structure.sides), time.perf_counter() - t0, variant
