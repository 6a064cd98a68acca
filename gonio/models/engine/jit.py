"""Dr.Jit building blocks shared by the compiled kernels (:mod:`gonio.models.fast`): the
Fresnel terms, microfacet lobes and Oren-Nayar shape, and the resident direction batches
(roughplastic's table quadratures, built on these, in :mod:`gonio.models.engine.jit_tables`). Every piece takes the Dr.Jit module and works in float64
and float32 alike (the type follows the inputs); Dr.Jit itself is imported only when a
piece runs.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from gonio.core.channels import CHANNELS
from gonio.core.geometry import as_directions

__all__ = ["Directions", "JitContext", "channels", "microfacet_lobe", "rotate_about_normal"]


def _dr():
    import drjit as dr
    from drjit.llvm.ad import Array3f64, Float64, UInt32

    return dr, Float64, Array3f64, UInt32


# -- shared pieces --------------------------------------------------------------------------
#
# Written for the throughput of the LLVM kernels: on this hardware a division or a square
# root costs as much as ten multiplications, so every term below is arranged as one
# fraction (the microfacet term D G / (4 cos_i cos_o), Fresnel's equations) with a single
# division at the end. The algebra is exact; results equal the numpy reference to rounding.
# Every piece works in float64 and float32 alike (the type follows the inputs).


def _floor(x):
    """Smallest argument :func:`_safe_sqrt` passes on for the precision of ``x``."""
    import drjit as dr

    return 1e-300 if dr.type_v(x) == dr.VarType.Float64 else 1e-30


def _is_f32(x):
    """True for a float32 Dr.Jit array (where rsqrt is cheaper than a division)."""
    import drjit as dr

    return dr.type_v(x) == dr.VarType.Float32


def _safe_sqrt(dr, x):
    # floor at a tiny positive number (not 0): the derivative stays finite, so masked lanes
    # give 0 * finite instead of 0 * inf = NaN in both AD modes
    return dr.sqrt(dr.maximum(x, _floor(x)))


def _fresnel_outside(dr, ci, eta, grad=False):
    """Dielectric Fresnel reflectance from the index-1 side, 0 <= ci <= 1; returns (F, cos_t)
    and, with ``grad``, dF / d eta as a third element.

    F = (a_s^2 + a_p^2) / 2 with a_s = (ci - eta ct) / (ci + eta ct), a_p = (ct - eta ci) /
    (ct + eta ci) (Born & Wolf, sec. 1.5.2), over one common denominator. With u = eta ct,
    du / d eta = 1 / ct and eta d ct / d eta = (1 - ct^2) / ct, so
    dF / d eta = (2 ci / ct) [(ct - eta ci)(1 - 2 ct^2) / dp^3 - (ci - u) / ds^3]."""
    ci = dr.minimum(ci, 1.0)
    ct = _safe_sqrt(dr, 1.0 - (1.0 - ci * ci) * (1.0 / (eta * eta)))
    es, ep = eta * ct, eta * ci
    ds, dp = ci + es, ct + ep
    ns, npp = (ci - es) * dp, (ct - ep) * ds
    den = ds * dp
    special = ci <= 0
    F = 0.5 * (ns * ns + npp * npp) / dr.select(special, 1.0, den * den)
    out = (dr.select(special, 1.0, F), ct)
    if grad:
        ds3, dp3 = ds * ds * ds, dp * dp * dp
        g = 2.0 * ci * ((ct - ep) * (1.0 - 2.0 * ct * ct) * ds3 - (ci - es) * dp3) / dr.select(special, 1.0, ct * ds3 * dp3)
        out += (dr.select(special, 0.0, g),)
    return out


def _fresnel_conductor(dr, c, eta, k, grad=False):
    """Unpolarised conductor reflectance (eta + i k), the form of Mitsuba's
    ``fresnel_conductor`` (after pbrt-v3's FrConductor): F = (R_s + R_p) / 2 with
    R_s = (T1 - T2) / (T1 + T2), R_p = R_s (T3 - T4) / (T3 + T4), i.e.
    F = (T1 - T2) T3 / (P Q), P = T1 + T2, Q = T3 + T4: one division.

    The cosine is floored at 1e-15: then P >= c^2 > 0 and Q > 0 for every eta > 0 (no guard
    needed), and F is unchanged wherever a model uses it (c = wi . m > 0 for two directions
    above the horizon).

    With ``grad``, returns (F, dF/d eta, dF/d k): with A = a^2 + b^2,
    dA/d eta = 2 eta (eta^2 + k^2 - s^2) / A, dA/dk = 2 k (eta^2 + k^2 + s^2) / A,
    da = (dA +- 2 eta|k) / (4 a) (or its cancellation-free form, below), dT1 = dA,
    dT2 = 2 c da, dT3 = c^2 dA, dT4 = s^2 dT2 and
    dF = [2 (dT1 T2 - dT2 T1) T3 Q + (T1 - T2)(dT3 T4 - dT4 T3) P] / (P Q)^2."""
    c = dr.clip(c, 1e-15, 1.0)
    c2 = c * c
    s2 = 1.0 - c2
    e2, k2 = eta * eta, k * k
    t1 = e2 - k2 - s2
    X = t1 * t1 + 4.0 * e2 * k2
    if grad and _is_f32(X):
        # float32 with derivatives, which need 1 / A and 1 / sqrt(q) anyway (q = A - t1 where
        # t1 < 0, a^2 elsewhere; see below): A and a from those two reciprocal square roots
        # (rsqrt14 and a Newton step), A = X / sqrt(X), a = a^2 / sqrt(a^2) or, where t1 < 0,
        # the cancellation-free a = sqrt(2) eta k / sqrt(A - t1). In float32 A + t1 cancels
        # wherever t1 < 0 (k -> 0 with eta < sin(theta), and every metal with k > eta: k = 3,
        # eta = 0.2 loses ~8 bits), and that error went into F and both derivatives: F to
        # 3.1e-4 relative near k = 0, now <= 8.7e-7 (tests/models/test_fast.py). Two square
        # roots fewer per channel, but no time saved that the bench can see (roughconductor
        # GGX chi2_grad, AVX2: 13.2-13.5 ms against 13.2-13.9 ms).
        Xf = dr.maximum(X, _floor(X))
        rA = dr.rsqrt(Xf)
        A = Xf * rA
        a2 = 0.5 * (A + t1)
        neg = t1 < 0
        q = dr.maximum(dr.select(neg, A - t1, a2), _floor(X))
        rq = dr.rsqrt(q)
        a = dr.select(neg, (math.sqrt(2.0) * eta * k) * rq, q * rq)
    else:
        A = _safe_sqrt(dr, X)  # a^2 + b^2
        a2 = 0.5 * (A + t1)
        a = _safe_sqrt(dr, a2)
    T1 = A + c2
    T2 = 2.0 * c * a
    T3 = A * c2 + s2 * s2
    T4 = T2 * s2
    if not grad:
        return dr.clip((T1 - T2) * T3 / ((T1 + T2) * (T3 + T4)), 0.0, 1.0)
    P, Q = T1 + T2, T3 + T4
    r = 1.0 / (P * Q)
    F = dr.clip((T1 - T2) * T3 * r, 0.0, 1.0)
    if not _is_f32(X):
        # 1 / A: in float64 a division (Dr.Jit's float64 rsqrt is a division and a square root)
        rA = 1.0 / A
    # da without cancellation. For t1 >= 0, a^2 = (A + t1) / 2 >= t1 and da = (dA + dt1) / (4a).
    # For t1 < 0 (k -> 0 with eta below sin(theta)) A + t1 cancels; there
    # a = sqrt(2) eta k / sqrt(R), R = A - t1 >= 2 |t1| (since (A + t1)(A - t1) = 4 eta^2 k^2),
    # whose derivative stays exact down to k = 0 (one-sided there: F ~ 1 - C k):
    # da = sqrt(2) d(eta k) / sqrt(R) - c1 (dA - dt1), c1 = eta k / (sqrt(2) R^1.5).
    # Both branches need one reciprocal square root, of R or of a^2: one rsqrt per lane
    # (float32: computed above)
    if not _is_f32(X):
        neg = t1 < 0
        rq = dr.rsqrt(dr.maximum(dr.select(neg, A - t1, a2), _floor(X)))
    c1 = (math.sqrt(0.5) * eta * k) * (rq * rq * rq)
    ra4 = 0.25 * rq
    # dF is linear in (dA, dT2) with coefficients shared by d/d eta and d/dk (dT1 = dA,
    # dT3 = c^2 dA, dT4 = s^2 dT2): dF = (al dA + be dT2) / (P Q)^2 with
    # al = 2 T2 T3 Q + (T1 - T2) s^2 c^2 T2 P, be = -(2 T1 T3 Q + (T1 - T2) s^2 T3 P);
    # and da = u dA + v (u, v per branch above), dT2 = 2 c da, so dF = g dA + b2 v
    r2 = r * r
    m12, s2P = T1 - T2, s2 * P
    al = (2.0 * T2 * T3 * Q + m12 * s2P * c2 * T2) * r2
    b2 = -2.0 * c * (2.0 * T1 * T3 * Q + m12 * s2P * T3) * r2
    g = al + b2 * dr.select(neg, -c1, ra4)
    sR = math.sqrt(2.0) * rq
    out = [F]
    for dA_num, dt1, d_ek in ((2.0 * eta * (e2 + k2 - s2), 2.0 * eta, k), (2.0 * k * (e2 + k2 + s2), -2.0 * k, eta)):
        v = dr.select(neg, sR * d_ek + c1 * dt1, ra4 * dt1)
        out.append(g * (dA_num * rA) + b2 * v)
    return tuple(out)


def _beckmann_g1_over_cos(dr, au, av, w):
    """Mitsuba's Beckmann G1 (Walter et al. 2007's rational fit in a = 1 / (alpha tan)) over
    cos(theta), as a fraction: with s = |(au x, av y)|, a = z / s, multiply the fit's
    numerator and denominator by s^2; G1 = 1 (num 1, den z) for a >= 1.6.
    Returns (num, den, s, a >= 1.6)."""
    s = _safe_sqrt(dr, (au * w.x) ** 2 + (av * w.y) ** 2)
    z = w.z
    big = z >= 1.6 * s
    num = dr.select(big, 1.0, 3.535 * s + 2.181 * z)
    return num, dr.select(big, z, s * s + 2.276 * s * z + 2.577 * z * z), s, big


def _beckmann_dlog_g1(dr, n, d, s, z, big):
    """The factor k of d ln(G1 / cos) / d a = (a x)^2 k / a for :func:`_beckmann_g1_over_cos`'s
    (num, den, s, big) at cosine z: 0 where G1 = 1 (``big``)."""
    return dr.select(big, 0.0, (3.535 * d - (2.0 * s + 2.276 * z) * n) / dr.select(big, 1.0, s * n * d))


def _half_vector(dr, wi, wo):
    """What :func:`_lobe` and :func:`_lobe_iso_geometry` share: (cos_i, cos_o, h = wi + wo, the
    mask ``ok`` (both above the horizon and h not vanishing), 1 / |h| (1 where not ok),
    cos(theta_m) and c = wi . m)."""
    ci, co = wi.z, wo.z
    h = wi + wo
    h2 = dr.squared_norm(h)
    ok = (ci > 0) & (co > 0) & (h2 > _floor(h2))
    inv = dr.rsqrt(dr.select(ok, h2, 1.0))
    mz = h.z * inv
    c = 0.5 * (dr.dot(wi, h) + dr.dot(wo, h)) * inv
    return ci, co, h, ok, inv, mz, c


def _lobe(dr, kind, au, av, wi, wo, grad=False):
    """Mitsuba's microfacet reflection term D(m) G(wi, wo, m) / (4 cos_i cos_o) as a
    fraction, for the half vector m of (wi, wo) and separable Smith G.

    Returns ``(num, den, c, ok)``: the term is num / den where ``ok`` (den is 1 elsewhere),
    c = wi . m (the Fresnel cosine). For GGX the cosines cancel exactly:
    G1(w) / (2 cos) = 1 / (cos + sqrt(cos^2 + (au x)^2 + (av y)^2)). D is 0 where
    D cos(theta_m) <= 1e-20, Mitsuba's cut.

    With ``grad``, also ``(gu, gv, gt)``: d ln(term) / d au, d / d av (for an isotropic
    alpha, d / d alpha = gu + gv) and d / d theta for directions turned by -theta about the
    normal before the term (d x / d theta = y, d y / d theta = -x: t changes by
    2 m_x m_y (1/au^2 - 1/av^2), S^2 = cos^2 + (au x)^2 + (av y)^2 by 2 (au^2 - av^2) x y),
    0 where the term is 0. GGX: ln den = ln(pi au av) +
    2 ln t + ln(ci + Si) + ln(co + So) with t = (mx/au)^2 + (my/av)^2 + mz^2; Beckmann:
    ln(term) = -e + ln(n_i/d_i) + ln(n_o/d_o) - ln(4 pi au av mz^4) with e = ((mx/au)^2 +
    (my/av)^2) / mz^2 and d s / d au = (au x)^2 / (au s) for each direction."""
    ci, co, h, ok, inv, mz, c = _half_vector(dr, wi, wo)
    iau, iav = 1.0 / au, 1.0 / av
    qx, qy = (h.x * inv * iau) ** 2, (h.y * inv * iav) ** 2
    px2 = qx + qy
    paa = math.pi * au * av
    ax_i, ay_i, ax_o, ay_o = (au * wi.x) ** 2, (av * wi.y) ** 2, (au * wo.x) ** 2, (av * wo.y) ** 2
    if grad:    # for gt: m_x m_y and au^2 - av^2
        mxy, d2 = h.x * h.y * inv * inv, au * au - av * av
    if kind == "ggx":
        t = px2 + mz * mz
        si = _safe_sqrt(dr, ci * ci + ax_i + ay_i)
        so = _safe_sqrt(dr, co * co + ax_o + ay_o)
        tt = paa * t * t
        num = 1.0 + 0.0 * ci
        den = tt * (ci + si) * (co + so)
        ok &= mz > 1e-20 * tt
        if grad:
            rt = 4.0 / t
            w_i = 1.0 / (si * (ci + si))
            w_o = 1.0 / (so * (co + so))
            gu = (qx * rt - 1.0 - ax_i * w_i - ax_o * w_o) * iau
            gv = (qy * rt - 1.0 - ay_i * w_i - ay_o * w_o) * iav
            gt = -(rt * mxy * (iau * iau - iav * iav) + d2 * (wi.x * wi.y * w_i + wo.x * wo.y * w_o))
    else:
        mz2 = mz * mz
        mz2 = dr.select(ok, mz2, 1.0)
        rmz2 = 1.0 / mz2 if grad else None
        ex = dr.exp(-(px2 * rmz2 if grad else px2 / mz2))
        ni, di, s_i, big_i = _beckmann_g1_over_cos(dr, au, av, wi)
        no, do, s_o, big_o = _beckmann_g1_over_cos(dr, au, av, wo)
        dd = paa * mz2 * mz2
        num = ex * ni * no
        den = 4.0 * dd * di * do
        ok &= ex * mz > 1e-20 * dd
        if grad:
            k_i, k_o = _beckmann_dlog_g1(dr, ni, di, s_i, ci, big_i), _beckmann_dlog_g1(dr, no, do, s_o, co, big_o)
            gu = (2.0 * qx * rmz2 - 1.0 + ax_i * k_i + ax_o * k_o) * iau
            gv = (2.0 * qy * rmz2 - 1.0 + ay_i * k_i + ay_o * k_o) * iav
            gt = d2 * (wi.x * wi.y * k_i + wo.x * wo.y * k_o) - 2.0 * mxy * (iau * iau - iav * iav) * rmz2
    ok &= den > 0
    out = (dr.select(ok, num, 0.0), dr.select(ok, den, 1.0), c, ok)
    if grad:
        out += (dr.select(ok, gu, 0.0), dr.select(ok, gv, 0.0), dr.select(ok, gt, 0.0))
    return out


def rotate_about_normal(dr, w, tangent_deg):
    """Directions ``w`` (a Dr.Jit 3-vector) turned by -tangent_deg about the normal: the
    holder frame -> a tangent frame whose x axis lies at tangent_deg from the holder's."""
    t = tangent_deg * (math.pi / 180.0)
    c, s = dr.cos(t), dr.sin(t)
    return type(w)(c * w.x + s * w.y, c * w.y - s * w.x, w.z)


def _lobe_iso_geometry(dr, wi, wo):
    """The parameter-independent part of :func:`_lobe` for an isotropic roughness, per pair:
    (cos_i, cos_o, sin^2_i, sin^2_o, sin^2(theta_m), cos(theta_m), c = wi . m), the cosines 0
    where :func:`_lobe`'s ``ok`` is false (a pair below the horizon, or h = 0)."""
    ci, co, h, ok, inv, mz, c = _half_vector(dr, wi, wo)
    sm2 = (h.x * inv) ** 2 + (h.y * inv) ** 2
    return (dr.select(ok, ci, 0.0), dr.select(ok, co, 0.0), wi.x * wi.x + wi.y * wi.y, wo.x * wo.x + wo.y * wo.y,
            sm2, mz, c)


def _lobe_iso(dr, kind, alpha, g, grad=False):
    """:func:`_lobe` for au = av = alpha on :func:`_lobe_iso_geometry`'s quantities ``g``
    (the same formulas; ``gu + gv`` as one derivative): ``(num, den, c, ok)`` and, with
    ``grad``, d ln(term) / d alpha."""
    ci, co, si2, so2, sm2, mz, c = g
    ok = (ci > 0) & (co > 0)
    ia2 = 1.0 / (alpha * alpha)
    a2 = alpha * alpha
    px2 = sm2 * ia2
    paa = math.pi * a2
    ax_i, ax_o = a2 * si2, a2 * so2
    if kind == "ggx":
        t = px2 + mz * mz
        si = _safe_sqrt(dr, ci * ci + ax_i)
        so = _safe_sqrt(dr, co * co + ax_o)
        tt = paa * t * t
        num = 1.0 + 0.0 * ci
        den = tt * (ci + si) * (co + so)
        ok &= mz > 1e-20 * tt
        if grad:
            w_i = 1.0 / (si * (ci + si))
            w_o = 1.0 / (so * (co + so))
            ga = (px2 * (4.0 / t) - 2.0 - ax_i * w_i - ax_o * w_o) * (1.0 / alpha)
    else:
        mz2 = dr.select(ok, mz * mz, 1.0)
        rmz2 = 1.0 / mz2 if grad else None
        ex = dr.exp(-(px2 * rmz2 if grad else px2 / mz2))

        def g1(z, sin2):
            s = _safe_sqrt(dr, a2 * sin2)
            big = z >= 1.6 * s
            n = dr.select(big, 1.0, 3.535 * s + 2.181 * z)
            return n, dr.select(big, z, s * s + 2.276 * s * z + 2.577 * z * z), s, big

        ni, di, s_i, big_i = g1(ci, si2)
        no, do, s_o, big_o = g1(co, so2)
        dd = paa * mz2 * mz2
        num = ex * ni * no
        den = 4.0 * dd * di * do
        ok &= ex * mz > 1e-20 * dd
        if grad:
            ga = (2.0 * px2 * rmz2 - 2.0 + ax_i * _beckmann_dlog_g1(dr, ni, di, s_i, ci, big_i)
                  + ax_o * _beckmann_dlog_g1(dr, no, do, s_o, co, big_o)) * (1.0 / alpha)
    ok &= den > 0
    out = (dr.select(ok, num, 0.0), dr.select(ok, den, 1.0), c, ok)
    if grad:
        out += (dr.select(ok, ga, 0.0),)
    return out


def microfacet_lobe_iso(dr, kind, alpha, g, grad):
    """:func:`microfacet_lobe` for an isotropic roughness on prepared geometry ``g``
    (:func:`_lobe_iso_geometry`): (s, c, {"alpha": ds / d alpha} or None)."""
    a = dr.maximum(alpha, 1e-4)
    num, den, c, ok, *rest = _lobe_iso(dr, kind, a, g, grad)
    s = num / den
    return s, c, ({"alpha": dr.select(alpha >= 1e-4, rest[0], 0.0) * s} if grad else None)


def _oren_nayar_geometry(dr, wi, wo):
    """The parameter-independent part of :func:`_oren_nayar_over_rho`: (u, v) =
    (cmax, max(0, xi xo + yi yo)) / (pi cmax), cmax = max(cos_i, cos_o) (at most 1); 0 below
    the horizon."""
    ci, co = wi.z, wo.z
    active = (ci > 0) & (co > 0)
    cmax = dr.minimum(dr.maximum(ci, co), 1.0)
    cd = dr.maximum(wi.x * wo.x + wi.y * wo.y, 0.0)
    r = dr.select(active, (1.0 / math.pi) / dr.select(active, cmax, 1.0), 0.0)
    return cmax * r, cd * r


def _oren_nayar_over_rho(dr, sigma, wi, wo, grad=False, geometry=None):
    """Qualitative Oren-Nayar (Oren & Nayar 1994, eq. 30) over rho:
    (A + B max(0, cos(phi_i - phi_o)) sin(theta_max) tan(theta_min)) / pi, written as
    (A cmax + B max(0, xi xo + yi yo)) / (pi cmax), cmax = max(cos_i, cos_o); 0 below the
    horizon: A u + B v with (u, v) from :func:`_oren_nayar_geometry` (or ``geometry``, the
    same prepared). Linear in (A, B), so with ``grad`` the same shape at (dA, dB) / d sigma
    = (-0.33 sigma / (s^2 + 0.33)^2, 0.081 sigma / (s^2 + 0.09)^2) is d / d sigma."""
    u, v = geometry if geometry is not None else _oren_nayar_geometry(dr, wi, wo)

    def shape(A, B):
        return A * u + B * v

    s2 = sigma * sigma
    value = shape(1.0 - s2 / (2.0 * (s2 + 0.33)), 0.45 * s2 / (s2 + 0.09))
    if not grad:
        return value
    return value, shape(-0.33 * sigma / ((s2 + 0.33) * (s2 + 0.33)), 0.081 * sigma / ((s2 + 0.09) * (s2 + 0.09)))


def _pairs(t):
    """A table of n values as its n - 1 neighbour pairs (t0, t1, t1, t2, ...), for
    :func:`_lerp_table` (differentiable: a gather)."""
    import drjit as dr

    F = type(t)
    U = dr.uint32_array_t(F)
    j = dr.arange(U, 2 * (dr.width(t) - 1))
    return dr.gather(F, t, (j >> 1) + (j & 1))


def _lerp_table(dr, F, U, pairs, x, n):
    """Linear interpolation of an n-node table on [0, 1] given as :func:`_pairs`, as
    Mitsuba's ``lerp_gather``: one two-element gather per lane (measured 0.68 ms against
    1.06 ms for two gathers and an unsigned index at 1e6 lanes; AVX2 converts to signed
    integers natively, to unsigned only by emulation)."""
    from drjit.llvm.ad import Array2f, Array2f64

    V2 = Array2f if dr.type_v(x) == dr.VarType.Float32 else Array2f64
    x = dr.clip(x, 0.0, 1.0) * (n - 1)
    i = dr.minimum(dr.int32_array_t(F)(x), n - 2)
    w1 = x - F(i)
    v = dr.gather(V2, pairs, dr.reinterpret_array(U, i))
    return v.x * (1.0 - w1) + v.y * w1


# -- resident batches: directions loaded once, evaluated many times ---------------------------
#
# What a fitter and a renderer do: the geometry of a capture is fixed while parameters
# change. :class:`Directions` holds it in Dr.Jit arrays (structure of arrays, like
# Mitsuba's own ``Vector3f``), in float32 (Mitsuba's precision, the fastest) or float64;
# :func:`eval_resident` and :func:`jacobian` then cost one fused kernel each, with no
# conversion from or to numpy unless asked for.


class Directions:
    """A batch of N direction pairs (wi, wo) held in Dr.Jit.

    Parameters
    ----------
    wi, wo : array_like, shape (N, 3)
        Unit directions in the local frame (non-finite rows are degenerate geometry:
        f_r = 0 there).
    dtype : numpy dtype, float32 (default) or float64
    """

    def __init__(self, wi, wo, dtype=np.float32):
        import drjit as dr

        dtype = np.dtype(dtype)
        if dtype == np.float32:
            from drjit.llvm.ad import Array3f as V3
            from drjit.llvm.ad import Float as F
        elif dtype == np.float64:
            from drjit.llvm.ad import Array3f64 as V3
            from drjit.llvm.ad import Float64 as F
        else:
            raise ValueError(f"dtype must be float32 or float64, got {dtype}")
        wi, wo = as_directions(wi, "wi"), as_directions(wo, "wo")
        if wi.shape != wo.shape:
            raise ValueError(f"wi and wo must have the same shape, got {wi.shape} and {wo.shape}")
        if not (np.isfinite(wi).all() and np.isfinite(wo).all()):  # (rows only then: 25x slower)
            ok = np.isfinite(wi).all(axis=1) & np.isfinite(wo).all(axis=1)
            down = np.array([0.0, 0.0, -1.0])
            wi, wo = np.where(ok[:, None], wi, down), np.where(ok[:, None], wo, down)
        self.n = wi.shape[0]
        self.dtype = dtype
        self.F = F
        # in Dr.Jit's own memory, as for channels(): a new alignment records the kernels again
        self.wi = dr.copy(V3(np.ascontiguousarray(wi.T, dtype=dtype)))
        self.wo = dr.copy(V3(np.ascontiguousarray(wo.T, dtype=dtype)))
        dr.make_opaque(self.wi, self.wo)
        self._geometry = {}

    def geometry(self, model):
        """The parameter-independent per-pair quantities ``model``'s kernel reads
        (``model.structure.geometry``), evaluated once per batch and kept (a tuple of
        Dr.Jit arrays of the batch's precision), or None where the model declares none."""
        import drjit as dr

        fn = model.structure.geometry
        if fn is None or model.structure.body is None:
            return None
        key = (model.name, tuple(sorted(model.options.items())))
        if key not in self._geometry:
            with dr.suspend_grad():
                g = fn(model, dr, self.wi, self.wo)
                if g is not None:
                    g = tuple(dr.copy(x) for x in g)
                    dr.eval(*g)
                    dr.make_opaque(*g)
            self._geometry[key] = g
        return self._geometry[key]

    def __len__(self):
        return self.n

    def channels(self, a, name="array"):
        """Per-pair data (N, 3), e.g. measured values or weights, as 3 resident Dr.Jit
        arrays of the batch's precision (for :func:`chi2_grad`)."""
        import drjit as dr

        a = np.asarray(a, dtype=np.float64)
        if a.shape != (self.n, CHANNELS):
            raise ValueError(f"{name} must have shape ({self.n}, {CHANNELS}), got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name} contains NaN or inf")
        # copied into Dr.Jit's own (aligned) memory: an array mapped from numpy's keeps numpy's
        # alignment, which differs from array to array, and every new alignment made the
        # frozen kernels (_freeze._frozen) record again (a roughconductor fit: ~3 recordings
        # of ~1-5 ms each, every fit, with new data or weights)
        out = [dr.copy(self.F(np.ascontiguousarray(a[:, c], dtype=self.dtype))) for c in range(CHANNELS)]
        dr.make_opaque(*out)
        return out


# -- what the models' own kernels share (the kernels live beside their models) ---------------
class JitContext(NamedTuple):
    """What every model kernel gets: the Dr.Jit module, the float and uint array types of the
    batch, the mask of pairs above the horizon (both cosines > 0) and a zero array."""

    dr: object
    F: type
    U: type
    active: object
    zero: object


def channels(P, name):
    """A parameter's value per colour channel (a shared parameter repeated)."""
    return P[name] if isinstance(P[name], list) else [P[name]] * CHANNELS


_channels = channels


def microfacet_lobe(dr, kind, alphas, wi, wo, grad, aniso):
    """The microfacet term D G / (4 cos_i cos_o) = s, the cosine c at the microfacet normal
    and, with ``grad``, ds per roughness parameter (``alpha`` or ``alpha_u``/``alpha_v``, then
    also ``tangent_deg`` for directions the caller turned by :func:`rotate_about_normal`);
    below the roughness floor alpha is clamped: derivative 0."""
    au, av = (dr.maximum(a, 1e-4) for a in alphas)
    lobe = _lobe(dr, kind, au, av, wi, wo, grad)
    num, den, c = lobe[:3]
    s = num / den
    ds = None
    if grad:
        gu, gv = (dr.select(a >= 1e-4, g, 0.0) * s for a, g in zip(alphas, lobe[4:6]))
        ds = {"alpha_u": gu, "alpha_v": gv} if aniso else {"alpha": gu + gv}
        if aniso:   # the directions were turned by -tangent_deg (rotate_about_normal): deg
            ds["tangent_deg"] = lobe[6] * s * (math.pi / 180.0)
    return s, c, ds
