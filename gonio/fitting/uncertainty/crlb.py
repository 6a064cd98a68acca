"""Cramer-Rao lower bound of the fit parameters, and a fit's efficiency against it.

For data y_k = f_k(x) + e_k with independent Gaussian e_k ~ N(0, sigma_k^2), the Fisher
information is I(x) = J^T Sigma^-1 J with J_kj = d f_k / d x_j at the truth (Kay 1993,
eq. 3.31); any unbiased estimator has Cov >= I^-1, so the CRLB of parameter j is
(I^-1)_jj. The efficiency of a fit over repeated captures is CRLB_j / Var_j(x_hat), 1 for
an efficient estimator (the maximum-likelihood fit is asymptotically efficient).

Kay, S. M. (1993). Fundamentals of Statistical Signal Processing: Estimation Theory, ch. 3.
"""

from __future__ import annotations

import numpy as np

from gonio.fitting.likelihood.problem import Problem as _Problem
from gonio.fitting.optimise.result import jacobian_chi2
from gonio.fitting.optimise.space import ParameterSpace

__all__ = ["crlb", "efficiency"]


def crlb(meas, model, truth: dict, *, fixed: dict | None = None) -> tuple[list, np.ndarray]:
    """(names, CRLB standard deviations) at ``truth`` for the noise model of ``meas``.

    Uses ``meas.brdf_std`` as sigma and ``meas.use`` as the captured values; the measured
    f_r values themselves do not enter. Parameters the data cannot determine get +inf.
    """
    space = ParameterSpace(model, meas.n_channels, fixed, meas.channels)
    problem = _Problem(meas, model, space, "chi2")
    x = space.from_params(model.validate(truth))
    J, _ = jacobian_chi2(problem, x)
    fisher = J.T @ J
    d = np.sqrt(np.clip(np.diag(fisher), 1e-300, None))
    w, v = np.linalg.eigh(fisher / np.outer(d, d))
    keep = w > w.max() * 1e-12
    inv = (v[:, keep] / w[keep]) @ v[:, keep].T / np.outer(d, d)
    std = np.sqrt(np.clip(np.diag(inv), 0.0, None))
    null = np.any(np.abs(v[:, ~keep]) > 0.3, axis=1) if np.any(~keep) else np.zeros(space.size, bool)
    return space.names, np.where(null, np.inf, std)


def efficiency(estimates, truth_x, crlb_std) -> dict:
    """Efficiency CRLB^2 / MSE per parameter over repeated captures (rows of ``estimates``).

    Uses the mean squared error about the truth, so a bias lowers the efficiency too.
    """
    est = np.asarray(estimates, dtype=np.float64)
    mse = np.mean((est - np.asarray(truth_x)) ** 2, axis=0)
    eff = np.asarray(crlb_std) ** 2 / np.maximum(mse, 1e-300)
    return {"mse": mse, "efficiency": eff, "bias": est.mean(axis=0) - truth_x, "std": est.std(axis=0, ddof=1)}
