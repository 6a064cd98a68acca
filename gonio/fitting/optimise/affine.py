"""The fit's fast path for models affine in one per-channel parameter.

Models that declare an affine per-channel parameter (``model.structure.affine``: the
coefficient, theta, q and dq/dtheta; today ``diffuse``, ``orennayar`` and ``roughplastic``
with ``nonlinear=False``) have

    f_r[c] = base(theta) + coef[c] * basis(theta)

with base and basis the same in every channel (:func:`gonio.models.fast.affine_parts`).
Variable projection then needs, per trial theta, only five weighted sums per channel, and the
kernel evaluates many thetas in one call. :class:`AffineFit` is this reduced problem for the
one fit loop (:func:`gonio.fitting.optimise.mle.refine_starts`). An answer whose coefficient
rests on an approximate bound, or whose exact parameters leave their bounds, is handed back to
the general path (``AffineFit.result`` is None), which is exact everywhere.
"""

# The sums are sum w^2 b^2, sum w^2 b y, sum w^2 b s, ... The loop: a stratified global
# stage, Levenberg-Marquardt on the reduced residuals (Kaufman's Jacobian) from the best starts
# in distinct basins, the Laplace covariance; every batch of thetas (the starts; theta and its
# forward-difference neighbours; the central differences at the optimum) is one kernel call.
# roughplastic's coefficient is rho / (1 - R_int(alpha, eta)), so the 128 x 128 quadrature of
# R_int is needed only at the end: rho = coef * q(theta*), q = 1 - R_int, computed exactly
# once (gonio.models.fast.affine_q). During the iterations the bound rho <= 1 becomes
# coef <= 1 / q with q from the precomputed grid (a few 1e-2 at worst); an answer whose
# coefficient rests on that approximate bound, or whose exact rho leaves its bounds, goes to
# the general path. The derivative dq/dtheta that maps the covariance from coef to rho comes
# from the grid's spline (the exact quadrature has square-root cusps where nodes cross the
# critical angle; the spline follows the trend, which is the physical derivative), or,
# outside the grid, from central differences of the exact q with a 1e-3 relative step.

from __future__ import annotations

import time

import numpy as np
from threadpoolctl import ThreadpoolController

from gonio.models import fast

from gonio.fitting.likelihood import loss as _loss
from gonio.fitting.optimise.lm import levenberg_marquardt
from gonio.fitting.optimise.result import FitResult, laplace
from gonio.fitting.optimise.starts import stratified

__all__ = ["AffineFit", "AffineKernel", "applicable", "single_threaded_blas"]


def applicable(meas, model, space, loss, enforce_energy, use_fast) -> bool:
    """True when :func:`fit_affine` can serve this fit."""
    if use_fast is False or enforce_energy or loss not in ("chi2",) + _loss.WEIGHTED_L2:
        return False
    if meas.n_channels != 3 or space.fixed:
        return False
    return fast.affine_spec(model) is not None and fast.available()


class AffineKernel:
    """Weighted sums of one dataset for batches of theta (see the module notes).

    Parameters
    ----------
    meas : Measurements
    model
        A model with ``fast.affine_spec(model)``.
    space : ParameterSpace
        The fit's parameter vector (no fixed parameters).
    weight : ndarray, shape (N, C)
        Residual weights (1 / sigma for chi^2).
    rows : slice, optional
        Use only these rows (the global stage scores on a subset).
    """

    def __init__(self, meas, model, space, weight, rows=slice(None)):
        self.model, self.space, self.meas = model, space, meas
        self.coef_name, self.theta_names = fast.affine_spec(model)
        self.lin_idx = np.array([i for i, e in enumerate(space.entries) if e.param == self.coef_name])
        self.nl_idx = np.array([next(i for i, e in enumerate(space.entries) if e.param == n)
                                for n in self.theta_names], dtype=int)
        use = meas.use[rows]
        self.use = use
        self.prep = fast.prepare(meas.wi[rows], meas.wo[rows])
        w = np.where(use, weight[rows], 0.0)
        self.w = w
        self.y = np.where(use, meas.brdf[rows], 0.0)
        self.W2 = w * w
        self.WY = self.W2 * self.y
        self.SYY = np.sum(self.WY * self.y, axis=0)
        self.n_evals = 0

    # -- kernel
    def parts(self, thetas, tables=None):
        thetas = np.atleast_2d(thetas)
        self.n_evals += thetas.shape[0]
        return fast.affine_parts(self.model, self.prep, thetas, tables)

    def tables(self, thetas):
        """The model's parameter-dependent tables at thetas (K, T), exactly (``fast.affine_tables``)."""
        return fast.affine_tables(self.model, np.atleast_2d(thetas))

    def exact_q(self, thetas):
        """q at thetas (K, T), exactly (``fast.affine_q``; 1 for a model without tables)."""
        return fast.affine_q(self.model, np.atleast_2d(thetas))

    def sums(self, parts):
        """Per (theta, channel) of ``parts = (base, basis)``: ``A = sum w^2 b^2``,
        ``Bv = sum w^2 b (y - s)`` and ``C0 = sum w^2 (y - s)^2`` (b the basis, s the base):
        the cost of a coefficient a is ``C0 - 2 a Bv + a^2 A``."""
        base, basis = parts
        A = (basis * basis) @ self.W2
        Bv = basis @ self.WY - (basis * base) @ self.W2
        C0 = self.SYY[None, :] - 2.0 * (base @ self.WY) + (base * base) @ self.W2
        return A, Bv, C0

    def coef_bounds(self, thetas, q=None):
        """Bounds of the coefficient per theta (K, C): the affine parameter's bounds / q."""
        q = approx_q(self.model, thetas) if q is None else q
        lo, hi = self.space.lower[self.lin_idx], self.space.upper[self.lin_idx]
        return lo[None, :] / q[:, None], hi[None, :] / q[:, None]

    def solve(self, thetas, parts=None, q=None):
        """Bounded least-squares coefficients and costs: (coef (K, C), cost (K, C), sums)."""
        A, Bv, C0 = self.sums(self.parts(thetas) if parts is None else parts)
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
    """q(theta) for the iterations, as the model declares it (``structure.affine``)."""
    return model.structure.affine.approx_q(thetas)


def q_gradient(model, theta):
    """dq/dtheta at theta (T,), as the model declares it (``structure.affine``)."""
    return model.structure.affine.q_grad(theta)


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

    if _CONTROLLER is None:
        _CONTROLLER = ThreadpoolController()
    return _CONTROLLER.limit(limits=1, user_api="blas")


#: the least number of starts the affine problem's global stage scores. A score is one bounded
#: linear solve per channel, all starts in one kernel call (256 starts: 30-60 ms at 55-1053
#: points), so the starts can cover the few nonlinear parameters' box densely: on sparse data a
#: plastic's specular basin can be a few hundredths of the box wide beside a plateau of
#: invisible coats, and 12 starts found it 3 times in 10 (docs/performance.md, issue 38)
SCORED = 256


class AffineFit:
    """The affine-reduced problem for :func:`gonio.fitting.optimise.mle.refine_starts`.

    The optimiser sees only theta (the nonlinear parameters, unit box); the per-channel
    coefficient is solved for each trial theta; the result maps it back to the model's own
    parameter exactly, or hands over (None) where the approximate bound decided it.
    """

    def __init__(self, meas, model, space, loss, score_rows=3000):
        self.meas, self.model, self.space, self.loss = meas, model, space, loss
        self.cos_i = np.broadcast_to(np.clip(meas.wi[:, 2:3], 0.0, 1.0), meas.brdf.shape)
        weight = (1.0 / meas.brdf_std if loss == "chi2" else np.broadcast_to(_loss.fixed_weight(loss, meas), meas.brdf.shape)) * _loss.value_weight(meas)
        self.kern = kern = AffineKernel(meas, model, space, weight)
        stride = max(1, int(np.ceil(meas.n_points / score_rows)))
        self.scorer = kern if stride == 1 else AffineKernel(meas, model, space, weight, slice(None, None, stride))
        self.nl = kern.nl_idx
        self.T = self.nl.size
        self.atol = 1e-4 if loss == "chi2" else 0.0
        self.ftol = 1e-10
        self._cache = {}
        self.handover = None

    @property
    def n_evals(self):
        return self.kern.n_evals

    def theta_of(self, v):
        u = np.zeros(self.space.size)
        u[self.nl] = v
        return self.space.from_unit(u)[self.nl]

    def starts(self, n_starts, rng):
        """The defaults and at least :data:`SCORED` Latin-hypercube starts (none with ``n_starts``
        0), all scored in one kernel call."""
        T = self.T
        u_default = self.space.to_unit(self.space.default())[self.nl]
        if n_starts is None:
            n_starts = min(24, 4 + 4 * T)
        if n_starts > 0:
            n_starts = max(n_starts, SCORED)
        starts = [u_default] + list(stratified(rng, n_starts if T else 0, T))
        _, costs, _ = self.scorer.solve(np.array([self.theta_of(v) for v in starts]).reshape(len(starts), T))
        return starts, costs.sum(axis=1)

    def _fun(self, v):
        kern, cache = self.kern, self._cache
        th = self.theta_of(v)[None, :]
        parts = kern.parts(th)
        coef = kern.solve(th, parts)[0][0]
        cache["v"], cache["parts"], cache["coef"] = v.copy(), parts, coef
        return kern.residuals(parts[0][0], parts[1][0], coef)

    def _jac(self, v, r, h=1e-6):
        kern, cache, T = self.kern, self._cache, self.T
        if cache.get("v") is None or not np.array_equal(cache["v"], v):
            self._fun(v)
        base0, basis0 = cache["parts"][0][0], cache["parts"][1][0]
        coef = cache["coef"]
        steps = np.where(v + h <= 1.0, h, -h)
        shifted = np.array([self.theta_of(v + steps[j] * np.eye(T)[j]) for j in range(T)])
        base, basis = kern.parts(shifted)
        dF = ((base - base0)[:, :, None] + (basis - basis0)[:, :, None] * coef[None, None, :]) / steps[:, None, None]
        J = kern.w[:, :, None] * np.moveaxis(dF, 0, -1)  # (N, C, T)
        # Kaufman: project off the coefficient columns that are free (not at a bound)
        lo, hi = kern.coef_bounds(self.theta_of(v)[None, :])
        for c in range(kern.w.shape[1]):
            if lo[0, c] < coef[c] < hi[0, c]:
                bc = kern.w[:, c] * basis0
                n2 = float(bc @ bc)
                if n2 > 0:
                    J[:, c, :] -= np.outer(bc, bc @ J[:, c, :]) / n2
        return J[kern.use]

    def refine(self, start, budget, abandon):
        if self.T == 0:
            return (np.zeros(0), float(self.kern.solve(np.zeros((1, 0)))[1].sum()), True, "linear least squares (exact)")
        lm = levenberg_marquardt(self._fun, start, atol=self.atol, ftol=self.ftol, budget=budget, abandon=abandon,
                                 jac=self._jac)
        return (lm.u.copy(), lm.cost, lm.converged, lm.message)

    def result(self, best, t0):
        """The FitResult in the model's own parameters, or None to hand over to the general path
        (an approximate bound decided a coefficient, or the Laplace Jacobian is not finite); then
        :attr:`handover` is the best refined point's parameters (the coefficients clipped to their
        bounds; None where not finite), for the general path to start from: the basin this stage
        found, not a new search."""
        v, _, converged, message = best
        theta = self.theta_of(v)
        x, exact = self._parameters(theta)
        if exact:
            coef, parts, q = self._solution
            J = self._laplace_jacobian(theta, coef, parts, q)
            if np.all(np.isfinite(J)):
                return self._assemble(x, J, coef, parts, t0, converged, message)
        self.handover = x if np.all(np.isfinite(x)) else None
        return None

    def _parameters(self, theta):
        """``(x, exact)``: x in natural units from theta (rho = coef * q, clipped to its bounds);
        ``exact`` False where the approximate upper bound decided a coefficient or the exact rho
        leaves its bounds: the general path then decides exactly."""
        kern, space, model = self.kern, self.space, self.model
        parts = kern.parts(theta[None, :])
        q_approx = approx_q(model, theta[None, :])
        coef, _, (_, _, _, lo, hi) = kern.solve(theta[None, :], parts, q_approx)
        coef = coef[0]
        on_bound = np.any((coef >= hi[0] * (1.0 - 1e-12)) & (hi[0] > 0))
        q = float(kern.exact_q(theta[None, :])[0])
        rho = coef * q
        lin_lo, lin_hi = space.lower[kern.lin_idx], space.upper[kern.lin_idx]
        outside = np.any(rho > lin_hi + 1e-12) or np.any(rho < lin_lo - 1e-12)
        x = np.empty(space.size)
        x[kern.lin_idx] = np.clip(rho, lin_lo, lin_hi)
        x[self.nl] = theta
        self._solution = (coef, parts, q)
        return x, not (on_bound or outside)

    def _laplace_jacobian(self, theta, coef, parts, q):
        """The chi^2 Jacobian in natural units at the optimum (theta by central differences,
        one kernel call; at fixed rho the coefficient moves with q)."""
        meas, space, kern, nl, T = self.meas, self.space, self.kern, self.nl, self.T
        base0, basis0 = parts[0][0], parts[1][0]
        sig_w = np.where(meas.use, _loss.value_weight(meas) / meas.brdf_std, 0.0)
        f0 = base0[:, None] + basis0[:, None] * coef[None, :]
        J = np.zeros((int(meas.use.sum()), space.size))
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
            dq = q_gradient(self.model, theta)
            for j in range(T):
                df = ((b_all[j] - b_all[T + j])[:, None] + (bs_all[j] - bs_all[T + j])[:, None] * coef[None, :])
                col = df * sig_w / (up[j] - dn[j])
                # at fixed rho the coefficient moves with q: d coef / d theta_j = -coef dq_j / q
                col = col - basis0[:, None] * sig_w * (coef * dq[j] / q)[None, :]
                J[:, nl[j]] = col[meas.use]
        return J

    def _assemble(self, x, J, coef, parts, t0, converged, message):
        meas, space, kern, loss = self.meas, self.space, self.kern, self.loss
        base0, basis0 = parts[0][0], parts[1][0]
        sig_w = np.where(meas.use, _loss.value_weight(meas) / meas.brdf_std, 0.0)
        y = np.where(meas.use, meas.brdf, 0.0)
        f0 = base0[:, None] + basis0[:, None] * coef[None, :]
        r_chi = (sig_w * (f0 - y))[meas.use]
        cov, undetermined = laplace(J, space)
        std = np.sqrt(np.clip(np.diag(cov), 0.0, None))
        r_obj = (kern.w * (f0 - y))[meas.use]
        diff = (f0 - meas.brdf)[meas.use]
        cos_u = self.cos_i[meas.use]
        n_evals = kern.n_evals + (self.scorer.n_evals if self.scorer is not kern else 0)
        return FitResult(
            model=self.model, space=space, x=x, std=std, cov=cov, loss=loss, objective=_loss.objective(loss, r_obj),
            chi2=float(r_chi @ r_chi), n_used=meas.n_used, n_evals=int(n_evals),
            time_s=time.perf_counter() - t0, converged=bool(converged), message=message,
            at_bound=[n for n, b in zip(space.names, space.at_bound(x)) if b],
            undetermined=undetermined,
            energy={"enforced": False, "max_albedo": None, "holds": True, "by_construction": True},
            rmse_fr=float(np.sqrt(np.mean(diff ** 2))), rmse_cos_fr=float(np.sqrt(np.mean((diff * cos_u) ** 2))),
            method=("variable projection + Levenberg-Marquardt" if self.T else "linear least squares")
            + " [drjit-llvm, batched affine kernel]",
            linear=[kern.coef_name],
        )
