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
"""

from __future__ import annotations

import math
import subprocess
import sys
from functools import lru_cache

import numpy as np

from ._base import CHANNELS, eval_inputs
from .geometry import as_directions
from ._rough_tables import _interp

__all__ = ["available", "eval", "value_and_grad", "Directions", "Bound", "eval_resident", "jacobian", "chi2_grad"]

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
    A = _safe_sqrt(dr, t1 * t1 + 4.0 * e2 * k2)  # a^2 + b^2
    a = _safe_sqrt(dr, 0.5 * (A + t1))
    T1 = A + c2
    T2 = 2.0 * c * a
    T3 = A * c2 + s2 * s2
    T4 = T2 * s2
    if not grad:
        return dr.clip((T1 - T2) * T3 / ((T1 + T2) * (T3 + T4)), 0.0, 1.0)
    P, Q = T1 + T2, T3 + T4
    r = 1.0 / (P * Q)
    F = dr.clip((T1 - T2) * T3 * r, 0.0, 1.0)
    rA = 1.0 / A
    # da without cancellation. For t1 >= 0, a^2 = (A + t1) / 2 >= t1 and da = (dA + dt1) / (4a).
    # For t1 < 0 (k -> 0 with eta below sin(theta)) A + t1 cancels; there
    # a = sqrt(2) eta k / sqrt(R), R = A - t1 >= 2 |t1| (since (A + t1)(A - t1) = 4 eta^2 k^2),
    # whose derivative stays exact down to k = 0 (one-sided there: F ~ 1 - C k)
    neg = t1 < 0
    rR = dr.rsqrt(dr.select(neg, A - t1, 1.0))
    ra4 = 1.0 / (4.0 * dr.select(neg, 1.0, a))
    out = [F]
    for dA_num, dt1, d_ek, x in ((2.0 * eta * (e2 + k2 - s2), 2.0 * eta, k, eta),
                                 (2.0 * k * (e2 + k2 + s2), -2.0 * k, eta, k)):
        dA = dA_num * rA
        da = dr.select(neg, math.sqrt(2.0) * rR * (d_ek - 0.5 * eta * k * (dA - dt1) * rR * rR), (dA + dt1) * ra4)
        dT2 = 2.0 * c * da
        dT3, dT4 = c2 * dA, s2 * dT2
        out.append((2.0 * (dA * T2 - dT2 * T1) * T3 * Q + (T1 - T2) * (dT3 * T4 - dT4 * T3) * P) * r * r)
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


def _lobe(dr, kind, au, av, wi, wo, grad=False):
    """Mitsuba's microfacet reflection term D(m) G(wi, wo, m) / (4 cos_i cos_o) as a
    fraction, for the half vector m of (wi, wo) and separable Smith G.

    Returns ``(num, den, c, ok)``: the term is num / den where ``ok`` (den is 1 elsewhere),
    c = wi . m (the Fresnel cosine). For GGX the cosines cancel exactly:
    G1(w) / (2 cos) = 1 / (cos + sqrt(cos^2 + (au x)^2 + (av y)^2)). D is 0 where
    D cos(theta_m) <= 1e-20, Mitsuba's cut.

    With ``grad``, also ``(gu, gv)``: d ln(term) / d au and d / d av (for an isotropic
    alpha, d / d alpha = gu + gv), 0 where the term is 0. GGX: ln den = ln(pi au av) +
    2 ln t + ln(ci + Si) + ln(co + So) with t = (mx/au)^2 + (my/av)^2 + mz^2; Beckmann:
    ln(term) = -e + ln(n_i/d_i) + ln(n_o/d_o) - ln(4 pi au av mz^4) with e = ((mx/au)^2 +
    (my/av)^2) / mz^2 and d s / d au = (au x)^2 / (au s) for each direction."""
    ci, co = wi.z, wo.z
    h = wi + wo
    h2 = dr.squared_norm(h)
    ok = (ci > 0) & (co > 0) & (h2 > _floor(h2))
    inv = dr.rsqrt(dr.select(ok, h2, 1.0))
    mz = h.z * inv
    c = 0.5 * (dr.dot(wi, h) + dr.dot(wo, h)) * inv
    iau, iav = 1.0 / au, 1.0 / av
    qx, qy = (h.x * inv * iau) ** 2, (h.y * inv * iav) ** 2
    px2 = qx + qy
    paa = math.pi * au * av
    ax_i, ay_i, ax_o, ay_o = (au * wi.x) ** 2, (av * wi.y) ** 2, (au * wo.x) ** 2, (av * wo.y) ** 2
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
            def k(n, d, s, z, big):
                return dr.select(big, 0.0, (3.535 * d - (2.0 * s + 2.276 * z) * n) / dr.select(big, 1.0, s * n * d))

            k_i, k_o = k(ni, di, s_i, ci, big_i), k(no, do, s_o, co, big_o)
            gu = (2.0 * qx * rmz2 - 1.0 + ax_i * k_i + ax_o * k_o) * iau
            gv = (2.0 * qy * rmz2 - 1.0 + ay_i * k_i + ay_o * k_o) * iav
    ok &= den > 0
    out = (dr.select(ok, num, 0.0), dr.select(ok, den, 1.0), c, ok)
    if grad:
        out += (dr.select(ok, gu, 0.0), dr.select(ok, gv, 0.0))
    return out


def _oren_nayar_over_rho(dr, sigma, wi, wo, grad=False):
    """Qualitative Oren-Nayar (Oren & Nayar 1994, eq. 30) over rho:
    (A + B max(0, cos(phi_i - phi_o)) sin(theta_max) tan(theta_min)) / pi, written as
    (A cmax + B max(0, xi xo + yi yo)) / (pi cmax), cmax = max(cos_i, cos_o); 0 below the
    horizon. Linear in (A, B), so with ``grad`` the same shape at (dA, dB) / d sigma
    = (-0.33 sigma / (s^2 + 0.33)^2, 0.081 sigma / (s^2 + 0.09)^2) is d / d sigma."""
    ci, co = wi.z, wo.z
    active = (ci > 0) & (co > 0)
    cmax = dr.minimum(dr.maximum(ci, co), 1.0)
    cd = dr.maximum(wi.x * wo.x + wi.y * wo.y, 0.0)
    r = dr.select(active, (1.0 / math.pi) / dr.select(active, cmax, 1.0), 0.0)

    def shape(A, B):
        return (A * cmax + B * cd) * r

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
    else:
        t, r = _tables(kind, dr.opaque(F64, max(alpha, 1e-4)), dr.opaque(F64, eta))
    dr.eval(t, r)
    return t, r


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
        ok = np.isfinite(wi).all(axis=1) & np.isfinite(wo).all(axis=1)
        down = np.array([0.0, 0.0, -1.0])
        self.n = wi.shape[0]
        self.dtype = dtype
        self.F = F
        self.wi = V3(np.ascontiguousarray(np.where(ok[:, None], wi, down).T, dtype=dtype))
        self.wo = V3(np.ascontiguousarray(np.where(ok[:, None], wo, down).T, dtype=dtype))
        dr.make_opaque(self.wi, self.wo)

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
        out = [self.F(np.ascontiguousarray(a[:, c], dtype=self.dtype)) for c in range(CHANNELS)]
        dr.make_opaque(*out)
        return out


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
        vi = dr.gather(V3, prepared.wi, i)
        vo = dr.gather(V3, prepared.wo, i)
        ci, co = vi.z, vo.z
        active = (ci > 0) & (co > 0)
        if model.name == "diffuse":
            base = F(0.0) * ci
            basis = dr.select(active, F(1.0 / math.pi), F(0.0))
        elif model.name == "orennayar":
            base = F(0.0) * ci
            basis = _oren_nayar_over_rho(dr, dr.gather(F, cols[0], k), vi, vo)
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
            num, den, c, ok = _lobe(dr, kind, al, al, vi, vo)
            Fr, _ = _fresnel_outside(dr, dr.clip(c, 0.0, 1.0), eta)
            base = Fr * num / den

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
    if not model.structure.affine.tables:
        return np.ones(th.shape[0])
    kind = model.options["distribution"]
    return np.array([1.0 - float(np.asarray(_cached_tables(kind, float(a), float(e))[1])[0]) for a, e in th])
