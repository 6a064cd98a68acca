"""roughplastic's tables in Dr.Jit (:mod:`gonio.models.engine.jit` holds the pieces they share with
the other kernels): the transmittance table and the internal reflectance of a rough
dielectric over a diffuse base, by the same quadrature as the numpy reference
(:mod:`gonio.models.physics.rough_tables`: 32 x 32 Gauss-Legendre over visible normals), cached per
(alpha, eta) with their derivatives, and in batches of K (alpha, eta) pairs for the affine
parts (:func:`_t_ext_batch`)."""

from __future__ import annotations

import math
from collections import OrderedDict
from functools import lru_cache

import numpy as np

from gonio.models.engine.jit import _dr, _fresnel_outside, _pairs, _safe_sqrt
from gonio.models.physics.rough_tables import RES, _disk, _gl, _mu


@lru_cache(maxsize=None)
def _table_grid(kind, n):
    """Parameter-free parts of the table quadrature (numpy): GL nodes and weights and,
    for GGX, the concentric-disk points; flattened index layout (r, i, j)."""
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


@lru_cache(maxsize=256)
def _cached_tables(kind, alpha, eta, F=None, paired=False):
    """roughplastic's (t_ext, r_int) at (alpha, eta), evaluated, as Dr.Jit arrays of type F
    (float64 by default; computed in float64 and cast); with ``paired``, t_ext as
    :func:`_pairs` for :func:`_lerp_table`."""
    dr, F64, V3, U = _dr()
    if paired:
        t, r = _cached_tables(kind, alpha, eta, F)
        t = _pairs(t)
    elif F is not None and F is not F64:
        t, r = _cached_tables(kind, alpha, eta)
        t, r = F(t), F(r)
    elif (seeded := _SEEDED.get((kind, alpha, eta))) is not None:      # one read: threads evict
        t, r = seeded
    else:
        t, r = _tables(kind, dr.opaque(F64, max(alpha, 1e-4)), dr.opaque(F64, eta))
    dr.eval(t, r)
    return t, r


#: (kind, alpha, eta) -> the float64 tables :func:`_cached_table_derivs` evaluated on its way
#: (the most recent 256), read by :func:`_cached_tables` in place of a second quadrature
_SEEDED: OrderedDict = OrderedDict()


def clear_cache():
    """Forget every table and derivative computed (the tests' fresh start)."""
    _SEEDED.clear()
    _cached_tables.cache_clear()
    _cached_table_derivs.cache_clear()


@lru_cache(maxsize=256)
def _cached_table_derivs(kind, alpha, eta, F=None):
    """d(t_ext, r_int)/d alpha and d/d eta of roughplastic's tables at (alpha, eta), by
    Dr.Jit's forward-mode AD through the quadrature (float64, cast to F): (dt/d alpha,
    dr/d alpha, dt/d eta, dr/d eta). alpha below the floor 1e-4 is clamped: d/d alpha = 0."""
    import drjit as dr

    F64 = _dr()[1]
    F = F or F64
    a, e = dr.opaque(F64, max(alpha, 1e-4)), dr.opaque(F64, eta)
    dr.enable_grad(a, e)
    t, r = _tables(kind, a, e)
    # the tables themselves come out of the same evaluation: hand them to _cached_tables
    # (float64, and in F paired as the kernel reads them) instead of a second quadrature
    t0, r0 = dr.detach(t) + dr.zeros(F64, 64), dr.detach(r) + dr.zeros(F64, 1)
    dr.eval(t0, r0)
    _SEEDED[(kind, alpha, eta)] = (t0, r0)
    while len(_SEEDED) > 256:
        try:
            _SEEDED.popitem(last=False)
        except KeyError:            # another thread emptied it first
            break
    out = []
    for x in (a, e):
        dr.set_grad(x, 1.0)
        dr.forward_to(t, r, flags=dr.ADFlag.ClearVertices)
        out += [dr.detach(dr.grad(t)) + dr.zeros(F64, 64), dr.detach(dr.grad(r)) + dr.zeros(F64, 1)]
        dr.clear_grad((t, r, x))
    if alpha < 1e-4:
        out[0], out[1] = dr.zeros(F64, 64), dr.zeros(F64, 1)
    out = [F(v) for v in out]
    out[0], out[2] = _pairs(out[0]), _pairs(out[2])
    dr.eval(*out)
    return tuple(out)


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
