"""Issue 16's defects on real-material fits, each pinned by a test that fails without its fix.

Synthetic stand-ins keep them fast; the real RGL files are used where present
(../shared/data/rgl) by tests/fitting/test_real_materials.py.
"""


import numpy as np
import pytest

import gonio.models as gm
from gonio.fitting import fit

from _simdata import simulate

#: a Cook-Torrance sample brighter than energy allows: rho_d = 0.95 plus a strong lobe;
#: its albedo exceeds 1 (Lambert 0.95 alone is 0.95; the lobe adds ~0.3 at normal incidence)
BRIGHT = {"diffuse_reflectance": [0.95, 0.95, 0.95], "specular_reflectance": [0.6, 0.6, 0.6],
          "roughness": 0.3, "f0": [0.9, 0.9, 0.9]}


def _failing_qp(*a, **k):
    """The polish's QP solver failing (what an unsolvable subproblem raises)."""
    from gonio.fitting.optimise.gn_sqp import QPError

    raise QPError("QP failure")


@pytest.mark.parametrize("loss", ["chi2", "log"])
def test_energy_holds_even_when_the_polish_fails(monkeypatch, loss):
    model = gm.get("cooktorrance")
    meas = simulate(model, BRIGHT, np.random.default_rng(3), n=200)
    assert float(np.max(model.albedo(np.array([[0.0, 0.0, 1.0]]), BRIGHT))) > 1.05   # the truth breaks energy
    monkeypatch.setattr("gonio.fitting.optimise.gn_sqp.solve_qp", _failing_qp)
    res = fit(meas, model, rng=np.random.default_rng(0), loss=loss)       # no traceback
    assert res.energy["enforced"] is True
    assert res.energy["holds"] is True, res.energy
    assert res.energy["max_albedo"] <= 1.0 + 1e-4
    assert "polish failed" in res.message and "scaled" in res.message


# ---------------------------------------------------------------- loss consistency (BIC)
def test_bic_comes_from_the_minimised_loss():
    """--loss log: BIC = n ln(objective / n) + (k + 1) ln n (Gaussian likelihood of the log
    residuals, variance profiled; Schwarz 1978), never chi2 + k ln n."""
    from gonio.fitting import select

    model = gm.get("roughplastic", distribution="ggx")
    truth = {"diffuse_reflectance": [0.4, 0.3, 0.2], "alpha": 0.2, "int_ior": 1.5}
    meas = simulate(model, truth, np.random.default_rng(5), n=200)
    res = fit(meas, model, rng=np.random.default_rng(0), loss="log")
    n, k = res.n_used, res.space.size
    assert res.bic == pytest.approx(n * np.log(res.objective / n) + (k + 1) * np.log(n), rel=1e-12)
    assert abs(res.bic - (res.chi2 + k * np.log(n))) > 1.0
    _, rows = select(meas, rng=np.random.default_rng(0), loss="log",
                     candidates=[("diffuse", {}), ("roughplastic", {"distribution": "ggx"})])
    assert all(r.loss == "log" for r in rows)
    assert rows[0].name == "roughplastic"          # the lobe is real: the log evidence says so too
    for r in rows:
        assert r.bic == pytest.approx(r.result.bic)
        assert r.row()["loss"] == "log"


def test_every_distribution_is_a_candidate():
    from gonio.fitting import CANDIDATES

    assert ("roughconductor", {"distribution": "beckmann"}) in CANDIDATES
    assert ("roughconductor", {"distribution": "ggx"}) in CANDIDATES
    assert ("roughplastic", {"distribution": "beckmann"}) in CANDIDATES


def test_named_model_without_distribution_selects_it():
    """--model roughplastic on a GGX sample: both distributions fitted, GGX chosen, said."""
    from gonio.cli.fit import fit_dataset

    model = gm.get("roughplastic", distribution="ggx")
    truth = {"diffuse_reflectance": [0.3, 0.3, 0.3], "alpha": 0.08, "int_ior": 1.5}
    meas = simulate(model, truth, np.random.default_rng(7), n=300)
    res, doc, _ = fit_dataset(meas, model="roughplastic", seed=0)
    assert doc["model"]["options"]["distribution"] == "ggx"
    assert {r["options"]["distribution"] for r in doc["selection"]} == {"ggx", "beckmann"}
    assert abs(res.params["alpha"] - 0.08) < 4 * res.std[res.space.names.index("alpha")]
    _, doc_b, _ = fit_dataset(meas, model="roughplastic", options={"distribution": "beckmann"}, seed=0)
    assert doc_b["model"]["options"]["distribution"] == "beckmann" and not doc_b["selection"]


# ---------------------------------------------------------------- honest intervals
def test_inadequate_fit_inflates_intervals_and_warns():
    """A diffuse model on a glossy sample: chi2/dof >> 1, so the fit file's sigma and ci90 are
    the Laplace ones times the Birge ratio sqrt(chi2/dof) (Birge 1932), and it warns."""
    from gonio.fitting import fit_document

    glossy = gm.get("roughplastic", distribution="ggx")
    meas = simulate(glossy, {"diffuse_reflectance": [0.3, 0.3, 0.3], "alpha": 0.1, "int_ior": 1.5},
                    np.random.default_rng(2), n=200)
    res = fit(meas, gm.get("diffuse"), rng=np.random.default_rng(0))
    assert res.chi2_dof > 10
    doc = fit_document(res, meas)
    g = doc["goodness"]
    birge = np.sqrt(res.chi2_dof)
    assert g["std_inflation"] == pytest.approx(birge) and g["warning"] and "Birge" in g["warning"]
    p = doc["parameters"]["reflectance[R]"]
    assert p["std"] == pytest.approx(res.std[0] * birge)
    assert p["ci90"][1] - p["ci90"][0] == pytest.approx(2 * 1.6448536269514722 * res.std[0] * birge, rel=1e-9)
    # an adequate fit is left alone
    diffuse = gm.get("diffuse")
    ok = simulate(diffuse, {"reflectance": [0.5, 0.4, 0.3]}, np.random.default_rng(1), n=200)
    r2 = fit(ok, diffuse, rng=np.random.default_rng(0))
    d2 = fit_document(r2, ok)
    assert d2["goodness"]["std_inflation"] == 1.0 and d2["goodness"]["warning"] is None


def test_unknown_loss_refused_before_fitting():
    from gonio.core.errors import GonioError
    from gonio.cli.fit import fit_dataset

    meas = simulate(gm.get("diffuse"), {"reflectance": [0.5, 0.4, 0.3]}, np.random.default_rng(1), n=50)
    with pytest.raises(GonioError, match="unknown loss"):
        fit_dataset(meas, model="auto", loss="nonsense")
