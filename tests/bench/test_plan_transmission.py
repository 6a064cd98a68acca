"""Transmission plans: the rear detector stop's inverse kinematics, its reachability and the
``transmission`` and ``both-sides`` presets."""

import math

import numpy as np
import pytest

from gonio.bench.plan import kinematics as k
from gonio.bench.plan.plans import check_plan, load_plan
from gonio.bench.settings import load_settings
from gonio.core.sides import Side
from gonio.sim.physics.kinematics import forward as sim_forward


def test_rear_inverse_round_trip_against_the_simulator():
    rng = np.random.default_rng(37)
    ti, pi_ = rng.uniform(0, 85, 100), rng.uniform(-180, 180, 100)
    to, po = rng.uniform(95, 180, 100), rng.uniform(-180, 180, 100)
    stage = k.inverse(ti, pi_, to, po)
    assert np.isfinite(stage).all()
    wi, wo = k.forward(stage, rear=k.detector_of(to))
    np.testing.assert_allclose(wi, k.directions(ti, pi_), atol=1e-12)
    np.testing.assert_allclose(wo, k.directions(to, po), atol=1e-12)
    for s, w_i, w_o in zip(stage[:10], wi, wo):           # the simulator's own forward model, rear stop
        g = sim_forward(*np.radians(s), detector="rear")
        np.testing.assert_allclose(g["wi"], w_i, atol=1e-12)
        np.testing.assert_allclose(g["wo"], w_o, atol=1e-12)


def test_straight_through_has_a_pose():
    # wo = -wi: the lamp on the front axis (L = 0), a family of poses; the closed form picks tilt 0
    # (40, 0, 140, 180) leaves sin L = 1e-8 from rounding, not 0: the closed form is 0 / 0 there
    stage = k.inverse([0.0, 30.0, 40.0], [0.0, 40.0, 0.0], [180.0, 150.0, 140.0], [0.0, -140.0, 180.0])
    assert np.isfinite(stage).all() and np.all(stage[:, 3] == 0.0)
    wi, wo = k.forward(stage, rear=True)
    np.testing.assert_allclose(wo, -wi, atol=1e-12)
    np.testing.assert_allclose(wi[1:], k.directions([30.0, 40.0], [40.0, 0.0]), atol=1e-12)


def test_rear_reachability():
    s = load_settings()
    r = k.reachable([88, 60, 40, 30], [0, 0, 0, 0], [93, 120, 179.0, 90.0], [0, 0, 0, 0], s,
                    sides=(Side.REFLECT, Side.TRANSMIT))
    assert r.ok.tolist() == [False, True, True, False]
    # wo' = -wo at 87 deg opposite wi at 88 deg: the lamp 180 - 5 deg from the front, 5 deg from the rear camera
    assert "lamp in front of the camera (L = 5.0 deg" in r.reason[0]
    assert "grazing" in r.reason[3]
    # a reflection-only instrument check keeps theta_o below 90
    assert not k.reachable(60, 0, 120, 0, s).ok[0]
    # the rear camera sees the holder mirrored: its regions are the front stop's, columns reversed
    st = k.inverse(30.0, 0.0, 150.0, 180.0)
    front, rear = k.roi_masks(st, s), k.roi_masks(st, s, rear=True)
    assert front[0].sum() > 100
    np.testing.assert_array_equal(rear[0], front[0][:, ::-1])


@pytest.mark.parametrize("name, sides", [("transmission", (Side.TRANSMIT,)),
                                         ("both-sides", (Side.REFLECT, Side.TRANSMIT))])
def test_presets_reachable(name, sides):
    plan = load_plan(name)
    assert plan.sides == sides
    through = plan.angles[:, 2] > 90
    assert through.sum() >= 40 and (through.all() if len(sides) == 1 else (~through).sum() >= 30)
    assert check_plan(plan, load_settings()) == []
    # fine near the forward direction: steps of at most 2 deg within 20 deg of straight through
    fwd = np.sort(plan.angles[through & (plan.angles[:, 0] == 20) & (np.abs(plan.angles[:, 3]) == 180), 2])
    near = fwd[fwd >= 160]
    assert len(near) >= 8 and np.diff(near).max() <= 2.0 + 1e-9
