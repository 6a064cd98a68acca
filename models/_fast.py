"""Compiled evaluation path: the same models written in Dr.Jit (LLVM backend).

The numpy implementations are the reference; this module evaluates the same formulas
(term for term, tested against the reference to 1e-10 relative) as fused, multithreaded
LLVM kernels, and differentiates them with Dr.Jit's automatic differentiation. It is
used only where Dr.Jit's LLVM backend works (:func:`available`); nothing else in
:mod:`gonio.models` depends on it.

* :func:`eval` -- f_r, shape (N, 3), like ``Model.eval``.
* :func:`value_and_grad` -- f_r and the gradient of ``sum(cotangent * f_r)`` with respect
  to every parameter (one reverse-mode pass; per-channel parameters get (3,) gradients).
  With ``cotangent = 2 w (f_r - y)`` this is the gradient of a weighted least-squares
  objective; with unit vectors it gives rows of the Jacobian.

For ``roughplastic`` the transmittance table and internal reflectance follow the
model's ``exact_tables`` setting: with ``exact_tables=False`` the interpolated grid of
:func:`gonio.models._rough_tables.rough_tables_interp` (gradients through the spline's
derivative); with ``exact_tables=True`` (the default, and in grid cells that fall back to
the exact tables) computed here as well (same quadrature as :mod:`gonio.models._rough_tables`), so that gradients
with respect to ``alpha`` and ``int_ior`` include their dependence through the table.

Kernels are cached by Dr.Jit: parameter values enter as opaque variables, so a new
parameter value does not trigger a recompilation.
"""

from __future__ import annotations

import math
import subprocess
import sys
from functools import lru_cache

import numpy as np

from ._base import CHANNELS, eval_inputs
from ._rough_tables import _interp

__all__ = ["available", "eval", "value_and_grad"]

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
    return r.returncode == 0


def _dr():
    import drjit as dr
    from drjit.llvm.ad import Array3f64, Float64, UInt32

    return dr, Float64, Array3f64, UInt32


# -- shared pieces --------------------------------------------------------------------------


def _safe_sqrt(dr, x):
    # floor at 1e-300 (not 0): the derivative stays finite, so masked lanes give 0 * finite
    # instead of 0 * inf = NaN in reverse mode; the value differs from 0 by 1e-150
    return dr.sqrt(dr.maximum(x, 1e-300))


def _half_vector(dr, F, wi, wo):
    h = wi + wo
    n2 = dr.squared_norm(h)
    valid = n2 > 1e-300
    inv = dr.rsqrt(dr.select(valid, n2, 1.0))
    return h * inv, valid


def _D(dr, kind, au, av, m):
    z2 = m.z * m.z
    up = m.z > 0
    z2s = dr.select(up, z2, 1.0)
    if kind == "beckmann":
        e = ((m.x / au) ** 2 + (m.y / av) ** 2) / z2s
        r = dr.exp(-e) / (math.pi * au * av * z2s * z2s)
    else:
        t = (m.x / au) ** 2 + (m.y / av) ** 2 + z2
        r = 1.0 / (math.pi * au * av * dr.select(up, t * t, 1.0))
    return dr.select(up & (r * m.z > 1e-20), r, 0.0)


def _g1(dr, kind, au, av, x, y, z, dot_wm):
    xy = (au * x) ** 2 + (av * y) ** 2
    z2 = z * z
    ok = z2 > 0
    t2 = xy / dr.select(ok, z2, 1.0)
    if kind == "ggx":
        g = 2.0 / (1.0 + dr.sqrt(1.0 + t2))
    else:
        pos = t2 > 0
        a = dr.rsqrt(dr.select(pos, t2, 1.0))
        a2 = a * a
        g = dr.select(a >= 1.6, 1.0, (3.535 * a + 2.181 * a2) / (1.0 + 2.276 * a + 2.577 * a2))
    g = dr.select(ok, g, 0.0)
    g = dr.select(xy == 0, 1.0, g)
    return dr.select(dot_wm * z <= 0, 0.0, g)


def _fresnel_outside(dr, ci, eta):
    """Dielectric Fresnel from the index-1 side, 0 <= ci <= 1; returns (F, cos_t)."""
    ci = dr.minimum(ci, 1.0)
    ct = _safe_sqrt(dr, 1.0 - (1.0 - ci * ci) / (eta * eta))
    den_s = ci + eta * ct
    den_p = ct + eta * ci
    special = ci <= 0
    a_s = (ci - eta * ct) / dr.select(special, 1.0, den_s)
    a_p = (ct - eta * ci) / dr.select(special, 1.0, den_p)
    return dr.select(special, 1.0, 0.5 * (a_s * a_s + a_p * a_p)), ct


def _fresnel_conductor(dr, c, eta, k):
    c = dr.clip(c, 0.0, 1.0)
    c2 = c * c
    s2 = 1.0 - c2
    s4 = s2 * s2
    t1 = eta * eta - k * k - s2
    a2pb2 = _safe_sqrt(dr, t1 * t1 + 4.0 * eta * eta * k * k)
    a = _safe_sqrt(dr, 0.5 * (a2pb2 + t1))
    term1 = a2pb2 + c2
    term2 = 2.0 * c * a
    den1 = term1 + term2
    r_s = dr.select(den1 > 0, (term1 - term2) / dr.select(den1 > 0, den1, 1.0), 1.0)
    term3 = a2pb2 * c2 + s4
    term4 = term2 * s2
    den2 = term3 + term4
    r_p = r_s * dr.select(den2 > 0, (term3 - term4) / dr.select(den2 > 0, den2, 1.0), 1.0)
    return dr.clip(0.5 * (r_s + r_p), 0.0, 1.0)


def _lerp_table(dr, F, U, table, x, n):
    x = dr.clip(x, 0.0, 1.0) * (n - 1)
    idx = dr.minimum(U(x), n - 2)
    w1 = x - F(idx)
    return dr.gather(F, table, idx) * (1.0 - w1) + dr.gather(F, table, idx + 1) * w1


# -- roughplastic tables ---------------------------------------------------------------------


@lru_cache(maxsize=None)
def _table_grid(kind, n):
    """Parameter-free parts of the table quadrature (numpy): GL nodes and weights and,
    for GGX, the concentric-disk points; flattened index layout (r, i, j)."""
    from ._rough_tables import RES, _disk, _gl, _mu

    mu, wx = _mu()
    u, w = _gl(n)
    h = n // 2
    if kind == "beckmann":
        a, b = n, h
        wgt = 0.5 * np.outer(w, w[:h])
        from scipy.special import erfinv

        sy = erfinv(2.0 * u[:h] - 1.0)  # y slope (alpha = 1), independent of mu and alpha
        extra = (u, sy)
    else:
        a, b = h, n
        wgt = 0.5 * np.outer(w[:h], w)
        px, py = _disk(n)
        extra = (px[:h].ravel(), py[:h].ravel())
    return mu, wx, a, b, wgt.ravel(), extra, RES


def _transmit(dr, kind, alpha, eta, mu, d, mz):
    """Integrand of Mitsuba's ``eval_transmittance``: (1 - F(wi . m)) G1(wt, m) for the
    refracted direction wt (z component ``oz``), 0 for back-facing or total reflection;
    ``d`` = wi . m, ``mz`` the normal's z, ``mu`` = wi_z."""
    front = d > 0
    Fr, ct = _fresnel_outside(dr, dr.select(front, d, 1.0), eta)
    eta_ti = 1.0 / eta
    oz = mz * (d * eta_ti - ct) - mu * eta_ti
    return dr.select(front & (oz < 0) & (ct > 0), _g1_z(dr, kind, alpha, oz) * (1.0 - Fr), 0.0)


def _ggx_warp(dr, F, alpha, cp, disk, ij):
    """Mitsuba's GGX visible-normal warp of the concentric-disk node ``ij`` for a direction
    with cosine ``cp`` (stretched): the slope-space normal's x and 1 / |(mx, my, 1)|."""
    px = dr.gather(F, F(disk[0]), ij)
    py = dr.gather(F, F(disk[1]), ij)
    s = 0.5 * (1.0 + cp)
    py = _safe_sqrt(dr, 1.0 - px * px) * (1.0 - s) + py * s
    z = _safe_sqrt(dr, 1.0 - px * px - py * py)
    sin_i = _safe_sqrt(dr, 1.0 - cp * cp)
    norm = alpha / (sin_i * py + cp * z)
    mx = -(cp * py - sin_i * z) * norm
    my = px * norm
    return mx, dr.rsqrt(mx * mx + my * my + 1.0)


def _tables(kind, alpha, eta):
    """Dr.Jit version of ``_rough_tables.rough_tables`` (differentiable in alpha, eta).

    Returns (t_ext Float64 of size 64, r_int Float64 of size 1)."""
    dr, F, V3, U = _dr()
    out = []
    for which, e in (("t", eta), ("r", 1.0 / eta)):
        n = 32 if which == "t" else 128  # Mitsuba: 32 nodes for eta > 1, 128 for eta < 1
        mu_np, wx_np, a, b, wgt_np, extra, res = _table_grid(kind, n)
        size = res * a * b
        idx = dr.arange(U, size)
        r = idx // (a * b)
        ij = idx - r * (a * b)
        i = ij // b
        j = ij - i * b
        mu = dr.gather(F, F(mu_np), r)
        wxr = dr.gather(F, F(wx_np), r)
        wgt = dr.gather(F, F(wgt_np), ij)
        cp = mu / dr.sqrt((alpha * wxr) ** 2 + mu * mu)
        if kind == "beckmann":
            u_np, sy_np = extra
            # the x slope depends on (r, i) only: solve it on that small grid, then gather
            k = dr.arange(U, res * a)
            rk = k // a
            muk = dr.gather(F, F(mu_np), rk)
            cpk = muk / dr.sqrt((alpha * dr.gather(F, F(wx_np), rk)) ** 2 + muk * muk)
            sxk = _beckmann_sx(dr, cpk, dr.gather(F, F(u_np), k - rk * a))
            sx = dr.gather(F, sxk, r * a + i)
            sy = dr.gather(F, F(sy_np), j)
            mx = -alpha * sx
            my2 = (alpha * sy) ** 2
            inv = dr.rsqrt(mx * mx + my2 + 1.0)
        else:
            mx, inv = _ggx_warp(dr, F, alpha, cp, extra, ij)
        mx = mx * inv
        mz = inv
        d = wxr * mx + mu * mz
        if which == "t":
            v = _transmit(dr, kind, alpha, e, mu, d, mz)
        else:
            oz = 2.0 * d * mz - mu
            front = (d > 0) & (oz > 0)
            Fr, _ = _fresnel_outside(dr, dr.select(front, d, 1.0), e)
            v = dr.select(front, _g1_z(dr, kind, alpha, oz) * Fr, 0.0)
        out.append(dr.block_sum(v * wgt, a * b))
    t_ext, refl = out
    r_int = dr.sum(refl * F(mu_np)) * (2.0 / res)
    return t_ext, r_int


def _g1_z(dr, kind, alpha, oz):
    oz2 = oz * oz
    t2 = alpha * alpha * (1.0 - oz2) / dr.select(oz2 > 0, oz2, 1.0)
    if kind == "ggx":
        return 2.0 / (1.0 + dr.sqrt(1.0 + t2))
    a = dr.rsqrt(dr.select(t2 > 0, t2, 1e-300))
    a2 = a * a
    return dr.select(a >= 1.6, 1.0, (3.535 * a + 2.181 * a2) / (1.0 + 2.276 * a + 2.577 * a2))


def _beckmann_sx(dr, c, u1):
    """x slope of Mitsuba's Beckmann ``sample_visible_11`` (Jakob 2014)."""
    inv_sqrt_pi = 1.0 / math.sqrt(math.pi)
    c = dr.clip(c, 1e-12, 1.0)
    s = _safe_sqrt(dr, 1.0 - c * c)
    tan_i = s / c
    pos = tan_i > 0
    cot_i = dr.select(pos, c / dr.select(s > 0, s, 1.0), 1e300)
    maxval = dr.erf(cot_i)
    u1 = dr.clip(u1, 1e-6, 1.0 - 1e-6)
    x = maxval - (maxval + 1.0) * dr.erf(dr.sqrt(-dr.log(u1)))
    ex = dr.select(pos, dr.exp(-dr.select(pos, cot_i, 0.0) ** 2), 0.0)
    u1 = u1 * (1.0 + maxval + inv_sqrt_pi * tan_i * ex)
    for _ in range(3):
        slope = dr.erfinv(x)
        value = 1.0 + x + inv_sqrt_pi * tan_i * dr.exp(-slope * slope) - u1
        deriv = 1.0 - slope * tan_i
        x = x - value / deriv
    return dr.erfinv(x)


# -- model kernels ---------------------------------------------------------------------------


def _channels(P, name):
    return P[name] if isinstance(P[name], list) else [P[name]] * CHANNELS


def _kernel(model, wi, wo, P):
    """f_r per channel (list of 3 Float64) for Dr.Jit inputs; P maps parameter names
    to Float64 scalars (per-channel parameters: lists of 3)."""
    dr, F, V3, U = _dr()
    name = model.name
    ci, co = wi.z, wo.z
    active = (ci > 0) & (co > 0)
    if name == "diffuse":
        rho = _channels(P, "reflectance")
        return [dr.select(active, r / math.pi + 0.0 * ci, 0.0) for r in rho]
    if name == "orennayar":
        rho = _channels(P, "reflectance")
        s2 = P["sigma"] * P["sigma"]
        A = 1.0 - s2 / (2.0 * (s2 + 0.33))
        B = 0.45 * s2 / (s2 + 0.09)
        cic, coc = dr.clip(ci, 0.0, 1.0), dr.clip(co, 0.0, 1.0)
        cd = wi.x * wo.x + wi.y * wo.y
        cmax = dr.maximum(cic, coc)
        term = dr.select(cmax > 0, dr.maximum(cd, 0.0) / dr.select(cmax > 0, cmax, 1.0), 0.0)
        f = A + B * term
        return [dr.select(active, r / math.pi * f, 0.0) for r in rho]
    wm, valid = _half_vector(dr, F, wi, wo)
    di, do = dr.dot(wi, wm), dr.dot(wo, wm)
    dh = 0.5 * (di + do)
    den = 4.0 * ci * co
    ok = active & valid & (den > 0)
    if name in ("roughplastic", "roughconductor"):
        kind = model.options["distribution"]
        if name == "roughconductor" and model.options["anisotropic"]:
            au, av = dr.maximum(P["alpha_u"], 1e-4), dr.maximum(P["alpha_v"], 1e-4)
        else:
            au = av = dr.maximum(P["alpha"], 1e-4)
        D = _D(dr, kind, au, av, wm)
        G = _g1(dr, kind, au, av, wi.x, wi.y, ci, di) * _g1(dr, kind, au, av, wo.x, wo.y, co, do)
        s = dr.select(ok, D * G / dr.select(ok, den, 1.0), 0.0)
        if name == "roughconductor":
            etas, ks = _channels(P, "eta"), _channels(P, "k")
            return [dr.select(active, _fresnel_conductor(dr, dh, e, k) * s, 0.0) for e, k in zip(etas, ks)]
        eta = P["int_ior"]
        Fr, _ = _fresnel_outside(dr, dr.clip(dh, 0.0, 1.0), eta)
        spec = Fr * s
        t_ext, r_int = P["_tables"]
        ti = _lerp_table(dr, F, U, t_ext, ci, 64)
        to = _lerp_table(dr, F, U, t_ext, co, 64)
        scale = ti * to / (math.pi * eta * eta)
        out = []
        for rho in _channels(P, "diffuse_reflectance"):
            denom = 1.0 - (rho * r_int if model.options["nonlinear"] else r_int)
            out.append(dr.select(active, spec + rho / denom * scale, 0.0))
        return out
    if name == "cooktorrance":
        m = P["roughness"]
        ch = wm.z
        up = ok & (ch > 0) & (dh > 0)
        ch2s = dr.select(up, ch * ch, 1.0)
        m2 = m * m
        tan2 = (wm.x * wm.x + wm.y * wm.y) / ch2s
        D = dr.exp(-tan2 / m2) / (m2 * ch2s * ch2s)
        G = dr.minimum(1.0, 2.0 * ch * dr.minimum(ci, co) / dr.select(up, dh, 1.0))
        s = dr.select(up, D * G / (math.pi * dr.select(up, ci * co, 1.0)), 0.0)
        x = 1.0 - dr.clip(dh, 0.0, 1.0)
        x2 = x * x
        x5 = x2 * x2 * x
        out = []
        for rd, rs, f0 in zip(_channels(P, "diffuse_reflectance"), _channels(P, "specular_reflectance"), _channels(P, "f0")):
            out.append(dr.select(active, rd / math.pi + rs * (f0 + (1.0 - f0) * x5) * s, 0.0))
        return out
    raise NotImplementedError(f"no compiled kernel for model {name!r}")


def _inputs(model, wi, wo, params, grad):
    """Dr.Jit inputs. Directions are loaded as flat (3N) arrays without copies and
    de-interleaved by gathers inside the fused kernel; non-finite directions are
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
        grid = None if getattr(model, "exact_tables", True) else _interp(kind, p["alpha"], p["int_ior"], grad=grad)
        if grid is not None:
            # the same interpolated tables as the numpy model; for gradients, their
            # first-order expansion about the current point (value unchanged: the
            # opaque alpha, eta equal p's), d/d(alpha, eta) from the spline
            if grad:
                t, r, dx, dy = grid
                da, de = P["alpha"] - p["alpha"], P["int_ior"] - p["int_ior"]
                P["_tables"] = (F(t) + da * F(dx[:-1]) + de * F(dy[:-1]), F([r]) + da * dx[-1] + de * dy[-1])
            else:
                P["_tables"] = (F(grid[0]), F([grid[1]]))
        elif grad:
            P["_tables"] = _tables(kind, dr.maximum(P["alpha"], 1e-4), P["int_ior"])
        else:
            P["_tables"] = _cached_tables(kind, p["alpha"], p["int_ior"])
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


@lru_cache(maxsize=256)
def _cached_tables(kind, alpha, eta):
    dr, F, V3, U = _dr()
    t, r = _tables(kind, dr.opaque(F, max(alpha, 1e-4)), dr.opaque(F, eta))
    dr.eval(t, r)
    return t, r


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

#: theta names of the models with an affine per-channel parameter: model name -> (affine
#: parameter, nonlinear parameters in theta's column order).
AFFINE = {
    "diffuse": ("reflectance", ()),
    "orennayar": ("reflectance", ("sigma",)),
    "roughplastic": ("diffuse_reflectance", ("alpha", "int_ior")),
}


def affine_spec(model):
    """(affine parameter, theta names) when :func:`affine_parts` serves ``model``, else None."""
    spec = AFFINE.get(model.name)
    if spec is None:
        return None
    if model.name == "roughplastic" and (model.options["nonlinear"] or not getattr(model, "exact_tables", True)):
        return None  # coef would not be affine (nonlinear) / the model uses interpolated tables
    return spec


class Prepared:
    """Directions loaded once into Dr.Jit (float64), for repeated :func:`affine_parts` calls."""

    def __init__(self, wi, wo):
        dr, F, V3, U = _dr()
        wi = np.asarray(wi, dtype=np.float64)
        wo = np.asarray(wo, dtype=np.float64)
        ok = np.isfinite(wi).all(axis=1) & np.isfinite(wo).all(axis=1)
        down = np.array([0.0, 0.0, -1.0])
        wi = np.where(ok[:, None], wi, down)
        wo = np.where(ok[:, None], wo, down)
        self.n = wi.shape[0]
        self.wi = [F(np.ascontiguousarray(wi[:, k])) for k in range(3)]
        self.wo = [F(np.ascontiguousarray(wo[:, k])) for k in range(3)]
        dr.make_opaque(*self.wi, *self.wo)


def prepare(wi, wo):
    """Load a batch of direction pairs (N, 3) for :func:`affine_parts`."""
    return Prepared(wi, wo)


def _t_ext_batch(kind, alpha, eta):
    """Transmittance tables of K (alpha, eta) pairs (Float64 arrays of size K): size K * 64,
    the same quadrature as :func:`_tables` (32 x 32 Gauss-Legendre over visible normals)."""
    dr, F, V3, U = _dr()
    mu_np, wx_np, a, b, wgt_np, extra, res = _table_grid(kind, 32)
    size = res * a * b
    idx = dr.arange(U, dr.width(alpha) * size)
    k = idx // size
    loc = idx - k * size
    r = loc // (a * b)
    ij = loc - r * (a * b)
    al = dr.gather(F, alpha, k)
    e = dr.gather(F, eta, k)
    mu = dr.gather(F, F(mu_np), r)
    wxr = dr.gather(F, F(wx_np), r)
    wgt = dr.gather(F, F(wgt_np), ij)
    cp = mu / dr.sqrt((al * wxr) ** 2 + mu * mu)
    if kind == "beckmann":
        u_np, sy_np = extra
        i = ij // b
        sx = _beckmann_sx(dr, cp, dr.gather(F, F(u_np), i))
        sy = dr.gather(F, F(sy_np), ij - i * b)
        mx = -al * sx
        inv = dr.rsqrt(mx * mx + (al * sy) ** 2 + 1.0)
    else:
        mx, inv = _ggx_warp(dr, F, al, cp, extra, ij)
    mx = mx * inv
    mz = inv
    d = wxr * mx + mu * mz
    return dr.block_sum(_transmit(dr, kind, al, e, mu, d, mz) * wgt, a * b)


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
    if model.name != "roughplastic":
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
    prepared : Prepared
        The directions (:func:`prepare`).
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
    spec = affine_spec(model)
    if spec is None:
        raise ValueError(f"model {model!r} has no affine-parts kernel")
    dr, F, V3, U = _dr()
    th = _theta_array(thetas, len(spec[1]))
    K, N = th.shape[0], prepared.n
    if N == 0:
        return np.zeros((K, 0)), np.zeros((K, 0))
    cols = [F(np.ascontiguousarray(th[:, j])) for j in range(th.shape[1])]
    if cols:
        dr.make_opaque(*cols)
    with dr.suspend_grad():
        lane = dr.arange(U, K * N)
        k = lane // N
        i = lane - k * N
        vi = V3(*(dr.gather(F, c, i) for c in prepared.wi))
        vo = V3(*(dr.gather(F, c, i) for c in prepared.wo))
        ci, co = vi.z, vo.z
        active = (ci > 0) & (co > 0)
        if model.name == "diffuse":
            base = F(0.0) * ci
            basis = dr.select(active, F(1.0 / math.pi), F(0.0))
        elif model.name == "orennayar":
            sig = dr.gather(F, cols[0], k)
            s2 = sig * sig
            A = 1.0 - s2 / (2.0 * (s2 + 0.33))
            B = 0.45 * s2 / (s2 + 0.09)
            cmax = dr.maximum(dr.clip(ci, 0.0, 1.0), dr.clip(co, 0.0, 1.0))
            cd = vi.x * vo.x + vi.y * vo.y
            term = dr.select(cmax > 0, dr.maximum(cd, 0.0) / dr.select(cmax > 0, cmax, 1.0), 0.0)
            base = F(0.0) * ci
            basis = dr.select(active, (A + B * term) / math.pi, 0.0)
        else:  # roughplastic, nonlinear=False
            kind = model.options["distribution"]
            alpha = dr.maximum(cols[0], 1e-4)
            if tables is None:
                t = _t_ext_batch(kind, alpha, cols[1])
            else:
                tb = np.asarray(tables, dtype=np.float64)
                if tb.shape != (K, 64):
                    raise ValueError(f"tables must have shape ({K}, 64), got {tb.shape}")
                t = F(tb.reshape(-1))
            al = dr.gather(F, alpha, k)
            eta = dr.gather(F, cols[1], k)
            wm, valid = _half_vector(dr, F, vi, vo)
            di, do = dr.dot(vi, wm), dr.dot(vo, wm)
            den = 4.0 * ci * co
            ok = active & valid & (den > 0)
            D = _D(dr, kind, al, al, wm)
            G = _g1(dr, kind, al, al, vi.x, vi.y, ci, di) * _g1(dr, kind, al, al, vo.x, vo.y, co, do)
            Fr, _ = _fresnel_outside(dr, dr.clip(0.5 * (di + do), 0.0, 1.0), eta)
            base = dr.select(ok, Fr * D * G / dr.select(ok, den, 1.0), 0.0)

            def lerp(x):
                x = dr.clip(x, 0.0, 1.0) * 63
                j = dr.minimum(U(x), 62)
                w1 = x - F(j)
                return dr.gather(F, t, k * 64 + j) * (1.0 - w1) + dr.gather(F, t, k * 64 + j + 1) * w1

            basis = dr.select(active, lerp(ci) * lerp(co) / (math.pi * eta * eta), 0.0)
        dr.eval(base, basis)
        return np.asarray(base).reshape(K, N), np.asarray(basis).reshape(K, N)


def affine_q(model, thetas):
    """q(theta), shape (K,): the model's affine parameter is ``coef * q`` (exact).

    1 for ``diffuse`` and ``orennayar``; ``1 - R_int(alpha, eta)`` for ``roughplastic``,
    from the same 128 x 128 quadrature as :func:`gonio.models._rough_tables.rough_tables`
    (cached per (alpha, eta))."""
    spec = affine_spec(model)
    if spec is None:
        raise ValueError(f"model {model!r} has no affine-parts kernel")
    th = _theta_array(thetas, len(spec[1]))
    if model.name != "roughplastic":
        return np.ones(th.shape[0])
    kind = model.options["distribution"]
    return np.array([1.0 - float(np.asarray(_cached_tables(kind, float(a), float(e))[1])[0]) for a, e in th])
