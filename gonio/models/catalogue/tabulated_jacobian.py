"""The ``tabulated`` model's exact Jacobian by the chain rule through its tables (issue 35).

Every pair interpolates a few table entries: two G1 entries per direction, two ln D knots, two
Fresnel and width knots. So d f_c / d ln D_{c,k} = S_c T_c, with S_c the sparse (pairs x
entries) matrix of d f / d entry (7 non-zeros a pair: the G1 entries at theta_i and theta_o,
the two ln D knots at theta_h / w, and ln Z) and T_c the small dense matrix d entry / d ln D_k
(:func:`gonio.models.catalogue.tabulated.table_derivatives`), times d ln D_k / d parameter, both
once per parameter vector. The same derivatives as
:meth:`gonio.models.catalogue.tabulated.Tabulated.jacobian_reference` (the dense numpy
formulation, kept as the oracle), to rounding, without its (pairs, channels, knots) temporaries.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import scipy.sparse

from gonio.core.geometry import half_vector
from gonio.models.base import CHANNELS

__all__ = ["jacobian"]


def _ndf_map(tab, p, c):
    """d ln D_{c,k} / d parameter (K, P_c) and the parameter names of channel c: the green
    knots ``ndf_k`` (ln of the parameter) and, for red and blue, their tilts (hat functions
    of the knot index, :data:`gonio.models.catalogue.tabulated.TILT_BASIS`)."""
    names = [f"ndf_{k}" for k in range(tab.FIRST_FREE, tab.N_KNOTS)]
    cols = [np.eye(tab.N_KNOTS)[k] / p[f"ndf_{k}"] for k in range(tab.FIRST_FREE, tab.N_KNOTS)]
    tilt = {0: "r", 2: "b"}.get(c)
    if tilt is not None:
        for kk, basis in zip(tab.TILT_KNOTS, tab.TILT_BASIS):
            names.append(f"ndf_tilt_{tilt}_{kk}")
            cols.append(basis / p[f"ndf_tilt_{tilt}_{kk}"])
    return np.stack(cols, axis=1), names


def jacobian(model, wi, wo, params):
    """(f_r (N, C), {parameter: d f_r / d parameter (N, C)}) of a ``tabulated`` model, in the
    layout of :meth:`~gonio.models.catalogue.tabulated.Tabulated.jacobian_reference` (a
    per-channel parameter's column c is d f_c / d p_c; a tilt reaches its own channel only).

    Notes
    -----
    f_c = rho_c body + F_c D_c G1_c(wi) G1_c(wo) / (4 cos_i cos_o w^2), D_c = exp(ln D_c(s_h) -
    ln Z_c). With a = F D / (4 cos_i cos_o w^2): d f_c / d G1_c[n] = a G1_c(wo) (its weight at
    theta_i) + a G1_c(wi) (at theta_o), d f_c / d ln D_c[k] = f_lobe (its weight at s_h),
    d f_c / d ln Z_c = -f_lobe; G1 and ln Z depend on the knots through the table derivatives
    (Heitz 2014, eq. 43; Walter et al. 2007, eq. 4).
    """
    import sys

    from gonio.models.inputs import eval_inputs

    tab = sys.modules[type(model).__module__]     # the model's own module: no import back into it
    wi, wo, p = eval_inputs(model, wi, wo, params)
    table = "body_1" in p
    g = _pairs(tab, wi, wo, tuple(model.structure.sides), table)
    t = tab.tables(p)
    n = g.ci.size
    ci, co, ok, s_f, th = g.ci, g.co, g.ok, g.s_f, g.th
    names = [q.name for q in model.parameters]
    out = np.zeros((len(names), n, CHANNELS))
    J = {name: out[j] for j, name in enumerate(names)}
    with np.errstate(all="ignore"):
        w = tab._interp(t.width, s_f)[:, 0]
        u = np.clip(th / w, 0.0, 0.5 * math.pi)
        s_h = tab.knot_index(th / w)
        ih, th_t = tab._lerp_parts(tab.N_KNOTS, s_h)
        L = tab._interp(t.ln_d - t.ln_z[:, None], s_h)
        slope = (t.ln_d[:, ih + 1] - t.ln_d[:, ih]).T
        ds_dw = np.where((u > 0.0) & (th / w < 0.5 * math.pi), -0.5 * s_h / w, 0.0)
        Gi, Go = tab._interp(t.g1, g.gi), tab._interp(t.g1, g.go)
        Fr = tab._interp(t.fresnel, s_f)
        den = np.where(ok, 4.0 * ci * co * w * w, 1.0)[:, None]
        D_over = np.where(ok[:, None], np.exp(L) / den, 0.0)
        DG = D_over * Gi * Go
        lobe = Fr * D_over * Gi * Go                     # jacobian_reference's order: f bit for bit
        body = g.body
        if table:
            gi_b, go_b = tab._interp(t.body, g.s_bi), tab._interp(t.body, g.s_bo)
            shape = body * (gi_b * go_b)
        else:
            shape = body
        f = t.rho[None, :] * body * (gi_b * go_b if table else 1.0) + lobe    # as jacobian_reference, bit for bit
        J["diffuse_reflectance"][:] = shape
        if table:
            rb = t.rho[None, :] * body
            for j, (hi, ho) in enumerate(g.body_hats, start=1):
                J[f"body_{j}"][:] = rb * (hi * go_b + gi_b * ho)
        lw = lobe * (slope * ds_dw[:, None] - 2.0 / w[:, None])
        for j, hat in enumerate(g.fresnel_hats):
            np.multiply(DG, hat, out=J[f"fresnel_{j}"])
            if j >= 1:
                np.multiply(lw, hat, out=J[f"width_{j}"])
        _ndf_columns(tab, t, p, out, names, (g.g_parts, ih, th_t), Fr * D_over, Gi, Go, lobe)
        if t.sheen is not None:     # option sheen="ggx": an added lobe (tabulated_sheen)
            from gonio.models.catalogue import tabulated_sheen

            S, JS = tabulated_sheen.columns(p, ci, co, g.cos_h, ok, g.fresnel_hats, tab._interp, s_f)
            f = f + S
            for name, col in JS.items():
                J[name][:] = col
    return f, J


class _Pairs(NamedTuple):
    ci: np.ndarray
    co: np.ndarray
    ok: np.ndarray
    s_f: np.ndarray
    th: np.ndarray
    cos_h: np.ndarray
    gi: np.ndarray
    go: np.ndarray
    body: np.ndarray
    s_bi: np.ndarray
    s_bo: np.ndarray
    body_hats: tuple
    fresnel_hats: tuple
    g_parts: tuple


def _pairs(tab, wi, wo, sides, table) -> _Pairs:
    """What the Jacobian needs of the directions alone (the half vector's angles, the lookups'
    indices and hat weights, the body's shape), remembered per direction set as flakepaint's
    geometry is (:mod:`gonio.models.catalogue.flake_memo`: compared value for value, read-only
    arrays): a fit asks for the Jacobian at the same directions every iteration."""
    from gonio.models.catalogue.flake_memo import geometry, memo

    geom = geometry(wi, wo)
    return memo(geom, ("tabulated_jacobian", sides, table), lambda: _pair_parts(tab, geom.wi, geom.wo, sides, table))


def _pair_parts(tab, wi, wo, sides, table) -> _Pairs:
    from gonio.core.sides import sides_mask

    fin = np.isfinite(wi).all(axis=1) & np.isfinite(wo).all(axis=1)
    if not fin.all():    # 0 at a non-finite pair, as eval; (0, 0, 1) keeps its lookups in range
        wi, wo = (np.where(fin[:, None], v, (0.0, 0.0, 1.0)) for v in (wi, wo))
    ci, co = wi[:, 2], wo[:, 2]
    with np.errstate(all="ignore"):
        wh, valid = half_vector(wi, wo)
        cd = 0.5 * (np.einsum("ij,ij->i", wi, wh) + np.einsum("ij,ij->i", wo, wh))
        pair = fin & sides_mask(sides, ci, co)
        ok = pair & valid & (ci > 0.0) & (co > 0.0) & (wh[:, 2] > 0.0) & (cd > 0.0)
        s_f = (tab.N_FRESNEL - 1) * np.clip(1.0 - cd, 0.0, 1.0)
        th = tab._polar(wh)
        gi, go = tab.g_index(tab._polar(wi)), tab.g_index(tab._polar(wo))
        body = np.where(pair, 1.0 / math.pi, 0.0)[:, None]
        s_bi = s_bo = np.zeros(0)
        body_hats = ()
        if table:
            body = body * (ci > 0.0)[:, None] * (co > 0.0)[:, None]
            s_bi, s_bo = tab.body_index(ci), tab.body_index(co)
            body_hats = tuple(tuple(tab._interp(np.eye(tab.N_BODY)[j:j + 1], s)[:, 0:1] for s in (s_bi, s_bo))
                              for j in range(1, tab.N_BODY))
        i_f, t_f = tab._lerp_parts(tab.N_FRESNEL, s_f)
        hats = tuple(np.where(i_f == j, 1.0 - t_f, np.where(i_f + 1 == j, t_f, 0.0))[:, None]
                     for j in range(tab.N_FRESNEL))
        g_parts = tab._lerp_parts(tab.N_G, gi) + tab._lerp_parts(tab.N_G, go)
    return _Pairs(np.array(ci), np.array(co), ok, s_f, th, wh[:, 2], gi, go, body, s_bi, s_bo, body_hats, hats, g_parts)


def _ndf_columns(tab, t, p, out, names, where, FD, Gi, Go, lobe):
    """Fill the NDF knots' and tilts' columns of ``out`` (P, N, C): per channel, the sparse
    d f / d entry (N, N_G + K + 1) times the dense d entry / d parameter."""
    (i_i, t_i, i_o, t_o), ih, th_t = where
    n = i_i.size
    dlnz, dg1 = tab.table_derivatives(t.ln_d)
    k0 = tab.N_G
    idx = np.stack([i_i, i_i + 1, i_o, i_o + 1, k0 + ih, k0 + ih + 1, np.full(n, k0 + tab.N_KNOTS)], axis=1)
    indptr = np.arange(0, 7 * n + 1, 7)
    row = {name: j for j, name in enumerate(names)}
    for c in range(CHANNELS):
        a, b, lc = FD[:, c] * Go[:, c], FD[:, c] * Gi[:, c], lobe[:, c]
        data = np.stack([a * (1.0 - t_i), a * t_i, b * (1.0 - t_o), b * t_o, lc * (1.0 - th_t), lc * th_t, -lc], axis=1)
        S = scipy.sparse.csr_matrix((data.ravel(), idx.ravel(), indptr), shape=(n, k0 + tab.N_KNOTS + 1))
        M, cols = _ndf_map(tab, p, c)
        T = np.vstack([dg1[c], np.eye(tab.N_KNOTS), dlnz[c][None, :]])      # d entry / d ln D_k
        X = S @ (T @ M)                                                     # (N, P_c)
        out[[row[name] for name in cols], :, c] = X.T
