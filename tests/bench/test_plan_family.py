"""The sequential plans' family choice (gonio.bench.plan.family): with ``candidates`` the adaptive
plan fits each to the points so far, keeps the one BIC supports and places its batches for it;
a resume replays those choices; a bad candidate list is one line."""

from __future__ import annotations

import numpy as np
import pytest

import gonio.models as gm
from gonio.bench.plan import family, plans
from gonio.bench.plan.adaptive import AdaptivePlan
from gonio.core.geometry import directions_deg
from strategy_run import run, synthetic

STANDARD = plans.load_plan("standard")
ORDER = list(range(len(STANDARD)))
# gold at 650, 550, 450 nm (Johnson & Christy 1972, Phys. Rev. B 6: 4370): n, k
GOLD = {"eta": np.array([0.166, 0.433, 1.45]), "k": np.array([3.15, 2.46, 1.85]), "alpha": 0.2}


def _gold(plan):
    """(f_r, 1-sigma) of a GGX gold conductor at ``plan``'s points, 1 % + 1e-4 noise."""
    a = plan.angles
    f = gm.get("roughconductor", distribution="ggx").eval(directions_deg(a[:, 0], a[:, 1]),
                                                          directions_deg(a[:, 2], a[:, 3]), GOLD)
    sd = 0.01 * f + 1e-4
    return f + sd * np.random.default_rng(2).standard_normal(f.shape), sd


@pytest.mark.long       # three 14-point plans, two families fitted per batch: about 4 s
def test_a_gold_sample_is_measured_as_a_conductor_and_a_resume_replays_it():
    """A metal has no diffuse body: once the points pin its Fresnel colour (the first pass's six
    fitted points, 4 starts, may not), BIC keeps the conductor over the plastic, the batches are
    placed for it and its roughness is recovered."""
    f, sd = _gold(STANDARD)
    table = {"points": 14, "seed": 1, "candidates": ["roughplastic:ggx", "roughconductor:ggx"]}
    whole = AdaptivePlan(STANDARD, ORDER, table)
    run(whole, f, sd)
    assert [e["model"] for e in whole.log][1:] == ["roughconductor:ggx"] * (len(whole.log) - 1) and len(whole.log) >= 2
    assert abs(whole.log[-1]["params"]["alpha"] - GOLD["alpha"]) < 0.01
    assert whole.state()["model"] == "roughconductor:ggx"
    first = AdaptivePlan(STANDARD, ORDER, whole.to_dict())             # session.toml's table read back
    journalled = run(first, f, sd, stop_after=10)
    again = AdaptivePlan(STANDARD, ORDER, whole.to_dict())
    todo = again.first(set(journalled))
    todo += again.more(journalled, tuple(todo))
    run(again, f, sd, results=journalled, todo=todo)
    assert again.batches == whole.batches


@pytest.mark.long       # Cook-Torrance's kernel built and fitted per batch: 2-4 s on a shared machine
def test_a_plastic_keeps_the_simpler_family():
    """Data a GGX roughplastic made: Cook-Torrance (10 parameters, Beckmann) cannot beat it by the
    k ln n BIC charges for its five more, so the simpler family is kept (Kass & Raftery 1995)."""
    f, sd = synthetic(STANDARD)
    plan = AdaptivePlan(STANDARD, ORDER, {"points": 11, "seed": 1, "candidates": ["cooktorrance", "roughplastic:ggx"]})
    run(plan, f, sd)
    assert plan.candidates[0][0] == "roughplastic"            # simplest first, whatever the order given
    assert {e["model"] for e in plan.log} == {"roughplastic:ggx"}


def test_the_candidates_are_checked():
    assert family.parse([]) == ()
    assert family.parse([{"model": "cooktorrance"}, "roughplastic:ggx"])[0] == (
        "roughplastic", {"distribution": "ggx"})
    assert family.parse(family.as_doc(family.FAMILIES)) == family.FAMILIES
    for bad, msg in (("roughplastic", "give a list"), (["nonsense"], "'nonsense'"), ([3], "not a model name"),
                     (["roughplastic:nonsense"], "roughplastic"), (["roughplastic:ggx"] * 2, "named twice"),
                     ([{"model": "diffuse", "colour": 1}], "not a model name")):
        with pytest.raises(ValueError, match=msg) as info:
            family.parse(bad)
        assert "\n" not in str(info.value)
    with pytest.raises(ValueError, match="candidates = \\[\\]"):
        AdaptivePlan(STANDARD, ORDER, {"candidates": ["roughplastic:ggx"], "fixed": {"alpha": 0.1}})


def test_cross_validation_tells_a_conductor_from_a_plastic():
    """Held-out points of a gold conductor are predicted by the conductor, those of a plastic by
    the plastic (each the family that made them); ValueError for too few points."""
    from gonio.fitting import Measurements

    a = STANDARD.angles
    wi, wo = directions_deg(a[:, 0], a[:, 1]), directions_deg(a[:, 2], a[:, 3])
    pair = [("roughplastic", {"distribution": "ggx"}), ("roughconductor", {"distribution": "ggx"})]
    for (f, sd), want in ((_gold(STANDARD), "roughconductor"), (synthetic(STANDARD), "roughplastic")):
        meas = Measurements(wi, wo, f, sd, np.ones(f.shape, bool))
        name, _, scores = family.choose_cv(meas, pair, seed=0, n_local=1)
        assert name == want, scores
    with pytest.raises(ValueError, match="too few"):
        family.choose_cv(meas.subset(np.arange(9)), pair, seed=0)
