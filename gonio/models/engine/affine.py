"""Affine parts of the models that declare an affine per-channel parameter
(``model.structure.affine``), batched over parameter sets: the fitter's hot loop
(re-exported by :mod:`gonio.models.fast`)."""

from __future__ import annotations


import numpy as np

from gonio.core.sides import sides_mask
from gonio.models.engine.freeze import _FREEZE_LOCK, _frozen_for
from gonio.models.engine.jit import Directions, JitContext, _dr
from gonio.models.engine.jit_tables import _cached_tables, _t_ext_batch

__all__ = ["affine_parts", "affine_q", "affine_spec", "affine_tables", "prepare"]


# -- affine parts, batched over parameter sets (the fitter's hot loop) -----------------------
#
# For the models whose f_r is affine in one per-channel parameter,
#
#     f_r[c](wi, wo) = base(wi, wo; theta) + coef[c] * basis(wi, wo; theta),
#
# with ``base`` and ``basis`` the same in every channel, a fit only needs base and basis
# for each trial theta: the per-channel coefficient follows by weighted linear least
# squares. :func:`affine_parts` evaluates them for K parameter sets theta_k at once (one
# LLVM kernel over K x N lanes, directions loaded once by :func:`prepare`), which is what
# a multi-start stage, a finite-difference Jacobian and an ensemble sampler's walkers need.
#
# ``coef`` is not always the model's own parameter. For ``roughplastic`` (nonlinear=False)
# f_r = spec + rho / (1 - R_int) * t(mu_i) t(mu_o) / (pi eta^2), so coef = rho / (1 - R_int)
# and rho = coef * q(theta) with q = 1 - R_int(alpha, eta): the fitter works with coef and
# needs the 128 x 128 quadrature of R_int (16 times the cost of the transmittance table)
# only to convert its answer back. :func:`affine_q` gives q exactly.

def affine_spec(model):
    """(affine parameter, theta names) when :func:`affine_parts` serves ``model``, else None:
    read from the model's declaration (``model.structure.affine``)."""
    affine = model.structure.affine
    return None if affine is None else (affine.coefficient, tuple(affine.theta))


def prepare(wi, wo):
    """Load a batch of direction pairs (N, 3) for :func:`affine_parts` (float64)."""
    return Directions(wi, wo, np.float64)


def _theta_array(thetas, n_theta):
    t = np.asarray(thetas, dtype=np.float64)
    if t.ndim == 1:
        t = t.reshape(-1, n_theta) if n_theta else t.reshape(-1, 0)
    if t.ndim != 2 or t.shape[1] != n_theta or t.shape[0] == 0:
        raise ValueError(f"thetas must have shape (K >= 1, {n_theta}), got {t.shape}")
    if not np.all(np.isfinite(t)):
        raise ValueError("thetas contain NaN or inf")
    return t


def affine_tables(model, thetas):
    """The parameter-dependent tables of :func:`affine_parts` at K parameter sets, exactly:
    for ``roughplastic`` the transmittance tables, shape (K, 64); (K, 0) for the others."""
    spec = affine_spec(model)
    if spec is None:
        raise ValueError(f"model {model!r} has no affine-parts kernel")
    dr, F, V3, U = _dr()
    th = _theta_array(thetas, len(spec[1]))
    if not model.structure.affine.tables:
        return np.zeros((th.shape[0], 0))
    a, e = F(np.maximum(th[:, 0], 1e-4)), F(th[:, 1])
    dr.make_opaque(a, e)
    with dr.suspend_grad():
        t = _t_ext_batch(model.options["distribution"], a, e)
        dr.eval(t)
        return np.asarray(t).reshape(th.shape[0], 64)


def affine_parts(model, prepared, thetas, tables=None):
    """``base`` and ``basis`` (each (K, N), float64) of ``model`` at K parameter sets.

    Parameters
    ----------
    model
        A model with :func:`affine_spec` not None.
    prepared : Directions
        The directions in float64 (:func:`prepare`).
    thetas : array_like, shape (K, T)
        Values of the nonlinear parameters, columns in ``affine_spec(model)[1]`` order
        (not validated against the model's bounds: the caller keeps them inside).

    tables : ndarray, shape (K, 64), optional
        The tables of :func:`affine_tables` at ``thetas`` (or a caller's approximation of
        them, e.g. an interpolant when many nearby thetas are evaluated); computed exactly
        in the same kernel call when omitted.

    Returns
    -------
    base, basis : ndarray, shape (K, N)
        f_r[c] = base + coef[c] * basis at theta_k (0 below the horizon); see the section
        notes for what ``coef`` means per model.
    """
    affine = model.structure.affine  # built anew by every read: read once (10 us a read)
    if affine is None:
        raise ValueError(f"model {model!r} has no affine-parts kernel")
    dr, F, V3, U = _dr()
    th = _theta_array(thetas, len(affine.theta))
    K, N = th.shape[0], prepared.n
    if N == 0:
        return np.zeros((K, 0)), np.zeros((K, 0))
    cols = [F(np.ascontiguousarray(th[:, j])) for j in range(th.shape[1])]
    if cols:
        dr.make_opaque(*cols)
    if tables is None and affine.tables:
        # the exact tables are made in the same kernel (a fit's trial thetas): traced
        with dr.suspend_grad():
            base, basis = _parts_kernel(model, cols, prepared.wi, prepared.wo, None, K, N)
            dr.eval(base, basis)
            return np.asarray(base).reshape(K, N), np.asarray(basis).reshape(K, N)
    t = None
    if tables is not None and affine.tables:
        tb = np.asarray(tables, dtype=np.float64)
        if tb.shape != (K, 64):
            raise ValueError(f"tables must have shape ({K}, 64), got {tb.shape}")
        t = F(np.ascontiguousarray(tb.reshape(-1)))
        dr.make_opaque(t)
    # tables given (a sampler's walkers) or none needed: replayed from its recording, which
    # skips the Python trace (~0.35 ms of a 0.5 ms call at 16 x 1000 pairs, emcee's
    # half-ensemble); K and N are part of the recording's key
    with _FREEZE_LOCK, dr.suspend_grad():
        base, basis = _frozen_for(_parts_replayed, model)(cols, prepared.wi, prepared.wo, t, K, N)
        return np.asarray(base).reshape(K, N), np.asarray(basis).reshape(K, N)


def _parts_kernel(model, cols, wi, wo, tables, K, N):
    """base and basis (each K * N lanes) of ``model`` at the K thetas ``cols``."""
    dr, F, V3, U = _dr()
    lane = dr.arange(U, K * N)
    k = lane // N
    i = lane - k * N
    vi = dr.gather(V3, wi, i)
    vo = dr.gather(V3, wo, i)
    active = sides_mask(model.structure.sides, vi.z, vo.z)
    ctx = JitContext(dr, F, U, active, None)
    return model.structure.affine.kernel(model, ctx, cols, k, K, vi, vo, tables)


def _parts_replayed(model, cols, wi, wo, tables, K, N):
    """:func:`_parts_kernel` with both outputs evaluated: what ``_freeze._frozen`` records."""
    import drjit as dr

    base, basis = _parts_kernel(model, cols, wi, wo, tables, K, N)
    dr.eval(base, basis)
    return base, basis


def affine_q(model, thetas):
    """q(theta), shape (K,): the model's affine parameter is ``coef * q`` (exact).

    1 for ``diffuse`` and ``orennayar``; ``1 - R_int(alpha, eta)`` for ``roughplastic``,
    from the same 128 x 128 quadrature as :func:`gonio.models.physics.rough_tables.rough_tables`
    (cached per (alpha, eta))."""
    spec = affine_spec(model)
    if spec is None:
        raise ValueError(f"model {model!r} has no affine-parts kernel")
    th = _theta_array(thetas, len(spec[1]))
    if not model.structure.affine.tables:
        return np.ones(th.shape[0])
    kind = model.options["distribution"]
    return np.array([1.0 - float(np.asarray(_cached_tables(kind, float(a), float(e))[1])[0]) for a, e in th])
