"""Posterior sampling with emcee, and an honest account of whether the chain is long enough.

Likelihood: the data's Gaussian noise model, ln L = -chi^2 / 2. Prior: uniform over the box
of the model's declared bounds (ln prior = -inf outside). Walkers start in a small Gaussian
ball drawn from the Laplace covariance around the optimum. The chain runs in chunks until it
is longer than 50 integrated autocorrelation times tau for every parameter (Goodman & Weare
2010; Foreman-Mackey et al. 2013, sec. 3; emcee's ``autocorr.integrated_time``) or the step
budget is spent; a shorter chain is *not* reported as a posterior (``converged`` is False and
``advice`` says how many steps would be needed). Affine per-channel parameters are
integrated out analytically (collapsed sampling, Liu 1994) and drawn exactly afterwards.
Proposals: emcee's differential-evolution moves (80 % DEMove, 20 % DESnookerMove; ter Braak
2006, ter Braak & Vrugt 2008) rather than its default stretch move.
"""

# Collapsed sampling: where the fit found parameters in which f_r is affine, one per channel
# (the albedo of roughplastic, Oren-Nayar), for a flat prior on [lo, hi] the marginal
# likelihood of the nonlinear parameters theta is, per channel,
# exp(-chi2_min(theta) / 2) sqrt(2 pi) s [Phi((hi - m) / s) - Phi((lo - m) / s)], with m and s
# the weighted least-squares estimate and its 1-sigma at theta. emcee samples theta only (2
# dimensions instead of 5 for roughplastic: shorter autocorrelation, fewer walkers), and each
# kept theta gets its affine parameters drawn exactly from their conditional truncated
# normal. The draws are exact posterior draws, not an approximation (Liu 1994, collapsed
# Gibbs). Why DE moves: docs/performance.md, gonio.fitting.uncertainty.posterior.
# References:
# Liu, J. S. (1994). The collapsed Gibbs sampler in Bayesian computations. JASA 89, 958-966.
# ter Braak, C. J. F. (2006). A Markov chain Monte Carlo version of the genetic algorithm
# Differential Evolution. Statistics and Computing 16, 239-249.
# ter Braak, C. J. F., Vrugt, J. A. (2008). Differential Evolution Markov Chain with snooker
# updater and fewer chains. Statistics and Computing 18, 435-446.

from __future__ import annotations

import dataclasses
import time

import numpy as np

from scipy.special import log_ndtr, ndtr, ndtri

from gonio.fitting.likelihood import loss as _loss
from gonio.fitting.optimise.affine import AffineFit, applicable, single_threaded_blas
from gonio.fitting.uncertainty.ensemble import Ensemble
from gonio.fitting.likelihood.problem import Problem as _Problem

__all__ = ["Posterior", "sample_posterior"]


@dataclasses.dataclass
class Posterior:
    names: list
    converged: bool
    n_walkers: int
    n_steps: int
    tau: np.ndarray
    n_independent: float
    samples: np.ndarray          # (n_samples, P), burn-in dropped and thinned by tau/2
    quantiles: dict              # percent -> (P,) values, for 5, 16, 50, 84, 95
    acceptance: float
    time_s: float
    advice: str
    #: Largest relative error of the sampler's local table interpolant (roughplastic), or None.
    surrogate_error: dict | None = None

    def interval(self, level: float = 90.0) -> np.ndarray:
        lo, hi = 50.0 - level / 2, 50.0 + level / 2
        return np.stack([np.percentile(self.samples, lo, axis=0), np.percentile(self.samples, hi, axis=0)], axis=-1)


def sample_posterior(meas, result, *, rng, n_walkers: int = 32, max_steps: int = 20000,
                     chunk: int = 500, tau_multiple: float = 50.0, time_budget_s: float | None = None,
                     collapse: bool = True) -> Posterior:
    """Sample the posterior of a finished chi^2 fit (``result`` from :func:`fit`).

    Parameters
    ----------
    rng : numpy.random.Generator
        Seeds the walkers' start and emcee's own random state.
    max_steps : int
        Step budget; sampling stops earlier once the chain exceeds ``tau_multiple`` tau.
    time_budget_s : float, optional
        Wall-time budget; a chain cut short by it is reported as not converged.
    collapse : bool
        Integrate one-per-channel affine parameters out analytically (see the module notes).
    """
    import emcee

    space, model = result.space, result.model

    affine = None
    if collapse and applicable(meas, model, space, "chi2", False, None) and model.structure.affine.theta:
        affine = _AffinePosterior(meas, result)
        collapsed = True
        sub = affine.nl
    else:
        problem = _Problem(meas, model, space, "chi2")
        groups_per_channel = len(problem.linear)
        collapsed = bool(collapse and problem.varpro and groups_per_channel == 1 and 0 < problem.nl_idx.size)
        sub = problem.nl_idx if collapsed else np.arange(space.size)
    P = sub.size
    lower, upper = space.lower[sub], space.upper[sub]

    full_x, log_prob = (None, None) if affine is not None else _log_prob(meas, result, problem, sub, collapsed)

    n_walkers = max(n_walkers, 2 * P + 2)
    start = _walker_start(result, sub, lower, upper, n_walkers, rng)

    # differential-evolution proposals (ter Braak 2006; ter Braak & Vrugt 2008's snooker
    # update), mixed as in emcee's documentation: on the bench's roughplastic posterior the
    # integrated autocorrelation time drops from 26.7 steps (emcee's default stretch move)
    # to 7.6, so a chain reaches 50 tau in a third of the steps
    moves = [(emcee.moves.DEMove(), 0.8), (emcee.moves.DESnookerMove(), 0.2)]
    # emcee's EnsembleSampler, draw for draw, without its per-step bookkeeping (_ensemble)
    sampler = Ensemble(affine or log_prob, start, moves, int(rng.integers(2**32 - 1)))
    t0 = time.perf_counter()
    tau, converged = _run_chain(sampler, P, chunk, max_steps, tau_multiple, time_budget_s, t0)
    n_steps = sampler.iteration
    tau_max = float(np.max(tau)) if np.all(np.isfinite(tau)) else float(n_steps)
    burn = int(min(n_steps // 2, 3 * tau_max))
    thin = max(1, int(tau_max / 2))
    samples = sampler.backend.get_chain(discard=burn, thin=thin, flat=True)
    if affine is not None:  # each kept theta gets its affine parameters from the exact conditional
        with single_threaded_blas():
            samples = affine.draw(samples, rng)
    elif collapsed:
        samples = np.array([_collapsed(problem, full_x(t), rng)[1] for t in samples])
    n_independent = (n_steps - burn) * n_walkers / max(tau_max, 1.0)
    advice = "" if converged else (
        f"chain of {n_steps} steps is shorter than {tau_multiple:.0f} tau (tau ~ {tau_max:.0f}): "
        f"run at least {int(tau_multiple * tau_max * 1.2)} steps before trusting these intervals")
    quantiles = {q: np.percentile(samples, q, axis=0) for q in (5, 16, 50, 84, 95)}
    return Posterior(names=space.names, converged=converged, n_walkers=n_walkers, n_steps=n_steps,
                     tau=np.asarray(tau), n_independent=float(n_independent), samples=samples,
                     quantiles=quantiles, acceptance=float(np.mean(sampler.acceptance_fraction)),
                     time_s=time.perf_counter() - t0, advice=advice,
                     surrogate_error=affine.surrogate_error if affine is not None else None)


def _log_prob(meas, result, problem, sub, collapsed):
    """(full_x, log_prob): the full parameter vector of a sampled sub-vector, and the
    vectorised log posterior (flat prior inside the bounds; collapsed: the affine
    parameter integrated out)."""
    lower, upper = result.space.lower[sub], result.space.upper[sub]

    def full_x(xs_row):
        x = result.x.copy()
        x[sub] = xs_row
        return x

    def log_prob(xs):
        xs = np.atleast_2d(xs)
        out = np.full(xs.shape[0], -np.inf)
        inside = np.all((xs >= lower) & (xs <= upper), axis=1)
        for k in np.where(inside)[0]:
            if collapsed:
                out[k] = _collapsed(problem, full_x(xs[k]))[0]
            else:
                r = _loss.residuals("chi2", problem.f_x(full_x(xs[k])), meas)
                if np.all(np.isfinite(r)):
                    out[k] = -0.5 * float(r @ r)
        return out

    return full_x, log_prob


def _walker_start(result, sub, lower, upper, n_walkers, rng):
    """Walkers in a small ball (1e-2 Laplace sigma) about the optimum, inside the bounds."""
    scale = np.sqrt(np.clip(np.diag(result.cov)[sub], 1e-24, None))
    start = result.x[sub] + 1e-2 * scale * rng.standard_normal((n_walkers, sub.size))
    span = upper - lower
    return np.clip(start, lower + 1e-9 * span, upper - 1e-9 * span)


def _run_chain(sampler, P, chunk, max_steps, tau_multiple, time_budget_s, t0):
    """Run the ensemble in chunks until it exceeds ``tau_multiple`` tau, the step budget or
    the time budget; returns (tau, converged)."""
    tau = np.full(P, np.inf)
    while sampler.iteration < max_steps:
        with single_threaded_blas():
            sampler.run(chunk)
        tau = sampler.backend.get_autocorr_time(tol=0)
        if np.all(np.isfinite(tau)) and sampler.iteration > tau_multiple * np.max(tau):
            return tau, True
        if time_budget_s is not None and time.perf_counter() - t0 > time_budget_s:
            break
    return tau, False


def _collapsed(problem, x, rng=None):
    """Log marginal likelihood of x's nonlinear part with the per-channel affine parameter
    integrated over its bounds (flat prior), and, with ``rng``, x with that parameter drawn
    from its conditional truncated normal."""
    space, meas = problem.space, problem.meas
    base, cols = problem.basis(x)
    B = cols[0]
    g = problem.linear[0]
    w = problem.weight
    logp = 0.0
    x = x.copy()
    for c in range(base.shape[1]):
        m = problem.use[:, c]
        wb, wr = w[m, c] * B[m, c], w[m, c] * (meas.brdf[m, c] - base[m, c])
        a = float(wb @ wb)
        if not (a > 0 and np.all(np.isfinite(wr))):
            return -np.inf, x
        mu, sd = float(wb @ wr) / a, 1.0 / np.sqrt(a)
        i = g["index"][c]
        lo, hi = (space.lower[i] - mu) / sd, (space.upper[i] - mu) / sd
        chi2_min = float(wr @ wr) - a * mu * mu
        # log(Phi(hi) - Phi(lo)), stably in either tail
        if lo > 0:
            mass = log_ndtr(-lo) + np.log1p(-np.exp(min(log_ndtr(-hi) - log_ndtr(-lo), 0.0)) + 1e-300)
        else:
            mass = log_ndtr(hi) + np.log1p(-np.exp(min(log_ndtr(lo) - log_ndtr(hi), 0.0)) + 1e-300)
        logp += -0.5 * chi2_min + np.log(sd) + mass
        if rng is not None:
            p_lo, p_hi = ndtr(lo), ndtr(hi)
            z = ndtri(np.clip(p_lo + rng.random() * (p_hi - p_lo), 1e-300, 1 - 1e-16))
            x[i] = np.clip(mu + sd * z, space.lower[i], space.upper[i])
    return float(logp), x


class _AffinePosterior:
    """Collapsed log posterior of theta, batched over walkers, for the models that declare an
    affine per-channel parameter (``model.structure.affine``), one kernel call per half-ensemble.

    It reads the model through the fit loop's own affine problem (:class:`~gonio.fitting.optimise.affine.AffineFit`:
    its kernel's weighted sums, coefficient bounds, exact tables and q), so the likelihood is the
    fit's chi^2, residual weights included, and nothing here knows a model by name.

    The walkers stay within a few sigma of the optimum, where roughplastic's transmittance
    table t(theta) and q(theta) = 1 - R_int are smooth. Both are taken from a local
    tensor-product polynomial through exact values at n x n Chebyshev-Lobatto points over
    +-8 Laplace sigma (n = 3, 5 or 9: the first whose error at four other points of the box
    is below 1e-6 for t and 1e-4 for q; ``surrogate_error`` reports the errors of the one
    used). This removes the per-walker quadratures from the sampler's inner loop: the
    64 x 512-node table (4x the work of the data kernel at 10^4 points) and the
    64 x 8192-node R_int (4 ms a walker). Thetas outside the box, or a table error still
    above 1e-6 at n = 9, use the exact table; q then keeps the n = 9 interpolant (the
    cusps of the exact quadrature where nodes cross the critical angle, ~1e-5, bound how
    well any smooth interpolant can follow it) and its error is reported.
    """

    BOX_SIGMA = 8.0
    T_TOL = 1e-6
    Q_TOL = 1e-4

    def __init__(self, meas, result):
        self.model, self.space = result.model, result.space
        self.kern = AffineFit(meas, result.model, result.space, "chi2").kern
        nl = self.kern.nl_idx
        self.nl = nl
        self.lin_idx = self.kern.lin_idx
        self.lower, self.upper = self.space.lower[nl], self.space.upper[nl]
        self.box = None
        self.t_ok = False
        self.surrogate_error = None
        self.tables = bool(result.model.structure.affine.tables)  # (the model builds its structure anew per read)
        if not self.tables:  # no tables: nothing to interpolate
            return
        theta = result.x[nl]
        sd = np.sqrt(np.clip(np.diag(result.cov)[nl], 0.0, None))
        lo = np.maximum(self.lower, theta - self.BOX_SIGMA * sd)
        hi = np.minimum(self.upper, theta + self.BOX_SIGMA * sd)
        if not np.all(hi > lo):
            return
        check = lo + (hi - lo) * np.array([[0.3, 0.2], [0.8, 0.35], [0.15, 0.7], [0.6, 0.9]])
        t_ex, q_ex = self.kern.tables(check), self.kern.exact_q(check)
        for n in (3, 5, 9):
            c = 0.5 - 0.5 * np.cos(np.pi * np.arange(n) / (n - 1))  # Chebyshev-Lobatto in [0, 1]
            nodes = lo[:, None] + (hi - lo)[:, None] * c[None, :]
            pts = np.array([[a, b] for a in nodes[0] for b in nodes[1]])
            self.box = (lo, hi, [_lagrange_denominators(z) for z in nodes])
            self.node_t = self.kern.tables(pts)
            self.node_q = self.kern.exact_q(pts)
            t_s, q_s = self._interp(check)
            err_t = float(np.max(np.abs(t_s - t_ex) / np.maximum(np.abs(t_ex), 1e-12)))
            err_q = float(np.max(np.abs(q_s - q_ex) / q_ex))
            self.surrogate_error = {"t": err_t, "q": err_q, "nodes": n}
            self.t_ok = err_t <= self.T_TOL
            if self.t_ok and err_q <= self.Q_TOL:
                break

    def _weights(self, thetas):
        """Tensor-product Lagrange weights (K, n^T) of the box's nodes at thetas."""
        _, _, lagrange = self.box
        W = None
        for d, (z, off, den) in enumerate(lagrange):
            # L_j(x) = prod_{m != j} (x - z_m) / (z_j - z_m): the factors of m = j set to 1
            L = (np.where(off, thetas[:, d, None, None] - z, 1.0) / den).prod(axis=2)
            W = L if W is None else (W[:, :, None] * L[:, None, :]).reshape(thetas.shape[0], -1)
        return W

    def _interp(self, thetas):
        W = self._weights(thetas)
        return W @ self.node_t, W @ self.node_q

    def tables_q(self, thetas):
        """(tables or None, q) at thetas (K, T): interpolated inside the box, exact outside."""
        if not self.tables:
            return None, np.ones(thetas.shape[0])
        kern = self.kern
        if self.box is None:
            return kern.tables(thetas), kern.exact_q(thetas)
        lo, hi, _ = self.box
        inside = ((thetas >= lo) & (thetas <= hi)).all(axis=1)
        if inside.all():  # the walkers' usual case: no scatter into the rows inside
            t, q = self._interp(thetas)
            return (t if self.t_ok else kern.tables(thetas)), q
        t, q = np.empty((thetas.shape[0], self.node_t.shape[1])), np.empty(thetas.shape[0])
        if np.any(inside):
            t[inside], q[inside] = self._interp(thetas[inside])
            if not self.t_ok:
                t[inside] = kern.tables(thetas[inside])
        if np.any(~inside):
            t[~inside] = kern.tables(thetas[~inside])
            q[~inside] = kern.exact_q(thetas[~inside])
        return t, q

    def stats(self, thetas):
        """Per (theta, channel): mean and sd of the coefficient, chi2_min, bounds, and q."""
        t, q = self.tables_q(thetas)
        A, Bv, C0 = self.kern.sums(self.kern.parts(thetas, t))
        ok = A > 0
        Asafe = np.where(ok, A, 1.0)
        mu = Bv / Asafe
        sd = 1.0 / np.sqrt(Asafe)
        chi2_min = C0 - Bv * mu
        lo, hi = self.kern.coef_bounds(thetas, q)
        return mu, sd, chi2_min, lo, hi, q, ok

    def __call__(self, xs):
        """Log posterior of the walkers xs (K, T), finite (:class:`~gonio.fitting.uncertainty.ensemble.Ensemble`
        checks them, as emcee does): -inf outside the bounds."""
        inside = ((xs >= self.lower) & (xs <= self.upper)).all(axis=1)
        if inside.all():
            return self._log_posterior(xs)
        out = np.full(xs.shape[0], -np.inf)
        if inside.any():
            out[inside] = self._log_posterior(xs[inside])
        return out

    def _log_posterior(self, thetas):
        """Log posterior of thetas (K, T) inside the bounds."""
        mu, sd, chi2_min, lo, hi, q, ok = self.stats(thetas)
        a, b = (lo - mu) / sd, (hi - mu) / sd
        # log(Phi(b) - Phi(a)) stably in either tail
        upper_tail = a > 0
        la, lb = log_ndtr(np.where(upper_tail, -b, a)), log_ndtr(np.where(upper_tail, -a, b))
        mass = lb + np.log1p(-np.exp(np.minimum(la - lb, 0.0)) + 1e-300)
        # prior uniform in the model's own parameter: coef = rho / q, so d rho = q d coef
        lp = -0.5 * chi2_min + np.log(sd) + np.log(q)[:, None] + mass
        return np.where(ok & np.isfinite(lp), lp, -np.inf).sum(axis=1)

    def draw(self, thetas, rng, chunk=256):
        """Full parameter vectors: each theta with its affine parameters drawn from their
        exact conditional (truncated normal in the coefficient, times q)."""
        thetas = np.atleast_2d(thetas)
        out = np.empty((thetas.shape[0], self.space.size))
        for s in range(0, thetas.shape[0], chunk):
            th = thetas[s:s + chunk]
            mu, sd, _, lo, hi, q, _ = self.stats(th)
            p_lo, p_hi = ndtr((lo - mu) / sd), ndtr((hi - mu) / sd)
            z = ndtri(np.clip(p_lo + rng.random(mu.shape) * (p_hi - p_lo), 1e-300, 1 - 1e-16))
            coef = np.clip(mu + sd * z, lo, hi)
            out[s:s + chunk, self.nl] = th
            out[s:s + chunk, self.lin_idx] = np.clip(coef * q[:, None], self.space.lower[self.lin_idx],
                                                     self.space.upper[self.lin_idx])
        return out


def _lagrange_denominators(z):
    """(z, off, den) of the nodes z (n,) for :meth:`_AffinePosterior._weights`, made once per
    box: ``off`` (1, n, n) marks the factors m != j of L_j, ``den`` (1, n, n) holds z_j - z_m
    there and 1 on the diagonal."""
    off = ~np.eye(z.size, dtype=bool)
    return z, off[None], np.where(off, z[:, None] - z[None, :], 1.0)[None]
