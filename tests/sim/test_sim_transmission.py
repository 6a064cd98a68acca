"""The simulator's transmissive samples: the rear detector, the open holder, the slab's second
surface and the open-beam frame (ASTM E2387)."""

import math

import numpy as np
import pytest

from gonio.sim.physics.kinematics import forward
from gonio.sim.physics.sample import SampleTruth, slab_exit
from gonio.sim.physics.scene import HolderScene

FROSTED = {"model": "roughdielectric", "options": {"distribution": "ggx"},
           "params": {"alpha": 0.3, "int_ior": 1.5, "ext_ior": 1.0}}


def test_rear_detector_sees_the_far_side():
    a = [math.radians(v) for v in (20.0, -10.0, 35.0, 50.0)]
    front, rear = forward(*a), forward(*a, detector="rear")
    np.testing.assert_allclose(rear["wo"], -front["wo"], atol=1e-15)
    np.testing.assert_allclose(rear["right"], -front["right"], atol=1e-15)
    np.testing.assert_allclose(np.cross(rear["right"], rear["up"]), rear["wo"], atol=1e-12)  # camera looks along -wo
    with pytest.raises(ValueError, match="front' or 'rear"):
        forward(*a, detector="side")


def test_slab_exit_normal_and_tir():
    # normal exit through a polished face of n = 1.5: F = ((1.5 - 1) / 2.5)^2 = 0.04, radiance / eta^2
    wg, fac = slab_exit(np.array([[0.0, 0.0, -1.0]]), 1.5)
    assert fac[0] == pytest.approx(0.96 / 2.25, rel=1e-12)
    np.testing.assert_allclose(wg[0], [0.0, 0.0, -1.0])
    # Snell across the back face, and Beer's law over the slant path d / cos(theta_g)
    wo = np.array([[math.sin(0.6), 0.0, -math.cos(0.6)]])
    wg, fac = slab_exit(wo, 1.5, thickness_mm=2.0, absorption_per_mm=0.1)
    assert math.hypot(wg[0, 0], wg[0, 1]) * 1.5 == pytest.approx(math.sin(0.6), rel=1e-12)
    _, clear = slab_exit(wo, 1.5, thickness_mm=2.0)
    assert fac[0] / clear[0] == pytest.approx(math.exp(-0.2 / -wg[0, 2]), rel=1e-12)
    # light inside the less dense side (eta < 1) beyond the critical angle does not get out
    _, fac = slab_exit(np.array([[math.sin(1.2), 0.0, -math.cos(1.2)]]), 1 / 1.5)
    assert fac[0] == 0.0


def test_slab_transmits_two_fresnel_losses():
    # a nearly smooth slab at normal incidence transmits (1 - R)^2 = 0.9216 (R = 0.04 at n = 1.5;
    # no multiple reflections, which add R^2 (1 - R)^2 / (1 - R^2) ~ 0.15 %: Born & Wolf sec. 1.6)
    slab = SampleTruth({**FROSTED, "params": {"alpha": 0.02, "int_ior": 1.5}, "slab": {"thickness_mm": 3.0}})
    x, w = np.polynomial.legendre.leggauss(200)
    th = 0.5 * 0.25 * (x + 1.0)                            # theta' from the -z axis, to 0.25 rad
    wt = 0.5 * 0.25 * w
    n_phi = 32
    phi = (np.arange(n_phi) + 0.5) * 2 * np.pi / n_phi
    T_, P_ = np.meshgrid(th, phi, indexing="ij")
    wo = np.stack([np.sin(T_) * np.cos(P_), np.sin(T_) * np.sin(P_), -np.cos(T_)], -1).reshape(-1, 3)
    wi = np.broadcast_to([0.0, 0.0, 1.0], wo.shape)
    f = slab.eval(wi, wo)[:, 1].reshape(T_.shape)
    T = np.sum(f * np.cos(T_) * np.sin(T_) * wt[:, None]) * 2 * np.pi / n_phi
    assert T == pytest.approx(0.96 ** 2, rel=5e-3)
    # the single interface alone sends 0.96 into the glass, its radiance eta^2 higher
    front = SampleTruth({**FROSTED, "params": {"alpha": 0.02, "int_ior": 1.5}})
    down = np.array([[0.0, 0.0, -1.0]])
    assert slab.eval(wi[:1], down)[0, 0] == pytest.approx(front.eval(wi[:1], down)[0, 0] * 0.96 / 2.25, rel=1e-12)


def test_sample_spec_bad_input():
    with pytest.raises(ValueError, match="back must be 'smooth'"):
        SampleTruth({**FROSTED, "slab": {"back": "rough"}})
    with pytest.raises(ValueError, match="thickness_mm"):
        SampleTruth({**FROSTED, "slab": {"thickness_mm": float("nan")}})
    with pytest.raises(ValueError, match="ext_ior"):
        SampleTruth({**FROSTED, "params": {"alpha": 0.3, "int_ior": 1.5, "ext_ior": 0.0}})
    with pytest.raises(ValueError, match="does not transmit"):
        SampleTruth({"model": "diffuse", "params": {}, "slab": {}})
    # ext_ior: eta = int / ext
    a = SampleTruth({**FROSTED, "params": {"alpha": 0.3, "int_ior": 1.65, "ext_ior": 1.1}})
    b = SampleTruth({**FROSTED, "params": {"alpha": 0.3, "int_ior": 1.5}})
    wi, wo = np.array([[0.3, 0.1, 0.9486833]]), np.array([[-0.2, 0.3, -0.9327379]])
    np.testing.assert_allclose(a.eval(wi, wo), b.eval(wi, wo), rtol=1e-12)
    assert a.transmits and not SampleTruth({"model": "diffuse", "params": {}}).transmits


@pytest.fixture(scope="module")
def scene():
    truth = SampleTruth(FROSTED)
    return truth, HolderScene(truth.mitsuba, {"type": "diffuse"}, width=64, height=48, pixel_size=0.02,
                              sample_half=0.25, offset=0.3, holder_reflectance=0.05, sample_truth=truth)


def test_open_holder_from_behind(scene):
    truth, sc = scene
    g = forward(*(math.radians(v) for v in (10.0, -15.0, 17.0, 40.0)), detector="rear")
    assert g["wo"][2] < 0 < g["wi"][2]
    img = sc.render(g["wi"], g["wo"], g["right"], g["up"])
    want = truth.eval(g["wi"][None], g["wo"][None])[0] * g["wi"][2]
    inner = img[..., 1] > 0.999 * want[1]
    assert inner.sum() > 400                           # the sample square, about 25 x 25 pixels
    np.testing.assert_allclose(img[inner], np.broadcast_to(want, img[inner].shape), rtol=1e-6)
    assert img.max() <= want.max() * (1 + 1e-6)       # no holder, no reference: nothing else shows
    # the reflective holder from the front still renders the sample's reflection (the twin)
    gf = forward(*(math.radians(v) for v in (10.0, -15.0, 17.0, 40.0)))
    assert sc.render(gf["wi"], gf["wo"], gf["right"], gf["up"]).max() > 0


def test_open_beam_frame(scene):
    _, sc = scene
    g = forward(0.0, 0.0, 0.0, 0.0, detector="rear")    # lamp straight behind the aperture
    np.testing.assert_allclose(g["wi"], [0, 0, 1], atol=1e-15)
    img = sc.open_beam(250.0, g["wo"], g["up"])
    assert img.max() == pytest.approx(250.0, rel=1e-6)
    # the aperture's area: (2 * 0.25 / 0.02)^2 = 625 pixels
    assert img[..., 0].sum() / 250.0 == pytest.approx(625.0, rel=1e-3)
