"""The Levenberg-Marquardt step from normal equations reduced in the compiled kernel
(issue 18: no N x P Jacobian per iteration, so a 1e6-point fit runs in memory independent
of P): the sums equal J^T W r and J^T W J formed from the kernel's own Jacobian, the fit
through them equals the fit through the Jacobian, and Dask's task chunks cover every
dataset once, in order."""

import numpy as np
import pytest

import gonio.models as gm
from gonio.fitting import fit
from gonio.fitting.batch.dask_batch import task_chunks
from gonio.fitting.likelihood.problem import Problem
from gonio.fitting.optimise.space import ParameterSpace
from gonio.models import fast

from _simdata import simulate

pytestmark = pytest.mark.skipif(not fast.available(), reason="Dr.Jit LLVM backend unavailable")


PRINCIPLED = {"base_color": np.array([0.6, 0.25, 0.1]), "roughness": 0.45, "metallic": 0.3, "specular": 0.6,
              "spec_tint": 0.4, "sheen": 0.3, "sheen_tint": 0.5, "clearcoat": 0.2, "clearcoat_gloss": 0.6,
              "flatness": 0.3}


@pytest.mark.parametrize("name,options", [("roughconductor", {"anisotropic": True}), ("cooktorrance", {}),
                                          ("roughplastic", {"distribution": "ggx"}), ("principled", {})])
@pytest.mark.parametrize("log", [False, True], ids=["linear", "log"])
def test_normal_equations_equal_the_jacobian_products(name, options, log):
    """cost, g, A against sum W r^2, J^T W r, J^T W J of fast.jacobian's columns, to 1e-12
    relative (float64 sums; only the order of the additions differs). Two batch sizes: a
    kernel traced for one size must not answer for another. Principled's base colour
    reaches every channel through its luminance (``structure.coupled``): its columns and
    the cross-channel blocks of A are not 0. ``log``: the log loss's residuals
    ln(1 + f cos_i) - ln(1 + y cos_i) and their derivatives cos_i / (1 + f cos_i) J, the
    transform the kernel applies (Loew et al. 2012, eq. 11)."""
    model = gm.get(name, **options)
    rng = np.random.default_rng(3)
    for n in (700, 1900):
        wi, wo = (gm.geometry.directions(np.arccos(rng.uniform(0.1, 1, n)), rng.uniform(-np.pi, np.pi, n))
                  for _ in range(2))
        dirs = fast.Directions(wi, wo, np.float64)
        p = PRINCIPLED if name == "principled" else model.defaults()
        f, J = fast.jacobian(model, dirs, p)
        y = f * (1 + 0.05 * rng.standard_normal(f.shape))
        w = rng.uniform(0.5, 2.0, f.shape)
        c = wi[:, 2:3]
        if log:
            y = np.log1p(y * c)
        cost, g, A, entries = fast.normal_equations(model, dirs, p, y, w, log=log)
        D = np.stack([fast.jacobian_column(model, J, param, ch).ravel() for param, ch in entries], 1)
        if log:
            D = D * np.broadcast_to(c / (1 + f * c), f.shape).ravel()[:, None]
            r = (np.log1p(f * c) - y).ravel()
            assert fast.weighted_sse(model, dirs, p, y, w, log=True) == pytest.approx(cost, rel=1e-12)
        else:
            r = (f - y).ravel()
        W = w.ravel()
        assert cost == pytest.approx(np.sum(W * r * r), rel=1e-12)
        np.testing.assert_allclose(g, D.T @ (W * r), rtol=1e-10, atol=1e-12 * np.abs(g).max())
        np.testing.assert_allclose(A, D.T @ (W[:, None] * D), rtol=1e-10, atol=1e-12 * np.abs(A).max())
        if name == "principled":  # the coupling is there: base_color[R] moves the green channel
            i = entries.index(("base_color", 0))
            assert np.max(np.abs(fast.jacobian_column(model, J, "base_color", 0)[:, 1])) > 1e-3
            assert abs(A[i, entries.index(("base_color", 1))]) > 1e-6 * A[i, i]


def _assert_normal_is_the_products(prob, u):
    """Problem.lm_normal_u / lm_cost_u (reduced in the kernel) are (J^T r, J^T J) and |r|^2 of
    lm_residuals_u / lm_jacobian_u at u."""
    assert prob.normal_available
    r, D = prob.lm_residuals_u(u), prob.lm_jacobian_u(u)
    g, A = prob.lm_normal_u(u)
    assert prob.lm_cost_u(u) == pytest.approx(r @ r, rel=1e-12)
    np.testing.assert_allclose(g, D.T @ r, rtol=1e-9, atol=1e-12 * np.abs(g).max())
    np.testing.assert_allclose(A, D.T @ D, rtol=1e-9, atol=1e-12 * np.abs(A).max())


def test_luminance_loss_normal_equations_are_the_residuals_products():
    """The luminance loss (a fixed weight cos_i / (a + Y cos_i) per value) without variable
    projection (``linear=[]``): the kernel's normal equations, mask and weights included."""
    model = gm.get("principled")
    meas = simulate(model, PRINCIPLED, np.random.default_rng(6), n=500)
    meas.weight = np.random.default_rng(7).uniform(0.5, 2.0, meas.n_points)
    meas.use[::7, 2] = False
    space = ParameterSpace(model, 3)
    prob = Problem(meas, model, space, "luminance", linear=[])
    _assert_normal_is_the_products(prob, space.to_unit(space.from_params(PRINCIPLED)) * 0.9 + 0.04)


def test_log_loss_steps_from_normal_equations_equal_the_jacobian_steps(monkeypatch):
    """The log loss's Problem.lm_normal_u / lm_cost_u (reduced in the kernel) are (J^T r,
    J^T J) and |r|^2 of lm_residuals_u / lm_jacobian_u, mask and solid-angle weights
    included, for principled (base colour coupled across channels); the fit through them
    reaches the Jacobian path's optimum (x within 1e-3 of its sigma)."""
    model = gm.get("principled")
    meas = simulate(model, PRINCIPLED, np.random.default_rng(5), n=700)
    meas.weight = np.random.default_rng(6).uniform(0.5, 2.0, meas.n_points)
    meas.use[::7, 2] = False
    space = ParameterSpace(model, 3)
    prob = Problem(meas, model, space, "log")
    _assert_normal_is_the_products(prob, space.to_unit(space.from_params(PRINCIPLED)) * 0.9 + 0.04)
    kw = dict(loss="log", rng=np.random.default_rng(0), n_starts=0, n_local=1, covariance=False)
    res = fit(meas, model, **kw)
    monkeypatch.setattr(Problem, "normal_available", property(lambda self: False))  # the Jacobian path
    ref = fit(meas, model, **{**kw, "rng": np.random.default_rng(0)})
    assert res.converged and ref.converged
    assert res.objective == pytest.approx(ref.objective, rel=1e-8)
    np.testing.assert_allclose(res.x, ref.x, atol=1e-3 * ref.std.max())


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
        sizes = [b - a for a, b in chunks]
        if threads == 0:
            assert sizes == [1] * n
        else:                           # factoring: non-increasing, single datasets last
            assert sizes == sorted(sizes, reverse=True) and sizes[-1] == 1
    assert task_chunks(0, 2) == []


def test_default_start_is_accepted_only_when_it_fits_to_the_noise(monkeypatch):
    """The general problem skips its global stage when the fit from the defaults has
    chi2 <= E + 3 sd (E = dof for unit weights, sd = sqrt(2 dof)); the optimum is then the one
    the full multi-start search finds; a chi2 beyond that bound, another loss or an
    unconverged run is never accepted."""
    from gonio.fitting.optimise.mle import GeneralFit

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
