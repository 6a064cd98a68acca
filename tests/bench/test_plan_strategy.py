"""The capture loop reads its plan strategy (gonio.bench.plan.strategy) and nothing else about
which point comes next: a strategy that chooses from the data so far runs through a real
simulated capture, and the fixed plan is its default."""

from __future__ import annotations

import numpy as np
import pytest

sim = pytest.importorskip("gonio.sim")

from gonio.bench.plan import plans
from gonio.bench.plan import strategy as st
from gonio.bench.session.capture import capture, resume
from gonio.bench.session.journal import Journal, read_session
from gonio.bench.settings import default_settings
from gonio.core.errors import GonioError, SessionError

S = default_settings()
GLOSSY = {"model": "roughplastic", "params": {"diffuse_reflectance": [0.6, 0.4, 0.2], "alpha": 0.15}}
CANDIDATES = plans.Plan("candidates", np.array(
    [[30, 0, t, 180] for t in (10, 20, 30, 40, 50, 60)] + [[30, 0, t, 0] for t in (20, 40, 60)], float))


class NearBrightest:
    """Measures two points, then each time the unmeasured candidate nearest in theta_o to the
    brightest point measured so far, up to ``budget`` points."""

    name = "near_brightest"

    def __init__(self, plan, order, table):
        self.plan, self.order = plan, [int(i) for i in order]
        self.budget = int(table.get("budget", 5))
        self.seen: list[int] = []            # how many results each choice was made from

    def first(self, done):
        return [i for i in self.order if i not in done][:2]

    def more(self, results, queued):
        if len(set(queued) | set(results)) >= self.budget or not results:
            return []
        best = max(results, key=lambda i: float(np.mean(results[i][0])))
        left = [i for i in range(len(self.plan)) if i not in queued and i not in results]
        self.seen.append(len(results))
        return [min(left, key=lambda i: abs(self.plan.angles[i, 2] - self.plan.angles[best, 2]))]

    def to_dict(self):
        return {"name": self.name, "budget": self.budget}


@pytest.fixture
def inst():
    i = sim.Instrument(S, sample=GLOSSY, seed=4).register("strategy-test")
    yield i
    i.unregister()


def _capture(inst, folder, **kw):
    return capture(folder, CANDIDATES, S, inst.url("zaber"), inst.url("meter"), inst.url("camera"), seed=inst.seed,
                   progress=False, sleep=inst.clock.advance, sample_truth=inst.sample_spec, **kw)


def test_a_strategy_that_chooses_from_the_data_drives_a_real_capture(inst, tmp_path, monkeypatch):
    made = []
    monkeypatch.setitem(st.STRATEGIES, "near_brightest", lambda p, o, t: made.append(NearBrightest(p, o, t)) or made[-1])
    res = _capture(inst, tmp_path / "s", strategy={"name": "near_brightest", "budget": 5})
    assert res.complete and res.n_done == res.n_new == 5 and res.n_points == 5
    strat = made[-1]
    assert strat.seen and max(strat.seen) >= 2                  # later choices read journalled results
    done = Journal(tmp_path / "s" / "journal.sqlite").done()
    assert len(done) == 5 and set(strat.first(set())) <= done
    # the brightest in-plane point of a glossy sample lit at 30 deg is the specular one (theta_o = 30,
    # phi_o = 180; Mitsuba roughplastic): the strategy walked toward it
    specular = int(np.flatnonzero((CANDIDATES.angles[:, 2] == 30) & (np.abs(CANDIDATES.angles[:, 3]) == 180))[0])
    assert specular in done
    assert read_session(tmp_path / "s")["strategy"] == {"name": "near_brightest", "budget": 5}
    again = resume(tmp_path / "s", inst.url("zaber"), inst.url("meter"), inst.url("camera"), progress=False,
                   sleep=inst.clock.advance)
    assert again.n_new == 0 and again.complete                  # a resume replays the recorded strategy


def test_the_fixed_plan_is_the_default_and_is_recorded(inst, tmp_path):
    res = _capture(inst, tmp_path / "f")
    assert res.complete and res.n_done == len(CANDIDATES)
    assert read_session(tmp_path / "f")["strategy"] == {"name": "fixed"}


def test_an_unknown_strategy_is_refused_before_anything_is_written(inst, tmp_path):
    with pytest.raises(GonioError, match="unknown plan strategy 'nope'; known: adaptive, fixed"):
        _capture(inst, tmp_path / "u", strategy={"name": "nope"})
    assert not (tmp_path / "u").exists()


def test_a_strategy_asking_for_a_point_outside_the_plan_stops_the_run(inst, tmp_path, monkeypatch):
    class Wild(NearBrightest):
        def more(self, results, queued):
            return [len(self.plan) + 3]

    monkeypatch.setitem(st.STRATEGIES, "wild", Wild)
    with pytest.raises(SessionError, match="asked for point 12 of a plan of 9"):
        _capture(inst, tmp_path / "w", strategy={"name": "wild"})
