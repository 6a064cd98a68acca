"""Constrained maximum-likelihood fit of a BRDF model, and its Laplace uncertainty.

f_r comes from the compiled kernels of :mod:`gonio.models.fast` (exact derivatives) where they
are available and agree with ``model.eval``, else from ``model.eval`` (forward differences).
Parameters in which f_r is affine are solved exactly for every value of the nonlinear ones
(variable projection, Golub & Pereyra 1973; ``chi2`` and ``cosine`` losses). A global stage
(the defaults plus ``n_starts`` stratified starts) picks the best starts in distinct basins,
Levenberg-Marquardt (:mod:`gonio.fitting.optimise.lm`) refines them, and for models that can
create energy a Gauss-Newton SQP polishes the optimum under ``albedo(wo_k) <= 1``.
:func:`refine_starts` drives :class:`GeneralFit` or :class:`~gonio.fitting.optimise.affine.AffineFit`.

At the optimum the Laplace approximation gives the covariance (J^T J)^-1 of the chi^2 loss;
the ``log`` and ``cosine`` losses report the cluster-robust sandwich covariance instead.
Parameters the data cannot determine are named, never returned as NaN; strongly correlated
pairs (|rho| >= 0.9) are listed in ``FitResult.correlated``.
"""

# Design notes (the measurements behind these choices, from `gonio bench fit`, gonio.perf.fit:
# docs/performance.md, gonio.fitting.optimise.mle):
# - Evaluation: gonio.models.fast is Dr.Jit LLVM kernels, float64, the directions loaded once
#   per fit. Where the steps come from the compiled normal equations the compiled path runs at
#   any number of points; the others use it from 500 points
#   (gonio.fitting.likelihood.problem.FAST_MIN_POINTS: the problem's shape decides;
#   `gonio bench fit` prints the crossover). The kernels compute f_r and d f_r / d parameter
#   together (gonio.models.fast.jacobian, one call for all parameters), chained through the
#   loss and the unit box.
# - Variable projection: the affine parameters (per-channel albedos) are detected numerically
#   from the model, never listed by hand, and solved by bounded weighted linear least squares;
#   the optimiser only sees the shared nonlinear parameters (roughplastic: alpha and eta, 2
#   instead of 5). robust and log fit all parameters jointly.
# - Global stage: the general problem first refines the defaults alone and stops there when
#   that chi2 fit already matches the data to their noise (GeneralFit.acceptable). The starts
#   are Latin hypercube points (caller's rng) of the nonlinear parameters' unit box, scored
#   with the linear parameters set from the data, on at most 3000 data rows; the best n_local
#   starts in distinct basins (unit-box distance >= 0.15) are refined.
# - Local stage: later starts are raced against the best refined one (abandoned when clearly
#   worse). For the chi2, cosine and log losses on the compiled path each step's normal
#   equations J^T r and J^T J are reduced inside the kernel
#   (gonio.models.fast.normal_equations, replayed by dr.freeze; the log loss's transform
#   ln(1 + f_r cos_i) applied there too): no N x P Jacobian per iteration, so the iterations'
#   memory does not grow with the parameters. Up to 2e4 points a trial step is costed by the
#   same kernel, so that an accepted step brings the next step's equations: one kernel call
#   per iteration. BLAS is held to one thread during a fit (its pool fights Dr.Jit's).
# - Energy: albedo(wo_k) <= 1 (each channel, fixed outgoing directions) is a nonlinear
#   inequality constraint, applied when the unconstrained optimum violates it; a Gauss-Newton
#   SQP (gonio.fitting.optimise.gn_sqp) polishes the full parameter vector.
# - Reciprocity needs no constraint: every gonio model is reciprocal by construction (tested
#   in tests/models); the data's reciprocal pairs are a measurement diagnostic, not a fit
#   constraint.
# - Layout: the loop is written once (refine_starts) and drives either problem through one
#   interface: GeneralFit (gonio.fitting.likelihood.problem: every parameter, or variable
#   projection on the numpy or compiled evaluator) and AffineFit (models that declare an affine
#   per-channel parameter, model.structure.affine: many thetas per kernel call). Starting
#   points live in gonio.fitting.optimise.starts, the energy constraint in
#   gonio.fitting.optimise.energy, the result and its Laplace covariance in
#   gonio.fitting.optimise.result.
# - Covariance: (J^T J)^-1 is the Fisher information of the Gaussian noise model, with J in
#   natural units (exact from the compiled kernel; on the numpy path exact columns for the
#   affine parameters, central differences for the others). log and cosine have no noise
#   model; their sandwich is gonio.fitting.optimise.result.sandwich. Undetermined: a singular
#   or near-singular Fisher matrix, or a 1-sigma wider than half the parameter's range.
# References:
# Golub, G. H., Pereyra, V. (1973). The differentiation of pseudo-inverses and nonlinear least
# squares problems whose variables separate. SIAM J. Numer. Anal. 10(2), 413-432.
# Nocedal, J., Wright, S. J. (2006). Numerical Optimization, 2nd ed., ch. 18 (the energy polish's SQP).

from __future__ import annotations

import dataclasses
import time

import numpy as np

from gonio.fitting.likelihood import loss as _loss
from gonio.fitting.optimise.affine import AffineFit, applicable, single_threaded_blas
from gonio.fitting.likelihood.discrepancy import fit_discrepancy
from gonio.fitting.optimise.energy import energy_directions, polish_energy
from gonio.fitting.optimise.lm import levenberg_marquardt
from gonio.fitting.likelihood.problem import NORMAL_LOSSES, Evaluator, Problem
from gonio.fitting.optimise.result import FitResult, jacobian_chi2, laplace, robust_covariance
from gonio.fitting.optimise.space import ParameterSpace
from gonio.fitting.optimise.starts import BASIN_DISTANCE, SCORE_ROWS, START_RATIO, choose_starts, global_starts

__all__ = ["FitResult", "fit", "Evaluator", "GeneralFit", "refine_starts"]


def refine_starts(problem, rng, *, n_starts, n_local, maxeval, t0):
    """The fit loop, for any problem with this interface:

    ``problem.starts(n_starts, rng) -> (starts, scores)`` (the global stage),
    ``problem.refine(start, budget, abandon) -> (state, cost, converged, message)`` (a local
    run under an evaluation budget, abandoned when ``abandon(iteration, cost)`` says so),
    ``problem.n_evals`` (model evaluations so far) and ``problem.result(best, t0)`` (a
    :class:`FitResult`, or None to hand over to the general problem).

    The best starts in distinct basins are refined in turn, each later one raced against the
    best refined so far.
    """
    best = skip = None
    if getattr(problem, "default_first", False) and n_starts != 0:
        # the default start first: where its optimum already fits the data to the noise
        # (chi2 within 3 sigma of its expectation) no other basin can fit significantly
        # better, and the global stage is skipped
        skip = problem.default_start()
        n0 = problem.n_evals
        best = problem.refine(skip, lambda: problem.n_evals - n0 < maxeval, lambda it, cost: False)
        if problem.acceptable(best):
            return problem.result(best, t0)
    starts, scores = problem.starts(n_starts, rng)
    chosen = choose_starts(starts, scores, n_local, START_RATIO, BASIN_DISTANCE)
    if getattr(problem, "refine_default", False) and skip is None and 0 not in chosen and np.isfinite(scores[0]):
        # the declared defaults (starts[0]) get a local run too, last, raced like the others
        chosen.append(0)
    for k in chosen:
        if skip is not None and np.array_equal(starts[k], skip):
            continue  # refined already
        n0 = problem.n_evals

        def budget(n0=n0):
            return problem.n_evals - n0 < maxeval

        def abandon(it, cost, best=best):  # race later starts against the best refined one
            return best is not None and ((it >= 1 and cost > START_RATIO * best[1] + 10.0)
                                         or (it >= 2 and cost > 1.5 * best[1] + 10.0))

        res = problem.refine(starts[k], budget, abandon)
        if best is None or res[1] < best[1]:
            best = res
    return problem.result(best, t0)


class GeneralFit:
    """The general problem for :func:`refine_starts`: all parameters by Levenberg-Marquardt,
    or the nonlinear ones with the affine ones projected out; energy polish; Laplace."""

    def __init__(self, meas, model, space, loss, use_fast, enforce_energy, maxeval, start=None):
        self.meas, self.model, self.space, self.loss = meas, model, space, loss
        self.enforce_energy, self.maxeval = enforce_energy, maxeval
        self.problem = problem = Problem(meas, model, space, loss, use_fast=use_fast)
        self.energy_wo = energy_directions()
        self.free = problem.nl_idx if problem.varpro else np.arange(space.size)
        self.given_start = start is not None
        x_default = space.default() if start is None else space.from_params(model.validate(start))
        u_default = space.to_unit(x_default)
        if problem.linear:  # affine parameters from the data (searched too where not projected: log, robust)
            u_default = space.to_unit(problem.solve_linear(x_default))
        self.u_default = u_default
        self.scorer = problem
        self.atol = 1e-4 if loss in ("chi2", "robust") else 0.0
        self.ftol = LM_FTOL

    @property
    def n_evals(self):
        return self.problem.n_evals

    @property
    def default_first(self):
        """Refine the defaults before the global stage (:func:`refine_starts`) where a local run
        is cheap: the chi2 loss on the compiled kernel's normal equations. (Elsewhere the
        loop stays as it was: the default start then also races the later ones.)"""
        return self.loss == "chi2" and self.problem.normal_available and not self.problem.varpro

    @property
    def refine_default(self):
        """Refine the declared defaults whatever their score, when the global stage cannot
        rank basins by score: without variable projection a start is scored at its own values
        of every parameter, and a flat region can outscore every start near the optimum (a
        plastic's lobe-free plateau: alpha -> 1e-4, int_ior at its bound, no specular lobe at
        all, scored better than any start with a lobe in the wrong place; an RGL geometry's
        log fit ended there at 6.4x the objective of the basin the defaults reach). A given
        ``start`` is always refined: it was given because it is near the basin wanted."""
        return not self.problem.varpro or self.given_start

    def default_start(self):
        """The declared defaults (affine parameters solved), in the searched coordinates."""
        return self.u_default[self.free].copy()

    def acceptable(self, res):
        """True when a refined chi2 fit (``refine``'s result) matches the data to their noise:
        converged, and sum w r^2 <= E + 3 sd with E = sum w - P and sd = sqrt(2 sum w^2) over
        the used values (w the relative solid-angle weights, 1 without: then the chi2_dof
        distribution's mean and sd). A fit this good needs no global search: another basin
        could lower chi2 only by what the noise allows. Only for the chi2 loss (a measured
        sigma); never for the others, whose scale is unknown."""
        x, cost, converged, _ = res
        if self.loss != "chi2" or x is None or not converged or not np.isfinite(cost):
            return False
        w = np.broadcast_to(_loss.value_weight(self.meas) ** 2, self.meas.brdf.shape)[self.meas.use]
        return bool(cost <= float(np.sum(w)) - self.space.size + 3.0 * np.sqrt(2.0 * float(np.sum(w * w))))

    def starts(self, n_starts, rng):
        """Stratified starts over the nonlinear parameters (or all of them), scored on at most
        :data:`SCORE_ROWS` rows."""
        meas, problem = self.meas, self.problem
        stride = max(1, int(np.ceil(meas.n_points / SCORE_ROWS)))
        if stride != 1:
            self.scorer = Problem(meas.subset(slice(None, None, stride)), self.model, self.space, self.loss,
                                  use_fast=problem.eval.fast, linear=problem.linear)
        return global_starts(self.scorer, self.free, self.u_default, n_starts, rng)

    def refine(self, start, budget, abandon):
        problem, space, loss, atol = self.problem, self.space, self.loss, self.atol
        try:
            if problem.varpro and self.free.size == 0:
                x = problem.solve_linear(space.default())
                r = problem.residuals_x(x)
                return (x, _loss.objective(loss, r), True, "linear least squares (exact)")
            if problem.varpro:
                lm = levenberg_marquardt(lambda v: problem.reduced_residuals(v, space.default()), start,
                                         atol=atol, ftol=self.ftol, budget=budget, abandon=abandon,
                                         jac=lambda v, r: problem.kaufman_jacobian(v, r, space.default()))
                x = problem.x_of(lm.u, space.default())
            else:
                u0 = self.u_default.copy()
                u0[self.free] = start
                lm = levenberg_marquardt(problem.lm_residuals_u, u0, atol=atol, ftol=self.ftol, budget=budget,
                                         abandon=abandon,
                                         jac=problem.lm_jacobian_u, normal=problem.lm_normal_u,
                                         cost=problem.lm_cost_u if problem.normal_available else None)
                x = space.from_unit(lm.u)
                if lm.r is None and loss in NORMAL_LOSSES:  # the cost is the objective: no evaluation
                    return (x, lm.cost, lm.converged, lm.message)
            return (x, _loss.objective(loss, problem.residuals_x(x)), lm.converged, lm.message)
        except FloatingPointError as exc:
            return (None, np.inf, False, str(exc))

    def result(self, best, t0):
        problem, space, meas = self.problem, self.space, self.meas
        x, best_val, converged, message = best
        if x is None:
            raise FloatingPointError(f"no start gave finite residuals: {message}")
        method = ("variable projection + Levenberg-Marquardt" if problem.varpro else "Levenberg-Marquardt")

        # ---- energy: constrained polish (Gauss-Newton SQP) where the optimum breaks albedo <= 1
        energy = {"enforced": bool(self.enforce_energy)}
        excess = np.max(problem.albedo_excess(x, self.energy_wo)) if self.enforce_energy else None
        if self.enforce_energy and excess > 1e-6:
            x, best_val, converged, message = polish_energy(problem, x, self.energy_wo, self.maxeval)
            method += " + Gauss-Newton SQP (albedo <= 1)"
            excess = np.max(problem.albedo_excess(x, self.energy_wo))     # else x's, found above
        if self.enforce_energy:
            max_albedo = float(excess + 1.0)
            energy.update(max_albedo=max_albedo, holds=bool(max_albedo <= 1.0 + 1e-4))
        else:  # the model conserves energy for every parameter in its bounds (tests/models)
            energy.update(max_albedo=None, holds=True, by_construction=True)

        # ---- Laplace uncertainty from the chi^2 residuals (Fisher information): J^T J from
        # the compiled normal equations where they serve (the last step's, no N x P
        # Jacobian), else from the Jacobian
        reduced = problem.fisher_chi2(x)
        if reduced is not None:
            chi2, fisher = reduced
            cov, undetermined = laplace(None, space, fisher=fisher)
        else:
            J, r_chi = jacobian_chi2(problem, x)
            chi2 = float(r_chi @ r_chi)
            cov, undetermined = laplace(J, space)
        std = np.sqrt(np.clip(np.diag(cov), 0.0, None))

        fr = problem.f_x(x, reuse=True)  # the Jacobian's f_r where it had one
        diff = (fr - meas.brdf)[meas.use]
        cos_i = np.broadcast_to(np.clip(meas.wi[:, 2:3], 0, 1), fr.shape)[meas.use]
        n_evals = problem.n_evals + (self.scorer.n_evals if self.scorer is not problem else 0)
        return FitResult(
            model=self.model, space=space, x=x, std=std, cov=cov, loss=self.loss, objective=float(best_val),
            chi2=chi2, n_used=meas.n_used, n_evals=int(n_evals),
            time_s=time.perf_counter() - t0, converged=bool(converged), message=message,
            at_bound=[n for n, b in zip(space.names, space.at_bound(x)) if b],
            undetermined=undetermined, energy=energy,
            rmse_fr=float(np.sqrt(np.mean(diff ** 2))),
            rmse_cos_fr=float(np.sqrt(np.mean((diff * cos_i) ** 2))),
            method=f"{method} [{problem.eval.backend}]",
            linear=[g["param"] for g in problem.linear] if problem.varpro else [],
        )


def fit(meas, model, *, loss: str = "chi2", fixed: dict | None = None, rng=None,
        n_starts: int | None = None, n_local: int = 3, maxeval: int = 2000, enforce_energy: bool | None = None,
        use_fast: bool | None = None, start: dict | None = None, covariance: bool = True,
        ftol: float | None = None) -> FitResult:
    """Fit ``model`` to ``meas``.

    Parameters
    ----------
    meas : Measurements
        The data (f_r in sr^-1 with 1-sigma).
    model
        A gonio model (``gonio.models.get(...)``).
    loss : {"chi2", "robust", "cosine", "log", "luminance", "discrepancy"}
        See :mod:`gonio.fitting.likelihood.loss`. ``chi2`` gives a calibrated covariance when the model
        holds; ``discrepancy`` fits a model-discrepancy variance with the model
        (:mod:`gonio.fitting.likelihood.discrepancy`), for real materials.
    fixed : dict, optional
        Parameters held fixed at the given values.
    rng : numpy.random.Generator
        Draws the global stage's starting points. Required: fits are reproducible.
    n_starts, n_local : int
        Stratified starting points scored (default 4 + 4 d for d parameters searched, at
        most 24; the affine path, whose scores cost one kernel call for all, scores at least
        :data:`~gonio.fitting.optimise.affine.SCORED`; 0: the defaults or ``start`` alone),
        and how many of the best (in distinct basins) are refined locally. Where the affine
        path hands over to the general one, the general path starts from the affine path's
        best point in place of the defaults.
    maxeval : int
        Model evaluations per local run.
    enforce_energy : bool, optional
        Constrain albedo <= 1; defaults to ``not model.energy_conserving``.
    use_fast : bool, optional
        Use the compiled Dr.Jit kernels (default: where available); False forces numpy.
    start : dict, optional
        A starting point (the model's params) that takes the declared defaults' place: the
        first start, refined like them, the global stage's starts beside it. For a nested
        model started from the simpler one's fit (:func:`gonio.fitting.select` does this for
        a model that declares ``start_from``). A model with a declared affine structure is
        then fitted by the general problem. None: the model's ``data_start(meas, fixed)`` where it
        has one (gratingpaint's period profiled), refined alone unless ``n_starts`` is given.
    covariance : bool
        False: the ``log`` and ``cosine`` losses skip their sandwich covariance
        (:func:`gonio.fitting.optimise.result.robust_covariance`: 2 P + 1 Jacobians, P^2 evaluations
        without a compiled kernel) and keep the Laplace one, for a fit that is refined again
        from its own result (:func:`gonio.fitting.fit_tabulated`'s rounds: 25 of its 90 s each
        on vch at 42 parameters). ``time_s`` never includes it.
    ftol : float, optional
        A local run stops where a step would lower the objective by less than ``ftol`` times
        it (default :data:`LM_FTOL`); a looser one for a screening fit
        (:mod:`gonio.fitting.selection.auto`).

    Returns
    -------
    FitResult
    """
    if rng is None or not isinstance(rng, np.random.Generator):
        raise TypeError("fit() needs rng=numpy.random.Generator (seeded) so the fit is reproducible")
    _loss.validate_loss(loss)
    kw = dict(loss=loss, fixed=fixed, n_local=n_local, maxeval=maxeval, enforce_energy=enforce_energy,
              use_fast=use_fast, covariance=covariance, ftol=ftol)
    if start is None and hasattr(model, "data_start"):     # a start the model reads from the data (its
        start = model.data_start(meas, fixed=fixed)         # multimodal parameters profiled) replaces
        if start is not None:                               # the global stage unless starts are asked for
            start = {k: v for k, v in start.items() if k not in (fixed or {})}
            n_starts = 0 if n_starts is None else n_starts
    res = _fit(meas, model, rng=rng, n_starts=n_starts, start=start, **kw)
    return _canonical(res, meas, model, rng, kw)


def _canonical(res, meas, model, rng, kw):
    """A model with a periodic parameter (``model.canonical``: roughconductor's tangent,
    period 180 deg, and alpha_u <-> alpha_v at a 90 deg turn) is refitted once, locally, from
    its canonical form (alpha_u <= alpha_v, tangent in [0, 180)) where the fit ended elsewhere,
    and from the other end of the tangent's box where it ended on a face of it (an optimum
    just past 0 deg is reached from 180); the refit is kept where its BIC is no worse, its
    time, evaluations and CPU seconds those of both runs."""
    canon = getattr(model, "canonical", None)
    names = {e.param for e in res.space.entries}
    if canon is None or "tangent_deg" not in names or {"alpha_u", "alpha_v"} - names:
        return res
    p = res.params
    q = canon(p)
    if "tangent_deg" in res.at_bound and q["tangent_deg"] in (0.0, 180.0):    # still on a face
        q["tangent_deg"] = 180.0 if p["tangent_deg"] < 90.0 else 0.0
    elif all(np.allclose(q[k], p[k], rtol=1e-12, atol=1e-12) for k in q):
        return res
    again = _fit(meas, model, rng=rng, n_starts=0, start=q, **kw)
    kept = again if again.bic <= res.bic + 1e-9 * abs(res.bic) else res
    cpu = None if res.cpu_s is None or again.cpu_s is None else res.cpu_s + again.cpu_s
    return dataclasses.replace(kept, time_s=res.time_s + again.time_s, n_evals=res.n_evals + again.n_evals,
                               cpu_s=cpu)      # the fit's time is both runs'


def _fit(meas, model, *, loss, fixed, rng, n_starts, n_local, maxeval, enforce_energy, use_fast, start, covariance,
         ftol):
    if loss == "discrepancy":
        return fit_discrepancy(meas, model, fit, rng=rng, fixed=fixed, n_starts=n_starts, n_local=n_local,
                               maxeval=maxeval, enforce_energy=enforce_energy, use_fast=use_fast, start=start)
    space = ParameterSpace(model, meas.n_channels, fixed, meas.channels)
    if space.size == 0:
        raise ValueError("every parameter is fixed: nothing to fit")
    if enforce_energy is None:
        enforce_energy = not getattr(model, "energy_conserving", True)
    t0, c0 = time.perf_counter(), time.process_time()
    loop = {"n_starts": n_starts, "n_local": n_local, "maxeval": maxeval}
    if start is None and applicable(meas, model, space, loss, enforce_energy, use_fast):
        with single_threaded_blas():
            affine = AffineFit(meas, model, space, loss, SCORE_ROWS)
            affine.ftol = LM_FTOL if ftol is None else float(ftol)
            res = refine_starts(affine, rng, t0=t0, **loop)
        if res is not None:
            res = dataclasses.replace(res, cpu_s=time.process_time() - c0)
            if _robust(loss, meas) and covariance:
                res = robust_covariance(res, meas, Problem(meas, model, space, loss, use_fast=use_fast, linear=[]))
            return res
        if affine.handover is not None:     # where the affine stage's best basin lies
            start = space.to_params(affine.handover)
    with single_threaded_blas():  # as for the affine problem: BLAS's threads fight Dr.Jit's (measured 3-5x)
        general = GeneralFit(meas, model, space, loss, use_fast, enforce_energy, maxeval, start)
        general.ftol = LM_FTOL if ftol is None else float(ftol)
        res = refine_starts(general, rng, t0=t0, **loop)
        res = dataclasses.replace(res, cpu_s=time.process_time() - c0)
        return robust_covariance(res, meas, general.problem) if _robust(loss, meas) and covariance else res


#: a local run's relative objective tolerance (gonio.fitting.optimise.lm.levenberg_marquardt)
LM_FTOL = 1e-10

#: losses without a noise model: their covariance is the sandwich of their own residuals
#: (:func:`gonio.fitting.optimise.result.sandwich`), not the chi^2 Fisher matrix
ROBUST_COV = _loss.PROFILED


def _robust(loss: str, meas) -> bool:
    """The sandwich covariance: a loss without a noise model, or chi2 with per-point weights (a
    weighted likelihood's Fisher matrix J^T W J understates its covariance; White 1982)."""
    return loss in ROBUST_COV or (loss == "chi2" and meas.weight is not None)
