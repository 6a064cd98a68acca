"""Where an adaptive capture stops (issue 38): at a budget of instrument time (each batch must
fit in what the session's journalled time leaves), at a colour target (the predicted CIEDE2000
1-sigma of the fitted albedo colour), and says which; bad values of the command line's stops
are one line and exit status 2 before anything is written."""

from __future__ import annotations

import math

import numpy as np
import pytest

import gonio.models as gm
from gonio.bench.plan import plans
from gonio.bench.plan.adaptive import AdaptivePlan, albedo_de00_u
from gonio.bench.plan.cli_options import cli_strategy
from gonio.core.geometry import directions_deg

QUICK = plans.load_plan("quick")
ORDER = list(range(len(QUICK)))
EXTRA = 1.5                     # a point's time besides its move, s (settle, exposures, readings)


def _synthetic(plan, seed=0):
    m = gm.get("roughplastic", distribution="ggx")
    a = plan.angles
    f = m.eval(directions_deg(a[:, 0], a[:, 1]), directions_deg(a[:, 2], a[:, 3]),
               {"diffuse_reflectance": np.array([0.5, 0.37, 0.25]), "alpha": 0.15, "int_ior": 1.49})
    sd = 0.01 * f + 1e-4
    return f + sd * np.random.default_rng(seed).standard_normal(f.shape), sd


F, SD = _synthetic(QUICK)


def _timed_run(strat, preparations):
    """Drive ``strat`` as `_Session.run` does, telling it the time before each request; each
    point takes EXTRA plus its move. The results and the points' times."""
    results, times, todo, n = {}, {}, strat.first(set()), 0
    while n < len(todo):
        strat.account(times, preparations)
        todo.extend(strat.more(results, tuple(todo)))
        i = todo[n]
        times[i] = EXTRA + (strat._move_s(todo[n - 1], i) if n else 0.0)
        results[i] = (F[i], SD[i])
        n += 1
    return results, times


def test_a_time_budget_stops_the_plan_inside_it_and_a_resume_replays_it():
    table = {"points": 0, "budget_s": 60.0, "overhead_s": 2.0, "seed": 3}
    strat = AdaptivePlan(QUICK, ORDER, table)
    assert strat.budget == len(QUICK)                      # points 0: as many as the time allows
    results, times = _timed_run(strat, [(0, 12.0)])
    spent = 12.0 + sum(times.values())
    assert strat.stopped_by == "time" and len(results) < len(QUICK)
    assert spent <= 60.0 and spent + strat.next_s > 60.0   # the next point would not have fitted
    assert 60.0 - spent < EXTRA + 20.0                      # ... and the budget was used, not left idle
    assert "stopped at its time budget" in strat.stop_line() and "of 60 s" in strat.stop_line()
    # a resume: a fresh strategy, every result and time at once, and the resume's own preparation
    # (after every point): the same choices, and the same stop
    again = AdaptivePlan(QUICK, ORDER, table)
    again.account(times, [(0, 12.0), (len(results), 9.0)])
    todo = again.first(set(results))
    todo += again.more(results, tuple(todo))
    assert again.batches == strat.batches and again.stopped_by == "time"


def test_a_first_pass_longer_than_the_budget_is_cut_or_refused():
    full = AdaptivePlan(QUICK, ORDER, {"points": 0, "budget_s": 1e4})
    cut = AdaptivePlan(QUICK, ORDER, {"points": 0, "budget_s": 60.0})   # 8 points: ~64 s, 7: ~55 s
    assert cut.space.size + 1 <= cut.first_n < full.first_n
    assert set(cut.batches[0]) <= set(full.batches[0])             # a prefix of the spread points
    with pytest.raises(ValueError, match=r"budget_s = 45 s: the first pass alone \(6 points\) takes about 47 s"):
        AdaptivePlan(QUICK, ORDER, {"points": 0, "budget_s": 45.0})
    for bad in ({"budget_s": -1.0}, {"budget_s": float("nan")}, {"target_de00": float("inf")},
                {"target_de00": "1"}, {"points": 0}):
        with pytest.raises(ValueError, match="budget_s|target_de00|points"):
            AdaptivePlan(QUICK, ORDER, bad)


def test_a_colour_target_stops_the_plan_and_says_so():
    strat = AdaptivePlan(QUICK, ORDER, {"points": 20, "seed": 1, "target_de00": 0.25})
    results, _ = _timed_run(strat, [])
    u = [e["de00_u"] for e in strat.log]
    assert strat.stopped_by == "target" and len(results) < 20
    assert u[-1] < 0.25 <= min(u[:-1]) and u == sorted(u, reverse=True)   # it fell as points came in
    assert "albedo colour's predicted CIEDE2000 1-sigma" in strat.stop_line()


def test_the_colour_proxy_scales_with_the_covariance():
    m = gm.get("roughplastic", distribution="ggx")
    strat = AdaptivePlan(QUICK, ORDER, {"points": 8})
    x = strat.space.from_params({"diffuse_reflectance": np.array([0.5, 0.37, 0.25]), "alpha": 0.15, "int_ior": 1.49})
    cov = np.diag((1e-3 * np.abs(x)) ** 2)
    u = albedo_de00_u(m, strat.space, x, cov)
    assert 0 < u < 1 and albedo_de00_u(m, strat.space, x, 4 * cov) == pytest.approx(2 * u, rel=0.02)
    assert albedo_de00_u(m, strat.space, x, 0 * cov) == 0.0
    assert albedo_de00_u(m, strat.space, x, cov * np.nan) == math.inf


@pytest.mark.parametrize("given, said", [
    ({"budget_minutes": -1.0}, "--budget-minutes -1.0: give the most instrument time as a number > 0 (minutes)"),
    ({"budget_minutes": math.nan}, "--budget-minutes nan: give"),
    ({"budget_minutes": 0.0}, "--budget-minutes 0.0: give"),
    ({"budget_minutes": 1e308}, "--budget-minutes 1e+308: more than a million minutes"),
    ({"target_de00": 0.0}, "--target-de00 0.0: give a CIEDE2000 colour difference as a number > 0"),
    ({"target_de00": -math.inf}, "--target-de00 -inf: give"),
    ({"target_rel_u": math.nan}, "--target-rel-u nan: give"),
    ({"points": 0}, "--points 0: give the most points"),
    ({"points": 5, "budget_minutes": 2.0}, "--points and --budget-minutes exclude each other"),
])
def test_bad_stops_are_refused_in_one_line(given, said):
    kw = {"points": None, "target_rel_u": None, "candidates": None, "seed": 0, **given}
    with pytest.raises(ValueError) as err:
        cli_strategy("adaptive", **kw)
    assert str(err.value).startswith(said) and "\n" not in str(err.value)
    with pytest.raises(ValueError, match="goes with --plan adaptive"):
        cli_strategy("quick", **kw)


def test_the_stops_become_the_strategy_table():
    assert cli_strategy("adaptive", points=None, target_rel_u=None, candidates="quick", seed=2, budget_minutes=1.5,
                        target_de00=0.5) == ("quick", {"name": "adaptive", "seed": 2, "points": 0, "budget_s": 90.0,
                                                        "target_de00": 0.5})


def test_gonio_capture_refuses_a_bad_stop_before_writing(tmp_path, capsys):
    from gonio.cli.main import main

    out = tmp_path / "s"
    code = main(["capture", "--sim", "--plan", "adaptive", "--budget-minutes", "nan", "--out", str(out), "--quiet"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and err == "gonio: error: --budget-minutes nan: give the most instrument time as a number > 0 " \
                                "(minutes)"
    assert not out.exists()


def test_an_adaptive_capture_stops_at_its_time_budget_on_the_simulator(tmp_path):
    sim = pytest.importorskip("gonio.sim")
    from gonio.bench.session.capture import capture
    from gonio.bench.settings import default_settings

    s = default_settings()
    s["capture"]["flat_frames"] = 8
    inst = sim.Instrument(s, seed=4).register("plan-stops-time")
    try:
        res = capture(tmp_path / "s", QUICK, s, inst.url("zaber"), inst.url("meter"), inst.url("camera"), seed=4,
                      progress=False, sleep=inst.clock.advance, sample_truth=inst.sample_spec,
                      strategy={"name": "adaptive", "points": 0, "budget_s": 40.0, "overhead_s": 1.0, "seed": 4})
    finally:
        inst.unregister()
    assert res.complete and not res.stopped and res.n_done < len(QUICK)
    assert res.plan_stop.startswith("adaptive plan: stopped at its time budget")
    assert 30.0 < res.instrument_s <= 40.0          # the session's journalled time: inside, and most of it used
