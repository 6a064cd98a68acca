"""The Gauss-Newton SQP energy polish (gonio.fitting.optimise.gn_sqp, .energy) on a white
Lambertian + Cook-Torrance lobe whose unconstrained optimum breaks albedo <= 1: feasible, a
KKT point, and the optimum scipy's trust-constr finds on the same objective and constraints."""

import numpy as np
import pytest
import scipy.optimize

import gonio.models as gm
from gonio.fitting import fit
from gonio.fitting.likelihood.problem import Problem
from gonio.fitting.optimise.energy import (_AlbedoQuadrature, albedo_constraints, energy_directions,
                                           least_squares_functions, polish_energy, scale_to_feasible)
from gonio.fitting.optimise.gn_sqp import QPError, gn_sqp, solve_qp
from gonio.fitting.optimise.space import ParameterSpace

from _simdata import simulate

#: rho_d = 0.9 (white) plus a lobe: albedo(wo) = 0.9 + the lobe's, above 1 (checked below)
WHITE = {"diffuse_reflectance": [0.9, 0.9, 0.9], "specular_reflectance": [0.3, 0.3, 0.3],
         "roughness": 0.3, "f0": [0.3, 0.3, 0.3]}


@pytest.fixture(scope="module")
def white():
    model = gm.get("cooktorrance")
    wo = energy_directions()
    assert float(np.max(model.albedo(wo, model.validate(WHITE)))) > 1.05
    meas = simulate(model, WHITE, np.random.default_rng(35), n=500)   # 500 points: the compiled path
    free = fit(meas, model, rng=np.random.default_rng(0), enforce_energy=False)
    space = ParameterSpace(model, meas.n_channels)
    problem = Problem(meas, model, space, "chi2")
    assert problem.normal_available
    assert float(np.max(problem.albedo_excess(free.x, wo))) > 0.02      # the unconstrained optimum breaks it
    return problem, free, wo


def test_solve_qp_against_scipy_slsqp():
    """The least-distance QP solver against scipy's SLSQP on random strictly convex QPs with
    inequality rows and a box (the same minimiser, multipliers to 1e-6 relative)."""
    rng = np.random.default_rng(7)
    for _ in range(5):
        M = rng.normal(size=(20, 8))
        H, b = M.T @ M + 1e-3 * np.eye(8), 5.0 * rng.normal(size=8)
        G, h = rng.normal(size=(4, 8)), 0.1 * rng.normal(size=4)
        lo, hi = np.full(8, -0.3), np.full(8, 0.3)
        d, lam = solve_qp(H, b, G, h, lo, hi)
        ref = scipy.optimize.minimize(lambda x: (0.5 * x @ H @ x + b @ x, H @ x + b), np.zeros(8), jac=True,
                                      method="SLSQP", bounds=list(zip(lo, hi)),
                                      constraints=[{"type": "ineq", "fun": lambda x: h - G @ x, "jac": lambda x: -G}],
                                      options={"ftol": 1e-12, "maxiter": 500})
        assert ref.success
        np.testing.assert_allclose(d, ref.x, atol=1e-6)
        np.testing.assert_allclose(lam, ref.multipliers[:4], rtol=1e-5, atol=1e-8)


def test_solve_qp_relaxes_rows_the_box_forbids():
    """Rows no d in the box meets: the least-violation (elastic) step, d = lo on the row."""
    d, _ = solve_qp(np.eye(2), np.zeros(2), np.array([[-1.0, 0.0]]), np.array([-1.0]), np.full(2, -0.5),
                    np.full(2, 0.5))
    np.testing.assert_allclose(d, [0.5, 0.0], atol=1e-9)
    with pytest.raises(QPError):
        solve_qp(np.array([[1.0, 0.0], [0.0, -1.0]]), np.zeros(2), np.zeros((1, 2)), np.zeros(1), -np.ones(2),
                 np.ones(2))


#: trust-constr's optimum of the problem below (the long test runs it: gtol 1e-8, 693
#: iterations, ~15 s on the shared 2-core machine, against GN-SQP's 5 trial points)
TRUST_CONSTR_CHI2 = 109506.5654449


def _coarse(white):
    """The solver's problem: the fit's functions with a coarse albedo quadrature (16 x 24
    nodes: the solver's test, not the quadrature's), trust-constr's c and G asked apart."""
    problem, free, wo = white
    quad = _AlbedoQuadrature(problem, wo, n_mu=16, n_phi=24)
    normal, cost = least_squares_functions(problem)
    plain = albedo_constraints(quad, [0.0])
    seen = {}

    def constraints(u, grad=True):
        key = (u.tobytes(), grad)
        if key not in seen:
            seen.clear()
            seen[key] = plain(u, grad)
        return seen[key]

    return normal, cost, constraints, problem.space.to_unit(free.x)


def test_gn_sqp_is_the_constrained_optimum(white):
    """From the unconstrained optimum: feasible; KKT (the projected gradient of the Lagrangian
    below 1e-3 of the objective's gradient, with the polish's own multipliers >= 0, zero on
    rows off their bound); and trust-constr's optimum (TRUST_CONSTR_CHI2). Tolerance: the
    polish stops at a relative objective change of 1e-7 (GN_SQP_FTOL): 1e-6 relative."""
    normal, cost, constraints, u0 = _coarse(white)
    res = gn_sqp(u0, normal, cost, constraints)
    assert res.converged, res.message
    c, G = constraints(res.u)
    assert float(np.max(c)) <= 1e-6
    f, g, _ = normal(res.u)
    f0 = normal(u0)[0]
    grad = 2.0 * g / f0 + G.T @ res.multipliers               # the Lagrangian's, in res's scaling
    assert np.all(res.multipliers >= 0.0) and np.max(res.multipliers) > 0.0   # the constraint binds
    assert np.all(res.multipliers[c < -1e-4] <= 1e-9)                          # complementarity
    proj = np.where((res.u <= 0.0) & (grad > 0) | (res.u >= 1.0) & (grad < 0), 0.0, grad)
    assert np.linalg.norm(proj) <= 1e-3 * np.linalg.norm(2.0 * g / f0), (proj, grad)
    assert f == pytest.approx(TRUST_CONSTR_CHI2, rel=1e-6)


@pytest.mark.long    # trust-constr's interior point: ~700 iterations, ~15 s
def test_gn_sqp_matches_trust_constr(white):
    """scipy's trust-constr (Byrd-Omojokun SQP with a barrier, gtol 1e-8) on the same
    functions: the same objective to 1e-6 relative, the same point to 1e-4 in the unit box
    (measured: 3.5e-6), both feasible."""
    normal, cost, constraints, u0 = _coarse(white)
    res = gn_sqp(u0, normal, cost, constraints)
    f0 = normal(u0)[0]
    ref = scipy.optimize.minimize(
        lambda u: (cost(u) / f0, 2.0 * normal(u)[1] / f0), u0, jac=True, method="trust-constr",
        bounds=scipy.optimize.Bounds(0.0, 1.0),
        constraints=[scipy.optimize.NonlinearConstraint(lambda u: constraints(u)[0], -np.inf, 0.0,
                                                        jac=lambda u: constraints(u)[1])],
        options={"gtol": 1e-8, "xtol": 1e-12, "maxiter": 2000})
    assert float(np.max(constraints(ref.x)[0])) <= 1e-6
    assert res.cost == pytest.approx(cost(ref.x), rel=1e-6)
    assert cost(ref.x) == pytest.approx(TRUST_CONSTR_CHI2, rel=1e-6)
    np.testing.assert_allclose(res.u, ref.x, atol=1e-4)


def test_polish_energy_meets_albedo_and_beats_the_scaled_start(white):
    """The whole polish (model.albedo's check, the margin rounds): albedo <= 1 within 1e-4 and
    an objective no worse than the scaled start's."""
    problem, free, wo = white
    x, objective, converged, message = polish_energy(problem, free.x, wo, 2000)
    assert converged, message
    assert float(np.max(problem.albedo_excess(x, wo))) <= 1e-4
    scaled, _ = scale_to_feasible(problem, free.x, wo)
    assert objective <= float(np.sum(problem.residuals_x(scaled) ** 2))
    assert objective >= free.objective                      # a constraint cannot lower the optimum


def test_polish_energy_falls_back_when_the_qp_fails(white, monkeypatch):
    """A QP the solver cannot solve: the scaled start, said so, albedo <= 1."""
    import gonio.fitting.optimise.gn_sqp as gs

    def broken(*a, **k):
        raise QPError("no solution")

    monkeypatch.setattr(gs, "solve_qp", broken)
    problem, free, wo = white
    x, _, converged, message = polish_energy(problem, free.x, wo, 2000)
    assert not converged and "polish failed" in message and "scaled" in message
    assert float(np.max(problem.albedo_excess(x, wo))) <= 1e-4


def _plane(a):
    """|u - a|^2 under u_1 + u_2 <= 1: its minimiser is a's projection onto the line,
    a - (a_1 + a_2 - 1) / 2 (1, 1) where that lies in the box."""
    def normal(u):
        r = u - a
        return float(r @ r), r, np.eye(2)

    def constraints(u, grad=True):
        return np.array([u[0] + u[1] - 1.0]), np.array([[1.0, 1.0]])

    return normal, lambda u: normal(u)[0], constraints


def test_gn_sqp_projection_onto_a_line():
    """Linear residuals and a linear constraint: the projection (0.45, 0.55), objective
    0.245, multiplier 2 (a_1 + a_2 - 1) / 2 / |r0|^2 in the objective's scaling. Tolerances:
    the stop at a relative objective change of 1e-7 leaves the objective within ~1e-7 of
    its minimum and the point within sqrt(1e-7) ~ 3e-4 along the line."""
    a = np.array([0.8, 0.9])
    normal, cost, constraints = _plane(a)
    u0 = np.array([0.7, 0.7])
    res = gn_sqp(u0, normal, cost, constraints)
    assert res.converged, res.message
    assert res.n_eval <= 10
    assert res.u[0] + res.u[1] <= 1.0 + 1e-6
    assert res.cost <= 0.245 * (1.0 + 1e-6)
    np.testing.assert_allclose(res.u, [0.45, 0.55], atol=3e-4)
    f0 = normal(u0)[0]
    np.testing.assert_allclose(res.multipliers, [2.0 * 0.35 / f0], rtol=1e-3)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_gn_sqp_refuses_a_start_that_is_not_finite(bad):
    normal, cost, constraints = _plane(np.array([0.8, 0.9]))
    with pytest.raises(FloatingPointError, match="not finite"):
        gn_sqp(np.array([0.7, 0.7]), normal, cost, lambda u, grad=True: (np.array([bad]), np.array([[1.0, 1.0]])))


def test_gn_sqp_rejects_trial_points_that_are_not_finite():
    """A cost that is NaN beyond u_1 = 0.6: those trials are rejected (never accepted as NaN),
    the step shrinks, and the answer stays finite and feasible."""
    a = np.array([0.8, 0.9])
    normal, cost, constraints = _plane(a)
    res = gn_sqp(np.array([0.3, 0.3]), normal, lambda u: np.nan if u[0] > 0.6 else cost(u), constraints)
    assert np.all(np.isfinite(res.u)) and np.isfinite(res.cost)
    assert res.u[0] + res.u[1] <= 1.0 + 1e-6


def test_gn_sqp_evaluation_cap_is_not_converged():
    """The safety net: stopped by its evaluation cap, it says so and does not claim convergence."""
    normal, cost, constraints = _plane(np.array([0.8, 0.9]))
    res = gn_sqp(np.array([0.05, 0.05]), normal, cost, constraints, maxeval=1)
    assert not res.converged and "evaluation cap" in res.message and res.n_eval == 1


def test_gn_sqp_refuses_a_start_that_is_not_a_number():
    normal, cost, constraints = _plane(np.array([0.8, 0.9]))
    with pytest.raises(FloatingPointError, match="not finite"):
        gn_sqp(np.array([np.nan, 0.5]), normal, cost, constraints)


@pytest.mark.parametrize("maxeval", [0, -5, np.inf, np.nan])
def test_polish_energy_takes_any_budget(white, maxeval):
    """A budget of 0 or below: no trial point, not converged, the scaled start or better,
    albedo <= 1; an infinite or NaN one: GN_SQP_MAXEVAL."""
    problem, free, wo = white
    x, _, converged, message = polish_energy(problem, free.x, wo, maxeval)
    assert float(np.max(problem.albedo_excess(x, wo))) <= 1e-4
    assert converged == (np.isinf(maxeval) or np.isnan(maxeval)), message


@pytest.mark.parametrize("rho,polished", [(0.3, False), (0.9, True)])
def test_a_fits_albedo_check_runs_once_where_nothing_is_polished(rho, polished, monkeypatch):
    """The fit's result checks albedo <= 1 at its optimum and reports the largest albedo: where
    the optimum holds, from one albedo quadrature at it (before eb9f60c: a second at the same
    x); after a polish, from the polished x's."""
    model = gm.get("cooktorrance")
    truth = {**WHITE, "diffuse_reflectance": [rho] * 3}
    meas = simulate(model, truth, np.random.default_rng(36), n=500)
    calls, real = [], Problem.albedo_excess
    monkeypatch.setattr(Problem, "albedo_excess", lambda self, x, wo: calls.append(np.array(x)) or real(self, x, wo))
    res = fit(meas, model, rng=np.random.default_rng(0), n_starts=0, n_local=1)
    after_polish = [x for x in calls if np.array_equal(x, res.x)]
    assert ("Gauss-Newton SQP" in res.method) is polished
    if not polished:
        assert len(after_polish) == 1
    assert res.energy["max_albedo"] == pytest.approx(float(np.max(model.albedo(energy_directions(), res.params))),
                                                     rel=1e-12)
