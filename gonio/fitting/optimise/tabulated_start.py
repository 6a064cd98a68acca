"""A data-driven starting point for the ``tabulated`` model, and its fit through :func:`fit`.

A tabulated NDF has 45 knot values, and a box-uniform or analytic start leaves the local
optimiser hundreds of iterations from the data's peak. :func:`data_start` reads the
distribution off the measured samples themselves, as Dupuy et al. (2015) do, alternating it
with the shadowing it implies (their power iteration: D from the measured values given G, G
from D), together with the Lambertian body, the Fresnel factor and the lobe's width factors.
The result becomes the model's declared defaults
(:class:`~gonio.models.catalogue.tabulated.Tabulated` ``start=``), so :func:`fit`'s
default-first start and its global stage begin there; :func:`fit_tabulated` runs the whole thing.

Reference: Dupuy, J., Heitz, E., Iehl, J.-C., Poulin, P., Ostromoukhov, V. (2015).
Extracting microfacet-based BRDF parameters from arbitrary materials with power iterations.
Computer Graphics Forum 34(4), 21-30.
"""

# data_start, step by step:
# 1. the Lambertian body rho_c: pi times a low quantile (BODY_QUANTILE) of f_c far from the
#    peak (theta_h > BODY_THETA_H deg);
# 2. the lobe's values y = (f - rho / pi) 4 cos_i cos_o = F D G1 G1;
# 3. repeated ROUNDS times: D at each knot from y / (F G1(wi) G1(wo)), a geometric mean with
#    the linear-interpolation (hat) weights of the knot grid (green's becomes the shared
#    table, red's and blue's differences give the colour tilts by least squares on the tilt's
#    hat functions); G1 again from the new D (gonio.models.catalogue.tabulated.g1_table); then
#    F at each Fresnel knot from y / (D G1 G1), the same way in x = 1 - cos(theta_d); then the
#    lobe's width factor at each Fresnel knot by a coordinate search (_widths), the knots' D
#    estimated at theta_h / w thereafter.
# The peer of `gonio bench fit --real` that gets this model starts from the same defaults.

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

import gonio.models as gm
from gonio.core.channels import CHANNELS
from gonio.models import tabulated as tab
from gonio.models.catalogue import tabulated_sheen
from gonio.core.geometry import half_vector

__all__ = ["data_start", "fit_tabulated", "unseen", "ROUNDS", "WEAK"]

ROUNDS = 4
BODY_THETA_H = 25.0
BODY_QUANTILE = 0.1
#: the colour tilts are estimated on the knots where green's ln D(theta_k) / D(0) is above this
TILT_FLOOR = -10.0
#: a shared parameter whose Jacobian column is below this fraction of the median is held
#: at its start (:func:`unseen`)
WEAK = 0.05
#: fit rounds at most (:func:`fit_tabulated`), and the relative gain below which it stops
ROUNDS_FIT = 4
RESTART_GAIN = 1e-3


def _hat(s, n):
    """Hat (linear-interpolation) weights of fractional indices s (N,) on n knots: (N, n)."""
    i = np.clip(np.floor(s), 0, n - 2).astype(np.int64)
    t = np.clip(s - i, 0.0, 1.0)
    W = np.zeros((s.size, n))
    W[np.arange(s.size), i] = 1.0 - t
    W[np.arange(s.size), i + 1] += t
    return W


def _knot_log_means(W, log_v, ok):
    """Per channel, the hat-weighted mean of log_v (N, C) at each knot (C, n), NaN where a
    knot has (almost) no weight."""
    out = np.full((log_v.shape[1], W.shape[1]), np.nan)
    for c in range(log_v.shape[1]):
        w = W * ok[:, c:c + 1]
        tot = w.sum(axis=0)
        val = (w * np.where(ok[:, c:c + 1], log_v[:, c:c + 1], 0.0)).sum(axis=0)
        out[c] = np.where(tot > 0.5, val / np.maximum(tot, 1e-300), np.nan)
    return out


def _fill(row, fallback_slope=-2.0):
    """Knots without data: interpolated between the nearest with data, held (or, past the
    last, falling by ``fallback_slope`` per knot) outside."""
    k = np.arange(row.size)
    have = np.isfinite(row)
    if not have.any():
        return np.zeros_like(row)
    out = np.interp(k, k[have], row[have])
    last = k[have].max()
    out[k > last] = row[last] + fallback_slope * (k[k > last] - last)
    return out


#: candidate width factors of the start's coordinate search (:func:`_widths`)
WIDTH_GRID = np.exp(np.linspace(-1.0, 1.0, 21))


def _widths(width, ln_d, ln_z, theta_h, s_f, W_f, log_y_over_g, ok):
    """Green's lobe width factor at each Fresnel knot j >= 1, one coordinate at a time over
    :data:`WIDTH_GRID`: the value whose D_w(theta_h) best explains ln(y / G) up to a
    constant (the Fresnel factor), samples weighted by the knot's hat function."""
    width = width.copy()
    for j in range(1, width.shape[1]):
        wt = W_f[:, j] * ok
        if wt.sum() < 5:
            continue
        best, best_v = np.inf, width[0, j]
        for v in WIDTH_GRID:
            width[0, j] = v
            w = tab._interp(width, s_f)[:, 0]
            r = log_y_over_g - (tab._interp(ln_d[None, :], tab.knot_index(theta_h / w))[:, 0] - ln_z - 2.0 * np.log(w))
            r = np.where(wt > 0, r, 0.0)
            mean = np.sum(wt * r) / wt.sum()
            cost = np.sum(wt * (r - mean) ** 2)
            if cost < best:
                best, best_v = cost, v
        width[0, j] = best_v
    return width


def data_start(meas, model=None) -> dict:
    """The starting parameters (validated dict) of ``tabulated`` for ``meas`` (module notes)."""
    model = model or gm.get("tabulated")
    wi, wo = meas.wi, meas.wo
    f = np.where(meas.use, meas.brdf, np.nan)
    wh, valid = half_vector(wi, wo)
    ci, co = wi[:, 2], wo[:, 2]
    theta_h = np.arctan2(np.hypot(wh[:, 0], wh[:, 1]), wh[:, 2])
    x = np.clip(1.0 - 0.5 * (np.einsum("ij,ij->i", wi, wh) + np.einsum("ij,ij->i", wo, wh)), 0.0, 1.0)
    good = valid & (ci > 1e-3) & (co > 1e-3)
    far = good & (theta_h > math.radians(BODY_THETA_H))
    rho = np.zeros(CHANNELS)
    for c in range(3):
        v = f[far, c]
        v = v[np.isfinite(v)]
        rho[c] = np.clip(math.pi * np.quantile(v, BODY_QUANTILE), 0.0, 1.0) if v.size else 0.0
    y = (f - rho / math.pi) * (4.0 * ci * co)[:, None]
    s_h = tab.knot_index(theta_h)
    s_f = (tab.N_FRESNEL - 1) * x
    W_d, W_f = _hat(s_h, tab.N_KNOTS), _hat(s_f, tab.N_FRESNEL)
    ok = good[:, None] & np.isfinite(y) & (y > 0.0)
    logy = np.log(np.where(ok, y, 1.0))
    p = model.defaults()
    ln_d = np.zeros((CHANNELS, tab.N_KNOTS))
    fres = np.stack([p[f"fresnel_{j}"] for j in range(tab.N_FRESNEL)], axis=1)
    g1 = tab.g1_table(ln_d)[1]
    width = np.ones((1, tab.N_FRESNEL))
    G = tab._interp(g1, tab.g_index(np.arccos(np.clip(ci, -1, 1)))) * tab._interp(g1, tab.g_index(np.arccos(np.clip(co, -1, 1))))
    for _ in range(ROUNDS):
        F = tab._interp(fres, s_f)
        w = tab._interp(width, s_f)  # (N, 1)
        W_d = _hat(tab.knot_index(theta_h / w[:, 0]), tab.N_KNOTS)
        okk = ok & (G > 1e-6) & (F > 1e-6)
        est = _knot_log_means(W_d, logy - np.log(np.where(okk, G * F, 1.0)) + 2.0 * np.log(w), okk)  # ln D_norm at knots
        seen = np.isfinite(est)
        est = np.stack([_fill(r) for r in est])
        rel = est - est[:, 1:2]
        green = np.clip(rel[1], *tab.LN_D_BOUNDS)
        green[:tab.FIRST_FREE] = 0.0
        B = np.stack(tab.TILT_BASIS, axis=1)  # (K, tilt knots)
        tilt = np.zeros((CHANNELS, B.shape[1]))
        for c in (0, 2):  # least squares of ln D_c - ln D_g on the tilt's hat functions, where both were seen
            use = seen[c] & seen[1] & (green > TILT_FLOOR)
            if use.sum() >= B.shape[1]:
                sol = np.linalg.lstsq(B[use], (rel[c] - green)[use], rcond=None)[0]
                tilt[c] = np.clip(sol, -tab.TILT, tab.TILT)
        ln_d = green[None, :] + tilt @ B.T
        ln_z, g1 = tab.g1_table(ln_d)
        G = tab._interp(g1, tab.g_index(np.arccos(np.clip(ci, -1, 1)))) * tab._interp(g1, tab.g_index(np.arccos(np.clip(co, -1, 1))))
        D = np.exp(tab._interp(ln_d, tab.knot_index(theta_h / w[:, 0])) - ln_z[None, :]) / (w * w)
        okk = ok & (G * D > 1e-8)
        fe = _knot_log_means(W_f, logy - np.log(np.where(okk, G * D, 1.0)), okk)
        fres = np.clip(np.exp(np.stack([_fill(r, 0.0) for r in fe])), 0.0, 1.0)
        width = _widths(width, ln_d[1], ln_z[1], theta_h, s_f, W_f, logy[:, 1] - np.log(np.maximum(G[:, 1], 1e-300)),
                        ok[:, 1] & (G[:, 1] > 1e-6))
    out = {"diffuse_reflectance": rho}
    for c, name in ((0, "r"), (2, "b")):
        for j, k in enumerate(tab.TILT_KNOTS):
            out[f"ndf_tilt_{name}_{k}"] = math.exp(tilt[c, j])
    for k in range(tab.FIRST_FREE, tab.N_KNOTS):
        out[f"ndf_{k}"] = math.exp(ln_d[1, k])
    for j in range(tab.N_FRESNEL):
        out[f"fresnel_{j}"] = fres[:, j]
    for j in range(1, tab.N_FRESNEL):
        out[f"width_{j}"] = float(np.clip(width[0, j], *tab.WIDTH))
    return model.validate(out)


def fit_tabulated(meas, *, rng, loss="log", rounds=ROUNDS_FIT, body="lambert", sheen="none", start=None, **kwargs):
    """``tabulated`` (options ``body``, ``sheen``) fitted to ``meas`` by :func:`gonio.fitting.fit`, starting from
    ``start`` (a parameter dict; default :func:`data_start`; parameters it lacks start at their
    defaults: ``body="table"`` from the plain fit's parameters starts at g = 1, ``sheen="ggx"``
    with no sheen, that fit itself) (the model instance carries it as its defaults), parameters the data
    do not see held there (:func:`unseen`). While gonio's Levenberg-Marquardt stops at its
    iteration cap (60) still improving, the fit is run again from its own result, the
    global stage skipped (``n_starts=0``), at most ``rounds`` times in all, until the
    objective improves by less than :data:`RESTART_GAIN`. Returns the last
    :class:`FitResult` with ``time_s`` the total (the start included) up to the covariance,
    as :func:`gonio.fitting.fit` counts it; its ``model`` is the instance carrying the last
    start. The rounds skip the sandwich covariance of the log and cosine losses
    (``covariance=False``), which is computed once, for the result returned (each round's
    cost 25 s at 42 parameters on vch, two rounds' covariances were 55 % of the fit)."""
    from gonio.fitting.optimise.mle import ROBUST_COV, fit
    from gonio.fitting.likelihood.problem import Problem
    from gonio.fitting.optimise.result import robust_covariance

    t0, c0 = time.perf_counter(), time.process_time()
    covariance = kwargs.pop("covariance", True)
    kwargs["covariance"] = False
    model = tab.Tabulated(start=data_start(meas, tab.Tabulated(body=body)) if start is None else start, body=body,
                          sheen=sheen)
    fixed = dict(kwargs.pop("fixed", None) or {})
    fixed.update(unseen(meas, model, loss, exclude=fixed))
    res = fit(meas, model, loss=loss, rng=rng, fixed=fixed or None, **kwargs)
    kwargs["n_starts"] = 0
    for _ in range(rounds - 1):
        if res.converged:
            break
        model = tab.Tabulated(start=res.params, body=body, sheen=sheen)
        nxt = fit(meas, model, loss=loss, rng=rng, fixed=fixed or None, **kwargs)
        gain = res.objective - nxt.objective
        if gain >= 0:
            res = nxt
        if gain < RESTART_GAIN * abs(res.objective):
            break
    res = dataclasses.replace(res, time_s=time.perf_counter() - t0, cpu_s=time.process_time() - c0)
    if covariance and loss in ROBUST_COV:
        res = robust_covariance(res, meas, Problem(meas, res.model, res.space, loss, use_fast=kwargs.get("use_fast")))
    return res


def unseen(meas, model, loss="log", weak=WEAK, exclude=()):
    """The shared parameters the data barely see at the start, {name: start value}: their
    Jacobian column (unit box, the fit's own residuals; the model's exact derivatives where
    the fit has them, else forward differences) is below
    ``weak`` times the median column. Measured on vch_golden_yellow: ndf_15 (theta_h = 90 deg,
    beyond the data's 80) at 0.04 of a median of ~3; left free, its Gauss-Newton step of
    ~140 box widths held gonio's Levenberg-Marquardt at damping 1e3-1e5 (60 iterations:
    log loss 36.9 -> 36.4, where scipy's trust region reached 24.5)."""
    from gonio.fitting.likelihood import loss as _loss
    from gonio.fitting.likelihood.problem import Problem
    from gonio.fitting.optimise.lm import forward_jacobian
    from gonio.fitting.optimise.space import ParameterSpace

    space = ParameterSpace(model, meas.n_channels, dict(exclude) or None, meas.channels)
    x0 = space.default()
    exact = Problem(meas, model, space, loss, linear=[]).residual_jacobian_x(x0, range(space.size))
    if exact is not None:       # the model's exact derivatives (one call), in the unit box
        J = exact[1] * space.dx_du(x0)[None, :]
    else:
        def res(u):
            return _loss.residuals(loss, model.eval(meas.wi, meas.wo, space.to_params(space.from_unit(u))), meas)

        u0 = space.to_unit(x0)
        J = forward_jacobian(res, u0, res(u0))
    col = np.sqrt(np.einsum("ij,ij->j", J, J))
    per = {p.name: p.per_channel for p in model.parameters}
    start = model.defaults()
    # the sheen's roughness acts through its amplitudes: at a start without sheen (all 0) its
    # column is 0 whatever the data, so it is not judged there
    off = {"sheen_alpha"} if "sheen_alpha" in start and not np.any(tabulated_sheen.amplitudes(start)) else set()
    out = {}
    for name, c in zip(space.names, col):
        if not per.get(name, True) and c < weak * np.median(col) and name not in off:
            out[name] = start[name]
    return out
