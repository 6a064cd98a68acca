"""Transmission through the simulated instrument: the open-beam normalisation (ASTM E2387) and
held-out style recovery of a frosted glass and an anti-glare film from rear-stop captures.

The instrument has frame noise, dark and fixed-pattern noise, lamp warm-up and drift and
monitor noise; its attenuator and beam solid angle are exact ([transmission] rel_std = 0), so
the stated uncertainty is the fit's statistical one and the open-beam frame's own error
(a type-B line per channel, shared by every point) combined by the budget (u_c). Expected
coverage: |z| = |estimate - truth| / u_c <= 2 at 95 % per parameter; the fast test (seed 3)
asks |z| < 3, the long one seeds 0..9 for both samples: at least 34 of the 40 draws within 2
(fewer has probability 1.4 % at 95 %), none beyond 4."""

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
from gonio.fitting.uncertainty.budget import budget_from_attrs, propagate

FROSTED = ("ggx", {"alpha": 0.3, "int_ior": 1.5})          # frosted glass
ANTI_GLARE = ("beckmann", {"alpha": 0.06, "int_ior": 1.5})  # anti-glare film


def test_open_beam_equation():
    # f_t = (S_t / S_open) a / (Omega cos theta_i): S_t / S_open = 0.5, a / Omega = 2 sr^-1, theta_i = 60 -> 2.0
    ob = OpenBeam(np.full(3, 100.0), np.zeros(3), 1e-3, 5e-4, 0.01)
    f, u = btdf(np.full((1, 3), 50.0), np.full((1, 3), 0.5), ob, [60.0])
    np.testing.assert_allclose(f, 2.0, rtol=1e-12)
    np.testing.assert_allclose(u, 2.0 * 0.01, rtol=1e-12)      # the point's own 1 %: the open beam's is shared
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
                         seed=seed, settings={"transmission": {"rel_std": 0.0}})
    try:
        d = capture_rear(inst, plan, inst.settings)
    finally:
        inst.release()
    meas = Measurements(d["wi"], d["wo"], d["brdf"], d["brdf_std"], d["use"], attrs=d["open_beam"].to_attrs())
    res = fit(meas, gm.get("roughdielectric", distribution=kind), rng=np.random.default_rng(seed))
    budget = budget_from_attrs(meas)
    assert [c.name for c in budget.components] == ["statistical", "open_beam_frame"]
    unc = propagate(res, meas, budget, res.std, res.cov)["parameters"]
    return {k: (res.params[k] - truth[k]) / unc[k]["u_combined"] for k in res.space.names}, res


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
    assert np.all(np.isfinite(zs)) and np.sum(zs <= 2.0) >= 34 and zs.max() < 4.0, zs
