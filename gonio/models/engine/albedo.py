"""The albedo's quadratures (:mod:`gonio.models.physics.albedo`) as Dr.Jit kernels.

For every direction of a level at once: the nodes, the model's own compiled f_r at them and
each direction's weighted sum; numpy builds nothing per node and only the (M, 3) sums come back.

* :func:`lobe_integral`: the lobe's nodes (the slope-space map, the horizon cut), f_r less
  a known Lambertian part;
* :func:`smooth_integral`: the smooth part's nodes (the cosine-warped disk), f_r, or f_r less
  f_r with the smooth part switched off (``Model.smooth_off``: roughplastic's
  ``diffuse_reflectance = 0``; ``Model.lobe_switch``: principled's kernel asked for its lobe
  alone), whose lobe :func:`lobe_integral` then takes.

In float64, where ``Model.eval`` would run its compiled kernel (:func:`applies`). The package
installs it into :mod:`gonio.models.physics.albedo`. The arithmetic is the numpy quadrature's,
term for term (tests/models/test_albedo.py holds it to 1e-12, roughplastic 2e-9).
"""

# applies(): Dr.Jit's LLVM backend works and GONIO_EVAL_BACKEND is not ``numpy``. The package
# (models/__init__) installs this module; nothing else imports it. Dr.Jit's float64
# transcendentals (atan2, tan, sin, cos), its block sums and the compiled f_r differ from
# numpy's in the last bits (roughplastic more: its compiled f_r's coating tables).

from __future__ import annotations

import math

import numpy as np

from gonio.core.channels import CHANNELS
from gonio.models.engine.fast import compiled_for
from gonio.models.structure import LOBE_ONLY

#: nodes a kernel launch covers at most (the directions of a level are cut into chunks): the
#: weighted values it keeps for the block sums are 24 bytes a node
CHUNK_NODES = 1 << 20


def applies(model) -> bool:
    """True where the compiled quadratures run: the model has a compiled kernel, Dr.Jit's
    LLVM backend works and ``GONIO_EVAL_BACKEND`` is not ``numpy`` (``Model.eval``'s own
    rule)."""
    return compiled_for(model)


def quadratures(model):
    """``(lobe_integral, smooth_integral)`` where they run for ``model`` (:func:`applies`),
    else None: what :meth:`gonio.models.Model.albedo` hands the quadrature
    (:func:`gonio.models.physics.albedo.albedo`), looked up when called."""
    return (lobe_integral, smooth_integral) if applies(model) else None


def _map(model, p, off=None):
    """The kernel's parameter map for ``p`` (``off`` None), or for f_r with the smooth part
    switched off: ``off`` is ``LOBE_ONLY`` (``p`` with the kernel's lobe switch on) or the
    parameter values that switch it off."""
    from gonio.models.engine import fast as _fast

    if off is None or (isinstance(off, str) and off == LOBE_ONLY):
        P = _fast._eval_params(model, p, np.float64)
        return P if off is None else {**P, LOBE_ONLY: True}    # a copy: the cached map is shared
    return _fast._eval_params(model, off, np.float64)


def _chunked(W, k, chunk):
    """``chunk(W[a:b])`` over the directions of ``W`` cut into launches of at most
    :data:`CHUNK_NODES` nodes (``k`` a direction, one direction at least), stacked."""
    step = max(1, CHUNK_NODES // k)
    return np.concatenate([chunk(W[a:a + step]) for a in range(0, W.shape[0], step)])


def lobe_integral(model, p, dist, W, n_u, n_phi, known, off=None):
    """Sum over the lobe's nodes of weight * (f_r - known / pi) for each direction of ``W``
    ((M, 3) float64, above the horizon), (M, 3), where :func:`applies`; with ``off``
    (:func:`_map`), of weight * f_r(off), the lobe alone."""
    P = _map(model, p, off)
    known = np.broadcast_to(np.asarray(known, np.float64), (CHANNELS,)) / math.pi
    return _chunked(W, n_u * n_phi, lambda w: _chunk(model, P, dist, w, n_u, n_phi, known))


def _chunk(model, P, dist, W, n_u, n_phi, known_over_pi):
    from gonio.models.physics.albedo import _gl01
    from gonio.models.engine.kernels import _kernel
    from gonio.models.engine.roundtrip import types

    dr, F, V3, U = types(np.float64)
    m, k = W.shape[0], n_u * n_phi
    x, wx = _gl01(n_u)
    # opaque: a new roughness or rho reuses the compiled kernels (literals would be new code)
    au, av = dr.opaque(F, float(dist.alpha_u)), dr.opaque(F, float(dist.alpha_v))
    Wd = V3(*(F(np.ascontiguousarray(W[:, j])) for j in range(3)))
    wphi = 2.0 * math.pi / n_phi
    # what depends on the direction and the azimuth alone (the transcendentals), once for
    # each (direction, azimuth) pair in a first kernel; the nodes gather it
    j = dr.arange(U, m * n_phi)
    dj = j // n_phi
    w = dr.gather(V3, Wd, dj)
    phi = dr.atan2(w.y, w.x) + (F(j - dj * n_phi) + 0.5) * wphi
    sp, cp = dr.sincos(phi)
    proj = dr.sqrt((au * cp) ** 2 + (av * sp) ** 2)     # |slope| / t
    cpsi, spsi = -au * cp / proj, -av * sp / proj        # the facet's azimuth
    a = w.x * cpsi + w.y * spsi
    theta_star = 0.5 * (math.pi - dr.atan2(w.z, a))
    t_max = dr.tan(theta_star) / proj
    u_max = t_max * t_max / (1.0 + t_max * t_max)
    dr.eval(cp, sp, u_max)
    idx = dr.arange(U, m * k)
    di = idx // k
    r = idx - di * k
    iu = r // n_phi
    jp = di * n_phi + (r - iu * n_phi)
    w = dr.gather(V3, Wd, di)
    cp, sp, u_max = (dr.gather(F, v, jp) for v in (cp, sp, u_max))
    xu, wxu = dr.gather(F, F(x), iu), dr.gather(F, F(wx), iu)
    uu = xu * u_max
    t = dr.sqrt(uu / (1.0 - uu))
    sx, sy = au * t * cp, av * t * sp
    inv = 1.0 / dr.sqrt(1.0 + sx * sx + sy * sy)
    wm = V3(-sx * inv, -sy * inv, inv)
    jac = inv * inv * inv * (au * av) / (2.0 * (1.0 - uu) ** 2) * (wxu * u_max) * wphi
    d = wm.x * w.x + wm.y * w.y + wm.z * w.z
    wi = 2.0 * d * wm - w
    ok = (d > 0.0) & (wi.z > 0.0)
    wi = dr.select(ok, wi, V3(0.0, 0.0, 1.0))
    weight = dr.select(ok, jac * 4.0 * d * wi.z, 0.0)
    f = _kernel(model, wi, w, P)
    sums = [dr.block_sum(weight * (f[c] - dr.opaque(F, float(known_over_pi[c]))), k) for c in range(CHANNELS)]
    dr.eval(*sums)
    return np.stack([np.asarray(s) for s in sums], axis=1)


def smooth_integral(model, p, off, W, n_theta, n_phi):
    """Sum over the smooth part's nodes of weight * f_r (``off`` None), or weight *
    (f_r - f_r(off)) (:func:`_map`), for each direction of ``W`` ((M, 3) float64, above
    the horizon), (M, 3), where :func:`applies`."""
    P, P_off = _map(model, p), (None if off is None else _map(model, p, off))
    return _chunked(W, n_theta * n_phi, lambda w: _smooth_chunk(model, P, P_off, w, n_theta, n_phi))


def _smooth_chunk(model, P, P_off, W, n_theta, n_phi):
    """:func:`gonio.models.physics.albedo._smooth_nodes` and the sums, in one kernel: u = sin^2 of
    the node's inclination by Gauss-Legendre on [0, sin^2 theta_o] and [sin^2 theta_o, 1],
    the midpoint rule in the azimuth from the direction's own. The node-independent
    trigonometry (each direction's azimuth, the rule's azimuths) is numpy's, as there."""
    from gonio.models.physics.albedo import _gl01
    from gonio.models.engine.kernels import _kernel
    from gonio.models.engine.roundtrip import types

    dr, F, V3, U = types(np.float64)
    m, k, half = W.shape[0], n_theta * n_phi, n_theta // 2
    x, wx = _gl01(half)
    phis = (np.arange(n_phi) + 0.5) * (2.0 * math.pi / n_phi)
    phi_o = np.arctan2(W[:, 1], W[:, 0])
    Wd = V3(*(F(np.ascontiguousarray(W[:, j])) for j in range(3)))
    idx = dr.arange(U, m * k)
    di = idx // k
    r = idx - di * k
    it = r // n_phi
    ip = r - it * n_phi
    w = dr.gather(V3, Wd, di)
    s2 = dr.clip(1.0 - w.z * w.z, 0.0, 1.0)
    upper = it >= half                                   # the piece [sin^2 theta_o, 1]
    xi = dr.select(upper, it - half, it)
    xg, wg = dr.gather(F, F(x), xi), dr.gather(F, F(wx), xi)
    u = dr.select(upper, s2 + xg * (1.0 - s2), xg * s2)
    wu = dr.select(upper, wg * (1.0 - s2), wg * s2)
    rr = dr.sqrt(u)
    cz = dr.sqrt(dr.maximum(1.0 - u, 0.0))
    lx, ly = rr * dr.gather(F, F(np.cos(phis)), ip), rr * dr.gather(F, F(np.sin(phis)), ip)
    c, s = dr.gather(F, F(np.cos(phi_o)), di), dr.gather(F, F(np.sin(phi_o)), di)
    wi = V3(c * lx - s * ly, s * lx + c * ly, cz)
    weight = wu * (math.pi / n_phi)                      # cos(theta_i) d(wi) = du dphi / 2
    f = _kernel(model, wi, w, P)
    if P_off is not None:
        off = _kernel(model, wi, w, P_off)
        f = [a - b for a, b in zip(f, off)]
    sums = [dr.block_sum(weight * f[ch], k) for ch in range(CHANNELS)]
    dr.eval(*sums)
    return np.stack([np.asarray(v) for v in sums], axis=1)
