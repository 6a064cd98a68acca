"""A Gauss-Newton SQP polish: a least-squares objective under smooth inequality constraints.

Each outer step linearises the residuals and the constraints at u (the unit box), solves the
quadratic programme ``min |r + J d|^2 + mu |D d|^2`` subject to ``c + G d <= 0`` and the box
(:func:`solve_qp`), and accepts the step on the l1 merit ``|r|^2 / |r0|^2 + rho sum max(c, 0)``
(Nocedal & Wright 2006, sec. 18.3-18.5). The damping mu is Levenberg-Marquardt's, updated from
the ratio of the merit's actual to predicted decrease (Madsen, Nielsen & Tingleff 2004, eq.
3.14); rho follows the multipliers and N&W eq. 18.36. It stops on a relative tolerance of the
objective (:data:`GN_SQP_FTOL`), never on wall time: its iterates are the same on any machine.

References: Madsen, Nielsen, Tingleff (2004), Methods for non-linear least squares problems,
2nd ed.; Nocedal, Wright (2006), Numerical Optimization, 2nd ed., ch. 18; Lawson, Hanson (1974),
Solving Least Squares Problems, ch. 23 (least-distance programming).
"""

# Why a least-distance programme: with H = L L^T (after Jacobi scaling) and z = L^T d + L^-1 b,
# the QP is min |z| subject to linear rows (the constraints and the box's 2P faces), which one
# non-negative least-squares problem solves exactly, multipliers included (Lawson & Hanson ch.
# 23; scipy's nnls): no model evaluation, no iteration of its own to tune. scipy's SLSQP on the
# quadratic model, tried first, stopped with "Positive directional derivative for linesearch"
# on a synthetic Cook-Torrance problem. Where the linearised constraints and the box admit no
# step, the least violation reachable (scipy's linprog, HiGHS) relaxes them (an elastic step).

from __future__ import annotations

import dataclasses

import numpy as np
import scipy.linalg
import scipy.optimize

__all__ = ["GN_SQP_FTOL", "GN_SQP_MAXEVAL", "GNSQPResult", "QPError", "gn_sqp", "solve_qp"]

#: the polish stops where an accepted step (or the model's prediction of the next) lowers the
#: objective by less than this fraction of it: -2 ln L = n ln(S / n) then moves by n * 1e-7
#: (2e-3 at 23,000 values), as the screening's SCREEN_FTOL (gonio.fitting.selection.auto)
GN_SQP_FTOL = 1e-7
#: a safety net: trial points evaluated at most (each one cost, one set of constraints);
#: reaching it is reported as not converged
GN_SQP_MAXEVAL = 100
#: a constraint c <= CTOL counts as met (albedo units)
CTOL = 1e-6
#: no unit-box coordinate moves more than this in one step (as gonio.fitting.optimise.lm)
MAX_STEP = 0.25


class QPError(ArithmeticError):
    """The quadratic subproblem has no solution the solver could find."""


@dataclasses.dataclass
class GNSQPResult:
    u: np.ndarray
    cost: float
    violation: float
    converged: bool
    message: str
    n_eval: int
    n_iter: int
    multipliers: np.ndarray


def solve_qp(H, b, G, h, lo, hi):
    """``min 1/2 d^T H d + b.d`` subject to ``G d <= h`` and ``lo <= d <= hi``, H positive
    definite: (d, the multipliers of the G rows). As a least-distance programme solved by
    non-negative least squares (Lawson & Hanson 1974, ch. 23, with scipy's ``nnls``) after
    Jacobi scaling; where no d meets every row, the G rows are relaxed by the least total
    violation the box allows (an elastic step). QPError where that fails too."""
    P = b.size
    s = 1.0 / np.sqrt(np.maximum(np.diag(H), 1e-300))          # d = s * e: unit diagonal
    Hs = H * np.outer(s, s)
    try:
        L = np.linalg.cholesky(Hs)
    except np.linalg.LinAlgError as exc:
        raise QPError(f"QP Hessian not positive definite ({exc})") from None
    Linv_T = scipy.linalg.solve_triangular(L, np.eye(P), lower=True).T * s[:, None]   # d = Linv_T (z - w)
    w = scipy.linalg.solve_triangular(L, s * b, lower=True)
    C = np.vstack([G, np.eye(P), -np.eye(P)])
    CL = C @ Linv_T
    if not (np.all(np.isfinite(CL)) and np.all(np.isfinite(w))):
        raise QPError("the QP is not finite")
    E = -CL                                                      # LDP: min |z|, E z >= f

    def ldp(rhs):
        f = -(rhs + CL @ w)
        scale = max(float(np.max(np.abs(f))), 1.0)
        Eb = np.vstack([E.T, f[None, :] / scale])
        e = np.zeros(P + 1)
        e[P] = 1.0
        mu, _ = scipy.optimize.nnls(Eb, e, maxiter=50 * Eb.shape[1])
        r = Eb @ mu - e
        if not np.isfinite(r[P]) or -r[P] <= 1e-12:                # |r| = 0: the rows admit no z
            return None
        return -r[:P] / r[P] * scale, mu / (-r[P]) * scale   # the LDP of f / scale, scaled back

    h_all = np.concatenate([h, hi, -lo])
    out = ldp(h_all)
    if out is None:
        out = ldp(h_all + np.concatenate([_least_violation(G, h, lo, hi) + 1e-12, np.zeros(2 * P)]))
        if out is None:
            raise QPError("the QP's constraints admit no step, even relaxed")
    z, lam = out
    d = Linv_T @ (z - w)
    if not np.all(np.isfinite(d)):
        raise QPError("the QP's solution is not finite")
    return d, lam[:G.shape[0]]


def _least_violation(G, h, lo, hi):
    """t >= 0 of least sum with G d <= h + t for some d in [lo, hi] (linprog, HiGHS)."""
    m, P = G.shape
    A = np.hstack([G, -np.eye(m)])
    out = scipy.optimize.linprog(np.concatenate([np.zeros(P), np.ones(m)]), A_ub=A, b_ub=h,
                                 bounds=list(zip(lo, hi)) + [(0.0, None)] * m, method="highs")
    if out.status != 0:
        raise QPError(f"no step within the box: {out.message}")
    return out.x[P:]


def gn_sqp(u0, normal, cost, constraints, *, ftol=GN_SQP_FTOL, maxeval=GN_SQP_MAXEVAL) -> GNSQPResult:
    """Minimise ``|r(u)|^2`` subject to ``c(u) <= 0`` over the unit box from ``u0``.

    Parameters
    ----------
    normal : callable
        ``normal(u) -> (|r|^2, J^T r, J^T J)`` at u.
    cost : callable
        ``cost(u) -> |r|^2`` (a trial point); may raise FloatingPointError (rejected).
    constraints : callable
        ``constraints(u, grad) -> (c, G)``: the constraint values (m,) and, where ``grad``,
        their derivatives (m, P) (else None: a trial point needs its values only).
    ftol : float
        Converged where, at a feasible point, an accepted step or the model's prediction for a
        (nearly) undamped one lowers the objective by less than ``ftol`` times it.
    maxeval : int
        Trial points evaluated at most; reaching it is not converged.

    Notes
    -----
    Merit phi(u) = |r|^2 / |r0|^2 + rho sum max(c, 0); the model of phi along d replaces r by
    r + J d and c by c + G d. A step is accepted where phi falls by more than 1e-4 of the
    model's predicted fall.
    """
    u = np.clip(np.asarray(u0, dtype=np.float64), 0.0, 1.0)
    f, g, A = normal(u)
    f0 = max(float(f), 1e-300)
    c, G = constraints(u, True)
    if not all(np.all(np.isfinite(v)) for v in (u, f, g, A, c, G)):
        raise FloatingPointError("GN-SQP: the start's objective, constraints or derivatives are not finite")
    rho, mu, nu = 1.0, 1e-4, 2.0
    lam = np.zeros(c.size)
    n_eval = it = 0
    message, converged = "evaluation cap reached", False

    def merit(fv, cv):
        return fv / f0 + rho * float(np.sum(np.maximum(cv, 0.0)))

    while True:
        it += 1
        Dm = np.maximum(np.diag(A), 1e-12 * max(float(np.max(np.diag(A))), 1e-300))
        H = 2.0 * (A + mu * np.diag(Dm)) / f0
        b = 2.0 * g / f0
        lo, hi = np.maximum(-u, -MAX_STEP), np.minimum(1.0 - u, MAX_STEP)
        d, lam = solve_qp(H, b, G, -c, lo, hi)
        d = np.clip(u + d, 0.0, 1.0) - u
        dq = float(2.0 * g @ d + d @ A @ d) / f0          # the Gauss-Newton model's change of |r|^2 / f0
        viol, viol_lin = float(np.sum(np.maximum(c, 0.0))), float(np.sum(np.maximum(c + G @ d, 0.0)))
        # N&W eq. 18.36 with sigma = 1/2, and the exact penalty's rho > max multiplier (sec. 18.3)
        need = max(1.1 * float(np.max(lam, initial=0.0)), 2.0 * dq / (viol - viol_lin) if viol - viol_lin > 1e-300 else 0.0)
        rho = max(rho, need)
        phi = merit(f, c)
        pred = -dq + rho * (viol - viol_lin)
        feasible = float(np.max(c)) <= CTOL
        if feasible and mu <= 1e-3 and pred <= ftol * f / f0:
            message, converged = "predicted decrease below tolerance", True
            break
        if n_eval >= maxeval:
            break
        n_eval += 1
        u_t = u + d
        try:
            f_t = float(cost(u_t))
            c_t, _ = constraints(u_t, False)
            phi_t = merit(f_t, c_t)
            phi_t = phi_t if np.isfinite(phi_t) else np.inf     # a trial that is not finite is rejected
        except FloatingPointError:
            phi_t = np.inf
        ratio = (phi - phi_t) / pred if pred > 0 else -np.inf
        if np.isfinite(phi_t) and ratio > 1e-4:
            decrease = f - f_t
            u, c = u_t, c_t
            f, g, A = normal(u)
            G = constraints(u, True)[1]
            if not (np.all(np.isfinite(g)) and np.all(np.isfinite(A)) and np.all(np.isfinite(G))):
                raise FloatingPointError("GN-SQP: the derivatives are not finite at an accepted point")
            mu *= max(1.0 / 3.0, 1.0 - (2.0 * ratio - 1.0) ** 3)
            nu = 2.0
            if float(np.max(c)) <= CTOL and abs(decrease) <= ftol * f and np.max(np.abs(d)) < MAX_STEP:
                message, converged = "ftol reached", True
                break
        else:
            mu *= nu
            nu *= 2.0
            if mu > 1e12:
                message, converged = "no decrease possible (at the optimum to working precision)", feasible
                break
    return GNSQPResult(u=u, cost=float(f), violation=float(np.max(c, initial=0.0)), converged=converged,
                       message=f"GN-SQP: {message}", n_eval=n_eval, n_iter=it, multipliers=lam)
