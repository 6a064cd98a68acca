"""The ``adaptive`` plan strategy (gonio.bench.plan.adaptive) on the simulated instrument: it
recovers a glossy sample's roughness from a dozen points, chooses the same points for the same
seed, and a resume after a stop replays its choices."""

from __future__ import annotations

import os
import re
import signal

import numpy as np
import pytest

sim = pytest.importorskip("gonio.sim")

from benchfakes.cameras import InterruptingCamera

import gonio.models as gm
from gonio.bench.plan import plans
from gonio.bench.plan import strategy as st
from gonio.bench.plan.adaptive import AdaptivePlan, spread_subset
from gonio.bench.plan.cli_options import cli_strategy
from gonio.bench.session.capture import capture, resume
from gonio.bench.session.journal import Journal, read_session
from gonio.bench.settings import default_settings
from gonio.core.errors import GonioError
from gonio.fitting import Measurements, fit
from strategy_run import run, synthetic

S = default_settings()
ALPHA = 0.15
GLOSSY = {"model": "roughplastic", "options": {"distribution": "ggx"},
          "params": {"diffuse_reflectance": [0.6, 0.4, 0.2], "alpha": ALPHA}}
QUICK = plans.load_plan("quick")
TABLE = {"name": "adaptive", "points": 12, "seed": 4}


@pytest.fixture
def made(monkeypatch):
    """Every AdaptivePlan the captures make, in order."""
    out = []
    monkeypatch.setitem(st.STRATEGIES, "adaptive", lambda p, o, t: out.append(AdaptivePlan(p, o, t)) or out[-1])
    return out


def _capture(name, folder, camera=None, seed=4):
    inst = sim.Instrument(S, sample=GLOSSY, seed=seed).register(name)
    try:
        res = capture(folder, QUICK, S, inst.url("zaber"), inst.url("meter"),
                      camera if camera is not None else inst.url("camera"), seed=seed, progress=False,
                      sleep=inst.clock.advance, sample_truth=inst.sample_spec, strategy=TABLE)
    except BaseException:
        inst.unregister()
        raise
    return inst, res


def _fit(folder):
    rows = Journal(folder / "journal.sqlite").points()
    a = QUICK.angles[[r["idx"] for r in rows]]
    from gonio.core.geometry import directions_deg
    meas = Measurements(directions_deg(a[:, 0], a[:, 1]), directions_deg(a[:, 2], a[:, 3]),
                        [r["brdf"] for r in rows], [r["brdf_std"] for r in rows], True)
    return fit(meas, gm.get("roughplastic", distribution="ggx"), rng=np.random.default_rng(0))


def test_an_adaptive_capture_recovers_alpha_and_repeats_its_choices(made, tmp_path):
    runs = []
    for k in range(2):                                   # two captures, same seed
        inst, res = _capture(f"adaptive-{k}", tmp_path / f"s{k}")
        inst.unregister()
        assert res.complete and res.n_done == res.n_points == 12
        strat = made[-1]
        assert strat.stopped_by == "budget" and len(strat.log) == len(strat.batches) - 1 >= 2
        done = Journal(tmp_path / f"s{k}" / "journal.sqlite").done()
        assert done == {i for b in strat.batches for i in b}
        runs.append(strat.batches)
    assert runs[0] == runs[1]                            # the same points, batch by batch
    assert read_session(tmp_path / "s0")["strategy"] == TABLE
    res = _fit(tmp_path / "s0")
    alpha = dict(zip(res.space.names, zip(res.x, res.std)))["alpha"]
    assert abs(alpha[0] - ALPHA) < 3 * alpha[1] and alpha[1] < 0.02 * ALPHA      # within 3 sigma; sigma < 2 %


def _stop_at_point(k):
    """A camera hook that presses Ctrl-C once as the ``k``-th measured point starts (0-based)."""
    seen: list[str] = []

    def hook(n, path):
        m = re.search(r"p(\d{5})_", os.fspath(path))
        if m and m.group(1) not in seen:
            seen.append(m.group(1))
            if len(seen) == k + 1:
                os.kill(os.getpid(), signal.SIGINT)
    return hook


def test_a_resume_after_a_stop_in_the_first_pass_finishes_the_plan(made, tmp_path):
    folder = tmp_path / "s"
    inst = sim.Instrument(S, sample=GLOSSY, seed=4).register("adaptive-stop")
    try:
        cam = InterruptingCamera(inst.url("camera"), hook=_stop_at_point(3))
        res = _capture_with(inst, folder, cam)
        assert not res.complete and "Ctrl-C" in res.stopped and res.n_done == 4
        again = resume(folder, camera=inst.url("camera"), sleep=inst.clock.advance, progress=False)
    finally:
        inst.unregister()
    assert again.complete and again.n_done == 12 and made[-1].name == "adaptive"
    assert made[-1].stopped_by == "budget"
    assert Journal(folder / "journal.sqlite").done() == {i for b in made[-1].batches for i in b}


def test_a_resume_after_a_stop_past_the_first_pass_finishes_the_plan(made, tmp_path):
    folder = tmp_path / "s"
    inst = sim.Instrument(S, sample=GLOSSY, seed=4).register("adaptive-stop2")
    try:
        res = _capture_with(inst, folder, InterruptingCamera(inst.url("camera"), hook=_stop_at_point(7)))
        assert not res.complete and res.n_done == 8 and len(made[-1].batches) >= 2
        again = resume(folder, camera=inst.url("camera"), sleep=inst.clock.advance, progress=False)
    finally:
        inst.unregister()
    assert again.n_done == 12 and again.complete


def _capture_with(inst, folder, camera):
    return capture(folder, QUICK, S, inst.url("zaber"), inst.url("meter"), camera, seed=4, progress=False,
                   sleep=inst.clock.advance, sample_truth=inst.sample_spec, strategy=TABLE)


def test_a_resume_replays_the_choices_from_the_journalled_results():
    plan = plans.load_plan("standard")
    f, sd = synthetic(plan)
    order = list(range(len(plan)))
    table = {"points": 20, "seed": 1}
    whole = AdaptivePlan(plan, order, table)
    run(whole, f, sd)
    assert whole.stopped_by == "budget" and sum(map(len, whole.batches)) == 20
    for stop in (3, 9, 13):                 # in the first pass, at a batch's end, inside a batch
        first = AdaptivePlan(plan, order, table)
        journalled = run(first, f, sd, stop_after=stop)
        again = AdaptivePlan(plan, order, table)             # a resume: a fresh strategy, every result at once
        todo = again.first(set(journalled))
        todo += again.more(journalled, tuple(todo))
        assert again.batches[:len(first.batches)] == first.batches
        rest = run(again, f, sd, results=journalled, todo=todo)
        assert again.batches == whole.batches and set(rest) == {i for b in whole.batches for i in b}
    # the fit found the truth, and a target stops the plan early and says so
    assert abs(whole.log[-1]["params"]["alpha"] - ALPHA) < 0.01
    early = AdaptivePlan(plan, order, {**table, "target_rel_u": 0.05})
    run(early, f, sd)
    assert early.stopped_by == "target" and sum(map(len, early.batches)) < 20
    assert early.state()["stopped_by"] == "target" and max(early.log[-1]["rel_u"].values()) < 0.05


def test_the_first_pass_is_spread_and_the_table_is_checked():
    a = plans.load_plan("dense").angles
    first = spread_subset(a, 8)
    assert len(set(first)) == 8 and first == spread_subset(a, 8)
    assert spread_subset(a, 3, first)[:1] == spread_subset(a, 9)[8:9]
    assert len(set(np.round(a[first, 0]))) >= 3          # several incidences, not one scan
    for bad, msg in (({"points": 0}, "points = 0"), ({"pointz": 3}, "unknown key 'pointz'"),
                     ({"target_rel_u": -1}, "target_rel_u"), ({"model": "nope"}, "model 'nope'")):
        with pytest.raises(ValueError, match=msg):
            AdaptivePlan(QUICK, range(len(QUICK)), bad)
    with pytest.raises(GonioError, match="points = 0"):
        capture("/nonexistent/never", QUICK, S, "sim://x/zaber", "sim://x/meter", "sim://x/camera",
                strategy={"name": "adaptive", "points": 0})
    assert cli_strategy("adaptive", points=30, target_rel_u=None, candidates=None, seed=2) == (
        "dense", {"name": "adaptive", "seed": 2, "points": 30})
    with pytest.raises(ValueError, match="--points goes with --plan adaptive"):
        cli_strategy("standard", points=30, target_rel_u=None, candidates=None, seed=0)


def test_the_first_pass_is_measured_in_its_least_move_order():
    """The first pass is a spread subset, far apart by design: visited in the session's order over
    the whole plan, demo seed 0's took 60.5 s of moves, its least order 31.3 s (docs/performance.md).
    Its order is the least move time from home between the poses the run moves to (session.toml's
    stage_deg, here a mirror solution for every second point), not the plan's order."""
    from itertools import permutations

    from gonio.bench.plan.ordering import mirror, path_time

    plan = plans.load_plan("dense")
    p = AdaptivePlan(plan, range(len(plan)), {"points": 0, "budget_s": 300.0, "seed": 0})
    first = sorted(p.batches[0])
    assert len(first) == 8 and set(first) == set(spread_subset(plan.angles, 8))
    poses = p.stage.copy()
    poses[1::2] = mirror(poses[1::2])
    p.use_session(poses, S)
    got = path_time(poses[p.first(set())], S, np.zeros(4))
    best = min(path_time(poses[list(o)], S, np.zeros(4)) for o in permutations(first))
    assert got == pytest.approx(best, abs=1e-9) and sorted(p.batches[0]) == first
    assert got < 0.75 * path_time(poses[first], S, np.zeros(4))       # the plan's own order


def _gonio(*args):
    import subprocess
    import sys
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    return subprocess.run([sys.executable, "-m", "gonio.cli.main", *args], capture_output=True, text=True,
                          timeout=120, env=env)


def test_the_adaptive_options_go_with_the_adaptive_plan(tmp_path):
    proc = _gonio("capture", "--sim", "--plan", "quick", "--points", "8", "--out", str(tmp_path / "s"))
    assert proc.returncode == 2 and proc.stderr.strip() == "gonio: error: --points goes with --plan adaptive"
    assert not (tmp_path / "s").exists()


def test_gonio_capture_plan_adaptive_on_the_simulator(tmp_path):
    from gonio.cli.main import main

    code = main(["capture", "--sim", "--plan", "adaptive", "--candidates", "quick", "--points", "8", "--quiet",
                 "--out", str(tmp_path / "s")])
    assert code == 0 and len(Journal(tmp_path / "s" / "journal.sqlite").done()) == 8
    assert read_session(tmp_path / "s")["strategy"] == {"name": "adaptive", "seed": 0, "points": 8}


def test_the_criterion_option():
    """``--criterion`` reaches the strategy table (session.toml records it) with --plan adaptive
    only: a fixed plan or ndf (which places its points by its own rule) refuse it in one line."""
    from gonio.bench.plan.cli_options import cli_strategy

    plan, table = cli_strategy("adaptive", points=8, target_rel_u=None, candidates="quick", seed=3, criterion="alc")
    assert plan == "quick" and table == {"name": "adaptive", "seed": 3, "points": 8, "criterion": "alc"}
    assert "criterion" not in cli_strategy("adaptive", points=8, target_rel_u=None, candidates=None, seed=0)[1]
    with pytest.raises(ValueError, match="--criterion goes with --plan adaptive"):
        cli_strategy("quick", points=None, target_rel_u=None, candidates=None, seed=0, criterion="alc")
    with pytest.raises(ValueError, match="ndf places its points"):
        cli_strategy("ndf", points=8, target_rel_u=None, candidates=None, seed=0, criterion="alc")
    with pytest.raises(ValueError, match="give one of d-optimal, alc"):
        cli_strategy("adaptive", points=8, target_rel_u=None, candidates=None, seed=0, criterion="bogus")


def test_the_toured_first_pass_keeps_the_front_stop_before_the_rear():
    """A plan with transmitted points: the session measures the reflected points, then moves the
    camera to the rear stop once (an operator's step each way). The first pass in least-move order
    keeps that: each stop's points toured on their own, front first."""
    from gonio.bench.plan import kinematics
    from gonio.bench.plan.ndf_seeded import NDFSeededPlan

    plan = plans.load_plan("both-sides")
    rear = np.asarray(kinematics.detector_of(plan.angles[:, 2]), bool)
    order = np.concatenate([np.flatnonzero(~rear), np.flatnonzero(rear)])      # as the session orders them
    for cls in (AdaptivePlan, NDFSeededPlan):
        p = cls(plan, order, {"points": 30, "seed": 0})
        assert rear[p.batches[0]].any() and not rear[p.batches[0]].all()
        p.use_session(p.stage, S)
        side = rear[p.first(set())].astype(int)
        assert np.count_nonzero(np.diff(side)) == 1 and side[0] == 0, side
