"""The NDF-seeded plan strategy ``ndf`` (gonio.bench.plan.ndf_seeded, issue 38): a first pass at
near retro-reflection, then points drawn where the fitted lobe sends light; deterministic for a
seed, and a resume replays its choices from the journalled results."""

from __future__ import annotations

import numpy as np
import pytest

from gonio.bench.plan import plans
from gonio.bench.plan import strategy as st
from gonio.bench.plan.cli_options import cli_strategy
from gonio.bench.plan.ndf_seeded import RETRO_MAX_DEG, NDFSeededPlan, retro_points
from gonio.core.geometry import directions_deg
from strategy_run import ALPHA, run, synthetic

def test_the_first_pass_is_near_retro_reflection_at_every_incidence():
    """retro_points: at each incidence of the dense plan, the candidate whose wo is nearest wi
    (within RETRO_MAX_DEG), spread over theta_i; they open the first pass."""
    plan = plans.load_plan("dense")
    a = plan.angles
    wi, wo = directions_deg(a[:, 0], a[:, 1]), directions_deg(a[:, 2], a[:, 3])
    picks = retro_points(wi, wo, a[:, 0], 6)
    gap = np.degrees(np.arccos(np.clip(np.sum(wi[picks] * wo[picks], axis=1), -1, 1)))
    assert len(picks) >= 4 and np.all(gap <= RETRO_MAX_DEG)
    assert len(set(np.round(a[picks, 0]))) == len(picks)              # one per incidence
    strat = NDFSeededPlan(plan, range(len(plan)), {"points": 20, "seed": 1})
    assert set(strat.retro) <= set(strat.batches[0]) and len(strat.batches[0]) == strat.first_n


def test_later_points_go_where_the_lobe_sends_light_and_a_resume_replays_them():
    """After the first pass every batch is drawn with probability proportional to the fitted
    f_r cos(theta_o) (times one plus its relative uncertainty): the chosen points' mean
    luminance is more than 1.5 times the candidates' (measured 1.68; 16 uniform draws give
    0.99 on average); the same seed gives the same points, another seed
    others; stopped after 9 points and resumed with the journalled results, it chooses what
    the whole run chose; the fit finds alpha."""
    plan = plans.load_plan("standard")
    f, sd = synthetic(plan)
    order = list(range(len(plan)))
    table = {"points": 24, "seed": 1}
    whole = NDFSeededPlan(plan, order, table)
    run(whole, f, sd)
    assert whole.stopped_by == "budget" and sum(map(len, whole.batches)) == 24
    later = [i for b in whole.batches[1:] for i in b]
    lum = f @ np.array([0.2126, 0.7152, 0.0722]) * np.clip(directions_deg(plan.angles[:, 2], plan.angles[:, 3])[:, 2],
                                                            0, None)
    assert lum[later].mean() > 1.5 * lum.mean()
    again = NDFSeededPlan(plan, order, table)
    run(again, f, sd)
    assert again.batches == whole.batches
    other = NDFSeededPlan(plan, order, {**table, "seed": 2})
    run(other, f, sd)
    assert other.batches[1:] != whole.batches[1:]
    first = NDFSeededPlan(plan, order, table)
    journalled = run(first, f, sd, stop_after=9)
    resumed = NDFSeededPlan(plan, order, table)
    todo = resumed.first(set(journalled))
    todo += resumed.more(journalled, tuple(todo))
    run(resumed, f, sd, results=journalled, todo=todo)
    assert resumed.batches == whole.batches
    assert abs(whole.log[-1]["params"]["alpha"] - ALPHA) < 0.02


def test_the_ndf_plan_is_a_strategy_and_a_cli_plan():
    assert st.STRATEGIES["ndf"] is NDFSeededPlan or callable(st.STRATEGIES["ndf"])
    assert cli_strategy("ndf", points=30, target_rel_u=None, candidates=None, seed=2) == (
        "dense", {"name": "ndf", "seed": 2, "points": 30})
    doc = NDFSeededPlan(plans.load_plan("quick"), range(30), {"points": 12}).to_dict()
    assert doc["name"] == "ndf"
    with pytest.raises(ValueError, match="unknown key"):
        NDFSeededPlan(plans.load_plan("quick"), range(30), {"pointz": 12})


def test_a_sequential_capture_that_stopped_at_its_budget_exports_complete(tmp_path, capsys):
    """An ndf capture of 10 points drawn from the quick plan (30) stops at its budget: its
    dataset is complete (``complete`` 1, ``strategy_stopped_by`` "budget") and ``gonio export``
    says so instead of "PARTIAL, 10 of 30 planned points ... --resume" (a resume has nothing to
    add: the strategy stopped)."""
    import xarray as xr

    from gonio.bench.dataset.export import strategy_stop
    from gonio.bench.session.simulated import capture_sim
    from gonio.cli.main import main

    assert strategy_stop([(0.0, "strategy", '{"stopped_by": "budget"}'), (1.0, "other", "x")]) == "budget"
    assert strategy_stop([(0.0, "strategy", "not json")]) is None and strategy_stop([]) is None
    session = tmp_path / "s"
    sample = {"model": "roughplastic", "options": {"distribution": "ggx"},
              "params": {"diffuse_reflectance": [0.5, 0.37, 0.25], "alpha": ALPHA, "int_ior": 1.49}}
    capture_sim(session, sample=sample, plan="quick", seed=2, progress=False,
                strategy={"name": "ndf", "seed": 2, "points": 10})
    assert main(["export", str(session)]) == 0
    out = capsys.readouterr().out
    assert "PARTIAL" not in out and "(10 points)" in out
    with xr.open_dataset(session / "dataset.nc") as ds:
        assert int(ds.attrs["complete"]) == 1 and ds.attrs["strategy_stopped_by"] == "budget"
