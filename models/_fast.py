"""Compiled evaluation path: the same models written in Dr.Jit (LLVM backend).

The numpy implementations are the reference; this module evaluates the same formulas
(tested against the reference to 1e-10 relative in float64, 2e-5 in float32) as fused,
multithreaded LLVM kernels, with their derivatives. It is used only where Dr.Jit's LLVM
backend works (:func:`available`); nothing else in :mod:`gonio.models` depends on it.

numpy in, numpy out (float64):

* :func:`eval` -- f_r, shape (N, 3), like ``Model.eval``.
* :func:`value_and_grad` -- f_r and the gradient of ``sum(cotangent * f_r)`` with respect
  to every parameter (Dr.Jit's reverse-mode AD; per-channel parameters get (3,) gradients).

On a resident batch (:class:`Directions`, float32 or float64, loaded once):

* :meth:`Bound.eval` / :func:`eval_resident` -- f_r, one kernel (``gonio bench models``
  times ``Bound.eval`` against Mitsuba's ``bsdf.eval``);
* :func:`jacobian` -- f_r and d f_r / d every parameter, one kernel, derivatives written
  by hand next to the values in :func:`_kernel`;
* :func:`chi2_grad` -- sum w (f_r - y)^2 and its gradient, reduced inside the kernel.

For ``roughplastic`` the transmittance table and internal reflectance follow the
model's ``exact_tables`` setting: with ``exact_tables=False`` the interpolated grid of
:func:`gonio.models._rough_tables.rough_tables_interp` (gradients through the spline's
derivative); with ``exact_tables=True`` (the default, and in grid cells that fall back to
the exact tables) computed here as well (same quadrature as :mod:`gonio.models._rough_tables`), so that gradients
with respect to ``alpha`` and ``int_ior`` include their dependence through the table.

Kernels are cached by Dr.Jit: parameter values enter as opaque variables, so a new
parameter value does not trigger a recompilation.

The building blocks (Fresnel, lobes, tables, :class:`Directions`) live in :mod:`._jit`, the
batched affine parts of the models that declare an affine parameter in :mod:`._fast_affine`
(re-exported here: ``affine_parts``, ``affine_tables``, ``affine_q``, ``affine_spec``,
``prepare``).
"""

from __future__ import annotations

import math
import subprocess
import sys
from functools import lru_cache

import numpy as np

from ._base import CHANNELS, eval_inputs
from ._rough_tables import _interp
from ._fast_affine import affine_parts, affine_q, affine_spec, affine_tables, prepare
from ._jit import (Directions, _cached_table_derivs, _cached_tables, _dr, _floor, _fresnel_conductor,
                   _fresnel_outside, _lerp_table, _lobe, _oren_nayar_over_rho, _pairs, _tables)

__all__ = ["available", "eval", "value_and_grad", "Directions", "Bound", "eval_resident", "jacobian", "chi2_grad",
           "affine_parts", "affine_q", "affine_spec", "affine_tables", "prepare"]

_PROBE = (
    "import drjit as dr\n"
    "from drjit.llvm.ad import Float64\n"
    "x = dr.sqrt(dr.arange(Float64, 16))\n"
    "dr.eval(x)\n"
    "print(x)\n"
)


@lru_cache(maxsize=1)
def available():
    """True when Dr.Jit's LLVM backend works in this environment (probed once, in a
    child process, because a broken libLLVM aborts instead of raising)."""
    try:
        import drjit  # noqa: F401
    except ImportError:
        return False
    try:
        r = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, timeout=120)
    except Exception:
        return False
    if r.returncode != 0:
        return False
    from ._jit_target import apply_env

    apply_env()  # GONIO_LLVM_TARGET, before this process compiles its first kernel
    return True


# -- model kernels ---------------------------------------------------------------------------


def _channels(P, name):
    return P[name] if isinstance(P[name], list) else [P[name]] * CHANNELS


def _kernel(model, wi, wo, P, grad=False):
    """f_r per channel (list of 3 arrays) for Dr.Jit direction vectors wi, wo (float64 or
    float32); P maps parameter names to scalars of the same type (per-channel parameters:
    lists of 3) and, for ``roughplastic``, ``_tables`` to (t_ext, r_int).

    With ``grad``, returns ``(f, J)``: J maps each parameter name to 3 arrays, d f[c] / d p
    (per-channel p: d f[c] / d p[c]), from derivatives written out by hand next to the value
    (forward mode, sharing every intermediate; tested against Dr.Jit's AD and finite
    differences). ``roughplastic`` then also needs ``P["_dtables"]`` = (dt/d alpha,
    dr/d alpha, dt/d eta, dr/d eta)."""
    import drjit as dr

    F = type(wi.z)
    U = dr.uint32_array_t(F)
    name = model.name
    ci, co = wi.z, wo.z
    active = (ci > 0) & (co > 0)
    zero = dr.zeros(F, dr.width(ci))
    J = {}
    if name == "diffuse":
        f = [dr.select(active, r * (1.0 / math.pi) + zero, 0.0) for r in _channels(P, "reflectance")]
        if grad:
            J["reflectance"] = [dr.select(active, 1.0 / math.pi + zero, 0.0)] * CHANNELS
    elif name == "orennayar":
        shape = _oren_nayar_over_rho(dr, P["sigma"], wi, wo, grad)
        basis, dbasis = shape if grad else (shape, None)
        f = [r * basis for r in _channels(P, "reflectance")]
        if grad:
            J["reflectance"] = [basis] * CHANNELS
            J["sigma"] = [r * dbasis for r in _channels(P, "reflectance")]
    elif name in ("roughplastic", "roughconductor"):
        kind = model.options["distribution"]
        aniso = name == "roughconductor" and model.options["anisotropic"]
        alphas = (P["alpha_u"], P["alpha_v"]) if aniso else (P["alpha"], P["alpha"])
        au, av = (dr.maximum(a, 1e-4) for a in alphas)
        lobe = _lobe(dr, kind, au, av, wi, wo, grad)
        num, den, c = lobe[:3]
        s = num / den
        if grad:
            # below the roughness floor alpha is clamped: derivative 0
            gu, gv = (dr.select(a >= 1e-4, g, 0.0) * s for a, g in zip(alphas, lobe[4:]))
            ds = {"alpha_u": gu, "alpha_v": gv} if aniso else {"alpha": gu + gv}
        if name == "roughconductor":
            fres = [_fresnel_conductor(dr, c, e, k, grad) for e, k in zip(_channels(P, "eta"), _channels(P, "k"))]
            if not grad:
                return [Fc * s for Fc in fres]
            f = [Fc[0] * s for Fc in fres]
            J["eta"] = [Fc[1] * s for Fc in fres]
            J["k"] = [Fc[2] * s for Fc in fres]
            for key, d in ds.items():
                J[key] = [Fc[0] * d for Fc in fres]
        else:
            eta = P["int_ior"]
            fres = _fresnel_outside(dr, dr.clip(c, 0.0, 1.0), eta, grad)
            spec = fres[0] * s
            t_ext, r_int = P["_tables"]
            ti = _lerp_table(dr, F, U, t_ext, ci, 64)
            to = _lerp_table(dr, F, U, t_ext, co, 64)
            k_eta = 1.0 / (math.pi * eta * eta)
            tt = dr.select(active, ti * to, 0.0)
            scale = tt * k_eta
            nonlinear = model.options["nonlinear"]
            rhos = _channels(P, "diffuse_reflectance")
            inv_den = [1.0 / (1.0 - (rho * r_int if nonlinear else r_int)) for rho in rhos]
            f = [spec + rho * q * scale for rho, q in zip(rhos, inv_den)]
            if grad:
                dt_a, dr_a, dt_e, dr_e = P["_dtables"]

                def dscale(dt):
                    dti = _lerp_table(dr, F, U, dt, ci, 64)
                    dto = _lerp_table(dr, F, U, dt, co, 64)
                    return dr.select(active, dti * to + ti * dto, 0.0) * k_eta

                ds_a = dscale(dt_a)
                ds_e = dscale(dt_e) - 2.0 * scale / eta
                # d/dx [rho / (1 - m r)] = rho m (dr/dx) / (1 - m r)^2 with m = rho or 1
                J["diffuse_reflectance"] = [scale * (q * q if nonlinear else q) for q in inv_den]
                J["alpha"] = []
                J["int_ior"] = []
                for rho, q in zip(rhos, inv_den):
                    m = rho if nonlinear else 1.0
                    J["alpha"].append(fres[0] * ds["alpha"] + rho * q * (ds_a + scale * m * dr_a * q))
                    J["int_ior"].append(fres[2] * s + rho * q * (ds_e + scale * m * dr_e * q))
    elif name == "cooktorrance":
        # Ngan et al. 2005: Beckmann D without pi, G = min(1, 2 cos_m min(cos_i, cos_o) / (wi . m)),
        # written with the unnormalised half vector h: cos_m = h_z / |h|, wi . m = (wi . h) / |h|
        m = P["roughness"]
        h = wi + wo
        h2 = dr.squared_norm(h)
        hz = h.z
        dh = 0.5 * (dr.dot(wi, h) + dr.dot(wo, h))  # |h| (wi . m)
        up = active & (h2 > _floor(h2)) & (hz > 0) & (dh > 0)
        r_hz2 = 1.0 / dr.select(up, hz * hz, 1.0)
        m2 = m * m
        e = (h.x * h.x + h.y * h.y) * r_hz2 * (1.0 / m2)  # tan^2(theta_m) / m^2
        g_num = 2.0 * hz * dr.minimum(ci, co)
        g_den = dr.select(g_num < dh, dh, g_num)  # G = g_num / g_den = min(1, 2 hz min / dh)
        # D G / (pi ci co) with D = exp(-e) / (m^2 cos^4(theta_m)), 1 / cos^2 = |h|^2 / hz^2
        # (ratios first: hz^4 ci co underflows float32 at grazing angles)
        sec2 = h2 * r_hz2
        s = dr.select(up, dr.exp(-e) * sec2 * sec2 * g_num / (math.pi * m2 * g_den * dr.select(up, ci * co, 1.0)), 0.0)
        x = 1.0 - dr.clip(dh * dr.rsqrt(dr.select(up, h2, 1.0)), 0.0, 1.0)
        x2 = x * x
        x5 = x2 * x2 * x
        rds, rss, f0s = (_channels(P, k) for k in ("diffuse_reflectance", "specular_reflectance", "f0"))
        lam = dr.select(active, 1.0 / math.pi + zero, 0.0)
        f = [rd * lam + rs * (f0 + (1.0 - f0) * x5) * s for rd, rs, f0 in zip(rds, rss, f0s)]
        if grad:
            ds = (2.0 * e - 2.0) * (1.0 / m) * s  # d ln s / dm = (2 e - 2) / m
            J["diffuse_reflectance"] = [lam] * CHANNELS
            J["specular_reflectance"] = [(f0 + (1.0 - f0) * x5) * s for f0 in f0s]
            J["roughness"] = [rs * (f0 + (1.0 - f0) * x5) * ds for rs, f0 in zip(rss, f0s)]
            J["f0"] = [rs * (1.0 - x5) * s for rs in rss]
    else:
        raise NotImplementedError(f"no compiled kernel for model {name!r}")
    if not grad:
        return f
    return f, {par.name: J[par.name] for par in model.parameters}


def _param_vars(model, p, F, grad, dtables=False):
    """Dr.Jit scalars of type F for validated parameters ``p`` (opaque: a new value reuses
    the compiled kernel), AD-enabled when ``grad``; for ``roughplastic`` also its tables
    (``P["_tables"]``, computed in float64 and cast to F) and, with ``dtables``, their
    derivatives (``P["_dtables"]``, for ``_kernel(..., grad=True)``). Returns (P, leaves)."""
    import drjit as dr

    F64 = _dr()[1]
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
    if model.name == "roughplastic":
        kind = model.options["distribution"]
        t_paired = False  # the cached exact tables come paired already
        grid = None if getattr(model, "exact_tables", True) else _interp(kind, p["alpha"], p["int_ior"], grad=grad)
        if grid is not None:
            # the same interpolated tables as the numpy model; for gradients, their
            # first-order expansion about the current point (value unchanged: the
            # opaque alpha, eta equal p's), d/d(alpha, eta) from the spline
            if grad:
                t, r, dx, dy = grid
                da, de = P["alpha"] - p["alpha"], P["int_ior"] - p["int_ior"]
                tables = (F(t) + da * F(dx[:-1]) + de * F(dy[:-1]), F([r]) + da * dx[-1] + de * dy[-1])
            else:
                tables = (F(grid[0]), F([grid[1]]))
        elif grad:
            tables = _tables(kind, dr.maximum(F64(P["alpha"]), 1e-4), F64(P["int_ior"]))
        else:
            tables = _cached_tables(kind, p["alpha"], p["int_ior"], F, paired=True)
            t_paired = True
        t, r = (x if type(x) is F else F(x) for x in tables)
        P["_tables"] = (t if t_paired else _pairs(t), r)
        if dtables:
            if grid is not None:
                dx, dy = _interp(kind, p["alpha"], p["int_ior"], grad=True)[2:]
                P["_dtables"] = (_pairs(F(dx[:-1])), F([dx[-1]]), _pairs(F(dy[:-1])), F([dy[-1]]))
            else:
                P["_dtables"] = _cached_table_derivs(kind, p["alpha"], p["int_ior"], F)
    return P, leaves


def _inputs(model, wi, wo, params, grad):
    """Dr.Jit inputs (float64) from numpy. Directions are loaded as flat (3N) arrays without
    copies and de-interleaved by gathers inside the fused kernel; non-finite directions are
    degenerate geometry (f_r = 0), as in the reference."""
    dr, F, V3, U = _dr()
    wi, wo, p = eval_inputs(model, wi, wo, params)
    n = wi.shape[0]
    idx = dr.arange(U, n) * 3
    flat_i, flat_o = F(wi.reshape(-1)), F(wo.reshape(-1))
    vi = V3(*(dr.gather(F, flat_i, idx + k) for k in range(3)))
    vo = V3(*(dr.gather(F, flat_o, idx + k) for k in range(3)))
    finite = dr.isfinite(vi.x) & dr.isfinite(vi.y) & dr.isfinite(vi.z)
    finite &= dr.isfinite(vo.x) & dr.isfinite(vo.y) & dr.isfinite(vo.z)
    down = V3(0.0, 0.0, -1.0)
    vi = dr.select(finite, vi, down)
    vo = dr.select(finite, vo, down)
    P, leaves = _param_vars(model, p, F, grad)
    return vi, vo, P, leaves, n


def _interleave(chans, n):
    """(N, 3) numpy array from three Dr.Jit arrays, evaluated in one fused kernel."""
    dr, F, V3, U = _dr()
    chans = [dr.detach(c) for c in chans]
    dr.eval(*chans)
    out = np.empty((n, CHANNELS))
    for c, ch in enumerate(chans):
        out[:, c] = np.asarray(ch)
    return out


def _empty(model, wi, wo, params):
    """Validate the arguments; True for an empty batch."""
    return eval_inputs(model, wi, wo, params)[0].shape[0] == 0


def eval(model, wi, wo, params):
    """Compiled f_r(wi, wo), shape (N, 3); same contract as ``model.eval``."""
    dr, F, V3, U = _dr()
    if _empty(model, wi, wo, params):
        return np.zeros((0, CHANNELS))
    vi, vo, P, _, n = _inputs(model, wi, wo, params, grad=False)
    with dr.suspend_grad():
        chans = _kernel(model, vi, vo, P)
        return _interleave(chans, n)


def value_and_grad(model, wi, wo, params, cotangent):
    """f_r and the gradient of ``sum(cotangent * f_r)`` with respect to the parameters.

    Parameters
    ----------
    cotangent : array_like, shape (N, 3)
        Weights of each value (e.g. ``2 w (f_r - y)`` for a weighted least squares).

    Returns
    -------
    f : ndarray, shape (N, 3)
    grad : dict
        Parameter name -> float, or (3,) array for per-channel parameters.

    Notes
    -----
    Roughness below Mitsuba's floor (1e-4) is clamped, so its gradient is 0 there.
    """
    dr, F, V3, U = _dr()
    if _empty(model, wi, wo, params):
        p = model.validate(params)
        return np.zeros((0, CHANNELS)), {k: (np.zeros(CHANNELS) if np.ndim(v) else 0.0) for k, v in p.items()}
    vi, vo, P, leaves, n = _inputs(model, wi, wo, params, grad=True)
    cot = np.asarray(cotangent, dtype=np.float64)
    if cot.shape != (n, CHANNELS):
        raise ValueError(f"cotangent must have shape ({n}, {CHANNELS}), got {cot.shape}")
    chans = _kernel(model, vi, vo, P)
    flat_c = F(np.ascontiguousarray(cot).reshape(-1))
    idx = dr.arange(U, n) * 3
    loss = 0.0
    for c, ch in enumerate(chans):
        loss = loss + dr.sum(ch * dr.gather(F, flat_c, idx + c))
    dr.backward(loss)
    f = _interleave(chans, n)
    grad = {}
    for par, vals in leaves:
        g = np.array([float(np.asarray(dr.grad(x)).ravel()[0]) for x in vals])
        grad[par.name] = g if par.per_channel else float(g[0])
    return f, grad


def _to_numpy(chans, n):
    out = np.empty((n, CHANNELS), dtype=np.asarray(chans[0]).dtype if n else np.float64)
    for c, ch in enumerate(chans):
        out[:, c] = np.asarray(ch)
    return out


class Bound:
    """A model with its parameters loaded into Dr.Jit once (validated now, tables and Dr.Jit
    scalars built at the first :meth:`eval`), the
    counterpart of a Mitsuba BSDF instance (``mitsuba.load_dict``): each :meth:`eval` on a
    resident batch is then one kernel launch, as ``bsdf.eval`` is.

    Parameters
    ----------
    model, params
        As for ``model.eval``.
    dtype : float32 (default) or float64
        Must match the batches it evaluates.
    """

    def __init__(self, model, params, dtype=np.float32):
        self.model = model
        self.params = model.validate(params)
        self.dtype = np.dtype(dtype)
        self._P = None

    def eval(self, dirs, numpy=True):
        """f_r on ``dirs`` (a :class:`Directions` of the same dtype): an (N, 3) numpy array,
        or (``numpy=False``) the three channels as evaluated Dr.Jit arrays."""
        import drjit as dr

        if dirs.dtype != self.dtype:
            raise ValueError(f"batch is {dirs.dtype}, the bound parameters are {self.dtype}")
        if dirs.n == 0:
            return np.zeros((0, CHANNELS), dtype=dirs.dtype) if numpy else [dirs.F() for _ in range(CHANNELS)]
        if self._P is None:
            self._P = _param_vars(self.model, self.params, dirs.F, grad=False)[0]
        with dr.suspend_grad():
            chans = _frozen_kernel(self.model)(dirs.wi, dirs.wo, self._P)
            dr.eval(*chans)
        return _to_numpy(chans, dirs.n) if numpy else chans


def eval_resident(model, dirs, params, numpy=True):
    """f_r on a resident batch: one fused kernel in the batch's precision
    (``Bound(model, params, dirs.dtype).eval(dirs, numpy)``).

    Returns an (N, 3) numpy array, or (``numpy=False``) the three channels as evaluated
    Dr.Jit arrays (for timing, or to keep working in Dr.Jit)."""
    return Bound(model, params, dirs.dtype).eval(dirs, numpy)


@lru_cache(maxsize=64)
def _frozen_kernel_for(name, options):
    """:func:`_kernel` for one model configuration under ``dr.freeze``: the first call per
    input layout traces and records the kernel launch, later calls replay it with the new
    inputs (parameters are opaque inputs), skipping Python tracing and Dr.Jit's code
    generation and hashing (~0.1 ms a call)."""
    import drjit as dr

    from . import get

    model = get(name, **dict(options))

    def run(wi, wo, P):
        return _kernel(model, wi, wo, P)

    return dr.freeze(run)


def _frozen_kernel(model):
    # _kernel reads only the model's name and options (tables arrive in P). The two
    # diffuse models' traces are so short that replaying a recording costs more (~19 us
    # against ~13 us for 1000 pairs)
    if model.name in ("diffuse", "orennayar"):
        return lambda wi, wo, P: _kernel(model, wi, wo, P)
    return _frozen_kernel_for(model.name, tuple(sorted(model.options.items())))


def jacobian(model, dirs, params, numpy=True):
    """f_r and its derivative with respect to every parameter, in one fused kernel.

    Forward-mode derivatives written out next to the value in :func:`_kernel` (every
    intermediate shared; tested against Dr.Jit's reverse-mode AD and against finite
    differences of the numpy reference). Channels are independent in every model, so for a
    per-channel parameter p, ``J[p][:, c]`` is d f_r[c] / d p[c] (and d f_r[c] / d p[c']
    = 0 for c' != c); for a shared one it is d f_r[c] / d p.

    Returns
    -------
    f : ndarray (N, 3), or list of 3 Dr.Jit arrays when ``numpy=False``
    J : dict
        Parameter name -> ndarray (N, 3) (or list of 3 Dr.Jit arrays).

    Notes
    -----
    Roughness below Mitsuba's floor (1e-4) is clamped, so its derivative is 0 there. For
    ``roughplastic`` the derivatives include the tables' dependence on alpha and int_ior.
    """
    import drjit as dr

    p = model.validate(params)
    n = dirs.n
    if n == 0:
        z = np.zeros((0, CHANNELS), dtype=dirs.dtype)
        return z, {par.name: z.copy() for par in model.parameters}
    P, _ = _param_vars(model, p, dirs.F, grad=False, dtables=True)
    with dr.suspend_grad():
        f, J = _kernel(model, dirs.wi, dirs.wo, P, grad=True)
        dr.eval(*f, *(t for ts in J.values() for t in ts))
    if not numpy:
        return f, J
    return _to_numpy(f, n), {k: _to_numpy(v, n) for k, v in J.items()}


def chi2_grad(model, dirs, params, y, w):
    """chi^2 = sum w (f_r - y)^2 over pairs and channels, and its gradient with respect to
    every parameter: what a gradient-based fitter (nlopt's SLSQP or MMA, a quasi-Newton
    step) needs, in one fused kernel that stores nothing per pair.

    The derivatives are :func:`jacobian`'s, reduced inside the kernel (``scatter_reduce``
    with ``ReduceMode.Expand`` into float64 targets, whatever the batch's precision) into
    d chi^2 / d p = 2 sum w (f_r - y) d f_r / d p. The order of the additions depends on the
    thread schedule: results can differ in the last bits between runs.

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

    p = model.validate(params)
    y = y if isinstance(y, list) else dirs.channels(y, "y")
    w = w if isinstance(w, list) else dirs.channels(w, "w")
    if dirs.n == 0:
        return 0.0, {par.name: (np.zeros(CHANNELS) if par.per_channel else 0.0) for par in model.parameters}
    P, _ = _param_vars(model, p, dirs.F, grad=False, dtables=True)
    with dr.suspend_grad():
        sums = _chi2_sums(model, dirs.wi, dirs.wo, P, y, w)
        dr.eval(*sums)
    vals = np.array([float(np.asarray(v)[0]) for v in sums])
    grad, k = {}, 1
    for par in model.parameters:
        m = CHANNELS if par.per_channel else 1
        g = 2.0 * vals[k:k + m]
        grad[par.name] = g if par.per_channel else float(g[0])
        k += m
    return float(vals[0]), grad


def _chi2_sums(model, wi, wo, P, y, w):
    """[chi^2, then sum w (f - y) d f / d p for each parameter (3 sums for a per-channel
    one)], each reduced in the kernel into its own 1-element float64 target: each thread
    adds into its own copy (ReduceMode.Expand), merged at the end, so no atomics per lane.
    (One shared target is slower: every sum then hits the same cache line.)"""
    import drjit as dr

    _, F64, _, U = _dr()
    f, J = _kernel(model, wi, wo, P, grad=True)
    wr = [wc * (fc - yc) for fc, yc, wc in zip(f, y, w)]
    terms = [sum(a * (fc - yc) for a, fc, yc in zip(wr, f, y))]
    for par in model.parameters:
        t = [a * d for a, d in zip(wr, J[par.name])]
        terms += t if par.per_channel else [t[0] + t[1] + t[2]]
    zero = dr.zeros(U, 1)
    out = []
    for t in terms:
        target = dr.zeros(F64, 1)
        dr.scatter_reduce(dr.ReduceOp.Add, target, F64(t), zero, mode=dr.ReduceMode.Expand)
        out.append(target)
    return out
