"""A model's declared affine colours are what the numeric probe finds (issue 35).

``model.affine_colours()`` lets a fit skip ``_linear_groups``' probes (O(groups^2)
evaluations: the ring table's 21 groups cost ~500). A wrong declaration would hand the
variable projection a parameter f_r is not affine in, so every declaring model, in every
option it has, is checked against the probe (two interior points, 1e-9 of the scale), on
simulated data at its defaults; and the probe is shown to reject a non-affine spread declared.
"""

import itertools

import numpy as np
import pytest

import gonio.models as gm
from gonio.fitting.likelihood.problem import Problem, _linear_groups
from gonio.fitting.optimise.space import ParameterSpace


def _configs():
    for name in gm.names():
        cls = type(gm.get(name))
        if not hasattr(cls, "affine_colours"):
            continue
        opts = getattr(cls, "OPTIONS", {}) or {}
        keys = sorted(opts)
        for values in itertools.product(*(opts[k] for k in keys)):
            yield name, dict(zip(keys, values))


def _problem(name, options, seed=3):
    from _simdata import simulate

    model = gm.get(name, **options)
    meas = simulate(model, model.validate({}), np.random.default_rng(seed), n=300, rel=0.02)
    return Problem(meas, model, ParameterSpace(model, 3), "log")


CONFIGS = list(_configs())


def test_the_painted_models_declare():
    assert {n for n, _ in CONFIGS} >= {"flakepaint", "gratingpaint", "tabulated"}


@pytest.mark.parametrize("body", ["lambert", "table"])
def test_a_tabulated_problem_is_built_without_probes(body):
    """tabulated's six colour groups (rho and the Fresnel knots) are taken as declared: the
    problem is set up without evaluating f_r (before b623d8b: probes, once per fit of the
    choice's tabulated fallback)."""
    pr = _problem("tabulated", {"body": body})
    assert pr.n_evals == 0
    assert [g["param"] for g in pr.linear] == ["diffuse_reflectance"] + [f"fresnel_{j}" for j in range(5)]


@pytest.mark.parametrize("name,options", CONFIGS, ids=[f"{n}-{'-'.join(map(str, o.values()))}" for n, o in CONFIGS])
def test_declared_affine_colours_are_what_the_probe_finds(name, options):
    pr = _problem(name, options)
    declared = [g["param"] for g in _linear_groups(pr)]
    probed = [g["param"] for g in _linear_groups(pr, probe=True)]
    assert declared == probed and declared
    assert [g["index"] for g in _linear_groups(pr)] == [g["index"] for g in _linear_groups(pr, probe=True)]


def test_the_probe_rejects_a_spread_declared_affine(monkeypatch):
    """flakepaint with one spread per channel: flake_alpha is per-channel but not affine; declared
    so, the probe (what the declaration test compares with) says otherwise."""
    from gonio.models.catalogue.flakepaint import FlakePaint

    pr = _problem("flakepaint", {"spread": "wavelength"})
    monkeypatch.setattr(FlakePaint, "affine_colours", lambda self: ("diffuse_reflectance", "flake_alpha"))
    declared = [g["param"] for g in _linear_groups(pr)]
    probed = [g["param"] for g in _linear_groups(pr, probe=True)]
    assert "flake_alpha" in declared and "flake_alpha" not in probed


@pytest.mark.parametrize("loss", ["chi2", "luminance"])
def test_the_projection_per_channel_is_the_projection_off_every_affine_column(loss):
    """Variable projection's Jacobian (Kaufman 1975) projects each channel's rows off that
    channel's affine columns only: an affine column of channel c is zero on the other
    channels' residuals, so the span is block-diagonal and this is the projection off all
    columns at once. Checked against one QR of the full (residuals x columns) matrix, with
    some unsaturated data (use False) so that the channels' row sets differ."""
    from _simdata import simulate

    model = gm.get("tabulated", body="lambert", sheen="ggx")
    meas = simulate(model, model.validate({}), np.random.default_rng(5), n=400, rel=0.02)
    meas.use[::9, 1] = False
    pr = Problem(meas, model, ParameterSpace(model, 3), loss)
    assert pr.varpro
    x0 = pr.space.default()
    v = pr.space.to_unit(x0)[pr.nl_idx]
    r = pr.reduced_residuals(v, x0)
    J = pr.kaufman_jacobian(v, r, x0)
    x = pr.x_of(v, x0)
    raw = pr.residual_jacobian_x(x, pr.nl_idx, scale=pr.space.dx_du(x)[pr.nl_idx])[1]
    cols = []
    for g, B in zip(pr.linear, pr._cols):
        for c, i in enumerate(g["index"]):
            if pr.space.lower[i] < x[i] < pr.space.upper[i]:
                full = np.zeros_like(B)
                full[:, c] = B[:, c] * pr.weight[:, c]
                cols.append(full[pr.use])
    Q, _ = np.linalg.qr(np.stack(cols, axis=1))
    want = raw - Q @ (Q.T @ raw)
    assert len(cols) > 6 and np.abs(raw).max() > 0
    np.testing.assert_allclose(J, want, rtol=0, atol=1e-9 * np.abs(raw).max())
