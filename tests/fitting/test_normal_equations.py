"""The Levenberg-Marquardt step from normal equations reduced in the compiled kernel
(issue 18: no N x P Jacobian per iteration, so a 1e6-point fit runs in memory independent
of P): the sums equal J^T W r and J^T W J formed from the kernel's own Jacobian, the fit
through them equals the fit through the Jacobian, and Dask's task chunks cover every
dataset once, in order."""

import numpy as np
import pytest

import gonio.models as gm
from gonio.fitting import fit
from gonio.fitting._batch import task_chunks
from gonio.fitting._problem import Problem
from gonio.fitting._space import ParameterSpace
from gonio.models import fast

from _simdata import simulate

pytestmark = pytest.mark.skipif(not fast.available(), reason="Dr.Jit LLVM backend unavailable")


@pytest.mark.parametrize("name,options", [("roughconductor", {"anisotropic": True}), ("cooktorrance", {}),
                                          ("roughplastic", {"distribution": "ggx"})])
def test_normal_equations_equal_the_jacobian_products(name, options):
    """cost, g, A against sum W r^2, J^T W r, J^T W J of fast.jacobian's columns, to 1e-12
    relative (float64 sums; only the order of the additions differs). Two batch sizes: a
    kernel traced for one size must not answer for another."""
    model = gm.get(name, **options)
    rng = np.random.default_rng(3)
    for n in (700, 1900):
        wi, wo = (gm.geometry.directions(np.arccos(rng.uniform(0.1, 1, n)), rng.uniform(-np.pi, np.pi, n))
                  for _ in range(2))
        dirs = fast.Directions(wi, wo, np.float64)
        p = model.defaults()
        f, J = fast.jacobian(model, dirs, p)
        y = f * (1 + 0.05 * rng.standard_normal(f.shape))
        w = rng.uniform(0.5, 2.0, f.shape)
        cost, g, A, entries = fast.normal_equations(model, dirs, p, y, w)
        cols = []
        for param, c in entries:
            col = J[param] if c == -1 else np.where(np.arange(3) == c, J[param], 0.0)
            cols.append(col.ravel())
        D, r, W = np.stack(cols, 1), (f - y).ravel(), w.ravel()
        assert cost == pytest.approx(np.sum(W * r * r), rel=1e-12)
        np.testing.assert_allclose(g, D.T @ (W * r), rtol=1e-10, atol=1e-12 * np.abs(g).max())
        np.testing.assert_allclose(A, D.T @ (W[:, None] * D), rtol=1e-10, atol=1e-12 * np.abs(A).max())


def test_lm_step_from_normal_equations_equals_the_jacobian_step(monkeypatch):
    """Problem.lm_normal_u is (J^T r, J^T J) of lm_residuals_u / lm_jacobian_u in the unit
    box, mask and solid-angle weights included; a fit through it reaches the optimum of the
    Jacobian path (same x to 1e-6 of its sigma)."""
    model = gm.get("roughconductor", distribution="ggx")
    truth = {"eta": np.array([0.2, 0.9, 1.1]), "k": np.array([3.0, 2.5, 2.0]), "alpha": 0.2}
    meas = simulate(model, truth, np.random.default_rng(4), n=800)
    meas.use[::9, 1] = False
    space = ParameterSpace(model, 3)
    prob = Problem(meas, model, space, "chi2")
    u = space.to_unit(space.default()) * 0.9 + 0.05
    r, D = prob.lm_residuals_u(u), prob.lm_jacobian_u(u)
    g, A = prob.lm_normal_u(u)
    np.testing.assert_allclose(g, D.T @ r, rtol=1e-9, atol=1e-12 * np.abs(g).max())
    np.testing.assert_allclose(A, D.T @ D, rtol=1e-9, atol=1e-12 * np.abs(A).max())
    assert Problem(meas, model, space, "robust").lm_normal_u(u) is None  # transformed residuals: not affine
    res = fit(meas, model, rng=np.random.default_rng(0), n_starts=0, n_local=1)
    monkeypatch.setattr(Problem, "lm_normal_u", lambda self, u, r=None: None)  # the Jacobian path
    ref = fit(meas, model, rng=np.random.default_rng(0), n_starts=0, n_local=1)
    np.testing.assert_allclose(res.x, ref.x, atol=1e-6 * ref.std.max())


def test_task_chunks_cover_every_dataset_once_in_order():
    for n, threads in ((16, 2), (3, 2), (100, 2), (7, 0), (1, 8)):
        chunks = task_chunks(n, threads)
        assert [i for a, b in chunks for i in range(a, b)] == list(range(n))
        assert len(chunks) == (n if threads == 0 else min(n, 4 * threads))
    assert task_chunks(0, 2) == []


def test_default_start_is_accepted_only_when_it_fits_to_the_noise(monkeypatch):
    """The general problem skips its global stage when the fit from the defaults has
    chi2 <= E + 3 sd (E = dof for unit weights, sd = sqrt(2 dof)); the optimum is then the one
    the full multi-start search finds; a chi2 beyond that bound, another loss or an
    unconverged run is never accepted."""
    from gonio.fitting._optimise import GeneralFit

    model = gm.get("roughconductor", distribution="ggx")
    truth = {"eta": np.array([0.2, 0.9, 1.1]), "k": np.array([3.0, 2.5, 2.0]), "alpha": 0.2}
    meas = simulate(model, truth, np.random.default_rng(6), n=600)
    space = ParameterSpace(model, 3)
    gen = GeneralFit(meas, model, space, "chi2", None, False, 2000)
    dof = meas.n_used - space.size
    bound = dof + 3.0 * np.sqrt(2.0 * meas.n_used)
    x = space.default()
    assert gen.acceptable((x, 0.99 * bound, True, ""))
    assert not gen.acceptable((x, 1.01 * bound, True, ""))
    assert not gen.acceptable((x, dof, False, "maxeval reached"))
    assert not GeneralFit(meas, model, space, "cosine", None, False, 2000).acceptable((x, 0.0, True, ""))
    quick = fit(meas, model, rng=np.random.default_rng(0))
    assert quick.chi2 <= bound
    monkeypatch.setattr(GeneralFit, "acceptable", lambda self, res: False)  # the full global stage
    full = fit(meas, model, rng=np.random.default_rng(0))
    assert full.n_evals > quick.n_evals
    np.testing.assert_allclose(quick.x, full.x, atol=1e-4 * full.std.max())
