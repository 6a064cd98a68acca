"""The models' compiled kernels as the resident paths call them (:mod:`gonio.models.engine.fast` re-exports
them): f_r per channel and, with ``grad``, its hand-written derivatives on Dr.Jit directions
(:func:`_kernel`) or on a batch's prepared geometry (:func:`_body`), the parameters as opaque
Dr.Jit scalars (:func:`_param_vars`), and one derivative column in numpy
(:func:`jacobian_column`)."""

from __future__ import annotations

import numpy as np

from gonio.core.sides import sides_mask
from gonio.models.engine.jit import JitContext


def _kernel(model, wi, wo, P, grad=False):
    """f_r per channel (list of 3 arrays) for Dr.Jit direction vectors wi, wo (float64 or
    float32); P maps parameter names to scalars of the same type (per-channel parameters:
    lists of 3) plus what the model's ``kernel_inputs`` adds (roughplastic: ``_tables``).

    The kernel itself is the model's own (``model.structure.kernel``, written beside the
    model with the pieces of :mod:`gonio.models.engine.jit`). With ``grad``, returns ``(f, J)``: J maps each
    parameter name to 3 arrays, d f[c] / d p (per-channel p: d f[c] / d p[c]), from
    derivatives written out by hand next to the value (forward mode, sharing every
    intermediate; tested against Dr.Jit's AD and finite differences)."""
    import drjit as dr

    impl = model.structure.kernel
    if impl is None:
        raise NotImplementedError(f"no compiled kernel for model {model.name!r}")
    if grad and not model.structure.derivatives:
        raise NotImplementedError(f"the compiled kernel of {model.name!r} gives values only")
    F = type(wi.z)
    ctx = JitContext(dr, F, dr.uint32_array_t(F), sides_mask(model.structure.sides, wi.z, wo.z), dr.zeros(F, dr.width(wi.z)))
    f, J = impl(model, ctx, wi, wo, P, grad)
    if not grad:
        return f
    aux = [c.aux for c in model.structure.coupled]
    return f, {name: J[name] for name in [par.name for par in model.parameters] + aux}


def jacobian_column(model, J, param, channel=-1):
    """d f_r / d one parameter entry, (N, 3), from :func:`jacobian`'s ``J`` (numpy): a
    shared parameter (``channel`` -1) acts on every channel, a per-channel one on its own
    channel only, unless the model declares it coupled (``structure.coupled``, a
    :class:`gonio.models.structure.Coupling`: principled's base colour), which adds
    weights[channel] * J[aux] in every channel."""
    d = np.asarray(J[param])
    if channel < 0:
        return d
    col = np.zeros_like(d)
    col[:, channel] = d[:, channel]
    link = model.structure.coupling(param)
    if link is not None:
        col = col + link.weights[channel] * np.asarray(J[link.aux])
    return col


def _body(model, g, P, grad=False):
    """:func:`_kernel` on a batch's prepared geometry ``g`` (:meth:`Directions.geometry`)
    instead of its directions: the model's ``structure.body``, the same formulas as its
    kernel after the geometry part."""
    import drjit as dr

    F = type(g[0])
    ctx = JitContext(dr, F, dr.uint32_array_t(F), None, dr.zeros(F, dr.width(g[0])))
    f, J = model.structure.body(model, ctx, g, P, grad)
    if not grad:
        return f
    aux = [c.aux for c in model.structure.coupled]
    return f, {name: J[name] for name in [par.name for par in model.parameters] + aux}


def _fJ(model, src, P, grad):
    """:func:`_kernel` on ``src``: the directions ``(wi, wo)``, or ``(g,)``, the batch's
    prepared geometry (:func:`_body`)."""
    if len(src) == 1:
        return _body(model, src[0], P, grad)
    return _kernel(model, *src, P, grad)


def _source(model, dirs):
    """What the resident paths (:func:`chi2_grad`, :func:`weighted_sse`,
    :func:`normal_equations`, :func:`jacobian`) read: ``(g,)``, the batch's geometry
    prepared once for the model (:meth:`Directions.geometry`), where the model declares
    one, else ``(wi, wo)``."""
    g = dirs.geometry(model)
    return (g,) if g is not None else (dirs.wi, dirs.wo)


def _param_vars(model, p, F, grad, dtables=False):
    """Dr.Jit scalars of type F for validated parameters ``p`` (opaque: a new value reuses
    the compiled kernel), AD-enabled when ``grad``; plus what the model's ``structure.kernel_inputs`` adds
    (roughplastic: its tables and, with ``dtables``, their derivatives). Returns (P, leaves)."""
    import drjit as dr

    P, leaves = {}, []
    for par in model.parameters:
        v = p[par.name]
        xs = [float(x) for x in v] if par.per_channel else [float(v)]
        vals = [dr.opaque(F, x) for x in xs]
        if grad:
            for x in vals:
                dr.enable_grad(x)
        leaves.append((par, vals))
        P[par.name] = vals if par.per_channel else vals[0]
    hook = model.structure.kernel_inputs
    if hook is not None:
        hook(model, p, P, F, grad, dtables)
    return P, leaves


def _needs_derivatives(model):
    """NotImplementedError for a kernel of values only (``structure.derivatives = False``),
    raised before any recording (a frozen function reports its errors as RuntimeError)."""
    if model.structure.kernel is not None and not model.structure.derivatives:
        raise NotImplementedError(f"the compiled kernel of {model.name!r} gives values only")
