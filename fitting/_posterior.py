"""Posterior sampling with emcee, and an honest account of whether the chain is long enough.

Likelihood: the data's Gaussian noise model, ln L = -chi^2 / 2. Prior: uniform over the box
of the model's declared bounds (ln prior = -inf outside). Walkers start in a small Gaussian
ball drawn from the Laplace covariance around the optimum.

Convergence is judged by the integrated autocorrelation time tau (Goodman & Weare 2010;
Foreman-Mackey et al. 2013, sec. 3): the chain runs in chunks until it is longer than 50 tau
for every parameter (emcee's own rule in ``autocorr.integrated_time``) or the step budget is
spent. A chain that is shorter is *not* reported as a posterior: ``converged`` is False and
``advice`` says how many steps would be needed.
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
                     chunk: int = 500, tau_multiple: float = 50.0, time_budget_s: float | None = None) -> Posterior:
    """Sample the posterior of a finished chi^2 fit (``result`` from :func:`fit`).

    Parameters
    ----------
    rng : numpy.random.Generator
        Seeds the walkers' start and emcee's own random state.
    max_steps : int
        Step budget; sampling stops earlier once the chain exceeds ``tau_multiple`` tau.
    time_budget_s : float, optional
        Wall-time budget; a chain cut short by it is reported as not converged.
    """
    import emcee

    space, model = result.space, result.model
    P = space.size
    lower, upper = space.lower, space.upper

    def log_prob(xs):
        xs = np.atleast_2d(xs)
        out = np.full(xs.shape[0], -np.inf)
        inside = np.all((xs >= lower) & (xs <= upper), axis=1)
        for k in np.where(inside)[0]:
            fr = model.eval(meas.wi, meas.wo, space.to_params(xs[k]))
            r = _loss.residuals("chi2", fr, meas)
            if np.all(np.isfinite(r)):
                out[k] = -0.5 * float(r @ r)
        return out

    n_walkers = max(n_walkers, 2 * P + 2)
    scale = np.sqrt(np.clip(np.diag(result.cov), 1e-24, None))
    start = result.x + 1e-2 * scale * rng.standard_normal((n_walkers, P))
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
    n_independent = (n_steps - burn) * n_walkers / max(tau_max, 1.0)
    advice = "" if converged else (
        f"chain of {n_steps} steps is shorter than {tau_multiple:.0f} tau (tau ~ {tau_max:.0f}): "
        f"run at least {int(tau_multiple * tau_max * 1.2)} steps before trusting these intervals")
    quantiles = {q: np.percentile(samples, q, axis=0) for q in (5, 16, 50, 84, 95)}
    return Posterior(names=space.names, converged=converged, n_walkers=n_walkers, n_steps=n_steps,
                     tau=np.asarray(tau), n_independent=float(n_independent), samples=samples,
                     quantiles=quantiles, acceptance=float(np.mean(sampler.acceptance_fraction)),
                     time_s=time.perf_counter() - t0, advice=advice)
