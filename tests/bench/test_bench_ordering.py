"""Move ordering: trapezoidal move times, the ordered plan, its lower bound."""

import numpy as np
import pytest

from gonio.bench.plan import kinematics
from gonio.bench.plan import plans
from gonio.bench.plan.ordering import _variants, cost_matrix, move_time, order_moves, path_time, tour
from gonio.bench.settings import default_settings

S = default_settings()


def test_trapezoid_move_time():
    v, a = 20.0, 40.0                                         # full speed after v^2/a = 10 deg
    assert move_time(0.0, v, a) == 0.0
    assert move_time(10.0, v, a) == pytest.approx(1.0)       # triangle: 2 sqrt(10/40)
    assert move_time(2.5, v, a) == pytest.approx(0.5)
    assert move_time(-50.0, v, a) == pytest.approx(50 / 20 + 20 / 40)
    assert move_time(10.0 + 1e-9, v, a) == pytest.approx(1.0)   # continuous at the switch


def test_axes_move_at_once():
    c = cost_matrix(np.zeros((1, 4)), np.array([[10.0, 50.0, 0, 0]]), S)
    assert c[0, 0] == pytest.approx(move_time(50.0, 20.0, 40.0))


def test_standard_preset_gain_and_bound():
    """The acceptance figures: >= 30 % less move time than plan order, within 15 % of the bound."""
    p = plans.load_plan("standard")
    st = kinematics.inverse(*p.angles.T)
    r = order_moves(st, S)
    assert sorted(r.order.tolist()) == list(range(len(p)))
    assert r.gain >= 0.30, r
    assert r.bound_s <= r.ordered_s and r.over_bound <= 0.15, r
    # the ordered poses see the same directions and are within the limits
    wi, wo = kinematics.forward(r.stage_deg)
    np.testing.assert_allclose(wi, kinematics.directions(p.angles[:, 0], p.angles[:, 1]), atol=1e-9)
    np.testing.assert_allclose(wo, kinematics.directions(p.angles[:, 2], p.angles[:, 3]), atol=1e-9)
    assert path_time(r.stage_deg[r.order], S, np.zeros(4)) == pytest.approx(r.ordered_s)
    lim = np.array([S["axes"][n][2:] for n in kinematics.AXES])
    assert np.all((r.stage_deg >= lim[:, 0]) & (r.stage_deg <= lim[:, 1]))


def exact_best(var, ok):
    """Exact optimum by dynamic programming over (visited set, last point, its variant)."""
    n = var.shape[0]
    start = np.zeros(4)
    best = {}
    for i in range(n):
        for c in (0, 1):
            if ok[i, c]:
                best[(1 << i, i, c)] = path_time(var[i:i + 1, c], S, start)
    for mask in range(1, 1 << n):
        for (m, i, c), t in [(key, v) for key, v in best.items() if key[0] == mask]:
            for j in range(n):
                if mask & (1 << j):
                    continue
                for d in (0, 1):
                    if ok[j, d]:
                        key = (mask | (1 << j), j, d)
                        tt = t + path_time(np.stack([var[i, c], var[j, d]]), S)
                        if tt < best.get(key, np.inf):
                            best[key] = tt
    return min(v for (m, _, _), v in best.items() if m == (1 << n) - 1)


def test_small_plans_against_exact_optimum():
    rng = np.random.default_rng(5)
    for trial in range(3):
        a = np.column_stack([rng.uniform(10, 70, 7), np.zeros(7), rng.uniform(10, 70, 7), rng.uniform(-180, 180, 7)])
        st = kinematics.inverse(*a.T)
        r = order_moves(st, S)
        var, ok = _variants(st, S)
        best = exact_best(var, ok)
        assert r.bound_s <= best + 1e-9 <= r.ordered_s + 1e-9
        assert r.ordered_s <= 1.05 * best


def test_empty_and_single():
    assert order_moves(np.zeros((0, 4)), S).ordered_s == 0.0
    r = order_moves(np.array([[10.0, 0, 0, 30]]), S)
    assert r.order.tolist() == [0] and r.ordered_s == pytest.approx(r.bound_s)


def test_tour_of_fixed_poses_is_the_least_move_time():
    """``tour`` keeps each pose as given (no mirror) and starts from home: exact (every order)
    up to 8 poses; above that, the local search is checked against every order of 9 poses."""
    from itertools import permutations

    rng = np.random.default_rng(11)
    for n in (1, 2, 5, 8, 9):
        a = np.column_stack([rng.uniform(0, 80, n), np.zeros(n), rng.uniform(0, 80, n), rng.uniform(-180, 180, n)])
        st = kinematics.inverse(*a.T)
        got = tour(st, S)
        assert sorted(got.tolist()) == list(range(n))
        t = path_time(st[got], S, np.zeros(4))
        best = min(path_time(st[list(p)], S, np.zeros(4)) for p in permutations(range(n))) if n <= 8 else None
        if n <= 8:
            assert t == pytest.approx(best, abs=1e-9)
        else:                                    # 9! orders, by the same cost: the search within 5 %
            D = cost_matrix(st, st, S)
            s0 = cost_matrix(np.zeros((1, 4)), st, S)[0]
            o = np.array(list(permutations(range(n))))
            best = float(np.min(s0[o[:, 0]] + D[o[:, :-1], o[:, 1:]].sum(1)))
            assert best - 1e-9 <= t <= 1.05 * best
        assert t <= path_time(st, S, np.zeros(4)) + 1e-9        # never worse than the order given
