"""The adaptive plan's ``alc`` criterion (gonio.bench.plan.alc), driven without an instrument on
the dense plan's candidates: its picks spread where D-optimal ones cluster, its greedy updates
equal a fresh computation, its discrepancy estimate, and its table keys refused when wrong."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gonio.bench.plan import plans
from gonio.bench.plan.adaptive import AdaptivePlan, _features
from gonio.bench.plan.alc import TAU_MIN, alc_batch, discrepancy_rel, reference_grid
from strategy_run import run, synthetic

DENSE = plans.load_plan("dense")
F, SD = synthetic(DENSE)


def _later(criterion):
    strat = AdaptivePlan(DENSE, range(len(DENSE)), {"points": 20, "seed": 0, "criterion": criterion})
    run(strat, F, SD)
    return [i for b in strat.batches[1:] for i in b]


def _nearest(points):
    x = _features(DENSE.angles[points])
    d = np.sqrt(np.sum((x[:, None] - x[None]) ** 2, -1))
    np.fill_diagonal(d, np.inf)
    return d.min(1)


def test_alc_picks_spread_where_d_optimal_picks_cluster():
    # D-optimality puts its picks where roughplastic's parameters move f_r most, mostly the
    # specular plane (phi_o = 180 deg) beside the points already there: 7 of 12 here, 12 of 12
    # when the first pass was measured in the plan's order (the first fit then lacked another
    # point). The alc criterion integrates the predicted variance of f_r cos over the hemisphere
    # with a discrepancy floor, so a point next to a measured one gains little: its picks keep
    # apart and leave the plane (2 of 12 in it, either order).
    d_pts, a_pts = _later("d-optimal"), _later("alc")
    assert len(d_pts) == len(a_pts) == 12
    in_plane = lambda pts: np.mean(np.isclose(np.abs(DENSE.angles[pts, 3]), 180.0))
    assert in_plane(d_pts) >= 0.5 and in_plane(a_pts) <= 0.25
    assert np.median(_nearest(a_pts)) > 2.0 * np.median(_nearest(d_pts))


def test_a_batch_equals_its_picks_made_one_at_a_time():
    # the greedy batch's rank-one updates against the posterior recomputed with the earlier
    # picks counted as pending points: the same choices (exact algebra, no tolerance)
    strat = AdaptivePlan(DENSE, range(len(DENSE)), {"points": 20, "seed": 0, "criterion": "alc"})
    basis = strat.batches[0]
    results = {i: (F[i], SD[i]) for i in basis}
    fitted = strat._fit(basis, results, 1)
    x, sigma_rel, sigma_floor = fitted[0], fitted[3], fitted[4]
    free = [i for i in range(len(DENSE)) if i not in basis]
    batch = alc_batch(strat, x, basis, basis, free, 3, results, sigma_rel, sigma_floor)
    queue, single = list(basis), []
    for _ in range(3):
        left = [i for i in free if i not in queue]
        single += alc_batch(strat, x, basis, queue, left, 1, results, sigma_rel, sigma_floor)
        queue.append(single[-1])
    assert batch == single and len(set(batch)) == 3


def test_the_discrepancy_is_the_residuals_beyond_the_noise():
    rng = np.random.default_rng(3)
    fit = rng.uniform(0.1, 2.0, 4000)
    eps = rng.standard_normal(4000)
    # a 20 % relative misfit and 5 % noise: tau^2 = E[(0.2 eps)^2 + s^2 - s^2] / 1 = 0.04
    s = 0.05 * fit
    meas = fit * (1 + 0.2 * eps) + s * rng.standard_normal(4000)
    # tau^2's 1-sigma: 0.04 sqrt(2 / 4000) (var eps^2 = 2), 2.2 %, so tau's 1.1 %: the 5 % bound is
    # 4.5 sigma (false alarm < 1e-5 for any seed); an estimator 10 % off fails it
    assert discrepancy_rel(meas, s, fit) == pytest.approx(0.2, rel=0.05)
    assert discrepancy_rel(fit, 0.01 * fit, fit) == TAU_MIN             # a perfect fit: the floor
    assert discrepancy_rel(np.array([np.nan]), np.array([1.0]), np.array([1.0])) == TAU_MIN


def test_the_reference_grid_is_equal_solid_angle_below_80_degrees():
    wi, wo = reference_grid()
    assert wi.shape == wo.shape == (6 * 8 * 12, 3)
    cmax = math.cos(math.radians(80.0))
    assert np.all(wi[:, 2] > cmax) and np.all(wo[:, 2] > cmax)
    # cell centres uniform in cos theta: the mean of cos theta is the hemisphere cap's, (1 + cmax) / 2
    assert np.mean(wo[:, 2]) == pytest.approx((1 + cmax) / 2, rel=1e-12)


@pytest.mark.parametrize("key, value", [("criterion", "i-optimal"), ("criterion", 3), ("criterion", None),
                                        ("discrepancy_length", 0.0), ("discrepancy_length", -1.0),
                                        ("discrepancy_length", math.nan), ("discrepancy_length", math.inf),
                                        ("discrepancy_length", "0.4"), ("discrepancy_length", True),
                                        ("design_weights", "yes"), ("design_weights", 1), ("design_weights", None)])
def test_a_wrong_criterion_or_length_is_refused_in_one_line(key, value):
    with pytest.raises(ValueError, match=rf"^\[strategy\] .*{key}.*give") as err:
        AdaptivePlan(DENSE, range(len(DENSE)), {"points": 20, key: value})
    assert "\n" not in str(err.value)
