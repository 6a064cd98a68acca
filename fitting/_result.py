"""What a fit returns (:class:`FitResult`) and its Laplace uncertainty.

At the optimum the Laplace approximation gives the covariance (J^T J)^-1 of the chi^2 loss
(Fisher information of the Gaussian noise model), with J in natural units (exact from the
compiled kernel; on the numpy path exact columns for the affine parameters, central
differences for the others). Parameters the data cannot determine (a singular or
near-singular Fisher matrix, or a 1-sigma wider than half the parameter's range) are named,
never returned as NaN.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from . import _loss
from ._space import ParameterSpace

__all__ = ["FitResult", "jacobian_chi2", "laplace"]


@dataclasses.dataclass
class FitResult:
    """What a fit found and how sure it is.

    ``x`` and ``std`` are in natural units, ordered as ``space.names``.
    """

    model: object
    space: ParameterSpace
    x: np.ndarray
    std: np.ndarray
    cov: np.ndarray
    loss: str
    objective: float
    chi2: float
    n_used: int
    n_evals: int
    time_s: float
    converged: bool
    message: str
    at_bound: list
    undetermined: list
    energy: dict
    rmse_fr: float
    rmse_cos_fr: float
    method: str = "levenberg-marquardt"
    linear: list = dataclasses.field(default_factory=list)
    #: the model-discrepancy term fitted with the model (loss ``discrepancy``): ``rel``,
    #: ``abs`` (sr^-1), ``neg2_loglik``, ``iterations``; None for the other losses
    discrepancy: dict | None = None

    @property
    def params(self) -> dict:
        return self.space.to_params(self.x)

    @property
    def dof(self) -> int:
        return max(self.n_used - self.space.size, 1)

    @property
    def chi2_dof(self) -> float:
        return self.chi2 / self.dof

    @property
    def neg2_loglik(self) -> float:
        """-2 ln L (up to a constant common to all models) of the loss that was minimised:

        * ``chi2``: chi^2 (Gaussian noise with the data's sigma);
        * ``robust``: its objective (pseudo-Huber on the sigma-scaled residuals);
        * ``cosine``, ``log``: n ln(objective / n), the Gaussian likelihood of the loss's
          residuals with their variance profiled out (one more parameter);
        * ``discrepancy``: sum r^2 / s^2 + ln s^2 with s^2 = sigma^2 + (rel f)^2 + abs^2.
        """
        if self.loss == "discrepancy" and self.discrepancy:
            return float(self.discrepancy["neg2_loglik"])
        if self.loss in ("cosine", "log"):
            return float(self.n_used * np.log(max(self.objective, 1e-300) / self.n_used))
        if self.loss == "robust":
            return float(self.objective)
        return float(self.chi2)

    @property
    def k_criterion(self) -> int:
        """Free parameters counted by the BIC: the model's, plus the noise parameters the
        loss estimates (one profiled variance for cosine/log, rel and abs for discrepancy)."""
        return self.space.size + {"cosine": 1, "log": 1, "discrepancy": 2}.get(self.loss, 0)

    @property
    def bic(self) -> float:
        """Bayesian information criterion -2 ln L + k ln n (Schwarz 1978), from the likelihood
        of the loss that was minimised (:attr:`neg2_loglik`), never from chi^2 when another
        loss was."""
        return self.neg2_loglik + self.k_criterion * np.log(self.n_used)

    @property
    def correlation(self) -> np.ndarray:
        """Correlation matrix of the Laplace covariance."""
        d = np.sqrt(np.clip(np.diag(self.cov), 1e-300, None))
        return np.clip(self.cov / np.outer(d, d), -1.0, 1.0)

    @property
    def correlated(self) -> list:
        """Pairs (name_a, name_b, rho) with |rho| >= 0.9: the data constrains only a combination."""
        c = self.correlation
        names = self.space.names
        return [(names[i], names[j], float(c[i, j]))
                for i in range(len(names)) for j in range(i + 1, len(names)) if abs(c[i, j]) >= 0.9]


def jacobian_chi2(problem, x, rel_step=1e-5):
    """chi^2 residuals at x and their Jacobian in natural units (M, P).

    Exact from the compiled kernel where it runs; otherwise columns of affine parameters are
    exact and the others central differences with a relative step (one-sided at a bound).
    """
    space, meas = problem.space, problem.meas
    exact = problem.residual_jacobian_x(x, range(space.size), loss="chi2")
    if exact is not None:
        return exact[1], exact[0]
    f0 = problem.f_x(x)
    r0 = _loss.residuals("chi2", f0, meas)
    J = np.empty((r0.size, space.size))
    lin = {}
    if problem.linear:
        _, cols = problem.basis(x)
        for g, B in zip(problem.linear, cols):
            for c, i in enumerate(g["index"]):
                Bc = np.zeros_like(B)
                Bc[:, c] = B[:, c]
                lin[i] = (Bc / meas.brdf_std)[meas.use]
    scale = np.maximum(np.abs(x), 1e-3 * (space.upper - space.lower))
    for j in range(space.size):
        if j in lin:
            J[:, j] = lin[j]
            continue
        h = rel_step * scale[j]
        hi, lo = min(x[j] + h, space.upper[j]), max(x[j] - h, space.lower[j])
        xp, xm = x.copy(), x.copy()
        xp[j], xm[j] = hi, lo
        fp = f0 if hi == x[j] else problem.f_x(xp)
        fm = f0 if lo == x[j] else problem.f_x(xm)
        J[:, j] = ((fp - fm) / meas.brdf_std)[meas.use] / (hi - lo)
    if not np.all(np.isfinite(J)):
        raise FloatingPointError("non-finite Jacobian at the optimum")
    return J, r0


def laplace(J, space, cond_limit=1e12):
    """Covariance (J^T J)^-1 and the names of parameters the data does not determine."""
    fisher = J.T @ J
    width = space.upper - space.lower
    # Scale to unit diagonal so the condition number measures correlation, not units.
    d = np.sqrt(np.clip(np.diag(fisher), 1e-300, None))
    corr = fisher / np.outer(d, d)
    w, v = np.linalg.eigh(corr)
    keep = w > w.max() / cond_limit
    inv_corr = (v[:, keep] / w[keep]) @ v[:, keep].T
    cov = inv_corr / np.outer(d, d)
    undetermined = set()
    for idx in np.where(~keep)[0]:  # null directions: the parameters that load on them
        undetermined.update(np.where(np.abs(v[:, idx]) > 0.3)[0].tolist())
        cov += np.outer(v[:, idx], v[:, idx]) * np.outer(width, width) / 12.0
    std = np.sqrt(np.clip(np.diag(cov), 0, None))
    undetermined.update(np.where(std > 0.5 * width)[0].tolist())
    return cov, [space.names[i] for i in sorted(undetermined)]
