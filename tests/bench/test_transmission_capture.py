"""Transmission through the simulated instrument: the open-beam normalisation (ASTM E2387) and
held-out style recovery of a frosted glass and an anti-glare film from rear-stop captures.

Expected coverage: the fit's 1-sigma (its covariance) holds the truth within 3 sigma at
99.7 % per parameter on an instrument with frame noise, dark and fixed-pattern noise, lamp
drift and monitor noise; the fast test uses seed 3, the long one seeds 0..9 (|z| <= 2 for at
least 16 of 20 parameter draws: 95 % expected, fewer than 16 has probability 0.3 %)."""

import math

import numpy as np
import pytest

import gonio.models as gm
import gonio.sim as gs
from gonio.bench.measure.transmission import OpenBeam, btdf, capture_rear, open_beam_rate, transmission_settings
from gonio.bench.plan.plans import Plan, load_plan
from gonio.core.errors import GonioError
from gonio.core.sides import Side
from gonio.fitting.measurements import Measurements
from gonio.fitting.optimise.mle import fit

FROSTED = ("ggx", {"alpha": 0.3, "int_ior": 1.5})          # frosted glass
ANTI_GLARE = ("beckmann", {"alpha": 0.06, "int_ior": 1.5})  # anti-glare film


def test_open_beam_equation():
    # f_t = (S_t / S_open) a / (Omega cos theta_i): S_t / S_open = 0.5, a / Omega = 2 sr^-1, theta_i = 60 -> 2.0
    ob = OpenBeam(np.full(3, 100.0), np.zeros(3), 1e-3, 5e-4, 0.01)
    f, u = btdf(np.full((1, 3), 50.0), np.full((1, 3), 0.5), ob, [60.0])
    np.testing.assert_allclose(f, 2.0, rtol=1e-12)
    np.testing.assert_allclose(u, 2.0 * 0.01, rtol=1e-12)
    attrs = ob.to_attrs()
    assert attrs["beam_solid_angle_sr"] == 5e-4 and attrs["open_beam_rate"] == [100.0] * 3
    x = np.random.default_rng(0).normal(1000.0, 10.0, (400, 3))
    ob = open_beam_rate(x, 0.01, 2e-3, {}, 1e-4)
    np.testing.assert_allclose(ob.rate, x.mean(0) / (0.01 * 2e-3))


def test_open_beam_bad_input():
    x = np.ones((10, 3))
    with pytest.raises(GonioError, match="lamp on"):
        open_beam_rate(x, 0.01, 0.0, {})
    with pytest.raises(GonioError, match="no signal"):
        open_beam_rate(np.zeros((10, 3)), 0.01, 1e-3, {})
    with pytest.raises(GonioError, match="open_beam_attenuation"):
        transmission_settings({"transmission": {"open_beam_attenuation": 2.0}})
    with pytest.raises(GonioError, match="beam_solid_angle_sr"):
        transmission_settings({"transmission": {"beam_solid_angle_sr": float("nan")}})
    with pytest.raises(GonioError, match="no transmitted point"):
        capture_rear(None, load_plan("quick"), {})


def _plan(stride):
    p = load_plan("transmission")
    return Plan("transmission-sub", p.angles[::stride], sides=(Side.TRANSMIT,))


def _recover(kind, truth, seed, plan):
    inst = gs.Instrument(sample={"model": "roughdielectric", "options": {"distribution": kind}, "params": truth},
                         seed=seed)
    try:
        d = capture_rear(inst, plan, inst.settings)
    finally:
        inst.release()
    meas = Measurements(d["wi"], d["wo"], d["brdf"], d["brdf_std"], d["use"], attrs=d["open_beam"].to_attrs())
    res = fit(meas, gm.get("roughdielectric", distribution=kind), rng=np.random.default_rng(seed))
    return {k: (res.params[k] - truth[k]) / s for k, s in zip(res.space.names, res.std)}, res


@pytest.mark.parametrize("kind, truth", [FROSTED, ANTI_GLARE], ids=["frosted-ggx", "anti-glare-beckmann"])
def test_recovery_fast(kind, truth):
    z, res = _recover(kind, truth, 3, _plan(2))
    assert set(z) == {"alpha", "int_ior"}
    assert all(abs(v) < 3.0 for v in z.values()), (res.params, res.std, z)
    assert res.std[0] < 0.01 * truth["alpha"]


@pytest.mark.long
def test_recovery_many_seeds():
    zs = []
    for kind, truth in (FROSTED, ANTI_GLARE):
        for seed in range(10):
            z, _ = _recover(kind, truth, seed, load_plan("transmission"))
            zs += list(z.values())
    zs = np.abs(np.array(zs))
    assert np.all(np.isfinite(zs)) and np.sum(zs <= 2.0) >= 16, zs
