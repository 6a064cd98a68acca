"""The Levenberg-Marquardt stage near the box's faces: where the optimum holds coordinates at a
face, the other coordinates' step is solved with them held there, so the fit converges in a
few iterations to the bounded least-squares solution (scipy.optimize.lsq_linear's, a
reference implementation) instead of crawling at a high damping."""

import numpy as np
import pytest
from scipy.optimize import lsq_linear

from gonio.fitting.optimise.lm import levenberg_marquardt


def _coupled_problem(seed, p=8, m=40):
    """A linear least-squares problem whose columns are strongly correlated (pairwise
    correlation about 0.9) and whose unconstrained minimiser lies outside the unit box in
    some coordinates: the case where clipping one coordinate and keeping the others' step
    makes the step fail."""
    rng = np.random.default_rng(seed)
    base = rng.normal(size=(m, 1))
    J = 0.95 * base + 0.3 * rng.normal(size=(m, p))
    x_free = rng.uniform(0.2, 0.8, p)
    x_free[: p // 3] = rng.uniform(-0.6, -0.2, p // 3)       # beyond the lower face
    x_free[-1] = 1.4                                         # beyond the upper face
    b = J @ x_free + 0.01 * rng.normal(size=m)
    return J, b


@pytest.mark.parametrize("seed", range(6))
def test_converges_to_the_bounded_solution_in_few_iterations(seed):
    J, b = _coupled_problem(seed)
    ref = lsq_linear(J, b, bounds=(0.0, 1.0), method="bvls", tol=1e-14)
    assert ref.success
    lm = levenberg_marquardt(lambda u: J @ u - b, np.full(J.shape[1], 0.5), jac=lambda u, r: J, max_iter=60)
    assert lm.converged, lm.message
    # the faces are approached geometrically (0.99 of the way a step), so 60 iterations is
    # generous; the clipped-alone step of before needed all 60 and stopped short (the
    # mutation check in the commit)
    assert lm.n_iter <= 25, lm.n_iter
    # the cost is the reference's to the ftol (1e-10 relative) the run stops at
    ref_cost = float(np.sum((J @ ref.x - b) ** 2))
    assert lm.cost <= ref_cost * (1 + 1e-6) + 1e-12
    np.testing.assert_allclose(lm.u, ref.x, atol=1e-4)


def test_a_step_never_leaves_the_box():
    J, b = _coupled_problem(11)
    seen = []

    def fun(u):
        seen.append(u.copy())
        return J @ u - b

    levenberg_marquardt(fun, np.full(J.shape[1], 0.5), jac=lambda u, r: J, max_iter=60)
    seen = np.array(seen)
    assert np.all(seen >= 0.0) and np.all(seen <= 1.0)
