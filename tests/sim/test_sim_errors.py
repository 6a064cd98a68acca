"""The virtual instrument's error model (gonio/sim/physics/errors.py): presets, overrides, physics of each term."""

import math
import sys
from pathlib import Path

import gonio.sim as gs
import numpy as np
import pytest
from gonio.sim.physics.errors import PRESETS, disk_rule, error_model, spectralon_factor

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "fitting"))
from _simdata import cone_directions  # noqa: E402  (the tests' Monte Carlo aperture reference)

GLOSSY = {"model": "roughconductor", "params": {"alpha": 0.1}}


def _frames(settings, seed=5):
    inst = gs.Instrument(settings, sample=GLOSSY, seed=seed)
    inst.home_all()
    out = []
    for yaw, lamp in ((20.0, 50.0), (35.0, 70.0)):
        a = inst.axes[inst.axis_names.index("yaw")]
        a.move_abs(inst.clock.now(), int(round(yaw * 2000)))
        inst.axes[inst.axis_names.index("lamp")].move_abs(inst.clock.now(), int(round(lamp * 2000)))
        inst.clock.advance(10.0)
        inst.lamp.switch(inst.clock.now(), True)
        out.append(inst.capture(0.004))
    return out


def test_ideal_is_the_error_free_instrument_bit_for_bit():
    """``[errors] preset = "ideal"`` (and per-term zeros) change no byte of a frame."""
    plain = _frames({})
    assert _frames({"errors": "ideal"}) == plain
    assert _frames({"errors": {"preset": "ideal", "stray": {"floor": 0.0}}}) == plain
    assert not error_model("ideal").active and error_model("typical").active


def test_typical_changes_frames_and_draws_are_seeded():
    a, b = gs.Instrument({"errors": "typical"}, seed=3), gs.Instrument({"errors": "typical"}, seed=3)
    assert a.error_state == b.error_state
    assert gs.Instrument({"errors": "typical"}, seed=4).error_state != a.error_state
    assert _frames({"errors": "typical"}) != _frames({})


def test_overrides_and_bad_input_name_the_key():
    m = error_model({"preset": "typical", "stray": {"floor": 0.0}, "stages": {"zero_deg": [0, 0, 0, 0.05]}})
    assert m.stray.floor == 0.0 and m.stages.zero_deg == (0.0, 0.0, 0.0, 0.05)
    assert m.aperture == PRESETS["typical"].aperture
    for bad, word in (({"preset": "awful"}, "preset"), ({"stray": {"flor": 1}}, "errors.stray.flor"),
                      ({"stray": {"floor": -1}}, "errors.stray.floor"), ({"lens": {}}, "lens"),
                      ({"stages": {"zero_deg": [0.1]}}, "errors.stages.zero_deg"),
                      ({"stray": {"floor": float("nan")}}, "errors.stray.floor")):
        with pytest.raises(ValueError, match=word.replace(".", r"\.")):
            error_model(bad)
    with pytest.raises(ValueError, match="errors"):
        gs.Instrument({"errors": {"preset": "awful"}})


def test_disk_rule_integrates_the_aperture():
    """Stroud's S2 5-1 rule: exact moments of the unit disk to degree 5 (E r^2 = 1/2, E r^4 = 1/3,
    E x^4 = 1/8, E x^2 y^2 = 1/24), and the simulator's 49-point source x detector average of a
    GGX lobe (alpha 0.1, 0.5 deg half-angles) equals a 400 000-sample Monte Carlo mean of the same
    integrand within 5 of its standard errors (false alarm 6e-7)."""
    p, w = disk_rule()
    r2 = (p ** 2).sum(1)
    assert np.allclose([w.sum(), w @ r2, w @ r2 ** 2, w @ p[:, 0] ** 4, w @ (p[:, 0] ** 2 * p[:, 1] ** 2)],
                       [1, 1 / 2, 1 / 3, 1 / 8, 1 / 24], rtol=0, atol=1e-14)
    inst = gs.Instrument({"errors": {"preset": "ideal", "aperture": {"source_half_deg": 0.5, "detector_half_deg": 0.5}}},
                         sample=GLOSSY)
    wi = np.array([math.sin(0.5), 0.0, math.cos(0.5)])
    wo = np.array([-math.sin(0.53), 0.0, math.cos(0.53)])
    rule, shown = inst.error_state.sample_radiance(inst.sample, wi, wo)
    assert np.allclose(shown, inst.sample.eval(wi, wo)[0] * wi[2])
    rng = np.random.default_rng(11)
    n, d = 400_000, math.radians(0.5)

    a, b = cone_directions(wi, d, n, rng), cone_directions(wo, d, n, rng)
    f = inst.sample.eval(a, b)[:, 1] * a[:, 2]
    assert abs(rule[1] - f.mean()) < 5 * f.std() / math.sqrt(n)
    assert abs(rule[1] / shown[1] - 1) > 10 * f.std() / math.sqrt(n) / shown[1]   # the aperture is visible


def test_stages_zero_offset_backlash_and_repeatability():
    """True angle = commanded + zero - backlash/2 * direction + repeatability draw (per real move)."""
    inst = gs.Instrument({"errors": {"preset": "ideal", "stages": {"zero_deg": [0.3, 0, 0, 0], "backlash_deg": 0.1}}},
                         seed=2)
    st = inst.error_state
    z = st.zero_deg[0]
    assert z != 0.0
    inst.home_all()
    yaw = inst.axes[inst.axis_names.index("yaw")]
    for target, direction in ((10.0, 1), (5.0, -1)):
        yaw.move_abs(inst.clock.now(), int(round(target * 2000)))
        inst.clock.advance(5.0)
        n = inst.geometry()["R"][:, 2]
        assert math.degrees(math.atan2(n[1], n[0])) == pytest.approx(target + z - 0.05 * direction, abs=1e-9)
    moves = yaw.moves
    yaw.move_abs(inst.clock.now(), int(round(5.0 * 2000)))      # to where it is: no move, no draw
    assert yaw.moves == moves


def test_reference_truth_and_stray_light_and_linearity():
    """The reference square shows rho_cert (1 + rel_std N) times Spectralon's factor; the stray
    floor adds floor/pi everywhere; the detector compresses DN by gamma at full scale."""
    s = {"errors": {"preset": "ideal", "reference": {"draw_certificate": True, "non_lambertian": 1.0},
                    "stray": {"floor": 1e-3}}, "reference": {"rel_std": 0.005}}
    inst = gs.Instrument(s, seed=8)
    st = inst.error_state
    assert st.rho_factor != 1.0 and abs(st.rho_factor - 1) < 0.03          # 6 sigma of 0.005
    wi = np.array([math.sin(1.2), 0.0, math.cos(1.2)])
    wo = np.array([0.0, math.sin(0.3), math.cos(0.3)])
    true, shown = st.reference_radiance(inst.reference, wi, wo)
    assert np.allclose(true / shown, st.rho_factor * spectralon_factor(1.2, 0.3))
    assert spectralon_factor(math.radians(70), 0.0) == pytest.approx(0.978, abs=1e-3)
    inst.home_all()
    inst.set_pose(yaw=20.0, lamp=50.0)
    ideal = gs.Instrument({}, seed=8)
    ideal.home_all()
    ideal.set_pose(yaw=20.0, lamp=50.0)
    diff = inst.radiance() - ideal.radiance()
    holder = np.isclose(diff, 1e-3 / math.pi, rtol=1e-6)
    assert holder.mean() > 0.5                       # every pixel off the reference square: exactly the floor
    lin = gs.Instrument({"errors": {"preset": "ideal", "linearity": {"gamma": 0.01}}}).error_state
    raw = np.array([[512, 512 + 8000, 16383]], dtype=np.uint16)
    out = lin.nonlinear(raw, 512, 16383).astype(float)
    assert out[0, 0] == 512 and out[0, 1] == pytest.approx(512 + 8000 * (1 - 0.01 * 8000 / 15871), abs=0.5)


def test_aperture_mean_across_a_transmission_cutoff():
    """Where f_r jumps to 0 inside the cones the simulator's truth is still the mean over the two
    uniform disks (Nicodemus et al. 1977's instrument function). The frosted glass (GGX 0.3,
    eta 1.5) at theta_i 39.6 / theta_o 120.4 / phi_o 180 (seed 5's true directions in the
    transmission study): the half-vector -(wi + eta wo) lies 0.6 deg below the surface, where
    Walter et al. 2007's BTDF is 0, and within the 0.5 deg cones it crosses to above, where it is
    about 0.19 sr^-1 (GGX's D stays alpha^2 / pi at theta_h = 90 deg: a jump, not a slope).
    Stroud's degree-5 rule, exact for smooth integrands, put 4 of its 49 pairs (1/64 each) past
    the jump: 2.1x the mean. The truth must equal a 400 000-sample Monte Carlo mean within 5 of
    its standard errors."""
    spec = {"model": "roughdielectric", "options": {"distribution": "ggx"}, "params": {"alpha": 0.3, "int_ior": 1.5}}
    inst = gs.Instrument({"errors": {"preset": "ideal", "aperture": {"source_half_deg": 0.5, "detector_half_deg": 0.5}}},
                         sample=spec)
    ti, to = math.radians(39.613), math.radians(120.396)
    wi = np.array([math.sin(ti), 0.0, math.cos(ti)])
    wo = np.array([-math.sin(to), 0.0, math.cos(to)])
    rule, shown = inst.error_state.sample_radiance(inst.sample, wi, wo)
    assert shown[0] == 0.0 and inst.sample.eval(wi, wo)[0, 0] == 0.0          # the point itself: past the cutoff
    rng = np.random.default_rng(12)
    n, d = 400_000, math.radians(0.5)

    a, b = cone_directions(wi, d, n, rng), cone_directions(wo, d, n, rng)
    f = inst.sample.eval(a, b)[:, 0] * a[:, 2]
    se = f.std() / math.sqrt(n)
    assert f.mean() > 20 * se                                   # the cones do reach the lobe
    assert abs(rule[0] - f.mean()) < 5 * se


def test_a_drawn_nonlinearity_is_uniform_below_its_bound_and_moves_no_other_draw():
    """``[errors.linearity] drawn = true``: each instrument's gamma is drawn uniformly in [0, bound]
    (the budget's rectangular [0, bound]), after every other draw, so a seed's zero offsets, tilt,
    wedge and certificate stay those of the bound; without it every instrument sits at the bound
    and the tables written before the option (no ``drawn`` key) compare equal. 400 seeds: the
    mean within 4 standard errors of bound / 2 (false alarm 6e-5), all within [0, bound], and a
    Kolmogorov-Smirnov test against U(0, bound) at p > 1e-4."""
    from scipy import stats

    bound = 0.01
    fixed = error_model({"preset": "poor"})
    drawn = error_model({"preset": "poor", "linearity": {"drawn": True}})
    g = np.array([drawn.draw(s, 0.005).linearity_gamma for s in range(400)])
    assert np.all((g >= 0.0) & (g <= bound))
    assert abs(g.mean() - bound / 2) < 4 * bound / math.sqrt(12 * 400)
    assert stats.kstest(g / bound, "uniform").pvalue > 1e-4
    for s in (0, 7, 500400):
        a, b = fixed.draw(s, 0.005), drawn.draw(s, 0.005)
        assert (a.zero_deg, a.tilt_deg, a.wedge_deg, a.rho_factor) == (b.zero_deg, b.tilt_deg, b.wedge_deg, b.rho_factor)
        assert a.linearity_gamma == bound
    assert "drawn" not in fixed.to_dict()["linearity"] and drawn.to_dict()["linearity"]["drawn"] is True
    raw = np.array([[512, 512 + 8000]], dtype=np.uint16)
    low = next(st for st in (drawn.draw(s, 0.005) for s in range(50)) if st.linearity_gamma < 0.5 * bound)
    assert low.nonlinear(raw, 512, 16383)[0, 1] > fixed.draw(0, 0.005).nonlinear(raw, 512, 16383)[0, 1]
    with pytest.raises(ValueError, match="true or false"):
        error_model({"preset": "poor", "linearity": {"drawn": 1}})
