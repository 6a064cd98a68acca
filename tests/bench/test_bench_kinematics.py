"""Kinematics of the 4-axis instrument: forward, closed-form inverse, reachability, regions."""

import numpy as np
import pytest

from gonio.bench.plan import kinematics as k
from gonio.bench.plan.ordering import mirror
from gonio.bench.settings import default_settings

S = default_settings()


def random_directions(rng, n):
    ti = np.degrees(np.arccos(rng.uniform(0.02, 1.0, n)))
    to = np.degrees(np.arccos(rng.uniform(0.02, 1.0, n)))
    return ti, rng.uniform(-180, 180, n), to, rng.uniform(-180, 180, n)


def test_zero_pose_faces_the_camera():
    wi, wo = k.forward([0, 0, 0, 30])
    np.testing.assert_allclose(wo, [0, 0, 1], atol=1e-15)                  # camera along the normal
    np.testing.assert_allclose(wi, [np.sin(np.radians(30)), 0, np.cos(np.radians(30))], atol=1e-15)
    R = k.rotation([0, 0, 0, 0])
    np.testing.assert_allclose(R, k.B)                                     # local z -> lab X etc.


def test_angle_between_wi_and_wo_is_the_lamp_angle():
    rng = np.random.default_rng(0)
    st = np.column_stack([rng.uniform(-90, 90, 500), rng.uniform(-88, 88, 500),
                          rng.uniform(-180, 180, 500), rng.uniform(-175, 175, 500)])
    wi, wo = k.forward(st)
    np.testing.assert_allclose(np.sum(wi * wo, -1), np.cos(np.radians(st[:, 3])), atol=1e-12)


def test_round_trip_angles_stage_angles():
    """directions -> stage -> directions, to 1e-9 (unit vectors), over random configurations."""
    rng = np.random.default_rng(1)
    ti, pi_, to, po = random_directions(rng, 20000)
    st = k.inverse(ti, pi_, to, po)
    wi, wo = k.forward(st)
    assert np.isfinite(st).all()
    assert np.max(np.abs(wi - k.directions(ti, pi_))) < 1e-9
    assert np.max(np.abs(wo - k.directions(to, po))) < 1e-9
    assert np.all(st[:, 3] > 0) and np.all(np.abs(st[:, 0]) < 90)


def test_round_trip_stage_angles_stage():
    """stage -> directions -> stage, to 1e-9 deg, for reachable poses with the lamp on the +Y side."""
    rng = np.random.default_rng(2)
    n = 20000
    st = np.column_stack([rng.uniform(-89, 89, n), rng.uniform(-88, 88, n), rng.uniform(-179.9, 179.9, n),
                          rng.uniform(6, 175, n)])
    a = k.forward_angles(st)
    keep = (a[:, 0] < 89.9) & (a[:, 2] < 89.9) & (a[:, 0] > 0.1) & (a[:, 2] > 0.1)
    back = k.inverse(*a[keep].T)
    d = back - st[keep]
    d[:, 2] = (d[:, 2] + 180) % 360 - 180
    assert keep.sum() > 5000 and np.max(np.abs(d)) < 1e-9


def test_mirror_solution_sees_the_same_directions():
    rng = np.random.default_rng(3)
    st = k.inverse(*random_directions(rng, 200))
    wi, wo = k.forward(st)
    wi2, wo2 = k.forward(mirror(st))
    np.testing.assert_allclose(wi2, wi, atol=1e-12)
    np.testing.assert_allclose(wo2, wo, atol=1e-12)


def test_agrees_with_the_simulator():
    sim = pytest.importorskip("gonio.sim")
    rng = np.random.default_rng(4)
    for st in k.inverse(*random_directions(rng, 20)):
        g = sim.forward(*np.radians(st))
        wi, wo = k.forward(st)
        np.testing.assert_allclose(g["wi"], wi, atol=1e-12)
        np.testing.assert_allclose(g["wo"], wo, atol=1e-12)


def test_reachable_reasons():
    r = k.reachable([30, 30, 30, 30, 89, 89, np.nan], [0] * 7, [40, 30, 33, 95, 89, 89, 10],
                    [180, 0, 0, 180, 90, 180, 0], S)
    assert list(r.ok) == [True] + [False] * 6
    assert "lamp in front of the camera (L = 0.0" in r.reason[1] and "(L = 3.0 deg" in r.reason[2]
    assert "horizon" in r.reason[3]
    assert r.reason[4].startswith("tilt = 88.6 deg outside its limits")
    assert r.reason[5].startswith("lamp = 178.0 deg outside")
    assert "finite" in r.reason[6]


def test_regions_of_interest_inside_their_squares():
    hold = S["holder"]
    for angles in [(0.1, 0, 30, 180), (60, 0, 60, 180), (30, 0, 75, 90), (70, 0, 70, 45)]:
        st = k.inverse(*angles)
        sm, rm = k.roi_masks(st, S)
        assert sm.sum() > 20 and rm.sum() > 20 and not (sm & rm).any()
        for mask, cx in ((sm, -hold["offset"]), (rm, hold["offset"])):
            i, j = np.nonzero(mask)
            xy = k.image_to_local(st, 2 * i + 0.5, 2 * j + 0.5, S)            # super-pixel centres
            assert np.all(np.abs(xy[:, 0] - cx) < hold["sample_half"])
            assert np.all(np.abs(xy[:, 1]) < hold["sample_half"])


def test_image_centre_sees_the_sample_centre():
    cam = S["camera"]
    st = k.inverse(40, 0, 50, 120)
    xy = k.image_to_local(st, (cam["height"] - 1) / 2, (cam["width"] - 1) / 2, S)
    np.testing.assert_allclose(xy, [0, 0], atol=1e-12)
