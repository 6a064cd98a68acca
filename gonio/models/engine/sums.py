"""The sums a fit needs, reduced inside one kernel that stores nothing per pair (issue 18):
chi^2 and its gradient (:func:`chi2_grad`), the weighted sum of squares (:func:`weighted_sse`)
and the Gauss-Newton normal equations (:func:`normal_equations`), in the linear or the log
loss; each replayed from its ``dr.freeze`` recording, float64 partial sums whatever the
batch's precision (:mod:`gonio.models.engine.reduce`). :mod:`gonio.models.engine.fast` re-exports them."""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from gonio.core.channels import CHANNELS
from gonio.models.engine.freeze import _FREEZE_LOCK, _frozen_for
from gonio.models.engine.jit import _dr
from gonio.models.engine.kernels import _fJ, _needs_derivatives, _param_vars, _source
from gonio.models.engine.reduce import _collect, _reduced


def chi2_grad(model, dirs, params, y, w):
    """chi^2 = sum w (f_r - y)^2 over pairs and channels, and its gradient with respect to
    every parameter: what a gradient-based fitter (nlopt's SLSQP or MMA, a quasi-Newton
    step) needs, in one fused kernel that stores nothing per pair.

    The derivatives are :func:`jacobian`'s, reduced inside the kernel (:func:`_reduced`:
    float64 partial sums, whatever the batch's precision, 16 per term, added in numpy) into
    d chi^2 / d p = 2 sum w (f_r - y) d f_r / d p. The order of the additions depends on the
    thread schedule: results can differ in the last bits between runs (tested: within
    1e-13 of the sum of the terms' absolute values from numpy's float64 sum at 1e6 pairs).

    Parameters
    ----------
    y, w : list of 3 Dr.Jit arrays (``dirs.channels(...)``) or array_like (N, 3)
        Measured values and weights (1 / sigma^2 for the maximum-likelihood chi^2).

    Returns
    -------
    chi2 : float
    grad : dict
        Parameter name -> float, or (3,) array for per-channel parameters.
    """
    import drjit as dr

    _needs_derivatives(model)
    p = model.validate(params)
    y = y if isinstance(y, list) else dirs.channels(y, "y")
    w = w if isinstance(w, list) else dirs.channels(w, "w")
    if dirs.n == 0:
        return 0.0, {par.name: (np.zeros(CHANNELS) if par.per_channel else 0.0) for par in model.parameters}
    P, _ = _param_vars(model, p, dirs.F, grad=False, dtables=True)
    run = _frozen_for(_chi2_sums, model)  # replayed, as Bound.eval
    with _FREEZE_LOCK, dr.suspend_grad():
        sums = run(*_source(model, dirs), P, y, w)
        dr.eval(sums)
    vals = _collect(sums, dirs.dtype)
    grad, k = {}, 1
    for par in model.parameters:
        m = CHANNELS if par.per_channel else 1
        g = 2.0 * vals[k:k + m]
        grad[par.name] = g if par.per_channel else float(g[0])
        k += m
    return float(vals[0]), grad


def _chi2_sums(model, *args):
    """[chi^2, then sum w (f - y) d f / d p for each parameter (3 sums for a per-channel
    one)], reduced in the kernel into one float64 array (:func:`_reduced`); ``args``: the
    :func:`_source`, P, y, w."""
    P, y, w = args[-3:]
    f, J = _fJ(model, args[:-3], P, grad=True)
    wr = [wc * (fc - yc) for fc, yc, wc in zip(f, y, w)]
    terms = [sum(a * (fc - yc) for a, fc, yc in zip(wr, f, y))]
    for par in model.parameters:
        t = [a * d for a, d in zip(wr, J[par.name])]
        link = model.structure.coupling(par.name)
        if link is not None:  # + weights[k] sum_c w r_c d f_c / d aux
            s = sum(a * d for a, d in zip(wr, J[link.aux]))
            t = [tk + float(wk) * s for tk, wk in zip(t, link.weights)]
        terms += t if par.per_channel else [t[0] + t[1] + t[2]]
    return _reduced(terms)


def _entries(model):
    """The parameter entries of the normal equations, in model order: (name, channel) for
    each channel of a per-channel parameter, (name, -1) for a shared one."""
    out = []
    for par in model.parameters:
        out += [(par.name, c) for c in range(CHANNELS)] if par.per_channel else [(par.name, -1)]
    return out


def _log_values(dr, f, J, wi):
    """Loew et al.'s (2012, eq. 11) log values l = ln(1 + max(f cos_i, -0.999)) of f_r and
    their derivatives dl = cos_i / (1 + f cos_i) df (0 where the floor holds), the transform
    of the ``log`` loss (:func:`gonio.fitting.likelihood.loss.residuals`) inside the kernel."""
    ci = dr.clip(wi.z, 0.0, 1.0)
    xs = [fc * ci for fc in f]
    out = [dr.log(1.0 + dr.maximum(x, -0.999)) for x in xs]
    if J is None:
        return out, None
    d = [dr.select(x > -0.999, ci / (1.0 + x), 0.0) for x in xs]
    return out, {name: [dc * jc for dc, jc in zip(d, cols)] for name, cols in J.items()}


def _normal_sums_log(model, wi, wo, P, y, w):
    """:func:`_normal_sums` of the log values (:func:`_log_values`), on the directions (the
    log values need cos_i, which the prepared geometry does not carry): ``y`` holds the data's."""
    return _normal_sums(model, wi, wo, P, y, w, log=True)


def _normal_sums(model, *args, log=False):
    """[sum w (f - y)^2, then g_a = sum w (f - y) J_a per entry, then A_ab = sum w J_a J_b
    for every pair a <= b that shares a channel], reduced in the kernel like
    :func:`_chi2_sums`; a per-channel entry's J is zero in the other channels (unless the
    model declares it coupled, :func:`_shares_channel`), so pairs of two different channels
    are 0 (skipped). ``args``: the :func:`_source` (with ``log``, the directions), P, y, w.
    With ``log``, f and J are the log values' (:func:`_log_values`)."""
    import drjit as dr

    P, y, w = args[-3:]
    f, J = _fJ(model, args[:-3], P, grad=True)
    if log:
        f, J = _log_values(dr, f, J, args[0])
    res = [fc - yc for fc, yc in zip(f, y)]
    wr = [wc * rc for wc, rc in zip(w, res)]
    ent = _entries(model)

    def col(e, c):  # d f_c / d entry e, None where it is 0
        name, ch = e
        link = model.structure.coupling(name)
        if link is not None and ch >= 0:
            cross = float(link.weights[ch]) * J[link.aux][c]
            return J[name][c] + cross if ch == c else cross
        return J[name][c] if ch in (-1, c) else None

    terms = [sum(a * rc for a, rc in zip(wr, res))]
    for e in ent:
        terms.append(sum(wr[c] * col(e, c) for c in range(CHANNELS) if col(e, c) is not None))
    for i, j in _shared_pairs(model):
        a, b = ent[i], ent[j]
        terms.append(sum(w[c] * col(a, c) * col(b, c) for c in range(CHANNELS)
                         if col(a, c) is not None and col(b, c) is not None))
    return _reduced(terms)


def _shared_pairs(model):
    """The (i, j), i <= j, of the entries (:func:`_entries`) whose normal-equation sum can
    differ from 0 (:func:`_shares_channel`), in the order the kernel reduces them; computed
    once per model configuration (per call it cost ~0.1 ms of a ~0.25 ms roughconductor
    normal-equations call at 100 pairs: 28 pairs of checks through ``model.structure``)."""
    return _shared_pairs_of(model.name, tuple(sorted(model.options.items())))


@lru_cache(maxsize=None)
def _shared_pairs_of(name, options):
    from gonio.models.registry import get

    model = get(name, **dict(options))
    ent = _entries(model)
    return tuple((i, j) for i, a in enumerate(ent) for j in range(i, len(ent)) if _shares_channel(model, a, ent[j]))


def _shares_channel(model, a, b):
    """Whether entries a and b (:func:`_entries`) both act on some channel, so that their
    normal-equation sum can differ from 0: a shared entry acts on every channel, a coupled
    per-channel one (``structure.coupled``) too, any other on its own channel."""
    def every(e):
        return e[1] == -1 or model.structure.coupling(e[0]) is not None

    return every(a) or every(b) or a[1] == b[1]


def normal_equations(model, dirs, params, y, w, log=False):
    """The weighted least-squares normal equations at ``params``, reduced in one kernel that
    stores nothing per pair: what Gauss-Newton and Levenberg-Marquardt need per iteration,
    in memory independent of N (no N x P Jacobian).

    With r = f_r - y over pairs and channels and W = ``w``: cost = sum W r^2,
    g = sum W r J (= J^T W r) and A = sum W J J^T (= J^T W J), J the derivatives of
    :func:`jacobian` with respect to every parameter entry (:func:`_entries`: a per-channel
    parameter has one entry per channel). Sums are float64 whatever the batch's precision;
    their order depends on the thread schedule (last bits).

    With ``log``, the residuals of the ``log`` loss: r = ln(1 + f_r cos_i) - y (``y`` the
    data's ln(1 + f cos_i)) and J their derivatives, cos_i / (1 + f_r cos_i) d f_r
    (:func:`_log_values`).

    Returns
    -------
    cost : float
    g : ndarray (E,)
    A : ndarray (E, E), symmetric
    entries : list of (parameter name, channel or -1)
    """
    import drjit as dr

    _needs_derivatives(model)
    p = model.validate(params)
    y = y if isinstance(y, list) else dirs.channels(y, "y")
    w = w if isinstance(w, list) else dirs.channels(w, "w")
    ent = _entries(model)
    E = len(ent)
    if dirs.n == 0:
        return 0.0, np.zeros(E), np.zeros((E, E)), ent
    P, _ = _param_vars(model, p, dirs.F, grad=False, dtables=True)
    # replayed (measured 0.05 ms a call at 3000 pairs against ~0.4 ms traced); a new
    # recording is made per alignment of the data's mapped memory (each its own kernel,
    # compiled once, then in Dr.Jit's kernel cache)
    run = _frozen_for(_normal_sums_log if log else _normal_sums, model)
    with _FREEZE_LOCK, dr.suspend_grad():
        sums = run(*((dirs.wi, dirs.wo) if log else _source(model, dirs)), P, y, w)
        dr.eval(sums)
    vals = _collect(sums, dirs.dtype)
    g = vals[1:1 + E].copy()
    A = np.zeros((E, E))
    pairs = _shared_pairs(model)
    if pairs:
        i, j = np.array(pairs).T
        A[i, j] = A[j, i] = vals[1 + E:1 + E + len(pairs)]
    return float(vals[0]), g, A, ent


def _sse_sum_log(model, wi, wo, P, y, w):
    """:func:`_sse_sum` of the log values (:func:`_log_values`), on the directions."""
    return _sse_sum(model, wi, wo, P, y, w, log=True)


def _sse_sum(model, *args, log=False):
    """sum w (f - y)^2 over pairs and channels, reduced in the kernel (one float64 target);
    ``args``: the :func:`_source` (with ``log``, the directions), P, y, w; with ``log``, f the
    log values (:func:`_log_values`)."""
    import drjit as dr

    _, F64, _, U = _dr()
    P, y, w = args[-3:]
    f = _fJ(model, args[:-3], P, grad=False)
    if log:
        f = _log_values(dr, f, None, args[0])[0]
    t = sum(wc * (fc - yc) * (fc - yc) for fc, yc, wc in zip(f, y, w))
    target = dr.zeros(F64, 1)
    dr.scatter_reduce(dr.ReduceOp.Add, target, F64(t), dr.zeros(U, 1), mode=dr.ReduceMode.Expand)
    return target


def weighted_sse(model, dirs, params, y, w, log=False):
    """sum w (f_r - y)^2 over pairs and channels in one kernel that stores nothing per pair
    (the cost of :func:`normal_equations` alone: a Levenberg-Marquardt trial step's; with
    ``log``, of the log residuals, as there). NaN where f_r is not finite somewhere with
    w > 0 (the caller raises)."""
    import drjit as dr

    p = model.validate(params)
    y = y if isinstance(y, list) else dirs.channels(y, "y")
    w = w if isinstance(w, list) else dirs.channels(w, "w")
    if dirs.n == 0:
        return 0.0
    P, _ = _param_vars(model, p, dirs.F, grad=False)
    run = _frozen_for(_sse_sum_log if log else _sse_sum, model)
    with _FREEZE_LOCK, dr.suspend_grad():
        out = run(*((dirs.wi, dirs.wo) if log else _source(model, dirs)), P, y, w)
        dr.eval(out)
    return float(np.asarray(out)[0])
