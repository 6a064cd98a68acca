"""The ``tabulated`` model's compiled kernel (values only): its tables built in numpy, interpolated in Dr.Jit.

:func:`inputs` builds the tables once per parameter vector (:func:`gonio.models.catalogue.tabulated.tables`);
:func:`kernel` gathers and interpolates them exactly as the numpy model does, the sheen lobe of
:mod:`gonio.models.catalogue.tabulated_sheen` included. The fit's derivatives come from the model's
own chain rule (:mod:`gonio.models.catalogue.tabulated_jacobian`), not from this kernel.
"""

from __future__ import annotations

import math
import sys

import numpy as np

from gonio.models.base import CHANNELS
from gonio.models.catalogue import tabulated_sheen

__all__ = ["inputs", "kernel"]



def inputs(model, p, P, F, grad, dtables):
    """The kernel's tables, built by the model module's ``tables`` in numpy (float64) and cast to F:
    ``P["_tab"]`` = (ln D - ln Z (C K), G1 (C N_G), Fresnel (C N_FRESNEL), width (N_FRESNEL),
    body factor (N_BODY), the sheen's amplitudes (C N_FRESNEL; zeros without the option))."""
    tab = sys.modules[type(model).__module__]     # the model's own module: no import back into it
    t = tab.tables(p)
    amp = tabulated_sheen.amplitudes(t.sheen) if t.sheen is not None else np.zeros((CHANNELS, tab.N_FRESNEL))
    P["_tab"] = tuple(F(np.ascontiguousarray(a).ravel()) for a in (t.ln_d - t.ln_z[:, None], t.g1, t.fresnel, t.width,
                                                                    t.body, amp))


def kernel(model, k, wi, wo, P, grad):
    """``Tabulated._lobe`` and the body in Dr.Jit: the same fractional indices and linear
    interpolation (``dr.gather``) into the tables of :func:`inputs`; polar angles by
    atan2(|xy|, z) as the numpy model's. Values only (``structure.derivatives = False``: the
    parameters act through tables built in numpy; the fit differences them)."""
    if grad:
        raise NotImplementedError("tabulated's kernel gives values only")
    tab = sys.modules[type(model).__module__]
    N_FRESNEL, N_KNOTS, N_G, N_BODY, BODY_MAX = tab.N_FRESNEL, tab.N_KNOTS, tab.N_G, tab.N_BODY, tab.BODY_MAX
    dr, U, active = k.dr, k.U, k.active
    F = k.F
    ln_d, g1, fresnel, width, body_table, sheen_amp = P["_tab"]

    def lerp(table, n, s, c):  # s: float64 fractional indices (a float32 one loses 128 * 6e-8 near the end)
        i = dr.clip(U(dr.floor(s)), 0, n - 2)
        t = F(dr.clip(s - type(s)(i), 0.0, 1.0))
        return dr.gather(F, table, c * n + i) * (1.0 - t) + dr.gather(F, table, c * n + i + 1) * t

    def polar(x, y, z):
        return dr.atan2(dr.sqrt(x * x + y * y), z)

    half_pi = 0.5 * math.pi
    ci, co = wi.z, wo.z
    # the table indices from float64 geometry whatever F is (as the Mitsuba plugin: float32's
    # atan2 is off by a few ulp, which the steep ln D table turns into 3e-4 relative; measured)
    F64 = dr.float64_array_t(F)
    vi = [F64(v) for v in (wi.x, wi.y, wi.z)]
    vo = [F64(v) for v in (wo.x, wo.y, wo.z)]
    h = [a + b for a, b in zip(vi, vo)]
    h2 = h[0] * h[0] + h[1] * h[1] + h[2] * h[2]
    valid = h2 > 1e-300
    inv = dr.rsqrt(dr.select(valid, h2, 1.0))
    cd = 0.5 * sum((a + b) * c for a, b, c in zip(vi, vo, h)) * inv
    ok = active & valid & (h[2] > 0) & (cd > 0)
    s_f = (N_FRESNEL - 1) * dr.clip(1.0 - cd, 0.0, 1.0)
    w = lerp(width, N_FRESNEL, s_f, 0)
    s_h = (N_KNOTS - 1) * dr.sqrt(dr.clip(polar(*h) / F64(w), 0.0, half_pi) / half_pi)
    s_i = (N_G - 1) * (1.0 - dr.sqrt(dr.clip(1.0 - polar(*vi) / half_pi, 0.0, 1.0)))
    s_o = (N_G - 1) * (1.0 - dr.sqrt(dr.clip(1.0 - polar(*vo) / half_pi, 0.0, 1.0)))
    den = 4.0 * dr.select(ok, ci * co, 1.0) * w * w
    body = dr.select(active, 1.0 / math.pi + k.zero, 0.0)
    rho = P["diffuse_reflectance"]
    table = model.options["body"] == "table"
    if table:       # g_c(theta_i) g_c(theta_o), :func:`body_index`
        b_i, b_o = ((N_BODY - 1) * dr.minimum(dr.acos(dr.clip(v[2], -1.0, 1.0)) / BODY_MAX, 1.0) for v in (vi, vo))
    sheen = model.options["sheen"] == "ggx"
    if sheen:       # tabulated_sheen.shape: A_c D / ((ci + q_i)(co + q_o)), GGX of sheen_alpha
        a2 = P["sheen_alpha"] * P["sheen_alpha"]
        # u = a^2 cos^2 + sin^2 of theta_h in float64, sin^2 from |h_xy|^2 (1 - cos^2 in
        # float32 loses the lobe's peak: 6e-5 relative at alpha 0.05, tests/models/test_tabulated.py)
        r2 = dr.select(valid, h2, 1.0)
        u = F(dr.select(ok, F64(a2) * dr.minimum(h[2] * h[2] / r2, 1.0) + (h[0] * h[0] + h[1] * h[1]) / r2, 1.0))
        ci_, co_ = dr.select(ok, ci, 1.0), dr.select(ok, co, 1.0)
        qi = dr.sqrt(ci_ * ci_ + a2 * (1.0 - ci_ * ci_))
        qo = dr.sqrt(co_ * co_ + a2 * (1.0 - co_ * co_))
        unit = a2 / (math.pi * u * u) / ((ci_ + qi) * (co_ + qo))
    f = []
    for c in range(CHANNELS):
        if table:
            body_c = dr.select(active & (ci > 0) & (co > 0), body * lerp(body_table, N_BODY, b_i, 0)
                               * lerp(body_table, N_BODY, b_o, 0), 0.0)
        else:
            body_c = body
        D = dr.exp(lerp(ln_d, N_KNOTS, s_h, c))
        G = lerp(g1, N_G, s_i, c) * lerp(g1, N_G, s_o, c)
        Fc = lerp(fresnel, N_FRESNEL, s_f, c)
        lobe = Fc * D * G / den
        if sheen:
            lobe = lobe + lerp(sheen_amp, N_FRESNEL, s_f, c) * unit
        f.append(rho[c] * body_c + dr.select(ok, lobe, 0.0))
    return f, {}
