"""The adaptive plan's ``angle_noise``: its design counts the stage angles' errors times f_r's
slope in each candidate's sigma, as the dataset's budget lines do (gonio.bench.dataset.budget),
so a steep point on a lobe's flank is not taken for a precise one. Checked against a direct
propagation (each input's angle shift applied to the directions, f_r evaluated), and the run
hands the plan the session's modes."""

from __future__ import annotations

import numpy as np
import pytest

import gonio.models as gm
from gonio.bench.calibrate import with_errors_and_calibration
from gonio.bench.measure.calpoint import angle_modes
from gonio.bench.plan import kinematics, plans
from gonio.bench.plan.adaptive import AdaptivePlan
from gonio.bench.settings import default_settings
from gonio.core.geometry import directions_deg
from strategy_run import TRUTH

STANDARD = plans.load_plan("standard")


def _settings():
    return with_errors_and_calibration(default_settings(), sim=True, seed=0, errors="typical", calibration=None)


def _plan(angle_noise=True):
    strat = AdaptivePlan(STANDARD, range(len(STANDARD)), {"points": 20, "seed": 0, "angle_noise": angle_noise})
    poses = np.nan_to_num(kinematics.inverse(*STANDARD.angles.T))
    strat.use_angle_modes(angle_modes(_settings(), poses))
    return strat


def test_the_design_sigma_is_the_angle_errors_propagated_through_f_r():
    strat = _plan()
    modes = strat._angle_modes
    assert modes.ndim == 3 and modes.shape[:2] == (len(STANDARD), 4) and np.abs(modes).max() > 0.01
    x = strat.space.from_params(strat.model.validate(TRUTH))
    var = strat._angle_var(x)
    # directly: move every point's four angles by +-1 sigma of each input, half the difference of f_r
    m = gm.get("roughplastic", distribution="ggx")
    a = STANDARD.angles
    direct = np.zeros_like(var)
    for k in range(modes.shape[2]):
        f = [m.eval(directions_deg(b[:, 0], b[:, 1]), directions_deg(b[:, 2], b[:, 3]), TRUTH)
             for b in (a + modes[:, :, k], a - modes[:, :, k])]
        direct += (0.5 * (f[0] - f[1])) ** 2
    big = direct > 1e-3 * direct.max()
    assert big.sum() >= 20
    assert np.allclose(var[big], direct[big], rtol=0.02)
    # on the lobe's flank the angles' error is above the 1 % noise; at most points, below it
    f0 = m.eval(directions_deg(a[:, 0], a[:, 1]), directions_deg(a[:, 2], a[:, 3]), TRUTH)
    rel = np.sqrt(var) / f0
    assert rel.max() > 0.02 and np.median(rel) < 0.01      # 4 % at the steepest (alpha 0.15), twice the noise


def test_without_angle_noise_the_modes_are_not_used_and_bad_ones_are_refused():
    strat = _plan(angle_noise=False)
    x = strat.space.from_params(strat.model.validate(TRUTH))
    assert strat._angle_modes is None and strat._angle_var(x) == 0.0
    with pytest.raises(ValueError, match="angle modes"):
        strat.use_angle_modes(np.zeros((3, 4, 2)))
    with pytest.raises(ValueError, match="angle modes"):
        strat.use_angle_modes(np.full((len(STANDARD), 4, 2), np.nan))
    with pytest.raises(ValueError, match="angle_noise"):
        AdaptivePlan(STANDARD, range(len(STANDARD)), {"points": 20, "angle_noise": "yes"})


def test_a_capture_hands_the_plan_the_sessions_angle_modes(tmp_path, monkeypatch):
    sim = pytest.importorskip("gonio.sim")
    from gonio.bench.plan import strategy as st
    from gonio.bench.session.capture import capture

    made = []
    monkeypatch.setitem(st.STRATEGIES, "adaptive", lambda p, o, t: made.append(AdaptivePlan(p, o, t)) or made[-1])
    s = _settings()
    plan = plans.load_plan("quick")
    truth = {k: np.asarray(v).tolist() for k, v in TRUTH.items()}
    inst = sim.Instrument(s, sample={"model": "roughplastic", "options": {"distribution": "ggx"}, "params": truth},
                          seed=0).register("plan-angle-noise")
    try:
        capture(tmp_path / "s", plan, s, inst.url("zaber"), inst.url("meter"), inst.url("camera"), seed=0,
                progress=False, sleep=inst.clock.advance, sample_truth=inst.sample_spec,
                strategy={"name": "adaptive", "points": 8, "seed": 0, "angle_noise": True})
    finally:
        inst.unregister()
    run_strategy = made[-1]                 # the run's own (the first: the capture's check)
    assert run_strategy._angle_modes is not None and run_strategy._angle_modes.shape[:2] == (len(plan), 4)


def test_a_bad_systematics_table_is_refused_before_anything_is_written(tmp_path):
    """With ``angle_noise`` the run reads ``[systematics]`` for the design's sigma: a bad value
    there is one line before the session folder is made (it was refused only by the run, after
    session.toml, the journal and raw/ were written)."""
    sim = pytest.importorskip("gonio.sim")
    from gonio.bench.session.capture import capture
    from gonio.core.errors import GonioError

    s = _settings()
    s["systematics"] = {**s["systematics"], "repeat_deg": -1.0}
    truth = {k: np.asarray(v).tolist() for k, v in TRUTH.items()}
    inst = sim.Instrument(s, sample={"model": "roughplastic", "options": {"distribution": "ggx"}, "params": truth},
                          seed=0).register("plan-angle-noise-bad")
    try:
        with pytest.raises(GonioError, match="repeat_deg") as e:
            capture(tmp_path / "s", plans.load_plan("quick"), s, inst.url("zaber"), inst.url("meter"),
                    inst.url("camera"), seed=0, progress=False, sleep=inst.clock.advance,
                    strategy={"name": "adaptive", "points": 8, "seed": 0, "angle_noise": True})
    finally:
        inst.unregister()
    assert "\n" not in str(e.value)
    assert not (tmp_path / "s").exists() or not any((tmp_path / "s").iterdir())


def test_a_point_without_a_finite_slope_is_one_the_design_does_not_trust(monkeypatch):
    import gonio.fitting.uncertainty.angle_shifts as shifts
    from gonio.bench.plan.alc import alc_batch
    from gonio.bench.plan.ndf_seeded import NDFSeededPlan
    from gonio.bench.measure.calpoint import hand_angle_modes
    from strategy_run import synthetic

    strat = _plan()
    x = strat.space.from_params(strat.model.validate(TRUTH))
    real = shifts.slope

    def nan_at_7_and_8(model, params, wi, wo, **kw):
        s = real(model, params, wi, wo, **kw)
        if len(wi) == len(STANDARD):
            s[[7, 8]] = np.nan
        return s

    monkeypatch.setattr(shifts, "slope", nan_at_7_and_8)
    assert np.all(np.isinf(strat._angle_var(x)[7])) and np.all(np.isfinite(strat._angle_var(x)[9]))
    rows, sigma = strat._rows(x, 0.01, 1e-4, strat._angle_var(x))
    assert np.all(rows[7] == 0.0) and np.all(np.isinf(sigma[7]))      # no information, not a precise point
    # alc: a measured point with infinite noise (7) leaves the posterior, which stays finite, and a
    # candidate with infinite noise (8, the first pick with its slope finite) tells nothing: not picked
    f, sd = synthetic(STANDARD)
    alc = _plan()
    alc.criterion = "alc"
    basis = list(range(0, 40, 3)) + [7]
    results = {i: (f[i], sd[i]) for i in basis}
    picks = alc_batch(alc, x, basis, basis, [i for i in range(len(STANDARD)) if i not in basis], 3, results, 0.01, 1e-4)
    assert len(picks) == 3 and 8 not in picks
    # the option where it cannot act is refused, in one line
    with pytest.raises(ValueError, match="angle_noise"):
        NDFSeededPlan(STANDARD, range(len(STANDARD)), {"points": 20, "angle_noise": True})
    with pytest.raises(ValueError, match="angle_noise needs"):
        hand_angle_modes(_plan(), {"capture": {}}, np.zeros((len(STANDARD), 4)))
