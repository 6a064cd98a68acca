"""Constrained maximum-likelihood fit of a BRDF model with nlopt, and its Laplace uncertainty.

The fit runs in two stages over the unit box of :class:`~gonio.fitting._space.ParameterSpace`:

1. global: the declared defaults plus ``n_starts`` points drawn from the box with the caller's
   numpy Generator are scored; the best ``n_local`` go on to
2. local: nlopt's SLSQP (Kraft 1988), a sequential quadratic programme that honours the bounds
   and, for models that can create energy, the nonlinear inequality constraint
   ``albedo(wo_k) <= 1`` on a fixed set of outgoing directions (each channel). Gradients are
   J^T dL/dr with J the forward-difference Jacobian of the residuals, evaluated as one batch.

Reciprocity needs no constraint: every gonio model is reciprocal by construction (tested in
tests/models); the data's reciprocal pairs are a measurement diagnostic, not a fit constraint.

At the optimum the Laplace approximation gives the covariance (J^T J)^-1 of the chi^2 loss
(Fisher information of the Gaussian noise model), with J the central-difference Jacobian in
natural units. Parameters the data cannot determine (a singular or near-singular Fisher
matrix, or a 1-sigma wider than half the parameter's range) are named, never returned as NaN.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from . import _loss
from ._space import ParameterSpace

__all__ = ["FitResult", "fit"]


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
    def bic(self) -> float:
        """Bayesian information criterion, chi^2 + k ln n (Schwarz 1978)."""
        return self.chi2 + self.space.size * np.log(self.n_used)


class _Problem:
    """Residuals, Jacobian and constraint of one fit, counting model evaluations."""

    def __init__(self, meas, model, space, loss, energy_wo):
        self.meas, self.model, self.space, self.loss = meas, model, space, loss
        self.energy_wo = energy_wo
        self.n_evals = 0

    def residuals_x(self, x):
        self.n_evals += 1
        fr = self.model.eval(self.meas.wi, self.meas.wo, self.space.to_params(x))
        r = _loss.residuals(self.loss, fr, self.meas)
        if not np.all(np.isfinite(r)):
            raise FloatingPointError(f"model {self.model.name} returned non-finite f_r at "
                                     f"{dict(zip(self.space.names, np.round(x, 6)))}")
        return r

    def residuals_u(self, u):
        return self.residuals_x(self.space.from_unit(u))

    def jacobian_u(self, u, r0, h=1e-7):
        """Forward differences in the unit box (backward at the upper face)."""
        J = np.empty((r0.size, u.size))
        for j in range(u.size):
            step = h if u[j] + h <= 1.0 else -h
            up = u.copy()
            up[j] += step
            J[:, j] = (self.residuals_u(up) - r0) / step
        return J

    def jacobian_x(self, x):
        """Central differences in natural units, relative steps."""
        scale = np.maximum(np.abs(x), 1e-3 * (self.space.upper - self.space.lower))
        J = None
        for j in range(x.size):
            h = 1e-5 * scale[j]
            lo, hi = x.copy(), x.copy()
            hi[j] = min(x[j] + h, self.space.upper[j])
            lo[j] = max(x[j] - h, self.space.lower[j])
            rp, rm = self.residuals_x(hi), self.residuals_x(lo)
            if J is None:
                J = np.empty((rp.size, x.size))
            J[:, j] = (rp - rm) / (hi[j] - lo[j])
        return J

    def albedo_excess(self, x):
        a = self.model.albedo(self.energy_wo, self.space.to_params(x))
        return np.asarray(a, dtype=np.float64).reshape(-1) - 1.0


def _energy_directions(n=6):
    theta = np.deg2rad(np.linspace(0.0, 85.0, n))
    return np.stack([np.sin(theta), np.zeros_like(theta), np.cos(theta)], axis=-1)


def fit(meas, model, *, loss: str = "chi2", fixed: dict | None = None, rng=None,
        n_starts: int = 24, n_local: int = 3, maxeval: int = 2000, enforce_energy: bool | None = None) -> FitResult:
    """Fit ``model`` to ``meas``.

    Parameters
    ----------
    meas : Measurements
        The data (f_r in sr^-1 with 1-sigma).
    model
        A gonio model (``gonio.models.get(...)``).
    loss : {"chi2", "robust", "cosine", "log"}
        See :mod:`gonio.fitting._loss`. Only ``chi2`` gives a calibrated covariance.
    fixed : dict, optional
        Parameters held fixed at the given values.
    rng : numpy.random.Generator
        Draws the global stage's starting points. Required: fits are reproducible.
    n_starts, n_local : int
        Starting points scored, and how many of the best are refined locally.
    maxeval : int
        Objective evaluations per local run.
    enforce_energy : bool, optional
        Constrain albedo <= 1; defaults to ``not model.energy_conserving``.

    Returns
    -------
    FitResult
    """
    import nlopt

    if rng is None or not isinstance(rng, np.random.Generator):
        raise TypeError("fit() needs rng=numpy.random.Generator (seeded) so the fit is reproducible")
    _loss.validate_loss(loss)
    space = ParameterSpace(model, meas.n_channels, fixed, meas.channels)
    if space.size == 0:
        raise ValueError("every parameter is fixed: nothing to fit")
    if enforce_energy is None:
        enforce_energy = not getattr(model, "energy_conserving", True)
    problem = _Problem(meas, model, space, loss, _energy_directions())
    t0 = time.perf_counter()

    # ---- global stage: score the defaults and random points of the box
    starts = np.vstack([space.to_unit(space.default())[None, :], rng.random((n_starts, space.size))])
    scores = []
    for u in starts:
        try:
            scores.append(_loss.objective(loss, problem.residuals_u(u)))
        except FloatingPointError:
            scores.append(np.inf)
    order = np.argsort(scores)[: max(1, n_local)]

    # ---- local stage: SLSQP from the best starts
    # The objective is divided by its value at the start: nlopt's SLSQP throws on objectives
    # of order 1e5 and more (seen with nlopt 2.11), which chi^2 far from the optimum reaches.
    norm = [1.0]

    def f(u, grad):
        r = problem.residuals_u(u)
        if grad.size:
            J = problem.jacobian_u(u, r)
            grad[:] = (J.T @ _loss.objective_weights(loss, r)) / norm[0]
        return _loss.objective(loss, r) / norm[0]

    def energy_constraint(result, u, grad):
        x = space.from_unit(u)
        c = problem.albedo_excess(x)
        result[:] = c
        if grad.size:
            for j in range(u.size):
                step = 1e-6 if u[j] + 1e-6 <= 1.0 else -1e-6
                up = u.copy()
                up[j] += step
                grad[:, j] = (problem.albedo_excess(space.from_unit(up)) - c) / step

    best_u, best_val, message, converged = None, np.inf, "", False
    for k in order:
        opt = nlopt.opt(nlopt.LD_SLSQP, space.size)
        opt.set_lower_bounds(np.zeros(space.size))
        opt.set_upper_bounds(np.ones(space.size))
        opt.set_min_objective(f)
        if enforce_energy:
            m = problem.energy_wo.shape[0] * meas.n_channels
            opt.add_inequality_mconstraint(energy_constraint, np.full(m, 1e-6))
        opt.set_ftol_rel(1e-12)
        opt.set_xtol_rel(1e-9)
        opt.set_maxeval(maxeval)
        u0 = np.clip(starts[k], 1e-9, 1 - 1e-9)
        norm[0] = max(float(scores[k]), 1.0) if np.isfinite(scores[k]) else 1.0
        try:
            u = opt.optimize(u0)
            val = opt.last_optimum_value() * norm[0]
            status = opt.last_optimize_result()
        except nlopt.RoundoffLimited:  # keep the start: its value is known exactly
            u, val, status = u0, float(scores[k]), nlopt.ROUNDOFF_LIMITED
        except (RuntimeError, ValueError) as exc:  # nlopt failure: keep the start's value, say so
            u, val, status = u0, float(scores[k]), -1
            message = f"nlopt failed from start {k}: {exc}"
        if val < best_val:
            best_u, best_val = np.asarray(u), float(val)
            converged = status in (1, 2, 3, 4) or status == nlopt.ROUNDOFF_LIMITED
            message = _status_text(status)
    x = space.from_unit(best_u)

    # ---- Laplace uncertainty from the chi^2 residuals (Fisher information)
    chi_problem = problem if loss == "chi2" else _Problem(meas, model, space, "chi2", problem.energy_wo)
    r_chi = chi_problem.residuals_x(x)
    J = chi_problem.jacobian_x(x)
    cov, undetermined = _laplace(J, space)
    std = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    energy = {"enforced": bool(enforce_energy)}
    max_albedo = float(np.max(problem.albedo_excess(x)) + 1.0)
    energy.update(max_albedo=max_albedo, holds=bool(max_albedo <= 1.0 + 1e-4))

    fr = model.eval(meas.wi, meas.wo, space.to_params(x))
    diff = (fr - meas.brdf)[meas.use]
    cos_i = np.broadcast_to(np.clip(meas.wi[:, 2:3], 0, 1), fr.shape)[meas.use]
    return FitResult(
        model=model, space=space, x=x, std=std, cov=cov, loss=loss, objective=best_val,
        chi2=float(r_chi @ r_chi), n_used=meas.n_used,
        n_evals=problem.n_evals + (chi_problem.n_evals if chi_problem is not problem else 0),
        time_s=time.perf_counter() - t0, converged=bool(converged), message=message,
        at_bound=[n for n, b in zip(space.names, space.at_bound(x)) if b],
        undetermined=undetermined, energy=energy,
        rmse_fr=float(np.sqrt(np.mean(diff ** 2))),
        rmse_cos_fr=float(np.sqrt(np.mean((diff * cos_i) ** 2))),
    )


def _laplace(J, space, cond_limit=1e12):
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


def _status_text(status) -> str:
    return {1: "success", 2: "stopval reached", 3: "ftol reached", 4: "xtol reached",
            5: "maxeval reached", 6: "maxtime reached", -1: "failure", -4: "roundoff limited"}.get(int(status), str(status))
