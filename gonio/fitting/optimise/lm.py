"""Levenberg-Marquardt in the unit box, with the caller's Jacobian or forward differences.

The fit's losses are all sums of squared residuals, so the local stage is a Gauss-Newton
method (Nocedal & Wright 2006, sec. 10.3) rather than a general quasi-Newton one. Each
iteration costs one Jacobian: the caller's exact one (``jac``) or P + 1 residual evaluations.
The iterate lives strictly inside the unit box [0, 1]^P (an active-set projection at the
faces); the damping is Marquardt's scaled diagonal (Marquardt 1963).

References
----------
Marquardt, D. W. (1963). An algorithm for least-squares estimation of nonlinear parameters.
J. SIAM 11(2), 431-441.
Nocedal, J., Wright, S. J. (2006). Numerical Optimization, 2nd ed., ch. 10 and sec. 16.7.
"""

# Why Gauss-Newton: near the optimum J^T J is the Hessian up to terms of the order of the
# residuals, and Gauss-Newton converges in a handful of iterations where SLSQP or MMA, which
# build curvature from gradients alone, need tens. The compiled kernels give jac in one call.
# Bounds: a coordinate at a face whose gradient pushes outward is frozen for that step; a
# coordinate that would cross a face goes 0.99 of the way to it and the others' step is
# solved again with it held there (_box_step; Coleman & Li 1996 scale the whole step
# instead). Clipping that coordinate alone and keeping the others' step, solved as if it had
# crossed, made a step that failed until the damping shortened it: near a face every
# iteration then moved little (docs/performance.md, gonio.fitting.optimise.lm). No
# coordinate moves more than a quarter of the box in one step. Damping: lambda divided by 5
# on success and multiplied by 8 on failure or on a step longer than that.
# Coleman, T. F., Li, Y. (1996). An interior trust region approach for nonlinear minimization
# subject to bounds. SIAM J. Optim. 6(2), 418-445.

from __future__ import annotations

import dataclasses

import numpy as np

__all__ = ["LMResult", "levenberg_marquardt", "forward_jacobian"]


@dataclasses.dataclass
class LMResult:
    u: np.ndarray
    r: np.ndarray
    cost: float
    converged: bool
    message: str
    n_iter: int


def forward_jacobian(fun, u, r0, h=1e-6):
    """Forward differences in the unit box (backward at the upper face), shape (M, P)."""
    J = np.empty((r0.size, u.size))
    for j in range(u.size):
        step = h if u[j] + h <= 1.0 else -h
        up = u.copy()
        up[j] += step
        J[:, j] = (fun(up) - r0) / step
    return J


#: Largest step in any unit-box coordinate (a quarter of the box): where two parameters are
#: nearly degenerate (a conductor channel far from its optimum, where F barely depends on
#: eta and k) the Gauss-Newton step along the weak direction is huge and lands on a face;
#: the global stage explores, the local stage stays local.
MAX_STEP = 0.25
#: Fraction of the way to a face of the box that a step crossing it goes (see _inside).
TO_FACE = 0.99
#: rounds of :func:`_box_step`: coordinates held at the faces they would cross, the rest solved
#: again (a round only adds held coordinates, never releases one: docs/performance.md)
HOLD_ROUNDS = 3


def _inside(u, step):
    """u + step, where a coordinate would leave the unit box moving only ``TO_FACE`` of the
    way to the face it crosses (strictly feasible iterates, after Coleman & Li 1996 and
    scipy's 'trf', which scale the whole step back; here each coordinate on its own). Clipping onto the face instead can strand a parameter at a point where
    the residuals do not depend on it to first order (a conductor's k = 0: F depends on
    k^2), where its Jacobian column vanishes and no Gauss-Newton step leaves; a coordinate
    already on a face stays there (it is not free unless the gradient points inward)."""
    t = u + step
    t = np.where(t < 0.0, u * (1.0 - TO_FACE), t)
    t = np.where(t > 1.0, 1.0 - (1.0 - u) * (1.0 - TO_FACE), t)
    return np.clip(t, 0.0, 1.0)


def _box_step(M, g, u):
    """The damped Gauss-Newton step ``-M^-1 g`` from ``u`` (the free coordinates), kept in the
    unit box: a coordinate that would cross a face is held ``TO_FACE`` of the way to it and
    the other coordinates' step is solved again with it held there (the subspace minimisation
    of a gradient-projection step, Nocedal & Wright 2006 sec. 16.7), up to
    :data:`HOLD_ROUNDS` times; :func:`_inside` takes what still crosses."""
    s = np.linalg.solve(M, -g)
    held = np.zeros(g.size, dtype=bool)
    for _ in range(HOLD_ROUNDS):
        t = u + s
        cross = ((t < 0.0) | (t > 1.0)) & ~held
        if not np.any(cross):
            break
        s[cross] = np.where(t[cross] < 0.0, -u[cross], 1.0 - u[cross]) * TO_FACE
        held |= cross
        rest = ~held
        if not np.any(rest):
            break
        s[rest] = np.linalg.solve(M[np.ix_(rest, rest)], -(g[rest] + M[np.ix_(rest, held)] @ s[held]))
    return s


def _value(fun, cost_fn, u):
    """(residuals or None, cost) at u: from ``cost_fn`` alone where the caller gives one."""
    if cost_fn is not None:
        return None, float(cost_fn(u))
    r = fun(u)
    return r, float(r @ r)


def _damped_step(fun, u, r, cost, J, Af, gf, free, lam, ftol, atol, budget, cost_fn=None):
    """Raise the damping until a step inside the box lowers the cost.

    Returns ``(outcome, u_new, r_new, c_new, lam)`` with outcome ``"accepted"``,
    ``"predicted"`` (a (nearly) Gauss-Newton step whose predicted decrease is below the
    tolerance: converged without evaluating it) or ``"none"`` (no decrease possible)."""
    d = np.maximum(np.diag(Af), 1e-12 * max(np.max(np.diag(Af)), 1e-300))
    u_new = r_new = None
    c_new = np.inf
    while lam < 1e12:
        try:
            step_f = _box_step(Af + lam * np.diag(d), gf, u[free])
        except np.linalg.LinAlgError:
            lam *= 8.0
            continue
        if not np.all(np.abs(step_f) <= MAX_STEP):  # a leap (or NaN), not a local step: damp more
            lam *= 8.0
            continue
        step = np.zeros_like(u)
        step[free] = step_f
        u_new = _inside(u, step)
        if lam <= 1e-3:  # (nearly) Gauss-Newton: is the step worth an evaluation?
            # |r|^2 - |r + J s|^2 = -(2 g.s + s^T A s): P x P work, and no cancellation
            s = (u_new - u)[free]
            pred = -float(2.0 * gf @ s + s @ Af @ s)
            if pred <= ftol * cost + atol:
                return "predicted", u_new, r_new, c_new, lam
        try:
            r_new, c_new = _value(fun, cost_fn, u_new)
        except FloatingPointError:
            c_new = np.inf
        if c_new < cost:
            return "accepted", u_new, r_new, c_new, lam
        lam *= 8.0
        if budget is not None and not budget():
            break
    return "none", u_new, r_new, c_new, lam


def levenberg_marquardt(fun, u0, *, max_iter: int = 60, ftol: float = 1e-10, atol: float = 0.0,
                        xtol: float = 1e-10, h: float = 1e-6, budget=None, jac=None,
                        abandon=None, normal=None, cost=None) -> LMResult:
    """Minimise ``sum(fun(u)**2)`` over the unit box from ``u0``.

    Parameters
    ----------
    fun : callable
        Residual vector of a unit-box point; may raise FloatingPointError (treated as +inf).
    ftol, atol : float
        Stop when an accepted step lowers the cost by less than ``ftol * cost + atol``.
    xtol : float
        Stop when the accepted step is shorter than ``xtol`` (unit box).
    budget : callable, optional
        Returns False once the caller's evaluation budget is spent.
    jac : callable, optional
        ``jac(u, r) -> J``, or None where it has no answer; forward differences of ``fun``
        by default and wherever ``jac`` returns None.
    abandon : callable, optional
        ``abandon(iteration, cost) -> bool``: give up a start that is clearly worse than one
        already refined (multi-start racing).
    normal : callable, optional
        ``normal(u, r) -> (J^T r, J^T J)``, or None where it has no answer (then ``jac``):
        the step's normal equations without the M x P Jacobian (reduced in a compiled
        kernel: memory independent of the number of residuals).
    cost : callable, optional
        ``cost(u) -> sum(fun(u)**2)`` without the residual vector (with ``normal``: then no
        step needs the residuals, unless ``normal`` has no answer); may raise
        FloatingPointError. The result's ``r`` is then None.

    Notes
    -----
    Convergence is declared *before* trying a step whose Gauss-Newton predicted decrease
    ``|r|^2 - |r + J s|^2`` is below ``ftol * cost + atol``, which saves the trial evaluation
    of the last, useless step.
    """
    u = np.clip(np.asarray(u0, dtype=np.float64), 0.0, 1.0)
    cost_fn = cost if normal is not None else None
    r, cost = _value(fun, cost_fn, u)
    lam = 1e-4
    message, converged = "max_iter reached", False
    it = 0
    for it in range(1, max_iter + 1):
        if budget is not None and not budget():
            message = "maxeval reached"
            break
        gA = normal(u, r) if normal is not None else None
        J = None
        if gA is not None:
            g, A = gA
        else:
            if r is None:
                r = fun(u)
            J = jac(u, r) if jac is not None else None
            if J is None:
                J = forward_jacobian(fun, u, r, h)
            g = J.T @ r
            A = J.T @ J
        free = ~(((u <= 0.0) & (g > 0)) | ((u >= 1.0) & (g < 0)))
        if not np.any(free) or np.max(np.abs(g[free])) <= 1e-14 * max(cost, 1e-300):
            message, converged = "gradient vanishes", True
            break
        outcome, u_new, r_new, c_new, lam = _damped_step(fun, u, r, cost, J, A[np.ix_(free, free)], g[free], free,
                                                         lam, ftol, atol, budget, cost_fn)
        if outcome == "predicted":
            return LMResult(u=u, r=r, cost=cost, converged=True,
                            message="predicted decrease below tolerance", n_iter=it)
        if outcome != "accepted":
            message, converged = "no decrease possible (at the optimum to working precision)", True
            break
        decrease = cost - c_new
        moved = float(np.max(np.abs(u_new - u)))
        u, r, cost = u_new, r_new, c_new
        lam = max(lam / 5.0, 1e-12)
        if decrease <= ftol * cost + atol:
            message, converged = "ftol reached", True
            break
        if moved <= xtol:
            message, converged = "xtol reached", True
            break
        if abandon is not None and abandon(it, cost):
            message, converged = "abandoned: worse than another start", False
            break
    return LMResult(u=u, r=r, cost=cost, converged=converged, message=message, n_iter=it)
