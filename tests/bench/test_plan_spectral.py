"""Spectral plans (issue 39): the ``spectral`` preset is the quick geometry times 400-700 nm,
ordered with wavelength as the fastest or the slowest axis by the plan's own time estimate
(stages: `ordering.path_time`; monochromator: the Cornerstone twin's timing, GRAT 6 s)."""

from __future__ import annotations

import numpy as np
import pytest

from gonio.bench.plan import kinematics
from gonio.bench.plan.plans import dry_run, load_plan, plan_from_dict
from gonio.bench.plan.spectral import (MonochromatorTimes, SpectralOrder, check_wavelengths, order_plan,
                                       spectral_order)
from gonio.bench.settings import default_settings
from gonio.core.errors import GonioError, PlanError


def test_the_preset_is_the_quick_geometry_at_every_wavelength():
    quick, plan = load_plan("quick"), load_plan("spectral")
    wl = np.arange(400.0, 701.0, 50.0)
    assert len(plan) == len(quick) * len(wl) == 30 * 7
    np.testing.assert_array_equal(np.unique(plan.wavelength_nm), wl)
    np.testing.assert_array_equal(np.unique(plan.angles, axis=0), np.unique(quick.angles, axis=0))
    again = plan_from_dict(plan.to_dict())            # session.toml's copy reads back the same
    np.testing.assert_array_equal(again.wavelength_nm, plan.wavelength_nm)
    np.testing.assert_array_equal(again.partner, plan.partner)
    twenty = load_plan("spectral:20")
    assert len(np.unique(twenty.wavelength_nm)) == 16 and twenty.source == "preset:spectral:20"
    # a reciprocal partner is at the same wavelength
    k = int(np.flatnonzero(plan.partner >= 0)[0])
    assert plan.wavelength_nm[plan.partner[k]] == plan.wavelength_nm[k]


@pytest.mark.parametrize("spec, says", [("spectral:0", "must be positive"), ("spectral:nan", "not a finite number"),
                                        ("spectral:x", "not a number"), ("spectral:-10", "must be positive"),
                                        ("spectral:0.001", "more than 201")])
def test_a_bad_step_is_one_line(spec, says):
    with pytest.raises(PlanError, match=says) as info:
        load_plan(spec)
    assert "\n" not in str(info.value)


def test_the_order_takes_the_cheaper_wavelength_axis():
    st = default_settings()
    for spec, axis in (("spectral", "fastest"), ("spectral:20", "fastest"), ("spectral:100", "slowest")):
        plan = load_plan(spec)
        stage = kinematics.inverse(*plan.angles.T)
        order, why = spectral_order(plan.angles, plan.wavelength_nm, stage, st)
        assert sorted(order.order) == list(range(len(plan)))
        assert why.axis == axis, why.line()
        f, s = why.fastest, why.slowest
        assert f[2] == 30 and s[2] == 1       # a 400-700 nm sweep crosses 650 nm once per geometry / once in all
        n = len(np.unique(plan.wavelength_nm))
        assert s[0] == pytest.approx(n * f[0], rel=0.1)   # one stage tour per wavelength
        chosen = f if axis == "fastest" else s
        assert order.ordered_s == pytest.approx(chosen[0])
        assert min(f[0] + f[1], s[0] + s[1]) == pytest.approx(chosen[0] + chosen[1])
        assert SpectralOrder.from_dict(why.to_dict()) == why     # as session.toml's [order] records it
        assert all(type(v) in (str, float, int) for v in why.to_dict().values())   # no numpy scalar in the TOML
    # the dry run says both and counts the monochromator's time in its estimate
    d = dry_run(load_plan("spectral"), st)
    assert "wavelength the fastest axis" in d.summary() and d.monochromator_s > 200
    assert "1 grating change)" in d.summary() and SpectralOrder.from_dict({"wavelength_axis": "x"}) is None


def test_monochromator_times_follow_the_twin():
    t = MonochromatorTimes({"monochromator": {}})
    # 600 -> 700 nm: grating 1 -> 2 (6 s), same filter, 0.05 s + 100 nm / (175 * 1200 / 600 nm/s)
    assert t.run([600.0, 700.0]) == (pytest.approx(6.0 + 0.05 + 100 / 350), 1)


def test_a_spectral_plan_needs_a_monochromator_that_reaches_its_wavelengths():
    plan = load_plan("spectral")
    stage = kinematics.inverse(*plan.angles.T)
    with pytest.raises(GonioError, match="needs a monochromator"):
        order_plan(plan, stage, default_settings())
    far = plan_from_dict({"name": "ir", "points": [[30, 0, 30, 180]],
                          "spectral": {"from_nm": 1300, "to_nm": 1500, "step_nm": 100}})
    with pytest.raises(GonioError, match="1500 nm is outside the monochromator's ranges") as info:
        check_wavelengths(far.wavelength_nm, {**default_settings(), "monochromator": {}})
    assert "\n" not in str(info.value)
    order, extra = order_plan(load_plan("quick"), kinematics.inverse(*load_plan("quick").angles.T), default_settings())
    assert extra == {}                        # a plan without wavelengths orders as before
