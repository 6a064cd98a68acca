"""The fit's fast path for models affine in one per-channel parameter.

``diffuse``, ``orennayar`` and ``roughplastic`` (``nonlinear=False``) have

    f_r[c] = base(theta) + coef[c] * basis(theta)

with base and basis the same in every channel (:func:`gonio.models._fast.affine_parts`).
Variable projection then needs, per trial theta, only five weighted sums per channel
(sum w^2 b^2, sum w^2 b y, sum w^2 b s, ...), and the kernel evaluates many thetas in one
call. This module runs the same algorithm as :func:`gonio.fitting._optimise.fit` -- a
stratified global stage, Levenberg-Marquardt on the reduced residuals (Kaufman's Jacobian)
from the best starts in distinct basins, the Laplace covariance -- with every batch of
thetas (the starts; theta and its forward-difference neighbours; the central differences
at the optimum) in one kernel call.

``roughplastic``'s coefficient is rho / (1 - R_int(alpha, eta)), so the 128 x 128
quadrature of R_int is needed only at the end: rho = coef * q(theta*), q = 1 - R_int,
computed exactly once (:func:`gonio.models._fast.affine_q`). During the iterations the
bound rho <= 1 becomes coef <= 1 / q with q from the precomputed grid (a few 1e-2 at
worst); an answer whose coefficient rests on that approximate bound, or whose exact rho
leaves its bounds, is handed back to the general path (``fit_affine`` returns None), which
is exact everywhere. The derivative dq/dtheta that maps the covariance from coef to rho
comes from the grid's spline (the exact quadrature has square-root cusps where nodes
cross the critical angle; the spline follows the trend, which is the physical
derivative), or, outside the grid, from central differences of the exact q with a 1e-3
relative step.
"""

from __future__ import annotations

import time

import numpy as np

from . import _loss
from ._lm import levenberg_marquardt

__all__ = ["AffineKernel", "applicable", "fit_affine"]


def applicable(meas, model, space, loss, enforce_energy, use_fast) -> bool:
    """True when :func:`fit_affine` can serve this fit."""
    if use_fast is False or enforce_energy or loss not in ("chi2", "cosine"):
        return False
    if meas.n_channels != 3 or space.fixed:
        return False
    from gonio.models import _fast

    return _fast.affine_spec(model) is not None and _fast.available()


class AffineKernel:
    """Weighted sums of one dataset for batches of theta (see the module notes).

    Parameters
    ----------
    meas : Measurements
    model
        A model with ``_fast.affine_spec(model)``.
    space : ParameterSpace
        The fit's parameter vector (no fixed parameters).
    weight : ndarray, shape (N, C)
        Residual weights (1 / sigma for chi^2).
    rows : slice, optional
        Use only these rows (the global stage scores on a subset).
    """

    def __init__(self, meas, model, space, weight, rows=slice(None)):
        from gonio.models import _fast

        self.model, self.space, self.meas = model, space, meas
        self.coef_name, self.theta_names = _fast.affine_spec(model)
        self.lin_idx = np.array([i for i, e in enumerate(space.entries) if e.param == self.coef_name])
        self.nl_idx = np.array([next(i for i, e in enumerate(space.entries) if e.param == n)
                                for n in self.theta_names], dtype=int)
        use = meas.use[rows]
        self.use = use
        self.prep = _fast.prepare(meas.wi[rows], meas.wo[rows])
        w = np.where(use, weight[rows], 0.0)
        self.w = w
        self.y = np.where(use, meas.brdf[rows], 0.0)
        self.W2 = w * w
        self.WY = self.W2 * self.y
        self.SYY = np.sum(self.WY * self.y, axis=0)
        self.n_evals = 0

    # -- kernel
    def parts(self, thetas, tables=None):
        from gonio.models import _fast

        thetas = np.atleast_2d(thetas)
        self.n_evals += thetas.shape[0]
        return _fast.affine_parts(self.model, self.prep, thetas, tables)

    def coef_bounds(self, thetas, q=None):
        """Bounds of the coefficient per theta (K, C): the affine parameter's bounds / q."""
        q = approx_q(self.model, thetas) if q is None else q
        lo, hi = self.space.lower[self.lin_idx], self.space.upper[self.lin_idx]
        return lo[None, :] / q[:, None], hi[None, :] / q[:, None]

    def solve(self, thetas, parts=None, q=None):
        """Bounded least-squares coefficients and costs: (coef (K, C), cost (K, C), sums)."""
        base, basis = self.parts(thetas) if parts is None else parts
        A = (basis * basis) @ self.W2
        Bv = basis @ self.WY - (basis * base) @ self.W2
        C0 = self.SYY[None, :] - 2.0 * (base @ self.WY) + (base * base) @ self.W2
        free = np.where(A > 0, Bv / np.where(A > 0, A, 1.0), 0.0)
        lo, hi = self.coef_bounds(np.atleast_2d(thetas), q)
        coef = np.clip(free, lo, hi)
        cost = np.maximum(C0 - 2.0 * coef * Bv + coef * coef * A, 0.0)
        return coef, cost, (A, Bv, C0, lo, hi)

    def residuals(self, base, basis, coef):
        """Weighted residuals w (f - y) of the used values, flattened like ``meas.use``."""
        f = base[:, None] + basis[:, None] * coef[None, :]
        return (self.w * (f - self.y))[self.use]


def approx_q(model, thetas):
    """q(theta) for the iterations: the grid interpolation of R_int where there is one
    (roughplastic), else exact."""
    from gonio.models import _fast
    from gonio.models._rough_tables import _interp

    thetas = np.atleast_2d(thetas)
    if model.name != "roughplastic":
        return np.ones(thetas.shape[0])
    kind = model.options["distribution"]
    out = np.empty(thetas.shape[0])
    for k, (a, e) in enumerate(thetas):
        g = _interp(kind, a, e, tol=np.inf)
        out[k] = (1.0 - g[1]) if g is not None else _fast.affine_q(model, [[a, e]])[0]
    return out


def q_gradient(model, theta):
    """dq/dtheta at theta (T,): grid spline where available, else central differences of
    the exact q with a 1e-3 relative step (see the module notes)."""
    from gonio.models import _fast
    from gonio.models._rough_tables import _interp

    theta = np.asarray(theta, dtype=np.float64)
    if model.name != "roughplastic":
        return np.zeros(theta.size)
    g = _interp(model.options["distribution"], theta[0], theta[1], grad=True, tol=np.inf)
    if g is not None:
        return -np.array([g[2][-1], g[3][-1]])
    out = np.empty(2)
    for j in range(2):
        h = 1e-3 * theta[j]
        tp, tm = theta.copy(), theta.copy()
        tp[j] += h
        tm[j] -= h
        qp, qm = _fast.affine_q(model, [tp, tm])
        out[j] = (qp - qm) / (2.0 * h)
    return out


_CONTROLLER = None


def single_threaded_blas():
    """Context manager holding BLAS to one thread.

    The kernels run on Dr.Jit's thread pool (one thread per core); OpenBLAS's own threads
    keep spinning for a while after each small matrix product, and on a 2-core machine the
    two pools then fight: the same 10^4-point kernel call took 0.7 ms or 5-8 ms at random
    (median fit 150 ms; 58 ms with BLAS held to one thread). The products here are small,
    so one BLAS thread costs nothing.
    """
    global _CONTROLLER
    from threadpoolctl import ThreadpoolController

    if _CONTROLLER is None:
        _CONTROLLER = ThreadpoolController()
    return _CONTROLLER.limit(limits=1, user_api="blas")


def fit_affine(meas, model, space, loss, rng, **options):
    """The fit on the fast path; returns a FitResult, or None to hand over to the general path."""
    with single_threaded_blas():
        return _fit_affine(meas, model, space, loss, rng, **options)


def _fit_affine(meas, model, space, loss, rng, *, n_starts=None, n_local=3, maxeval=2000,
                score_rows=3000, start_ratio=30.0, basin_distance=0.15):
    from ._optimise import FitResult, _laplace, _stratified, choose_starts

    t0 = time.perf_counter()
    cos_i = np.broadcast_to(np.clip(meas.wi[:, 2:3], 0.0, 1.0), meas.brdf.shape)
    weight = 1.0 / meas.brdf_std if loss == "chi2" else cos_i
    kern = AffineKernel(meas, model, space, weight)
    stride = max(1, int(np.ceil(meas.n_points / score_rows)))
    scorer = kern if stride == 1 else AffineKernel(meas, model, space, weight, slice(None, None, stride))
    nl = kern.nl_idx
    T = nl.size

    def theta_of(v):
        u = np.zeros(space.size)
        u[nl] = v
        return space.from_unit(u)[nl]

    # ---- global stage: all starts in one kernel call
    u_default = space.to_unit(space.default())[nl]
    if n_starts is None:
        n_starts = min(24, 4 + 4 * T)
    starts = [u_default] + list(_stratified(rng, n_starts if T else 0, T))
    _, costs, _ = scorer.solve(np.array([theta_of(v) for v in starts]).reshape(len(starts), T))
    scores = costs.sum(axis=1)
    chosen = choose_starts(starts, scores, n_local, start_ratio, basin_distance)

    # ---- local stage
    cache = {}

    def fun(v):
        th = theta_of(v)[None, :]
        parts = kern.parts(th)
        coef = kern.solve(th, parts)[0][0]
        cache["v"], cache["parts"], cache["coef"] = v.copy(), parts, coef
        return kern.residuals(parts[0][0], parts[1][0], coef)

    def jac(v, r, h=1e-6):
        if cache.get("v") is None or not np.array_equal(cache["v"], v):
            fun(v)
        base0, basis0 = cache["parts"][0][0], cache["parts"][1][0]
        coef = cache["coef"]
        steps = np.where(v + h <= 1.0, h, -h)
        shifted = np.array([theta_of(v + steps[j] * np.eye(T)[j]) for j in range(T)])
        base, basis = kern.parts(shifted)
        dF = ((base - base0)[:, :, None] + (basis - basis0)[:, :, None] * coef[None, None, :]) / steps[:, None, None]
        J = kern.w[:, :, None] * np.moveaxis(dF, 0, -1)  # (N, C, T)
        # Kaufman: project off the coefficient columns that are free (not at a bound)
        lo, hi = kern.coef_bounds(theta_of(v)[None, :])
        for c in range(kern.w.shape[1]):
            if lo[0, c] < coef[c] < hi[0, c]:
                bc = kern.w[:, c] * basis0
                n2 = float(bc @ bc)
                if n2 > 0:
                    J[:, c, :] -= np.outer(bc, bc @ J[:, c, :]) / n2
        J = J[kern.use]
        return J

    atol = 1e-4 if loss == "chi2" else 0.0
    best = None
    n_lm = 0
    for k in chosen:
        if T == 0:
            best = (np.zeros(0), float(kern.solve(np.zeros((1, 0)))[1].sum()), True, "linear least squares (exact)")
            break
        n0 = kern.n_evals

        def budget(n0=n0):
            return kern.n_evals - n0 < maxeval

        def abandon(it, cost, best=best):
            return best is not None and ((it >= 1 and cost > start_ratio * best[1] + 10.0)
                                         or (it >= 2 and cost > 1.5 * best[1] + 10.0))

        lm = levenberg_marquardt(fun, starts[k], atol=atol, budget=budget, abandon=abandon, jac=jac)
        n_lm += 1
        if best is None or lm.cost < best[1]:
            best = (lm.u.copy(), lm.cost, lm.converged, lm.message)
    v, _, converged, message = best
    theta = theta_of(v)

    # ---- back to the model's own parameters, exactly
    from gonio.models import _fast

    parts = kern.parts(theta[None, :])
    q_approx = approx_q(model, theta[None, :])
    coef, _, (_, _, _, lo, hi) = kern.solve(theta[None, :], parts, q_approx)
    coef = coef[0]
    if np.any((coef >= hi[0] * (1.0 - 1e-12)) & (hi[0] > 0)):
        return None  # resting on the approximate upper bound: the general path decides exactly
    q = float(_fast.affine_q(model, theta[None, :])[0])
    rho = coef * q
    lin_lo, lin_hi = space.lower[kern.lin_idx], space.upper[kern.lin_idx]
    if np.any(rho > lin_hi + 1e-12) or np.any(rho < lin_lo - 1e-12):
        return None
    rho = np.clip(rho, lin_lo, lin_hi)
    x = np.empty(space.size)
    x[kern.lin_idx] = rho
    x[nl] = theta

    # ---- Laplace covariance from the chi^2 Jacobian in natural units
    base0, basis0 = parts[0][0], parts[1][0]
    sig_w = np.where(meas.use, 1.0 / meas.brdf_std, 0.0)
    y = np.where(meas.use, meas.brdf, 0.0)
    f0 = base0[:, None] + basis0[:, None] * coef[None, :]
    r_chi = (sig_w * (f0 - y))[meas.use]
    J = np.zeros((r_chi.size, space.size))
    for c, i in enumerate(kern.lin_idx):
        col = np.zeros_like(f0)
        col[:, c] = basis0 * sig_w[:, c] / q
        J[:, i] = col[meas.use]
    if T:
        scale = np.maximum(np.abs(theta), 1e-3 * (space.upper[nl] - space.lower[nl]))
        hstep = 1e-5 * scale
        up = np.minimum(theta + hstep, space.upper[nl])
        dn = np.maximum(theta - hstep, space.lower[nl])
        pts = np.concatenate([theta[None, :] + np.diag(up - theta), theta[None, :] + np.diag(dn - theta)])
        b_all, bs_all = kern.parts(pts)
        dq = q_gradient(model, theta)
        for j in range(T):
            df = ((b_all[j] - b_all[T + j])[:, None] + (bs_all[j] - bs_all[T + j])[:, None] * coef[None, :])
            col = df * sig_w / (up[j] - dn[j])
            # at fixed rho the coefficient moves with q: d coef / d theta_j = -coef dq_j / q
            col = col - basis0[:, None] * sig_w * (coef * dq[j] / q)[None, :]
            J[:, nl[j]] = col[meas.use]
    if not np.all(np.isfinite(J)):
        return None
    cov, undetermined = _laplace(J, space)
    std = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    r_obj = (kern.w * (f0 - y))[meas.use]
    diff = (f0 - meas.brdf)[meas.use]
    cos_u = cos_i[meas.use]
    return FitResult(
        model=model, space=space, x=x, std=std, cov=cov, loss=loss, objective=_loss.objective(loss, r_obj),
        chi2=float(r_chi @ r_chi), n_used=meas.n_used, n_evals=int(kern.n_evals + (scorer.n_evals if scorer is not kern else 0)),
        time_s=time.perf_counter() - t0, converged=bool(converged), message=message,
        at_bound=[n for n, b in zip(space.names, space.at_bound(x)) if b],
        undetermined=undetermined,
        energy={"enforced": False, "max_albedo": None, "holds": True, "by_construction": True},
        rmse_fr=float(np.sqrt(np.mean(diff ** 2))), rmse_cos_fr=float(np.sqrt(np.mean((diff * cos_u) ** 2))),
        method=("variable projection + Levenberg-Marquardt" if T else "linear least squares")
        + " [drjit-llvm, batched affine kernel]",
        linear=[kern.coef_name],
    )
