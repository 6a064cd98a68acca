"""Rough dielectric transmittance and internal reflectance tables of ``roughplastic``.

Mitsuba 3's ``roughplastic`` (``src/bsdfs/roughplastic.cpp``, ``parameters_changed``)
precomputes, for each (distribution, alpha, eta), with ``include/mitsuba/render/microfacet.h``:

* the external transmittance ``t(mu)`` of the rough interface at 64 equally spaced
  ``mu = cos(theta)`` in [0, 1] (``mu`` floored at 1e-6), by ``eval_transmittance``: a 32 x 32
  Gauss-Legendre quadrature over the visible-normal sampling domain of
  ``(1 - F(wi . wm)) G1(wt, wm)`` with ``wt`` the refracted direction;
* the internal diffuse reflectance ``R_int = 2 mean_mu(R(mu; 1/eta) mu)`` over the same 64
  ``mu``, ``R`` from ``eval_reflectance`` (a 128 x 128 Gauss-Legendre quadrature because
  1/eta < 1) of ``F(wi . wm; 1/eta) G1(wr, wm)``, ``wr`` the reflected direction.

This module reproduces the same quadrature nodes and visible-normal warps (so the same
discretisation error) in float64 numpy. Tables are cached (LRU) on (distribution, alpha, eta).
"""

# The separable structure of the warp keeps this cheap: for a direction in the x-z plane the
# Beckmann x-slope depends on (mu, u1) only and the y-slope on u2 only, and the GGX
# concentric-disk point does not depend on mu at all.

from __future__ import annotations

from functools import lru_cache
from importlib.resources import files

import numpy as np

from gonio.models.physics.microfacet import ALPHA_MIN, MicrofacetDistribution, _concentric_disk

__all__ = ["RES", "rough_tables", "rough_tables_interp", "lerp_table", "clear_cache"]

#: Table resolution (Mitsuba ``MI_ROUGH_TRANSMITTANCE_RES``).
RES = 64

#: Working precision of the quadrature (Mitsuba uses float32 in its llvm/scalar rgb
#: variants; float64 here is the reference, and differs from it by ~1e-7).
_DT = np.float64


@lru_cache(maxsize=None)
def _gl(n):
    x, w = np.polynomial.legendre.leggauss(n)
    return (0.5 * x + 0.5).astype(_DT), w.astype(_DT)


@lru_cache(maxsize=None)
def _disk(n):
    u, _ = _gl(n)
    u1, u2 = np.meshgrid(u, u, indexing="ij")
    return _concentric_disk(u1, u2)


def _mu():
    mu = np.maximum(1e-6, np.linspace(0.0, 1.0, RES)).astype(_DT)
    return mu, np.sqrt(1.0 - mu * mu)


def _visible_normals(kind, alpha, n):
    """Visible normals for the 64 table directions at the n x n GL nodes.

    Only half of the grid is built: the y slope is odd under u2 -> 1 - u2 (Beckmann)
    or u1 -> 1 - u1 (GGX, concentric disk) while m_x, m_z are unchanged, and the
    integrands depend on m_y only through m_y^2, so the other half contributes the
    same (weights doubled).

    Returns mx, mz of shape (RES, a, b) and the weights (a, b) including Mitsuba's
    factor 1/4, with (a, b) = (n, n/2) for Beckmann and (n/2, n) for GGX.
    """
    mu, sx_dir = _mu()
    u, w = _gl(n)
    h = n // 2
    # cosine of the stretched direction (alpha x, 0, z) / |.|
    cp = mu / np.sqrt((alpha * sx_dir) ** 2 + mu * mu)
    if kind == "beckmann":
        dist = MicrofacetDistribution(kind, alpha)
        sx, _ = dist._sample_visible_11(cp[:, None], u[None, :], np.full((1, n), 0.5))
        _, sy = dist._sample_visible_11(np.ones(1), np.full(h, 0.5), u[:h])
        # slope (sx, sy): x from (mu, u1), y from u2
        mx = -alpha * sx[:, :, None]
        my2 = (alpha * sy[None, None, :]) ** 2
        inv = 1.0 / np.sqrt(mx * mx + my2 + 1.0)
        return mx * inv, inv, 0.5 * np.outer(w, w[:h])
    else:
        px, py = _disk(n)
        px, py = px[:h], py[:h]
        c = cp[:, None, None]
        s = 0.5 * (1.0 + c)
        py = np.sqrt(np.maximum(1.0 - px * px, 0.0)) * (1.0 - s) + py * s
        z = np.sqrt(np.maximum(1.0 - px * px - py * py, 0.0))
        sin_i = np.sqrt(np.maximum(1.0 - c * c, 0.0))
        norm = alpha / (sin_i * py + c * z)
        mx = -(c * py - sin_i * z) * norm
        my = px * norm
        inv = 1.0 / np.sqrt(mx * mx + my * my + 1.0)
        mx = mx * inv
    return mx, inv, 0.5 * np.outer(w[:h], w)


def _g1(kind, alpha, oz):
    """Mitsuba Smith G1 of a unit direction with z component ``oz`` (front-facing facet)."""
    oz2 = oz * oz
    t2 = alpha * alpha * (1.0 - oz2) / np.where(oz2 > 0.0, oz2, 1.0)
    if kind == "ggx":
        return 2.0 / (1.0 + np.sqrt(1.0 + t2))
    a = 1.0 / np.sqrt(np.where(t2 > 0.0, t2, 1e-300))
    a2 = a * a
    return np.where(a >= 1.6, 1.0, (3.535 * a + 2.181 * a2) / (1.0 + 2.276 * a + 2.577 * a2))


def _dielectric_F(d, eta):
    """Fresnel reflectance for 0 <= d <= 1 arriving from the side of index 1 (eta = n2/n1)."""
    ci = np.minimum(d, 1.0)
    ct = np.sqrt(np.maximum(1.0 - (1.0 - ci * ci) / (eta * eta), 0.0))
    a_s = (ci - eta * ct) / (ci + eta * ct)
    a_p = (ct - eta * ci) / (ct + eta * ci)
    return 0.5 * (a_s * a_s + a_p * a_p), ct


def _transmittance(kind, alpha, eta):
    """Mitsuba ``eval_transmittance`` at the 64 table cosines (eta > 1: light enters)."""
    mu, wx = _mu()
    mx, mz, wgt = _visible_normals(kind, alpha, 32 if eta > 1 else 128)
    mub = mu[:, None, None]
    d = wx[:, None, None] * mx + mub * mz
    front = d > 0.0
    F, ct = _dielectric_F(np.where(front, d, 1.0), eta)
    eta_ti = 1.0 / eta
    # refracted direction wt = m (d eta_ti - ct) - wi eta_ti: unit, wt . m = -ct
    oz = mz * (d * eta_ti - ct) - mub * eta_ti
    v = np.where(front & (oz < 0.0) & (ct > 0.0), _g1(kind, alpha, oz) * (1.0 - F), 0.0)
    return np.einsum("rij,ij->r", v, wgt, dtype=np.float64)


def _reflectance(kind, alpha, eta):
    """Mitsuba ``eval_reflectance`` at the 64 table cosines."""
    mu, wx = _mu()
    mx, mz, wgt = _visible_normals(kind, alpha, 32 if eta > 1 else 128)
    mub = mu[:, None, None]
    d = wx[:, None, None] * mx + mub * mz
    # reflected direction wr = 2 d m - wi: unit, wr . m = d; visible iff wr_z > 0
    oz = 2.0 * d * mz - mub
    front = (d > 0.0) & (oz > 0.0)
    F, _ = _dielectric_F(np.where(front, d, 1.0), eta)
    v = np.where(front, _g1(kind, alpha, oz) * F, 0.0)
    return np.einsum("rij,ij->r", v, wgt, dtype=np.float64)


@lru_cache(maxsize=512)
def rough_tables(kind, alpha, eta):
    """External transmittance table and internal reflectance of a rough interface.

    Parameters
    ----------
    kind : {"beckmann", "ggx"}
    alpha : float
        Roughness (floored at 1e-4).
    eta : float
        Relative index interior / exterior (> 1).

    Returns
    -------
    t_ext : ndarray, shape (64,), read-only
        Rough transmittance from outside at ``cos(theta) = i / 63``.
    r_int : float
        Hemispherical (cosine-weighted) internal reflectance of the interface.
    """
    alpha = max(float(alpha), ALPHA_MIN)
    eta = float(eta)
    with np.errstate(all="ignore"):
        t = _transmittance(kind, alpha, eta)
        r = _reflectance(kind, alpha, 1.0 / eta)
    mu, _ = _mu()
    r_int = float(np.mean(r * mu) * 2.0)
    t = t.astype(np.float64)
    t.setflags(write=False)
    return t, r_int


def clear_cache():
    """Forget all cached tables (exact and interpolated)."""
    rough_tables.cache_clear()
    rough_tables_interp.cache_clear()


def lerp_table(table, x):
    """Linear interpolation of a table sampled at ``i / (len - 1)``, i = 0..len-1
    (Mitsuba ``roughplastic::lerp_gather``); ``x`` is clamped to [0, 1]."""
    n = table.shape[0]
    x = np.clip(x, 0.0, 1.0) * (n - 1)
    idx = np.minimum(x.astype(np.intp), n - 2)
    w1 = x - idx
    return table[idx] * (1.0 - w1) + table[idx + 1] * w1


# -- interpolated tables ------------------------------------------------------------------
#
# ``rough_tables`` costs 25-70 ms per new (alpha, eta) (the 128 x 128 quadrature of R_int
# dominates). Fits and samplers change alpha and eta at every step, so the tables are also
# precomputed on a grid (``models/data/roughplastic_tables.npz``, written by
# ``python -m gonio.models.build_tables``) and interpolated with a tensor-product cubic
# spline (not-a-knot) in (x, y) = (log alpha, log(eta - 1 + ETA_SHIFT)).
#
# The exact tables are not smooth everywhere: every quadrature node whose microfacet
# crosses the critical angle of total internal reflection adds a square-root cusp to
# R_int (and the Beckmann G1 approximation has a kink), so no smooth interpolant follows
# them to better than the cusp amplitude. The build therefore also evaluates the exact
# tables at the centre of every grid cell and stores, per cell, the error of the
# interpolant there in terms of the relative error it causes in the diffuse term
# t(mu_i) t(mu_o) / (1 - R_int):  ``2 max_k |dt_k| / t_k + |dR_int| / (1 - R_int)``.
# Cells whose error exceeds ``INTERP_TOL`` fall back to the exact computation, as do
# points outside the grid and a missing data file.

#: Name of the grid file inside the package data folder.
GRID_FILE = "roughplastic_tables.npz"

#: Largest per-cell interpolation error (relative, of the diffuse term of f_r) accepted;
#: cells above it are evaluated exactly. The issue's bound against Mitsuba is 1e-3.
INTERP_TOL = 2e-4

_GRID = None  # False: no usable grid file; else dict per kind


def _load_grid():
    """Load the grid once (lazily); False when the file is missing or unreadable."""
    global _GRID
    if _GRID is None:
        try:
            with files(__package__).joinpath("data", GRID_FILE).open("rb") as fh:
                with np.load(fh) as z:
                    data = {k: z[k] for k in z.files}
            _GRID = _prepare_grid(data)
        except (OSError, KeyError, ValueError, ModuleNotFoundError):
            _GRID = False
    return _GRID


def _prepare_grid(data):
    """Spline coefficients from the node values of the grid file."""
    from scipy.interpolate import make_interp_spline

    x, y = data["log_alpha"], data["y_eta"]
    out = {"x": x, "y": y, "eta_shift": float(data["eta_shift"])}
    for kind in ("beckmann", "ggx"):
        vals = np.concatenate([data[f"t_{kind}"], data[f"r_{kind}"][..., None]], axis=-1)
        sx = make_interp_spline(x, vals, k=3, axis=0)
        sy = make_interp_spline(y, sx.c, k=3, axis=1)
        # make_interp_spline puts the interpolation axis first
        out[kind] = (np.ascontiguousarray(np.moveaxis(sy.c, 0, 1)), data[f"err_{kind}"])
        out["tx"], out["ty"] = sx.t, sy.t
    return out


def _bspline_basis(knots, nodes, v):
    """Span index s and the 4 cubic B-spline values and derivatives at ``v`` (inside
    [nodes[0], nodes[-1]]): the spline is sum_i b[i] c[s - 3 + i]; ``cell`` is the index
    of the grid interval holding ``v``."""
    cell = min(max(int(np.searchsorted(nodes, v, side="right")) - 1, 0), len(nodes) - 2)
    s = min(max(int(np.searchsorted(knots, v, side="right")) - 1, 3), len(knots) - 5)
    t = knots
    # Cox-de Boor (The NURBS Book, A2.2), keeping the degree-2 values for the derivative
    left = [v - t[s + 1 - j] for j in range(1, 4)]
    right = [t[s + j] - v for j in range(1, 4)]
    b = [1.0]
    for j in range(1, 4):
        if j == 3:
            b2 = b
        saved = 0.0
        nb = []
        for r in range(j):
            tmp = b[r] / (right[r] + left[j - r - 1])
            nb.append(saved + right[r] * tmp)
            saved = left[j - r - 1] * tmp
        nb.append(saved)
        b = nb
    # derivative: N'_{i,3} = 3 (N_{i,2} / (t_{i+3} - t_i) - N_{i+1,2} / (t_{i+4} - t_{i+1}))
    n2 = [0.0] + b2 + [0.0]  # N_{s-3,2} = 0, N_{s-2..s,2} = b2, N_{s+1,2} = 0
    db = []
    for i in range(4):
        k = s - 3 + i
        a = n2[i] / (t[k + 3] - t[k]) if n2[i] else 0.0
        c = n2[i + 1] / (t[k + 4] - t[k + 1]) if n2[i + 1] else 0.0
        db.append(3.0 * (a - c))
    return s, cell, np.array(b), np.array(db)


def _interp(kind, alpha, eta, grad=False, tol=None):
    """Interpolated (t, r_int) or None (no grid, outside it, or a cell above ``tol``).

    With ``grad``: also d(t, r_int)/d alpha and d(t, r_int)/d eta of the interpolant."""
    g = _load_grid()
    if not g or kind not in g:
        return None
    alpha = max(float(alpha), ALPHA_MIN)
    eta = float(eta)
    if not eta > 1.0:
        return None
    xv = np.log(alpha)
    yv = np.log(eta - 1.0 + g["eta_shift"])
    x, y = g["x"], g["y"]
    if not (x[0] <= xv <= x[-1] and y[0] <= yv <= y[-1]):
        return None
    coef, err = g[kind]
    sx, cx, bx, dbx = _bspline_basis(g["tx"], x, xv)
    sy, cy, by, dby = _bspline_basis(g["ty"], y, yv)
    if err[cx, cy] > (INTERP_TOL if tol is None else tol):
        return None
    c = coef[sx - 3:sx + 1, sy - 3:sy + 1]
    v = np.einsum("i,j,ijk->k", bx, by, c)
    if not grad:
        return v[:-1], float(v[-1])
    dx = np.einsum("i,j,ijk->k", dbx, by, c) / alpha  # d/d alpha = d/dx / alpha
    dy = np.einsum("i,j,ijk->k", bx, dby, c) / (eta - 1.0 + g["eta_shift"])
    return v[:-1], float(v[-1]), dx, dy


@lru_cache(maxsize=4096)
def rough_tables_interp(kind, alpha, eta):
    """Like :func:`rough_tables`, from the precomputed grid (~40 us instead of 25-70 ms).

    Falls back to :func:`rough_tables` (exact) outside the grid, in the few grid cells
    whose interpolation error exceeds :data:`INTERP_TOL`, and when the data file is
    missing. Inside, the relative error of the diffuse term ``t t / (1 - R_int)`` is
    below ``INTERP_TOL`` at the cell centres (measured at the build; see the report of
    ``python -m gonio.models.build_tables``).
    """
    out = _interp(kind, alpha, eta)
    if out is None:
        return rough_tables(kind, alpha, eta)
    t, r = out
    t = t.copy()
    t.setflags(write=False)
    return t, r
