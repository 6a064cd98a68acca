"""The albedo's lobe quadrature (:func:`gonio.models._albedo._lobe_integral`) as one Dr.Jit
kernel: the nodes (the slope-space map, the horizon cut), the model's own compiled f_r at
them and each direction's weighted sum, for every direction of a level at once; numpy
builds nothing per node and only the (M, 3) sums come back.

For the models whose smooth part the quadrature knows without integrating it (``lobe_only``:
roughconductor; ``lambert_smooth``: cooktorrance), in float64, where ``Model.eval`` would
run its compiled kernel (Dr.Jit's LLVM backend works, ``GONIO_EVAL_BACKEND`` is not
``numpy``). Installed into :mod:`._albedo` by the package (``models/__init__``), which
does not import this module: :func:`lobe_integral` returns None where it does not apply and
the numpy nodes are used.

The arithmetic is the numpy quadrature's, term for term; Dr.Jit's float64 transcendentals
(atan2, tan, sin, cos) and its block sums differ from numpy's in the last bits: equal to
the numpy path to ~1e-15 (tests/models/test_albedo.py holds them to 1e-12).
"""

from __future__ import annotations

import math

import numpy as np

from ._base import CHANNELS, _compiled

#: nodes a kernel launch covers at most (the directions of a level are cut into chunks): the
#: weighted values it keeps for the block sums are 24 bytes a node
CHUNK_NODES = 1 << 20


def applies(model) -> bool:
    """True where :func:`lobe_integral` runs: the model has a compiled kernel, Dr.Jit's LLVM
    backend works and ``GONIO_EVAL_BACKEND`` is not ``numpy`` (``Model.eval``'s own rule)."""
    return _compiled(model)


def lobe_integral(model, p, dist, W, n_u, n_phi, known):
    """Sum over the lobe's nodes of weight * (f_r - known / pi) for each direction of ``W``
    ((M, 3) float64, above the horizon), (M, 3), where :func:`applies`."""
    from . import _fast

    k = n_u * n_phi
    step = max(1, CHUNK_NODES // k)
    P = _fast._eval_params(model, p, np.float64)
    known = np.broadcast_to(np.asarray(known, np.float64), (CHANNELS,)) / math.pi
    return np.concatenate([_chunk(model, P, dist, W[a:a + step], n_u, n_phi, known) for a in range(0, W.shape[0], step)])


def _chunk(model, P, dist, W, n_u, n_phi, known_over_pi):
    from ._albedo import _gl01
    from ._kernels import _kernel
    from ._roundtrip import types

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
