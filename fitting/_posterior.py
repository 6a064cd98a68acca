"""Posterior sampling with emcee, and an honest account of whether the chain is long enough.

Likelihood: the data's Gaussian noise model, ln L = -chi^2 / 2. Prior: uniform over the box
of the model's declared bounds (ln prior = -inf outside). Walkers start in a small Gaussian
ball drawn from the Laplace covariance around the optimum.

Convergence is judged by the integrated autocorrelation time tau (Goodman & Weare 2010;
Foreman-Mackey et al. 2013, sec. 3): the chain runs in chunks until it is longer than 50 tau
for every parameter (emcee's own rule in ``autocorr.integrated_time``) or the step budget is
spent. A chain that is shorter is *not* reported as a posterior: ``converged`` is False and
``advice`` says how many steps would be needed.

Collapsed sampling. Where the fit found parameters in which f_r is affine, one per channel
(the albedo of roughplastic, Oren-Nayar), they are integrated out analytically: for a flat
prior on [lo, hi] the marginal likelihood of the nonlinear parameters theta is, per channel,
exp(-chi2_min(theta) / 2) sqrt(2 pi) s [Phi((hi - m) / s) - Phi((lo - m) / s)], with m and s
the weighted least-squares estimate and its 1-sigma at theta. emcee samples theta only (2
dimensions instead of 5 for roughplastic: shorter autocorrelation, fewer walkers), and each
kept theta gets its affine parameters drawn exactly from their conditional truncated normal.
The draws are exact posterior draws, not an approximation (Liu 1994, collapsed Gibbs).

Liu, J. S. (1994). The collapsed Gibbs sampler in Bayesian computations. JASA 89, 958-966.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from . import _loss

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

    from ._optimise import _Problem

    space, model = result.space, result.model
    problem = _Problem(meas, model, space, "chi2")
    groups_per_channel = len(problem.linear)
    collapsed = bool(collapse and problem.varpro and groups_per_channel == 1 and 0 < problem.nl_idx.size)
    sub = problem.nl_idx if collapsed else np.arange(space.size)
    P = sub.size
    lower, upper = space.lower[sub], space.upper[sub]

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

    n_walkers = max(n_walkers, 2 * P + 2)
    scale = np.sqrt(np.clip(np.diag(result.cov)[sub], 1e-24, None))
    start = result.x[sub] + 1e-2 * scale * rng.standard_normal((n_walkers, P))
    span = upper - lower
    start = np.clip(start, lower + 1e-9 * span, upper - 1e-9 * span)

    sampler = emcee.EnsembleSampler(n_walkers, P, log_prob, vectorize=True)
    sampler.random_state = np.random.RandomState(int(rng.integers(2**32 - 1))).get_state()
    t0 = time.perf_counter()
    state = start
    tau = np.full(P, np.inf)
    converged = False
    while sampler.iteration < max_steps:
        state = sampler.run_mcmc(state, chunk, progress=False)
        tau = sampler.get_autocorr_time(tol=0)
        if np.all(np.isfinite(tau)) and sampler.iteration > tau_multiple * np.max(tau):
            converged = True
            break
        if time_budget_s is not None and time.perf_counter() - t0 > time_budget_s:
            break
    n_steps = sampler.iteration
    tau_max = float(np.max(tau)) if np.all(np.isfinite(tau)) else float(n_steps)
    burn = int(min(n_steps // 2, 3 * tau_max))
    thin = max(1, int(tau_max / 2))
    samples = sampler.get_chain(discard=burn, thin=thin, flat=True)
    if collapsed:  # each kept theta gets its affine parameters from the exact conditional
        samples = np.array([_collapsed(problem, full_x(t), rng)[1] for t in samples])
    n_independent = (n_steps - burn) * n_walkers / max(tau_max, 1.0)
    advice = "" if converged else (
        f"chain of {n_steps} steps is shorter than {tau_multiple:.0f} tau (tau ~ {tau_max:.0f}): "
        f"run at least {int(tau_multiple * tau_max * 1.2)} steps before trusting these intervals")
    quantiles = {q: np.percentile(samples, q, axis=0) for q in (5, 16, 50, 84, 95)}
    return Posterior(names=space.names, converged=converged, n_walkers=n_walkers, n_steps=n_steps,
                     tau=np.asarray(tau), n_independent=float(n_independent), samples=samples,
                     quantiles=quantiles, acceptance=float(np.mean(sampler.acceptance_fraction)),
                     time_s=time.perf_counter() - t0, advice=advice)


def _collapsed(problem, x, rng=None):
    """Log marginal likelihood of x's nonlinear part with the per-channel affine parameter
    integrated over its bounds (flat prior), and, with ``rng``, x with that parameter drawn
    from its conditional truncated normal."""
    from scipy.special import log_ndtr, ndtr, ndtri

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
