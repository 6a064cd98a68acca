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
                       (["--plans", "quick,alc", "--budget-fraction", "0.1"], "dense")):
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
    assert "front" in capsys.readouterr().out
