"""The energy constraint: albedo(wo_k) <= 1 (each channel, fixed outgoing directions) as a
nonlinear inequality, and the polish that meets it where the unconstrained optimum violates
it: the Gauss-Newton SQP of :mod:`gonio.fitting.optimise.gn_sqp` on the fit's own residuals,
with the constraint's exact derivatives from the compiled kernel. For a model that transmits
(``Structure.sides`` holds transmission) the constraint is R + T <= 1: the light from each
fixed direction, integrated over the outgoing directions on both faces."""

from __future__ import annotations

import numpy as np

from gonio.core.sides import Side
from gonio.models import fast

from gonio.fitting.likelihood import loss as _loss
from gonio.fitting.optimise.gn_sqp import GN_SQP_MAXEVAL, QPError, gn_sqp
from gonio.fitting.optimise.lm import forward_jacobian
from gonio.fitting.likelihood.problem import Evaluator

__all__ = ["albedo_constraints", "energy_directions", "least_squares_functions", "polish_energy",
           "scale_to_feasible"]


def energy_directions(n=6):
    theta = np.deg2rad(np.linspace(0.0, 85.0, n))
    return np.stack([np.sin(theta), np.zeros_like(theta), np.cos(theta)], axis=-1)


def polish_energy(problem, x0, energy_wo, maxeval):
    """The fit's least-squares objective minimised from ``x0`` under albedo(wo_k) <= 1 (each
    channel) by the Gauss-Newton SQP (:func:`gonio.fitting.optimise.gn_sqp.gn_sqp`):
    ``(x, objective, converged, message)``. The point returned meets albedo <= 1 within 1e-4
    (``model.albedo``) and is never worse than the scaled start (:func:`scale_to_feasible`),
    which is also what a failed polish returns."""
    space, loss = problem.space, problem.loss
    r_of = problem.lm_residuals_u
    u0 = np.clip(space.to_unit(x0), 0.0, 1.0)
    quad = _AlbedoQuadrature(problem, energy_wo)
    # margin: the gap between this quadrature and model.albedo, row by row, taken at the start
    # and again where each round ends, until it no longer moves on the rows near their bound
    # (at most 3 rounds): the polish then constrains model.albedo itself, neither looser nor
    # tighter
    margin = [_albedo_gap(problem, quad, space.from_unit(u0), energy_wo)]

    normal, cost = least_squares_functions(problem)
    constraints = albedo_constraints(quad, margin)

    # the caller's evaluation budget, at most GN_SQP_MAXEVAL trial points a round
    cap = int(min(max(float(maxeval), 0.0), GN_SQP_MAXEVAL)) if np.isfinite(float(maxeval)) else GN_SQP_MAXEVAL
    u, res, n_eval = u0, None, 0
    for _ in range(3):
        try:
            res = gn_sqp(u, normal, cost, constraints, maxeval=cap)
        except (QPError, FloatingPointError, np.linalg.LinAlgError) as exc:
            x, note = scale_to_feasible(problem, space.from_unit(u0), energy_wo)
            reason = " ".join(str(exc).split())[:120] or type(exc).__name__
            return x, _loss.objective(loss, problem.residuals_x(x)), False, f"GN-SQP polish failed ({reason}){note}"
        u, n_eval = res.u, n_eval + res.n_eval
        excess = problem.albedo_excess(space.from_unit(u), energy_wo)
        gap = _albedo_gap(problem, quad, space.from_unit(u), energy_wo)
        near = excess > -1e-3
        if float(np.max(excess)) <= 1e-4 and float(np.max(np.abs(gap - margin[0])[near], initial=0.0)) <= 1e-4:
            break
        margin[0] = gap
    x, ok, note = space.from_unit(u), res.converged, ""
    # never worse than the scaled start, and albedo <= 1 (model.albedo) whatever the polish did
    scaled, scaled_note = scale_to_feasible(problem, space.from_unit(u0), energy_wo)
    tries = [(x, ""), (scaled, scaled_note + " (the polish's point was worse)")]
    ranked = [(float(np.sum(r_of(space.to_unit(xt)) ** 2)), k) for k, (xt, _) in enumerate(tries)
              if np.max(problem.albedo_excess(xt, energy_wo)) <= 1e-4]
    if ranked:
        x, note = tries[min(ranked)[1]]
    else:
        ok = False
        x, note = scale_to_feasible(problem, x, energy_wo)
    message = f"{res.message} ({n_eval} evaluations){note}"
    return x, _loss.objective(loss, problem.residuals_x(x)), ok, message


def _albedo_gap(problem, quad, x, energy_wo):
    """model.albedo - the quadrature's albedo at x, one per constraint row (0 where not finite)."""
    gap = problem.albedo_excess(x, energy_wo) - quad(x)
    return np.where(np.isfinite(gap), gap, 0.0)


def least_squares_functions(problem):
    """``(normal, cost)`` of the fit's sum of squares in the unit box for
    :func:`~gonio.fitting.optimise.gn_sqp.gn_sqp`: the compiled kernel's normal equations
    where it has them (a trial's kernel brings them), else the exact or differenced Jacobian."""
    r_of = problem.lm_residuals_u

    def cost(u):
        if problem.normal_available:
            return problem.lm_cost_u(u)
        r = r_of(u)
        return float(r @ r)

    def normal(u):
        if problem.normal_available:
            f = problem.lm_cost_u(u)
            gA = problem.lm_normal_u(u)
            if gA is not None:
                return f, gA[0], gA[1]
        r = r_of(u)
        J = problem.lm_jacobian_u(u)
        J = forward_jacobian(r_of, u, r) if J is None else J
        return float(r @ r), J.T @ r, J.T @ J

    return normal, cost


def albedo_constraints(quad, margin):
    """``constraints(u, grad) -> (c, G)``: albedo - 1 + margin[0] by ``quad`` (an
    :class:`_AlbedoQuadrature`; margin[0] a number or one per row) and, where ``grad``, its
    derivatives: exact from the compiled kernel where it has them (one Jacobian, not P + 1
    quadratures), else forward differences."""
    space = quad.space

    def constraints(u, grad=True):
        if not grad:
            return quad(space.from_unit(u)) + margin[0], None
        exact = quad.value_and_grad(u)
        if exact is not None:
            return exact[0] + margin[0], exact[1]
        c = quad(space.from_unit(u)) + margin[0]
        G = np.empty((c.size, u.size))
        for j in range(u.size):
            step = 1e-6 if u[j] + 1e-6 <= 1.0 else -1e-6
            up = u.copy()
            up[j] += step
            G[:, j] = (quad(space.from_unit(up)) + margin[0] - c) / step
        return c, G

    return constraints


def scale_to_feasible(problem, x, energy_wo):
    """The fallback when the polish fails or ends infeasible: shrink each channel's affine
    parameters toward their lower bounds, ``a = lo + s_c (a - lo)``, by the largest s_c in
    [0, 1] with albedo_c(wo_k) <= 1. The albedo is affine in those parameters, so two
    albedo evaluations give s_c exactly. Returns (x, a note for the message); x unchanged
    (and the note says why) where no affine parameters exist or even s_c = 0 is infeasible."""
    groups = getattr(problem, "linear", None) or []
    c_n = problem.meas.n_channels
    if not groups:
        return x, "; no affine parameter to scale: albedo <= 1 NOT met"
    lo = problem.space.lower
    idx = [[g["index"][c] for g in groups] for c in range(c_n)]
    x0 = x.copy()
    for chan in idx:
        x0[chan] = lo[chan]
    a1 = (problem.albedo_excess(x, energy_wo) + 1.0).reshape(-1, c_n)
    a0 = (problem.albedo_excess(x0, energy_wo) + 1.0).reshape(-1, c_n)
    if np.any(a0 > 1.0):
        return x, "; albedo > 1 even at the affine parameters' lower bounds: NOT met"
    out = x.copy()
    for c, chan in enumerate(idx):
        slope = a1[:, c] - a0[:, c]
        over = slope > 0
        s = min([1.0] + list((1.0 - 1e-6 - a0[over, c]) / slope[over]))
        out[chan] = lo[chan] + max(s, 0.0) * (x[chan] - lo[chan])
    return out, "; affine parameters scaled to meet albedo <= 1"


class _AlbedoQuadrature:
    """albedo(wo_k) - 1 by a fixed product rule over wi (Gauss-Legendre in cos(theta_i),
    uniform in phi_i), evaluated with the fit's (compiled) evaluator: one batched evaluation
    instead of ``model.albedo``'s quadrature per call, so that the polish's constraint gradients
    stay cheap. The final albedo check uses ``model.albedo``."""

    def __init__(self, problem, wo, n_mu=64, n_phi=96):
        through = Side.TRANSMIT in tuple(problem.model.structure.sides)
        x, w = np.polynomial.legendre.leggauss(n_mu)
        mu, w_mu = 0.5 * (x + 1.0), 0.5 * w
        if through:                      # both faces: mu in (-1, 1), each half with its own nodes
            mu, w_mu = np.concatenate([mu, -mu]), np.concatenate([w_mu, w_mu])
        phi = (np.arange(n_phi) + 0.5) * 2.0 * np.pi / n_phi
        M, PHI = np.meshgrid(mu, phi, indexing="ij")
        s = np.sqrt(1.0 - M ** 2)
        free = np.stack([s * np.cos(PHI), s * np.sin(PHI), M], axis=-1).reshape(-1, 3)
        self.weight = (w_mu[:, None] * np.abs(M) * (2.0 * np.pi / n_phi)).reshape(-1)
        self.k = wo.shape[0]
        self.n = free.shape[0]
        self.space = problem.space
        fixed = np.repeat(wo, self.n, axis=0)
        # a reflector: albedo(wo_k) over wi (reciprocity makes it the reflectance); a transmitter
        # (not reciprocal across the interface): R + T of light from wo_k, over wo on both faces
        wi_, wo_ = (fixed, np.tile(free, (self.k, 1))) if through else (np.tile(free, (self.k, 1)), fixed)
        self.eval = Evaluator(problem.model, wi_, wo_, problem.meas.n_channels, use_fast=problem.eval.fast)

    def __call__(self, x):
        f = self.eval(self.space.to_params(x)).reshape(self.k, self.n, -1)
        return (np.einsum("knc,n->kc", f, self.weight) - 1.0).reshape(-1)

    def value_and_grad(self, u):
        """(albedo - 1, its derivative with respect to the unit-box coordinates u, (K C, P))
        from the compiled kernel's exact derivatives; None on the numpy path or where a
        derivative is not finite (the caller then differences)."""
        space = self.space
        x = space.from_unit(u)
        out = self.eval.jacobian(space.to_params(x))
        if out is None:
            return None
        f, J = out
        c_n = f.shape[1]
        value = (np.einsum("knc,n->kc", f.reshape(self.k, self.n, -1), self.weight) - 1.0).reshape(-1)
        G = np.zeros((self.k, c_n, space.size))
        dx_du = space.dx_du(x)
        for j, e in enumerate(space.entries):
            if e.param not in J:
                return None
            col = fast.jacobian_column(space.model, J, e.param, e.channel)  # (N, C): every channel it reaches
            G[:, :, j] = np.einsum("knc,n->kc", col.reshape(self.k, self.n, -1), self.weight) * dx_du[j]
        G = G.reshape(-1, space.size)
        if not (np.all(np.isfinite(value)) and np.all(np.isfinite(G))):
            return None
        return value, G
