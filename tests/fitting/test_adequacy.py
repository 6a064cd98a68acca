"""The adequacy verdict is a stated test (issue 34, "Honest numbers").

``goodness.adequacy`` of a fit document names its test (``budget_chi2``: the residuals'
generalised chi^2 against the budget's covariance, every shared input profiled out as a
nuisance; ``chi2``: chi^2 against the fit's sigma), its statistic, dof, p-value and level
alpha = ADEQUACY_ALPHA = 1e-3 (its false-alarm rate), and the verdict; ``model_adequate`` is
that verdict. Before, a chi2 fit with a budget was "adequate" while chi^2 <= E + 4 sd, E and
sd its null mean and spread: a few large shared inputs make that null a skewed sum of scaled
chi^2_1 terms with sd ~ E, so the rule passed a wrong family at chi^2/dof 50.7
(`test_a_wrong_family_at_chi2_dof_50_is_inadequate_in_every_draw` reproduces it), and the one
test that covered it fed fixed numbers to the rule and could not fail.

What is checked, each with its own false-alarm rate (every draw from a seeded numpy
Generator; counts and margins, nothing that depends on one machine's floating-point order):

- false alarms of the right family (`test_the_right_family_is_adequate_at_the_stated_rate`):
  N_RIGHT = 500 cheap draws (tests/fitting/_simdata.py; half with a shared line of SHARED = 3
  sigma in the data and the budget, half without): the count of "inadequate" within the 99.9 %
  binomial interval of 500 draws at alpha ([0, 4]), and the count of p < 0.05 within the 99.9 %
  interval at 0.05 ([11, 42]: the statistic's calibration, which the verdict's 1e-3 alone
  resolves poorly). Test false alarm <= 2e-3. Power of the second count against a statistic
  7 % too large (sigma 3.4 % too narrow): > 0.999 (:func:`power_calibration`); against the
  old 1.33: 1. The statistic is exact to first order; a model that follows a shared error only
  non-linearly is refitted (Gauss-Newton) where the first order rejects it, which holds the
  rate at 3 and 4 sigma (0 of 150 draws at p < 1e-3) but not quite at 7 sigma, where the
  weighted fit lands on its bounds (2 of 150).
- a wrong family (diffuse on a glossy roughplastic, chi^2/dof ~ 50, the shared line of the
  old bug) is inadequate in every one of N_WRONG draws: power per draw 1 - 1e-300 at
  chi^2/dof >= 20 (non-central chi^2, :func:`power_wrong`); the test fails only if the
  verdict does.
- the full instrument chain (`test_a_gold_capture_on_the_ideal_simulator`): one ideal
  standard-plan capture of gold (roughconductor, Beckmann): the right family adequate (false
  alarm alpha, if the budget is honest: 39 seeded captures gave T/dof 1.032 +- 0.089 against
  chi^2_293's 1 +- 0.083), a diffuse fit inadequate. Before the fix of the HDR merge's weights
  (gonio/bench/measure/hdr.py) and the budget's dark_frame line, 20 such captures (seeds 1-20)
  had chi^2/dof 1.29-2.62 and T/dof 1.82-4.03; this one (seed 9) 2.44 and 4.03.
"""

import sys
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

import gonio.models as gm
from gonio.fitting import fit, fit_document
from gonio.fitting.uncertainty.adequacy import ADEQUACY_ALPHA
from gonio.fitting.uncertainty.budget import Budget, BudgetComponent

sys.path.insert(0, str(Path(__file__).parent))
from _simdata import simulate  # noqa: E402

ALPHA = ADEQUACY_ALPHA
N_RIGHT = 500
N_WRONG = 40
SHARED = 3.0                     # the right family's shared line: 3 sigma of each value
TAIL = 5e-4                      # each side of a 99.9 % binomial interval
GOLD = {"eta": [0.143, 0.374, 1.442], "k": [3.983, 2.385, 1.603], "alpha": 0.1}
GLOSSY = {"diffuse_reflectance": [0.3, 0.3, 0.3], "alpha": 0.1, "int_ior": 1.5}


def interval(n: int, p: float) -> tuple[int, int]:
    """The 99.9 % binomial interval of a count of n draws at rate p (TAIL each side)."""
    return int(stats.binom.ppf(TAIL, n, p)), int(stats.binom.isf(TAIL, n, p))


def power_calibration(scale: float, n: int = N_RIGHT, dof: int = 293) -> float:
    """P(the count of p < 0.05 leaves its interval) when the statistic is ``scale`` x chi^2_dof."""
    q = float(stats.chi2.sf(stats.chi2.isf(0.05, dof) / scale, dof))
    lo, hi = interval(n, 0.05)
    return float(stats.binom.cdf(lo - 1, n, q) + stats.binom.sf(hi, n, q))


def power_wrong(chi2_dof: float, dof: int = 297) -> float:
    """P(a wrong family at chi2/dof is called inadequate): T non-central chi^2 with
    non-centrality (chi2_dof - 1) dof."""
    return float(stats.ncx2.sf(stats.chi2.isf(ALPHA, dof), dof, (chi2_dof - 1.0) * dof))


def shared_line(meas, scale: float) -> np.ndarray:
    """A shared error's signed line, ``scale`` times each value's sigma times cos(4 theta_o):
    a pattern that neither family absorbs (a stray-light or reference-table error)."""
    theta_o = np.arccos(np.clip(meas.wo[:, 2], -1.0, 1.0))
    return scale * meas.brdf_std * np.cos(4.0 * theta_o)[:, None]


def draw(model, truth, rng, *, rel, shared):
    """Cheap simulated data (tests/fitting/_simdata.py) and its budget: type A (the sigma) and,
    with ``shared`` > 0, one fully shared line whose error (one N(0, 1) draw) is in the data."""
    meas = simulate(model, truth, rng, n=100, rel=rel, floor=1e-3)
    comps = [BudgetComponent("statistical", meas.brdf_std, "A", "none")]
    if shared:
        u = shared_line(meas, shared)
        meas.brdf = meas.brdf + rng.standard_normal() * u
        comps.append(BudgetComponent("stray", u, "B", "full", "a shared error"))
    return meas, Budget(comps)


def test_the_sizing_stated_in_the_docstring():
    assert interval(N_RIGHT, ALPHA) == (0, 4)
    assert interval(N_RIGHT, 0.05) == (11, 42)
    assert 2 * 2 * TAIL <= 2e-3
    assert power_calibration(1.0) < 2e-3
    assert power_calibration(1.07) > 0.999 and power_calibration(1.33) > 1 - 1e-12
    assert power_wrong(20.0) > 1 - 1e-300 or power_wrong(20.0) == 1.0


def test_the_right_family_is_adequate_at_the_stated_rate():
    model = gm.get("roughconductor", distribution="beckmann")
    p, inadequate, tests = [], 0, set()
    for k in range(N_RIGHT):
        rng = np.random.default_rng([34, k])
        meas, budget = draw(model, GOLD, rng, rel=0.02, shared=SHARED if k % 2 else 0.0)
        res = fit(meas, model, rng=np.random.default_rng([35, k]))
        a = fit_document(res, meas, budget=budget)["goodness"]["adequacy"]
        p.append(a["p_value"])
        inadequate += a["verdict"] == "inadequate"
        tests.add(a["test"])
    p = np.asarray(p)
    lo, hi = interval(N_RIGHT, ALPHA)
    assert lo <= inadequate <= hi, f"{inadequate} false alarms in {N_RIGHT} draws at alpha {ALPHA}: outside [{lo}, {hi}]"
    lo, hi = interval(N_RIGHT, 0.05)
    assert lo <= (p < 0.05).sum() <= hi, f"{(p < 0.05).sum()} of {N_RIGHT} p-values below 0.05: outside [{lo}, {hi}]"
    assert tests == {"chi2", "budget_chi2"}


def test_a_wrong_family_at_chi2_dof_50_is_inadequate_in_every_draw():
    """Diffuse on a glossy roughplastic with a large shared line in its budget: chi^2/dof ~ 50.
    The old rule (chi^2 <= E + 4 sd) called most of these draws adequate (chi^2/dof 50.7: 15055
    <= 5697 + 4 x 7636); the stated test calls every one inadequate."""
    glossy, wrong = gm.get("roughplastic", distribution="ggx"), gm.get("diffuse")
    seen = []
    for k in range(N_WRONG):
        rng = np.random.default_rng([36, k])
        meas, budget = draw(glossy, GLOSSY, rng, rel=0.075, shared=7.0)
        res = fit(meas, wrong, rng=np.random.default_rng([37, k]))
        doc = fit_document(res, meas, budget=budget)
        g = doc["goodness"]
        a = g["adequacy"]
        seen.append(res.chi2_dof)
        assert a["verdict"] == "inadequate" and g["model_adequate"] is False, (k, res.chi2_dof, a)
        assert a["test"] == "budget_chi2" and a["p_value"] < ALPHA and a["nuisance_inputs"] == 1
        assert power_wrong(a["statistic"] / a["dof"], a["dof"]) > 1 - 1e-12
        assert g["std_inflation"] > 1.0 and f"p = {a['p_value']:.2g} < alpha = {ALPHA:g}" in g["warning"]
    assert 20.0 < np.median(seen) < 120.0             # the chi^2/dof ~ 50 of the issue


def test_goodness_names_the_test_its_level_and_verdict():
    model = gm.get("roughconductor", distribution="beckmann")
    meas, budget = draw(model, GOLD, np.random.default_rng([38, 0]), rel=0.02, shared=0.0)
    res = fit(meas, model, rng=np.random.default_rng(0))
    g = fit_document(res, meas, budget=budget)["goodness"]
    a = g["adequacy"]
    assert set(a) >= {"test", "description", "statistic", "dof", "p_value", "alpha", "false_alarm_rate", "verdict"}
    assert a["alpha"] == a["false_alarm_rate"] == ALPHA and a["dof"] == res.dof
    assert a["statistic"] == pytest.approx(res.chi2, rel=1e-6)       # no shared input: the fit's chi^2
    assert a["p_value"] == pytest.approx(stats.chi2.sf(res.chi2, res.dof), rel=1e-5)
    assert g["model_adequate"] is (a["verdict"] == "adequate")
    # a loss without a budget to test against: its chi^2 against the nominal sigma, same level
    r2 = fit(meas, model, loss="log", rng=np.random.default_rng(0))
    a2 = fit_document(r2, meas)["goodness"]["adequacy"]
    assert a2["test"] == "chi2" and a2["alpha"] == ALPHA


def test_a_gold_capture_on_the_ideal_simulator(tmp_path):
    """The issue's case on the real instrument chain (capture, HDR merge, reference, export,
    budget, fit): Beckmann roughconductor on an ideal gold capture was "inadequate" at chi2/dof
    1.33 (293 dof). The cause: the HDR merge weighed each value's exposures by its own dark
    frame's reading, a positive bias at zero signal (the capture's many dark points at z = +1.5),
    and the dark frames' noise, shared by every point whose regions overlap, was not in the
    budget. One capture: false alarm alpha = 1e-3."""
    from gonio.bench.dataset.export import export
    from gonio.bench.dataset.reader import open_budget
    from gonio.bench.samples import check_sample
    from gonio.bench.session.simulated import capture_sim
    from gonio.bench.settings import default_settings
    from gonio.fitting import fit_dataset, load_dataset

    sample = check_sample({"model": "roughconductor", "options": {"distribution": "beckmann"}, "params": GOLD})
    settings = default_settings()
    settings["errors"] = {"preset": "ideal"}
    capture_sim(tmp_path / "s", sample=sample, plan="standard", seed=9, settings=settings, progress=False)
    path = export(tmp_path / "s")
    meas = load_dataset(path)
    budget = open_budget(path, meas)
    assert "dark_frame" in {c.name for c in budget.components}
    _, doc, _ = fit_dataset(meas, model="roughconductor", options={"distribution": "beckmann"}, seed=0, budget=budget)
    a = doc["goodness"]["adequacy"]
    assert a["test"] == "budget_chi2" and a["dof"] == 293
    assert a["verdict"] == "adequate", a
    _, doc, _ = fit_dataset(meas, model="diffuse", seed=0, budget=budget)
    assert doc["goodness"]["adequacy"]["verdict"] == "inadequate"
