"""A budget line of known mean (a systematic of known sign left in the data; issue 34).

An uncalibrated capture's detector non-linearity is known to compress and is not linearised:
gamma lies in [0, bound], a rectangular distribution with mean bound / 2 and u = bound /
sqrt(12) (JCGM 100 4.3.7). The dataset states the line with ``input_mean`` = sqrt(3) (its
mean in its own u); the fit corrects its values by the line's expected effect and the
adequacy test centres that input's prior there. Before, the line was carried as
+-bound/sqrt(3) about zero while the simulator's truth sat at the bound: rho's z was +0.13
(G) and +0.09 (B) higher with the non-linearity than without it on the same session (seed
601, glossy), a line whose effect is known in sign counted as noise.

Checks here are deterministic (noise drawn once from seeded Generators, each margin many
times the noise's effect), so their false-alarm rate is nil; the power is shown by the
uncorrected value, which misses by the full effect.
"""

import math

import numpy as np
import pytest

import gonio.models as gm
from gonio.fitting import fit, fit_document
from gonio.fitting.uncertainty.budget import Budget, BudgetComponent

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from _simdata import simulate  # noqa: E402

MEAN = math.sqrt(3.0)
U_REL = 0.004                    # the line's u: 0.4 % of every value, one shared input


def _case(seed):
    """A Lambertian capture (noise 1e-4 relative) and one shared line whose shape varies with
    the incidence (so the reflectances cannot absorb it all), at its mean in the data."""
    model = gm.get("diffuse")
    truth = {"reflectance": np.array([0.5, 0.35, 0.2])}
    meas = simulate(model, truth, np.random.default_rng(seed), n=200, rel=1e-4, floor=1e-6)
    shape = 1.0 + 0.5 * meas.wi[:, 2:3]
    value = model.eval(meas.wi, meas.wo, truth) * U_REL * shape
    meas.brdf += MEAN * value                  # the systematic at its known mean, in the data
    line = BudgetComponent("linearity", value, "B", "full", "test", mean=MEAN)
    stat = BudgetComponent("statistical", meas.brdf_std, "A", "none", "test")
    return model, truth, meas, Budget([stat, line])


def test_the_fit_document_corrects_for_the_lines_mean():
    model, truth, meas, budget = _case(1)
    result = fit(meas, model, rng=np.random.default_rng(0))
    doc = fit_document(result, meas, seed=0, budget=budget)
    for k, c in enumerate("RGB"):
        p = doc["parameters"][f"reflectance[{c}]"]
        t = truth["reflectance"][k]
        # corrected: within a few statistical sigma of the truth (1e-4 relative noise), while the
        # fitted value misses by about MEAN x U_REL x 1.3 = 0.9 % (~100 sigma)
        assert abs(p["value"] - t) < 5 * p["std"] + 1e-12, c
        assert abs(p["value_fitted"] - t) > 50 * p["std"], c
        # u_c about the mean: the line's own u (its effect on the reflectance), not its mean
        assert p["u_combined"] == pytest.approx(abs(p["systematic_correction"]) / MEAN, rel=0.01)
    assert doc["uncertainty"]["components"]["linearity"]["input_mean"] == pytest.approx(MEAN)


def test_the_adequacy_tests_prior_is_centred_on_the_mean():
    """With the input at its mean the centred test sees nothing; a prior at 0 would see a
    sqrt(3)-sigma input (T larger by about 3)."""
    model, truth, meas, budget = _case(2)
    result = fit(meas, model, rng=np.random.default_rng(0))
    centred = fit_document(result, meas, seed=0, budget=budget)["goodness"]["adequacy"]
    zero = Budget([budget.components[0], BudgetComponent("linearity", budget.components[1].value, "B", "full")])
    at_zero = fit_document(result, meas, seed=0, budget=zero)["goodness"]["adequacy"]
    assert at_zero["statistic"] - centred["statistic"] == pytest.approx(MEAN ** 2, rel=0.05)


def test_an_uncalibrated_compressive_non_linearity_is_stated_with_its_mean():
    from gonio.bench.dataset.budget import _levels, budget_variables
    from gonio.bench.measure import systematics
    from gonio.bench.settings import default_settings

    sys.path.insert(0, str(Path(__file__).parents[1] / "bench"))
    from test_uncalibrated_budget import brdf, rows

    s = default_settings()
    v0 = budget_variables(rows(), s, *brdf())
    assert "input_mean" not in v0["u_linearity"][2]           # instrument.toml: sign unknown
    s["systematics"] = {**s["systematics"], "linearity_compressive": True}
    v = budget_variables(rows(), s, *brdf())
    f = brdf()[0]
    lev = _levels(rows(), s, "reference") - _levels(rows(), s, "sample")
    np.testing.assert_allclose(v["u_linearity"][1], f * 0.003 / math.sqrt(12.0) * lev, rtol=1e-12)
    assert v["u_linearity"][2]["input_mean"] == pytest.approx(MEAN)
    typical = systematics.for_session({**default_settings(), "errors": {"preset": "typical"}})
    assert typical["systematics"]["linearity_compressive"] is True       # the simulator compresses
