"""LED warm-up and drift statistics."""

import numpy as np
import pytest

from gonio.sim import Lamp


def test_warm_up_settles_exponentially():
    lamp = Lamp(seed=0, drift_sigma=0.0)
    lamp.switch(0.0, True)
    p = np.array([lamp.power(t) for t in (0.0, 120.0, 240.0, 3600.0)])
    settled = 0.01
    assert p[-1] == pytest.approx(settled, rel=1e-9)
    excess = (p[:3] - settled) / (p[0] - settled)
    np.testing.assert_allclose(excess, np.exp(-np.array([0.0, 1.0, 2.0])), rtol=1e-9)
    assert p[0] / settled == pytest.approx(1 / (1 - 0.004 * 15))   # cold LED starts 6 % high
    lamp.switch(4000.0, False)
    assert lamp.power(4001.0) == 0.0
    assert lamp.temperature(4000.0 + 5 * 120) == pytest.approx(25.0, abs=0.11)


def test_drift_is_a_seeded_random_walk():
    a, b, c = Lamp(seed=5), Lamp(seed=5), Lamp(seed=6)
    for lamp in (a, b, c):
        lamp.switch(0.0, True)
    ts = np.arange(0.0, 20000.0, 1.0)
    da = np.log([a.drift(t) for t in ts])
    db = np.log([b.drift(t) for t in ts[::-1]])[::-1]    # query order does not matter
    dc = np.log([c.drift(t) for t in ts])
    np.testing.assert_array_equal(da, db)
    assert not np.array_equal(da, dc)
    steps = np.diff(da)
    assert steps.std() == pytest.approx(2e-4, rel=0.05)
    assert abs(steps.mean()) < 5 * 2e-4 / np.sqrt(steps.size)
    assert da[0] == 0.0


def test_dead_lamp_emits_nothing():
    lamp = Lamp(seed=0)
    lamp.switch(0.0, True)
    lamp.die(10.0)
    lamp.switch(20.0, True)
    assert lamp.power(30.0) == 0.0 and lamp.on
