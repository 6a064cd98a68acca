"""Problem.residual_jacobian_x builds a per-channel entry's column from its own channel's rows
(issue 35: the choice's numpy candidates and tabulated spent more time on the N x P Jacobian's
columns than on the model's derivatives): the same residuals and Jacobian, bit for bit, as
the full (N, 3) columns of fast.jacobian_column masked by ``use``; a coupled entry
(principled's base colour) and a shared one keep the full column."""

import numpy as np
import pytest

import gonio.models as gm
from gonio.fitting.likelihood import loss as _loss
from gonio.fitting.likelihood.problem import Problem
from gonio.fitting.optimise.space import ParameterSpace
from gonio.models import fast

from _simdata import simulate

pytestmark = pytest.mark.skipif(not fast.available(), reason="Dr.Jit LLVM backend unavailable")


def _full_columns(prob, x, cols, loss):
    """The Jacobian as the whole (N, 3) column of every entry, masked: the reference."""
    out = prob.eval.jacobian(prob.space.to_params(x))
    if out is None:     # no exact derivatives on this path (principled on numpy)
        return None
    f, J = out
    drdf = np.broadcast_to(_loss.residual_derivative(loss, f, prob.meas), f.shape)
    r = _loss.residuals(loss, f, prob.meas)
    D = np.stack([(fast.jacobian_column(prob.model, J, prob.space.entries[j].param, prob.space.entries[j].channel)
                   * drdf)[prob.meas.use] for j in cols], axis=1)
    return r, D


@pytest.mark.parametrize("name,options", [("principled", {}), ("roughplastic", {"distribution": "ggx"}),
                                          ("flakepaint", {"distribution": "ggx", "spread": "shared"})])
@pytest.mark.parametrize("loss", ["log", "chi2", "robust"])
def test_per_channel_columns_equal_the_full_columns(name, options, loss, monkeypatch):
    """Residuals, Jacobian (natural units, a subset of the columns) and lm_jacobian_u (unit
    box) equal to the bit; values masked out on one channel; only the shared and coupled
    entries go through fast.jacobian_column (before: every entry, 2/3 of a per-channel
    column zeros)."""
    model = gm.get(name, **options)
    rng = np.random.default_rng(7)
    meas = simulate(model, model.defaults(), rng, n=300)
    meas.weight = rng.uniform(0.5, 2.0, meas.n_points)
    meas.use[::5, 1] = False
    space = ParameterSpace(model, 3)
    prob = Problem(meas, model, space, loss, linear=[])
    u = rng.uniform(0.1, 0.9, space.size)
    x = space.from_unit(u)
    ref = _full_columns(prob, x, range(space.size), loss)
    if ref is None:
        assert prob.residual_jacobian_x(x, range(space.size)) is None
        return
    r0, D0 = ref
    calls = []
    real = fast.jacobian_column
    monkeypatch.setattr(fast, "jacobian_column", lambda m, J, p, c=-1: calls.append((p, c)) or real(m, J, p, c))
    r1, D1 = prob.residual_jacobian_x(x, range(space.size))
    assert np.array_equal(r0, r1) and np.array_equal(D0, D1) and D1.flags.c_contiguous
    shared = [(e.param, e.channel) for e in space.entries
              if e.channel < 0 or model.structure.coupling(e.param) is not None]
    assert calls == shared
    assert len(shared) < space.size or name == "principled"     # its per-channel base colour is coupled
    sub = [1, space.size - 1]
    assert np.array_equal(prob.residual_jacobian_x(x, sub)[1], D0[:, sub])
    ref = D0 * space.dx_du(x)[None, :]
    if loss == "robust":
        s = np.sqrt(1.0 + r0 * r0)
        ref = ref * (np.sqrt(0.5 * (s + 1.0)) / s)[:, None]
    assert np.array_equal(prob.lm_jacobian_u(u), ref)


def test_a_non_finite_derivative_still_means_no_jacobian():
    """A used value whose d r / d f_r is not finite (sigma 0 under chi2): None, as the full
    columns gave (0 * inf in every per-channel column), so the caller differences."""
    model = gm.get("roughplastic", distribution="ggx")
    meas = simulate(model, model.defaults(), np.random.default_rng(8), n=200)
    meas.brdf_std[3, 2] = 0.0
    space = ParameterSpace(model, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        prob = Problem(meas, model, space, "chi2", linear=[])
        assert prob.residual_jacobian_x(space.default(), range(space.size)) is None
