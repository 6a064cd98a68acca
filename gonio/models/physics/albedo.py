"""Directional albedo by deterministic quadrature.

a(wo) = integral over the upper hemisphere of f_r(wi, wo) cos(theta_i) d(wi).

Smooth parts (Lambert, Oren-Nayar, roughplastic's transmittance-weighted diffuse term) are
integrated in the cosine-warped disk, microfacet lobes over the microfacet normal ``wm`` placed
in slope space by the GGX inverse CDF, so that the nodes follow the lobe whatever alpha is.
The rule is applied at (n_theta, n_phi) x 2^level until two successive levels agree to ``tol``
(default 1e-4 absolute) or ``max_level`` is reached; the last difference is returned as the
error estimate (``return_error=True``). Every direction still refining at a level is integrated
at once: in Dr.Jit kernels where Dr.Jit works (:mod:`gonio.models.engine.albedo`), else in numpy
(the reference). Error (tested in tests/models/test_albedo.py against a 16x finer quadrature):
below :data:`QUADRATURE_ERROR` = 1e-3 absolute for every model over its parameter box, views up
to 90 deg - 1e-4 included; typically below 1e-5.
"""

# The rules. Smooth parts: cos(theta_i) d(wi) = r dr dphi with r = sin(theta_i); Gauss-Legendre
# in r^2 (n_theta nodes, split at sin^2(theta_o)) times the midpoint rule in phi measured from
# phi_o (n_phi nodes; spectrally accurate for smooth periodic integrands, and the kinks of
# Oren-Nayar at phi_o +- pi/2 fall on cell boundaries). Lobes: wi = reflect(wo, wm),
# d(wi) = 4 |wo . wm| d(wm), slope = alpha * sqrt(u / (1 - u)) (cos phi, sin phi),
# d(wm) = cos^3(theta_m) alpha_u alpha_v / (2 (1 - u)^2) du dphi; Gauss-Legendre in u.
#
# The compiled path (gonio.models.engine.albedo, installed by the package): where the model says
# enough of its parts, each level is one or two Dr.Jit kernels (the nodes, the model's compiled
# f_r at them and every direction's sums). A smooth part known without integration (lobe_only:
# roughconductor; lambert_smooth: cooktorrance, tabulated) leaves the lobe's nodes alone; no lobe
# distribution (diffuse, Oren-Nayar) means f_r at the smooth part's nodes; parameter values that
# switch the smooth part off (smooth_off: roughplastic at rho = 0) split f_r into f_r - f_r(off)
# at the smooth part's nodes and f_r(off) at the lobe's, and a kernel that gives its lobe alone
# on request (lobe_switch: principled, whose base colour is in its lobe too) is split the same
# way. Elsewhere (GONIO_EVAL_BACKEND=numpy, no Dr.Jit) numpy builds the nodes and evaluates the
# reference. Timings and agreement: docs/performance.md, gonio.models.physics.albedo.
#
# The hard cases for the error bound are lobes cut by the horizon (wo within a few alpha of
# grazing) and the Cook-Torrance min() geometry term.

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from gonio.core.channels import CHANNELS
from gonio.models.structure import LOBE_ONLY
from gonio.core.geometry import as_directions

__all__ = ["albedo", "QUADRATURE_ERROR"]

#: Stated absolute error bound of :func:`albedo` with its default resolution.
QUADRATURE_ERROR = 1e-3


@lru_cache(maxsize=None)
def _gl01(n):
    x, w = np.polynomial.legendre.leggauss(n)
    return 0.5 * x + 0.5, 0.5 * w


def _compiled_for(model, dist, compiled):
    """The compiled quadratures ``(lobe_integral, smooth_integral)`` where they take the
    whole albedo of ``model``: its smooth part known (``lobe_only``, ``lambert_smooth``) or
    switched off by parameter values (``smooth_off``) under a lobe distribution, or no lobe
    distribution at all (f_r at the smooth part's nodes); the compiled path working. Else
    None."""
    if compiled is None:
        return None
    known = model.lobe_only or model.lambert_smooth is not None
    if dist is not None and not known and model.smooth_off is None and not model.lobe_switch:
        return None
    return compiled


def _switched_off(model, p):
    """What switches the model's smooth part off for the compiled quadratures: its
    parameters with ``smooth_off`` (validated), or :data:`gonio.models.structure.LOBE_ONLY` (its
    kernel's ``lobe_switch``)."""
    if model.smooth_off is None:
        return LOBE_ONLY
    return model.validate({**p, **model.smooth_off})


#: quadrature nodes evaluated in one call (the directions of a level are cut into chunks of
#: about this many nodes: a (nodes, 3) float64 array of 0.8 MB, in a core's L2 cache)
CHUNK_NODES = 1 << 15


def _smooth_nodes(W, n_theta, n_phi):
    """Nodes and weights of the cosine-weighted hemisphere for the smooth part, for each
    direction of ``W`` (M, 3): (M, K, 3) directions and (M, K) weights, K = n_theta n_phi,
    azimuths measured from each direction's own. u = sin^2(theta_i) is split at
    sin^2(theta_o) (where max/min(theta_i, theta_o) kinks, e.g. Oren-Nayar) with
    Gauss-Legendre on each piece; the midpoint rule in phi puts phi = +-pi/2 (kinks of
    max(0, cos dphi)) on cell boundaries (n_phi multiple of 4)."""
    cos_o = W[:, 2]
    s2 = np.clip(1.0 - cos_o * cos_o, 0.0, 1.0)[:, None]
    x, w = _gl01(n_theta // 2)
    u = np.concatenate([x * s2, s2 + x * (1.0 - s2)], axis=1)         # (M, n_theta)
    wu = np.concatenate([w * s2, w * (1.0 - s2)], axis=1)
    phis = (np.arange(n_phi) + 0.5) * (2.0 * math.pi / n_phi)
    r = np.sqrt(u)[:, :, None]
    cz = np.sqrt(np.maximum(1.0 - u, 0.0))[:, :, None]
    lx, ly = r * np.cos(phis), r * np.sin(phis)                      # (M, n_theta, n_phi)
    phi_o = np.arctan2(W[:, 1], W[:, 0])
    c, s = np.cos(phi_o)[:, None, None], np.sin(phi_o)[:, None, None]
    wi = np.stack([c * lx - s * ly, s * lx + c * ly, np.broadcast_to(cz, lx.shape)], -1)
    # cos(theta_i) d(wi) = r dr dphi = du dphi / 2
    wgt = np.broadcast_to(wu[:, :, None] * (math.pi / n_phi), lx.shape)
    m = W.shape[0]
    return wi.reshape(m, -1, 3), wgt.reshape(m, -1)


def _known_smooth(model, p):
    """The smooth part's albedo where the model declares it (``lobe_only``: 0; a Lambertian
    ``lambert_smooth``: its rho), else None (integrated at the smooth part's nodes)."""
    if model.lobe_only:
        return 0.0
    if model.lambert_smooth is not None:
        return np.asarray(p[model.lambert_smooth], np.float64)
    return None


def _weighted(weight, values):
    """sum_k weight[m, k] values[m, k, c]: (M, C) (C = 1 for a part shared by the channels)."""
    return np.einsum("mk,mkc->mc", weight, values)


def _integral(model, p, dist, W, n_theta, n_phi, compiled=None):
    """Albedo of each direction of ``W`` (M, 3) at one resolution, (M, 3): every node of
    every direction in one evaluation (a chunk of :data:`CHUNK_NODES`); ``compiled``: the
    compiled quadratures (:func:`_compiled_for`), which build the nodes themselves."""
    known = _known_smooth(model, p)
    m = W.shape[0]
    if known is not None and dist is not None:      # the lobe's nodes alone
        lobe = (_lobe_integral(model, p, dist, W, n_theta, n_phi) if compiled is None
                else compiled[0](model, p, dist, W, n_theta, n_phi, known))
        return np.broadcast_to(known + lobe, (m, model.n_channels(p)))
    if compiled is not None:
        if dist is None:                            # f_r at the smooth part's nodes
            return compiled[1](model, p, None, W, n_theta, n_phi)
        off = _switched_off(model, p)               # smooth: f_r - f_r(off); lobe: f_r(off)
        return (compiled[1](model, p, off, W, n_theta, n_phi)
                + compiled[0](model, p, dist, W, n_theta, n_phi, 0.0, off))
    wi, wgt = _smooth_nodes(W, n_theta, n_phi)
    m, k = wgt.shape
    smooth, lobe = model._eval_parts(wi.reshape(-1, 3), np.repeat(W, k, axis=0), p)
    acc = _weighted(wgt, np.asarray(smooth).reshape(m, k, -1))
    if lobe is not None:
        if dist is None:
            acc = acc + _weighted(wgt, lobe.reshape(m, k, -1))
        else:
            acc = acc + _lobe_integral(model, p, dist, W, n_theta, n_phi)
    return np.broadcast_to(acc, (m, model.n_channels(p)))


def albedo(model, wo, params, n_theta=32, n_phi=32, tol=1e-4, max_level=3, return_error=False, compiled=None):
    """Directional albedo of ``model`` for each ``wo``; shape (N, 3).

    Parameters
    ----------
    model : gonio.models.Model
    wo : array_like, shape (N, 3)
        Unit directions toward the detector.
    params : dict
    n_theta, n_phi : int
        Base quadrature resolution (see module docstring).
    tol : float
        Absolute tolerance: the resolution doubles (up to ``max_level`` times) until two
        successive estimates differ by less than ``tol`` in every channel.
    return_error : bool
        Also return the error estimate (the last difference), shape (N, 3).
    compiled : tuple, optional
        The compiled quadratures ``(lobe_integral, smooth_integral)`` of
        :mod:`gonio.models.engine.albedo` where they run for ``model``
        (:func:`gonio.models.engine.albedo.quadratures`; :meth:`gonio.models.Model.albedo`
        passes them); None: numpy.

    Returns
    -------
    ndarray, shape (N, 3)
        0 for ``wo`` at or below the horizon.

    Every direction still refining at a level is integrated at once: one to three Dr.Jit
    kernels a level where Dr.Jit works (:mod:`gonio.models.engine.albedo`), else numpy in chunks of
    :data:`CHUNK_NODES` nodes.
    """
    wo = as_directions(wo, "wo")
    p = model.validate(params)
    n = wo.shape[0]
    nc = model.n_channels(p)             # one per wavelength in a spectral fit
    out = np.zeros((n, nc))
    err = np.zeros((n, nc))
    dist = model._lobe_distribution(p)
    n_theta = max(2, n_theta + n_theta % 2)
    n_phi = max(4, n_phi + (-n_phi) % 4)
    idx = np.flatnonzero(np.isfinite(wo).all(axis=1) & (wo[:, 2] > 0.0))
    if idx.size == 0:
        return (out, err) if return_error else out

    compiled = _compiled_for(model, dist, compiled) if nc == CHANNELS else None    # the kernels hold 3 channels

    def level_of(sel, level):
        nt, nph = n_theta << level, n_phi << level
        if compiled is not None:        # one kernel for the level; it cuts its own chunks
            return _integral(model, p, dist, wo[sel], nt, nph, compiled)
        step = max(1, CHUNK_NODES // (nt * nph))
        return np.concatenate([_integral(model, p, dist, wo[sel[a:a + step]], nt, nph)
                               for a in range(0, sel.size, step)])

    with np.errstate(all="ignore"):
        prev = np.array(level_of(idx, 0))      # written into below (a level may be a broadcast view)
        e = np.full((idx.size, nc), np.nan)  # no estimate without a second level
        active = np.arange(idx.size)
        for level in range(1, max_level + 1):
            if active.size == 0:
                break
            cur = level_of(idx[active], level)
            e[active] = np.abs(cur - prev[active])
            prev[active] = cur
            active = active[~(e[active].max(axis=1) <= tol)]
    out[idx], err[idx] = prev, e
    return (out, err) if return_error else out  # err is NaN where max_level = 0


def _lobe_integral(model, p, dist, W, n_u, n_phi):
    """Lobe part integrated over microfacet normals (slope-space map, see module doc), for
    each direction of ``W`` (M, 3), (M, 3); phi is measured from each direction's azimuth.

    Along each slope azimuth the reflected direction leaves the upper hemisphere at a
    facet inclination theta* with ``a sin(2 theta*) + b cos(2 theta*) = 0`` (``a`` the
    tangential component of wo along the facet azimuth, ``b = cos(theta_o)``); the
    u-interval is truncated there, so the horizon cut lies on the boundary of the rule.
    """
    au, av = dist.alpha_u, dist.alpha_v
    x, wx = _gl01(n_u)
    m = W.shape[0]
    phi_o = np.arctan2(W[:, 1], W[:, 0])[:, None]
    phis = phi_o + (np.arange(n_phi) + 0.5) * (2.0 * math.pi / n_phi)     # (M, n_phi)
    wphi = 2.0 * math.pi / n_phi
    cp, sp = np.cos(phis), np.sin(phis)
    proj = np.sqrt((au * cp) ** 2 + (av * sp) ** 2)  # |slope| / t
    # facet azimuth psi of slope (-au t cos phi, -av t sin phi)
    cpsi, spsi = -au * cp / proj, -av * sp / proj
    a = W[:, 0:1] * cpsi + W[:, 1:2] * spsi
    theta_star = 0.5 * (math.pi - np.arctan2(np.broadcast_to(W[:, 2:3], a.shape), a))
    t_max = np.tan(theta_star) / proj
    u_max = (t_max**2 / (1.0 + t_max**2))[:, None, :]                    # (M, 1, n_phi)
    U = x[None, :, None] * u_max                                           # (M, n_u, n_phi)
    wU = wx[None, :, None] * u_max
    t = np.sqrt(U / (1.0 - U))
    sx, sy = au * t * cp[:, None, :], av * t * sp[:, None, :]
    inv = 1.0 / np.sqrt(1.0 + sx * sx + sy * sy)
    wm = np.stack([-sx * inv, -sy * inv, inv], -1).reshape(m, -1, 3)
    jac = (inv**3 * au * av / (2.0 * (1.0 - U) ** 2) * wU * wphi).reshape(m, -1)
    d = np.einsum("mkj,mj->mk", wm, W)
    wi = 2.0 * d[:, :, None] * wm - W[:, None, :]
    ok = (d > 0.0) & (wi[:, :, 2] > 0.0)
    wi = np.where(ok[:, :, None], wi, np.array([0.0, 0.0, 1.0])).reshape(-1, 3)
    wo = np.repeat(W, ok.shape[1], axis=0)
    # numpy's reference lobe: where Dr.Jit works the whole quadrature is one kernel a level
    # instead (:mod:`gonio.models.engine.albedo`), and this path is what it is tested against
    lobe = model._eval_parts(wi, wo, p)[1]
    weight = np.where(ok, jac * 4.0 * d * wi.reshape(m, -1, 3)[:, :, 2], 0.0)
    return _weighted(weight, lobe.reshape(m, ok.shape[1], -1))
