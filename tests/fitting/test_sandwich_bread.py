"""The sandwich covariance's bread (gonio.fitting.optimise.result): the differenced Hessian stops
at the first leading block that is not positive definite, and the covariance is the same."""

import numpy as np
import pytest

import gonio.fitting.optimise.result as _result
from gonio.fitting.optimise.result import _positive_definite, objective_hessian


def test_a_leading_block_that_fails_means_the_whole_fails():
    """Cauchy interlacing: lambda_min(H) <= lambda_min(H_k) and lambda_max(H_k) <= lambda_max(H),
    so _positive_definite's test (lambda_min > 1e-9 lambda_max after diagonal scaling) failing
    on a leading block fails on H. Random symmetric matrices near the boundary (seeded)."""
    rng = np.random.default_rng(35)
    for _ in range(300):
        n = int(rng.integers(2, 9))
        M = rng.normal(size=(n, n))
        H = M @ M.T - rng.uniform(0.0, 2.0) * np.eye(n)
        full = _positive_definite(H)
        for k in range(1, n + 1):
            if not _positive_definite(H[:k, :k]):
                assert not full
                break


class _Space:
    size = 3
    lower = np.zeros(3)
    upper = np.ones(3)


class _Saddle:
    """r(x) = (x0 x1 - a, x2 - 0.5, x0 + 2 x1 + x2): at x0 = 0.01, x1 = 0.02 and a = 6 the term
    r_0 d^2 r_0 = -6 (0 1; 1 0) makes the leading 2 x 2 block indefinite (off-diagonal -4); at x0 = x1 = 0.9 and
    a = 0.81, r_0 = 0 and the Hessian is J^T J (full rank). The exact Jacobian, counted."""
    space = _Space()

    def __init__(self, a):
        self.a, self.calls = a, 0

    def loss_jacobian(self, problem, x, loss):
        self.calls += 1
        r = np.array([x[0] * x[1] - self.a, x[2] - 0.5, x[0] + 2.0 * x[1] + x[2]])
        J = np.array([[x[1], x[0], 0.0], [0.0, 0.0, 1.0], [1.0, 2.0, 1.0]])
        return J, r


@pytest.mark.parametrize("x, a, definite", [([0.01, 0.02, 0.5], 6.0, False), ([0.9, 0.9, 0.6], 0.81, True)])
def test_definite_only_gives_the_same_bread(monkeypatch, x, a, definite):
    """Where the Hessian is positive definite, the same matrix; where it is not, None (the
    caller then takes J^T J, as for the full matrix), from fewer Jacobians."""
    p = _Saddle(a)
    monkeypatch.setattr(_result, "loss_jacobian", p.loss_jacobian)
    x = np.array(x)
    full = objective_hessian(p, x, "log")
    n_full = p.calls
    p.calls = 0
    early = objective_hessian(p, x, "log", definite_only=True)
    assert _positive_definite(full) is definite
    if definite:
        np.testing.assert_array_equal(early, full)
        assert p.calls == n_full
    else:
        assert early is None and p.calls == 3 < n_full    # J at x, then 2 columns: the 2 x 2 block
