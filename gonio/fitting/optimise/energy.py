"""The energy constraint: albedo(wo_k) <= 1 (each channel, fixed outgoing directions) as a
nonlinear inequality for nlopt's SLSQP (Kraft 1988), which polishes the full parameter
vector when the unconstrained optimum violates it; its objective is divided by its starting
value (SLSQP throws on objectives of order 1e5 with nlopt 2.11). For a model that transmits
(``Structure.sides`` holds transmission) the constraint is R + T <= 1: the light from each
fixed direction, integrated over the outgoing directions on both faces."""

from __future__ import annotations

import nlopt
import numpy as np

from gonio.core.sides import Side
from gonio.models import fast

from gonio.fitting.likelihood import loss as _loss
from gonio.fitting.optimise.lm import forward_jacobian
from gonio.fitting.likelihood.problem import Evaluator

__all__ = ["NLOPT_ERRORS", "SLSQP_MAXTIME_S", "energy_directions", "scale_to_feasible", "slsqp_energy"]

#: What nlopt's optimize() raises on failure: its own classes (``nlopt.runtime_error`` and
#: friends are not Python's RuntimeError) and the standard ones.
NLOPT_ERRORS = tuple({RuntimeError, ValueError, nlopt.ForcedStop} | {
    getattr(nlopt, n) for n in ("runtime_error", "logic_error", "domain_error", "range_error", "overflow_error",
                                "underflow_error", "length_error") if isinstance(getattr(nlopt, n, None), type)})

#: Wall-time cap of the constrained SLSQP polish (each constraint gradient integrates the
#: albedo P + 1 times); a polish cut short is reported as not converged.
SLSQP_MAXTIME_S = 20.0


def energy_directions(n=6):
    theta = np.deg2rad(np.linspace(0.0, 85.0, n))
    return np.stack([np.sin(theta), np.zeros_like(theta), np.cos(theta)], axis=-1)


def slsqp_energy(problem, x0, energy_wo, maxeval):
    """SLSQP on the full unit box with albedo(wo_k) <= 1 (each channel) as constraints."""
    space, loss = problem.space, problem.loss
    r_of = problem.lm_residuals_u
    u0 = np.clip(space.to_unit(x0), 1e-9, 1 - 1e-9)
    norm = max(float(np.sum(r_of(u0) ** 2)), 1e-300)

    seen = {}                # objective at each point SLSQP evaluated, and the best point its own constraints allow
    best = {"u": None, "value": np.inf}

    def f(u, grad):
        r = r_of(u)
        if grad.size:
            J = problem.lm_jacobian_u(u)
            grad[:] = 2.0 * ((J if J is not None else forward_jacobian(r_of, u, r)).T @ r) / norm
        seen[u.tobytes()] = value = float(r @ r) / norm
        return value

    quad = _AlbedoQuadrature(problem, energy_wo)
    margin = [0.0]  # grows by the gap between this quadrature and model.albedo, if any

    def cons(result, u, grad):
        exact = quad.value_and_grad(u) if grad.size else None  # one compiled Jacobian, not P + 1 quadratures
        c = (exact[0] if exact is not None else quad(space.from_unit(u))) + margin[0]
        result[:] = c
        value = seen.get(u.tobytes(), np.inf)
        if np.max(c) <= 0.0 and value < best["value"]:
            best.update(u=u.copy(), value=value)
        if exact is not None:
            grad[:] = exact[1]
        elif grad.size:
            for j in range(u.size):
                step = 1e-6 if u[j] + 1e-6 <= 1.0 else -1e-6
                up = u.copy()
                up[j] += step
                grad[:, j] = (quad(space.from_unit(up)) + margin[0] - c) / step

    u = u0
    for _ in range(3):
        opt = nlopt.opt(nlopt.LD_SLSQP, space.size)
        opt.set_lower_bounds(np.zeros(space.size))
        opt.set_upper_bounds(np.ones(space.size))
        opt.set_min_objective(f)
        m = energy_wo.shape[0] * problem.meas.n_channels
        opt.add_inequality_mconstraint(cons, np.full(m, 1e-6))
        opt.set_ftol_rel(1e-12)
        opt.set_xtol_rel(1e-9)
        opt.set_maxeval(min(maxeval, 200))
        opt.set_maxtime(SLSQP_MAXTIME_S)
        try:
            u = opt.optimize(np.clip(u, 1e-9, 1 - 1e-9))
            status = opt.last_optimize_result()
        except nlopt.RoundoffLimited:
            status = nlopt.ROUNDOFF_LIMITED
        except NLOPT_ERRORS as exc:
            x, note = scale_to_feasible(problem, space.from_unit(u0), energy_wo)
            reason = " ".join(str(exc).split())[:120] or type(exc).__name__
            return x, _loss.objective(loss, problem.residuals_x(x)), False, f"nlopt SLSQP failed ({reason}){note}"
        excess = float(np.max(problem.albedo_excess(space.from_unit(u), energy_wo)))
        if excess <= 1e-4:
            break
        margin[0] += excess + 1e-4
    x = space.from_unit(u)
    ok = status in (1, 2, 3, 4) or status == nlopt.ROUNDOFF_LIMITED
    note = ""
    # SLSQP's iterates need not be feasible, nor its last one its best (cut short by maxeval or
    # maxtime it can end far above where it passed): the lowest objective among its last point,
    # the best point its constraints allowed and the scaled start, of those albedo <= 1 allows
    scaled, scaled_note = scale_to_feasible(problem, space.from_unit(u0), energy_wo)
    tries = [(x, ""), (scaled, scaled_note + " (SLSQP's points were worse)")]
    if best["u"] is not None:
        tries.insert(1, (space.from_unit(best["u"]), "; its best feasible point kept"))
    ranked = [(float(np.sum(problem.lm_residuals_u(space.to_unit(xt)) ** 2)), k) for k, (xt, _) in enumerate(tries)
              if np.max(problem.albedo_excess(xt, energy_wo)) <= 1e-4]
    if ranked:
        x, extra = tries[min(ranked)[1]]
        note += extra if min(ranked)[1] else ""
    else:
        ok = False
        x, note = scale_to_feasible(problem, x, energy_wo)
    return x, _loss.objective(loss, problem.residuals_x(x)), ok, _status_text(status) + note


def scale_to_feasible(problem, x, energy_wo):
    """The fallback when SLSQP fails or ends infeasible: shrink each channel's affine
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
    instead of ``model.albedo``'s quadrature per call, so that SLSQP's constraint gradients
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


def _status_text(status) -> str:
    return {1: "success", 2: "stopval reached", 3: "ftol reached", 4: "xtol reached",
            5: "maxeval reached", 6: "maxtime reached", -1: "failure", -4: "roundoff limited"}.get(int(status), str(status))
