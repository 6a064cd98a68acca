"""``gonio perf acquisition`` (issue 38): per plan, the simulated capture's instrument time
against the fit's error against the truth, and the front of plans no other beats on both."""

import numpy as np
import pytest


def test_the_front_keeps_the_plans_no_other_beats_on_both():
    from gonio.perf.acquisition import front

    rows = [{"plan": "a", "time_s": 60.0, "ngan": 0.05}, {"plan": "b", "time_s": 100.0, "ngan": 0.02},
            {"plan": "c", "time_s": 120.0, "ngan": 0.03}, {"plan": "d", "time_s": 60.0, "ngan": 0.06}]
    assert [r["plan"] for r in front(rows)] == ["a", "b"]       # c: b faster and closer; d: a as fast and closer


def test_each_sequential_plan_is_the_strategy_it_names():
    """alc is the adaptive plan with the alc criterion; -unweighted leaves the design weights
    out of its dataset (gonio.bench.plan.design_weights); a time budget lifts the point count."""
    from gonio.bench.plan.design_weights import wanted
    from gonio.perf.acquisition import SEQUENTIAL, check_plans, strategy_table

    assert check_plans(",".join(SEQUENTIAL)) == SEQUENTIAL
    assert strategy_table("alc", 3, 24) == {"name": "adaptive", "seed": 3, "points": 24, "criterion": "alc"}
    assert strategy_table("adaptive-unweighted", 0, 24, 120.0) == {
        "name": "adaptive", "seed": 0, "points": 0, "design_weights": False, "budget_s": 120.0}
    assert [wanted(strategy_table(p, 0, 24)) for p in SEQUENTIAL] == [True, True, True, False, False]


def test_bad_options_are_one_line_before_anything_runs(tmp_path, capsys):
    from gonio.cli.main import main

    out = tmp_path / "acq.csv"
    for args, what in ((["--plans", "quick,nonsense"], "--plans"), (["--plans", ","], "--plans"),
                       (["--points", "0"], "--points"), (["--model", "nonsense"], "--model"),
                       (["--sample", str(tmp_path / "missing.toml")], "missing.toml"),
                       (["--errors", "nonsense"], "nonsense"), (["--budget-fraction", "0"], "--budget-fraction"),
                       (["--plans", "dense,alc", "--budget-fraction", "nan"], "--budget-fraction"),
                       (["--plans", "dense,alc", "--budget-fraction", "1.5"], "--budget-fraction"),
                       (["--plans", "quick,alc", "--budget-fraction", "0.1"], "dense"),
                       (["--seeds", "3"], "--seeds"), (["--seeds", "1,x"], "--seeds"),
                       (["--seed", "1", "--seeds", "1,2"], "--seeds"),
                       (["--plans", "quick,adaptive", "--seeds", "1,2"], "dense")):
        assert main(["perf", "acquisition", *args, "--out", str(out)]) == 2, args
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and what in err, err
    assert not out.exists()


@pytest.mark.long       # two simulated captures, fits and previews: about 15 s
def test_every_plan_reports_its_instrument_time_and_error(tmp_path, capsys):
    """quick (30 points) and a 12-point adaptive plan on the demo's glossy plastic, typical
    errors: each row has the dataset's instrument time (> the stages' motion alone: 30 points
    cannot be measured in under 30 s of settling and exposure), an Ngan error of the sample's
    own family below 0.05 and a finite rendered dE00; the CSV carries the seed and version."""
    import csv

    from gonio.perf.acquisition import run

    rows = run(("quick", "adaptive"), seed=3, points=12, out=tmp_path / "acq.csv")
    assert [r["plan"] for r in rows] == ["quick", "adaptive"]
    assert rows[0]["points"] == 30 and rows[1]["points"] == 12
    assert all(r["time_s"] > 30.0 and r["ngan"] < 0.05 and np.isfinite(r["de00"]) for r in rows)
    with open(tmp_path / "acq.csv") as fh:
        got = list(csv.DictReader(fh))
    assert got[0]["seed"] == "3" and got[0]["errors"] == "typical" and got[0]["gonio"]
    assert all(r["estimate_angles"] == "True" for r in got)          # the protocol's default since 2026-12-05
    # the sample's own family on typical errors: the estimate applied on both plans, and said so
    assert [r["angles_applied"] for r in got] == ["True", "True"]
    out = capsys.readouterr().out
    assert "front" in out and "the shared angle errors estimated" in out


def test_seeds_parse_as_ranges_and_lists_and_bad_ones_are_one_line():
    from gonio.core.errors import GonioError
    from gonio.perf.acquisition import parse_seeds

    assert parse_seeds("10-13") == (10, 11, 12, 13)
    assert parse_seeds("0-2, 8") == (0, 1, 2, 8)
    for bad in ("5", "3-1", "a", "5,5", "0-3,2", "-1,2", "1,,2", "0-5000", "1.5,2"):
        with pytest.raises(GonioError) as e:
            parse_seeds(bad)
        assert "--seeds" in str(e.value) and "\n" not in str(e.value), bad


def _rows(dense, plan, plan_name="alc"):
    """Rows of two plans at seeds 0..n-1: (ngan, log, time) per seed each."""
    rows = []
    for s, (d, p) in enumerate(zip(dense, plan)):
        rows.append({"plan": "dense", "seed": s, "ngan": d[0], "log": d[1], "time_s": d[2]})
        rows.append({"plan": plan_name, "seed": s, "ngan": p[0], "log": p[1], "time_s": p[2]})
    return rows


def test_each_plan_is_paired_with_the_dense_grid_of_its_own_seed():
    from scipy import stats

    from gonio.perf.acquisition import paired

    dense = [(0.20, 0.010, 1000.0), (0.10, 0.020, 1000.0), (0.40, 0.010, 2000.0)]
    # seed 0 passes; seed 1 fails on log; seed 2 is closer on both but takes 11 % of the time
    plan = [(0.18, 0.009, 90.0), (0.09, 0.022, 95.0), (0.36, 0.008, 220.0)]
    (e,) = paired(_rows(dense, plan))
    assert e["plan"] == "alc" and e["n"] == 3 and e["passes"] == 1
    # Ngan: 0.9 of its own seed's dense grid each time (against seed 0's it would be 0.9, 0.45, 1.8):
    # the mean 0.9 and no width
    assert e["ngan"] == pytest.approx((0.9, 0.9, 0.9))
    r = np.log([0.9, 1.1, 0.8])             # log ratios; t(0.975, 2) = 4.303 (a t table)
    half = stats.t.ppf(0.975, 2) * r.std(ddof=1) / np.sqrt(3)
    assert e["log"] == pytest.approx(tuple(np.exp([r.mean(), r.mean() - half, r.mean() + half])))
    assert stats.t.ppf(0.975, 2) == pytest.approx(4.303, abs=1e-3)
    assert e["log"][1] < 0.9 < 1.1 < e["log"][2] and e["log"][0] == pytest.approx(0.792 ** (1 / 3), rel=1e-3)
    assert e["time"] == pytest.approx((0.09 + 0.095 + 0.11) / 3)
    d = np.array([0.20, 0.10, 0.40])
    assert e["dense_cv"]["ngan"] == pytest.approx(d.std(ddof=1) / d.mean())
    assert paired([r for r in _rows(dense, plan) if r["plan"] != "dense"]) == []


def test_several_seeds_print_the_paired_summary_and_one_csv(tmp_path, capsys, monkeypatch):
    import csv

    import gonio.perf.acquisition as acq

    dense = [(0.20, 0.010, 1000.0), (0.22, 0.011, 1010.0)]
    plan = [(0.19, 0.009, 95.0), (0.23, 0.010, 96.0)]
    by_seed = {s: [r for r in _rows(dense, plan) if r["seed"] == s] for s in (0, 1)}
    calls = []

    def fake_run(plans, sample, *, seed, errors, **kw):
        calls.append((seed, kw.get("out")))
        return [{k: v for k, v in r.items() if k != "seed"} for r in by_seed[seed - 7]]

    monkeypatch.setattr(acq, "run", fake_run)
    rows, summary = acq.run_seeds(("dense", "alc"), None, (7, 8), out=tmp_path / "all.csv")
    assert calls == [(7, None), (8, None)]          # one CSV for every seed, not one a run
    assert [r["seed"] for r in rows] == [7, 7, 8, 8] and summary[0]["passes"] == 1
    out = capsys.readouterr().out
    assert "over 2 seeds" in out and "alc" in out and "1/2" in out
    with open(tmp_path / "all.csv") as fh:
        got = list(csv.DictReader(fh))
    assert [g["seed"] for g in got] == ["7", "7", "8", "8"] and got[0]["gonio"]



def test_a_ratio_that_is_not_finite_is_said_not_averaged():
    from gonio.perf.acquisition import paired

    dense = [(0.20, 0.010, 1000.0), (0.0, 0.020, 1000.0)]        # seed 1: a dense Ngan of exactly 0
    plan = [(0.18, 0.009, 90.0), (0.09, float("nan"), 95.0)]     # and a NaN log error
    (e,) = paired(_rows(dense, plan))
    assert e["not_finite"] == {"ngan": 1, "log": 1}
    assert all(np.isnan(v) for v in e["ngan"] + e["log"])
    assert set(e["dense_cv"]) == {"ngan", "log"}        # the summary's last line reads both


def test_the_thinned_peer_takes_a_stride_that_fits_its_budget_in_few_captures():
    """thinned_stride measures each stride's time: from dense / budget (11) up along the line
    through the last two captures' times against their points (11 -> 16 -> 19), then bisects
    between the largest stride over the budget (16) and the least within it (19): 17. The times
    are paper_white seed 16's (not monotone in the stride: each is another tour). With a fixed
    cost per capture (8 s) near the budget the search takes 13 captures, not one per stride;
    where not even one point fits it ends at the last stride after three."""
    from gonio.perf.acquisition import THINNED, check_plans, thinned_stride

    times = {11: 170.7, 12: 160.0, 13: 156.8, 14: 150.0, 15: 127.6, 16: 132.0, 17: 120.4, 18: 118.0, 19: 116.0}
    asked = []

    def spent(k):
        asked.append(k)
        return times[k]

    assert thinned_stride(11, 121.5, spent, 1053) == 17 and asked == [11, 16, 19, 17]
    asked.clear()
    assert thinned_stride(11, 200.0, spent, 1053) == 11 and asked == [11]      # fits at once: no search
    asked.clear()

    def fixed_cost(k):                      # 8 s of preparation, then 1.3 s a point, longer as they thin out
        asked.append(k)
        return 8.0 + 1.3 * len(range(0, 1053, k)) * (1 + 0.02 * k ** 0.5)

    k = thinned_stride(35, 12.0, fixed_cost, 1053)
    assert fixed_cost(k) <= 12.0 < fixed_cost(k - 1) and len(asked) <= 15
    asked.clear()
    assert thinned_stride(35, 9.5, fixed_cost, 1053) == 1053 and asked == [35, 196, 1053]
    assert check_plans(f"dense,{THINNED}") == ("dense", THINNED)


@pytest.mark.long       # a dense capture and the thinned ones: about 60 s
def test_the_thinned_peer_is_the_dense_plan_thinned_within_the_budget(tmp_path):
    """The demo's plastic, seed 3, 9.5 % of the dense time: thinned is every k-th dense point from
    point 3 mod k, within the budget, fitted without design weights as the dense grid is."""
    import xarray as xr

    from gonio.bench.plan.plans import load_plan
    from gonio.perf.acquisition import run

    rows = run(("dense", "thinned"), seed=3, folder=tmp_path, budget_fraction=0.095)
    dense, thinned = rows
    assert thinned["time_s"] <= 0.095 * dense["time_s"]
    tried = {}
    for session in tmp_path.glob("thinned-*"):
        with xr.open_dataset(session / "dataset.nc") as ds:
            tried[int(session.name.split("-")[1])] = (float(ds.attrs["instrument_time_s"]), ds.sizes["point"],
                                                     "design_weight" in ds)
    k = [j for j, v in tried.items() if v == (thinned["time_s"], thinned["points"], False)][0]
    assert all(t > 0.095 * dense["time_s"] for j, (t, _, _) in tried.items() if j < k)   # none fewer fitted
    assert min(tried) == 11 and thinned["points"] == len(load_plan("dense").angles[3 % k::k])
    assert thinned["ngan"] < 0.05          # the sample's own family: the thinned fit is a fit
