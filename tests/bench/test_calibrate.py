"""gonio calibrate (gonio/bench/calibrate.py, gonio/bench/measure/alignment.py) against the simulator's hidden errors.

Statistics: every check of an estimate against the truth is a two-sided z-test with the
estimate's own stated standard uncertainty; each test's family of k parameters shares a false
alarm of 1e-3 (Bonferroni: |z| < Phi^-1(1 - 5e-4 / k)). Power: the simulated offsets are drawn
with 1-sigma 0.1-0.2 deg and their stated uncertainties are 0.001-0.01 deg, so an alignment that
found nothing (estimate 0) fails each test with the drawn truth here (checked in the tests).
Outcomes depend on the seeded noise, not on float summation order (|z| here are below 2.3 in
16 seeded sessions, the threshold is 3.8 or more).
"""

import math

import gonio.sim as gs
import numpy as np
import pytest
from gonio.bench.measure import alignment as al
from gonio.bench import calibrate as C
from gonio.bench.settings import default_settings, validate_settings
from gonio.cli.main import main
from gonio.sim.physics.errors import spectralon_factor
from scipy.stats import norm

SEED = 3


def _threshold(k: int, alpha: float = 1e-3) -> float:
    return float(norm.isf(alpha / (2 * k)))


@pytest.fixture(scope="module")
def run():
    s = default_settings()
    s["errors"] = {"preset": "typical"}
    cal = C.calibrate(s, seed=SEED)
    truth = gs.Instrument(s, seed=SEED).error_state
    return s, cal, truth


def _effective_tilt(truth):
    """The holder's normal in the azimuth counter's frame (the azimuth zero turns it) as (ax, ay)."""
    n = al._rz(math.radians(truth.zero_deg[2])) @ al.holder_rotation(*truth.tilt_deg)[:, 2]
    return math.degrees(math.atan2(-n[1], n[2])), math.degrees(math.asin(n[0]))


def test_alignment_recovers_zero_offsets_tilt_and_backlash(run):
    s, cal, truth = run
    a = cal["alignment"]
    ax, ay = _effective_tilt(truth)
    b = truth.model.stages.backlash_deg
    pairs = {"yaw_zero_deg": truth.zero_deg[0], "tilt_zero_deg": truth.zero_deg[1], "holder_tilt_x_deg": ax,
             "holder_tilt_y_deg": ay, "backlash_yaw_deg": b, "backlash_tilt_deg": b, "backlash_lamp_deg": b}
    z = {k: (a[k] - v) / a[f"u_{k}"] for k, v in pairs.items()}
    assert max(abs(v) for v in z.values()) < _threshold(len(z)), z
    # power: "no alignment" (all zero) is rejected for the offsets drawn here
    z0 = [abs(pairs[k]) / a[f"u_{k}"] for k in ("yaw_zero_deg", "tilt_zero_deg", "holder_tilt_x_deg", "holder_tilt_y_deg")]
    assert min(z0) > _threshold(4), z0
    assert 0 <= a["chi2"] < 16.3                                  # chi2_3 0.999 point: the peaks' u are honest


def test_linearity_and_reference_factor(run):
    s, cal, truth = run
    lin = cal["linearity"]
    assert abs(lin["gamma"] - truth.model.linearity.gamma) / lin["u_gamma"] < _threshold(1)
    assert truth.model.linearity.gamma / lin["u_gamma"] > _threshold(1)      # non-linearity detected
    ref = cal["reference"]
    g = np.radians(ref["factor_theta_i"])
    true = spectralon_factor(g[:, None], g[None, :], truth.model.reference.non_lambertian)
    u = np.asarray(ref["u_factor"])
    z = (np.asarray(ref["factor"]) - true)[u > 0] / u[u > 0]
    assert np.max(np.abs(z)) < _threshold(z.size), z
    assert np.max(np.abs(true - 1)) / np.max(u) > _threshold(1)            # the departure is resolved


def test_calibrated_angles_are_the_true_ones_within_their_uncertainty(run):
    """At capture poses of the same (typical) instrument the calibrated angles match its hidden
    geometry within the stated per-point u; the uncalibrated kinematics miss it by more."""
    s, cal, truth = run
    sim = gs.Instrument(s, seed=SEED)
    bench = C.SimBench(sim)
    poses = [(20.0, 0.0, 0.0, 60.0), (40.0, 10.0, 45.0, 90.0), (-30.0, -15.0, 120.0, 20.0), (55.0, 5.0, 200.0, 110.0)]
    u = C.angle_uncertainty(cal, poses)
    est = u["angles"]
    nominal = C.calibrated_angles({}, poses)
    zs, miss = [], []
    for k, pose in enumerate(poses):
        bench.move(pose)
        g = sim.geometry()
        ti, to = (math.degrees(math.acos(g[w][2])) for w in ("wi", "wo"))
        zs += [(est[k, 0] - ti) / u["u_theta_i"][k], (est[k, 2] - to) / u["u_theta_o"][k]]
        miss += [abs(nominal[k, 0] - ti) / u["u_theta_i"][k], abs(nominal[k, 2] - to) / u["u_theta_o"][k]]
    assert max(abs(z) for z in zs) < _threshold(len(zs)), zs
    assert max(miss) > _threshold(len(zs)), miss
    assert np.all(u["cov_shared"][:, 0, 0] > 0) and np.all(u["cov_independent"][:, 0, 0] > 0)
    m = u["shared_modes"]
    assert np.allclose(np.einsum("nak,nbk->nab", m, m), u["cov_shared"], rtol=1e-9, atol=1e-15)
    coords, data, attrs = C.dataset_angles(C.merge_calibration(s, cal), poses)
    assert np.array_equal(coords["theta_o"][1], est[:, 2]) and np.array_equal(data["theta_o_nominal"][1], nominal[:, 2])
    assert np.array_equal(data["theta_i_u"][1], u["u_theta_i"]) and attrs["aperture_source_half_deg"] == 0.5
    assert C.dataset_angles(s, poses) == ({}, {}, {})


def test_file_round_trip_merges_into_settings(run, tmp_path):
    s, cal, _ = run
    path = C.write_calibration(tmp_path / "cal.toml", cal)
    back = C.read_calibration(path)
    assert back["alignment"]["yaw_zero_deg"] == cal["alignment"]["yaw_zero_deg"]
    assert back["calibration"]["seed"] == SEED and "gonio" in back["calibration"]["versions"]
    merged = validate_settings(C.merge_calibration(default_settings(), back))
    assert merged["reference"]["reflectance"] == 0.99 and merged["reference"]["factor"] == cal["reference"]["factor"]
    assert C.instrument_response(merged) == {"aperture_source_half_deg": 0.5, "aperture_detector_half_deg": 0.5,
                                             "aperture_profile": "uniform disk"}
    assert C.u_reference_factor(merged, 40.0, 40.0) > 0
    (tmp_path / "bad.toml").write_text("[alignment]\nyaw_zero_deg = nan\n[calibration]\n")
    for bad in (tmp_path / "bad.toml", tmp_path / "missing.toml"):
        with pytest.raises(C.GonioError):
            C.read_calibration(bad)


@pytest.mark.parametrize("argv, words", [
    (["calibrate", "--out", "{tmp}/c.toml"], "--sim"),
    (["calibrate", "--sim", "--out", "{tmp}"], "folder"),
    (["calibrate", "--sim", "--errors", "awful", "--out", "{tmp}/c.toml"], "invalid choice"),
])
def test_cli_refuses_bad_input_in_one_line(tmp_path, capsys, argv, words):
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    try:
        rc = main(argv)
    except SystemExit as exc:                      # argparse's own refusals
        rc = exc.code
    err = capsys.readouterr().err
    assert rc == 2 and words in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "c.toml").exists()


def test_uncertainty_helpers():
    from gonio.bench.measure.hdr import linearise

    x = np.linspace(0.0, 15000.0, 7)
    assert np.allclose(linearise(x * (1 - 0.003 * x / 15871.0), 0.003, 15871.0), x, rtol=1e-12, atol=1e-9)
    assert linearise(x, 0.0, 15871.0) is x
    assert C.u_linearity_rel(0.8, 0.2, 1e-4) == pytest.approx(6e-5)
    assert C.u_stray_rel(1.0, 1.0, 1e-3) == 0.0
    assert C.u_stray_rel(0.01, 0.3, 1e-3) == pytest.approx(1e-3 / math.pi * (100 - 1 / 0.3) / math.sqrt(3))
    empty = C.angle_uncertainty({}, [(10.0, 0.0, 0.0, 40.0)])
    assert empty["u_theta_i"][0] == 0.0 and empty["u_theta_o"][0] == 0.0


def test_the_stray_correction_is_exact():
    """A floor s = floor / pi added to both squares (radiances per unit irradiance L_s, L_r):
    (R - q) / (1 - q) with q = s / (L_r + s) is L_s / L_r to rounding; when the true floor is
    u above the corrected one the corrected ratio moves by stray_shift_rel(L_s, L_r, u) (first
    order: within 1e-3 of it for u = 1e-5)."""
    ls = np.array([0.003, 0.05, 0.3, 2.0, 40.0])
    lr = np.array([0.31, 0.25, 0.2, 0.28, 0.1])
    floor, u = 1e-4, 1e-5
    q = C.stray_fraction(lr, floor)
    assert np.allclose(C.stray_corrected((ls + floor / math.pi) / (lr + floor / math.pi), q), ls / lr, rtol=1e-12)
    s2 = (floor + u) / math.pi
    moved = C.stray_corrected((ls + s2) / (lr + s2), q) / (ls / lr) - 1.0
    assert np.allclose(moved, C.stray_shift_rel(ls, lr, u), rtol=1e-3)
    assert np.all(np.sign(C.stray_shift_rel(ls, lr, u)) == np.sign(lr - ls))     # signed: not |...|


def test_a_capture_removes_the_stated_stray_floor(tmp_path):
    """A dark Lambertian sample (rho 0.1) on an instrument whose only error is a stray floor of
    3e-3: without a stated level the bench's f_r is 2-4 % high (floor/pi (1/L_s - 1/L_r)), every
    value tens of its own sigma off the truth rho / pi; with [stray] floor and u_floor (gonio
    calibrate's table) each value lies within 4.4 sigma of it (z-tests on 18 values, Bonferroni
    false alarm 1e-3), the same captured frames (one seed) giving both, and the budget has no
    stray line for u_floor = 0 (the bound-only table keeps its rectangular line)."""
    import xarray as xr
    from gonio.cli import capture as session_runner
    from gonio.bench.dataset.export import export
    from gonio.bench.plan.plans import Plan

    plan = Plan("six", [[10.0, 0.0, 30.0, 180.0], [30.0, 0.0, 10.0, 180.0], [50.0, 0.0, 20.0, 180.0],
                        [20.0, 90.0, 50.0, 270.0], [60.0, 0.0, 0.0, 0.0], [40.0, 45.0, 40.0, 225.0]])
    sample, truth = {"model": "diffuse", "params": {"reflectance": 0.1}}, 0.1 / math.pi
    out = {}
    for name, stray in (("bound", {"floor": 3e-3}), ("stated", {"floor": 3e-3, "u_floor": 0.0})):
        s = default_settings()
        s["errors"] = {"preset": "ideal", "stray": {"floor": 3e-3}}
        s["stray"] = stray
        s["capture"] = {**s["capture"], "flat_frames": 0}
        session_runner.capture_sim(tmp_path / name, sample=sample, plan=plan, seed=SEED, settings=s, progress=False)
        with xr.open_dataset(export(tmp_path / name)) as ds:
            out[name] = (ds["brdf"].values, ds["brdf_std"].values, "u_stray_light" in ds)
    limit = float(norm.isf(1e-3 / 2 / 18))
    f, sd, has_line = out["stated"]
    assert np.all(np.abs(f - truth) <= limit * sd), (f / truth - 1, sd / f)
    assert not has_line
    f, sd, has_line = out["bound"]
    assert np.all(f / truth - 1 > 0.015) and np.all(np.abs(f - truth) > 10 * sd), (f / truth - 1, sd / f)
    assert has_line


def test_a_calibrated_capture_exports_the_calibrated_angles(run, tmp_path):
    """gonio capture with a calibration: session.toml keeps the tables, dataset.nc has the
    calibrated angles (calibrated_angles of the journalled stage angles and the directions of
    each axis's last move: the measured lost motion corrected), the nominal ones, their u, and
    the aperture attributes fitting's angular response reads."""
    import xarray as xr
    from gonio.cli import capture as session_runner
    from gonio.bench.dataset.export import export
    from gonio.bench.plan.plans import Plan

    s, cal, _ = run
    settings = C.merge_calibration(s, cal)
    settings["capture"] = {**settings["capture"], "flat_frames": 0}
    plan = Plan("two", [[30.0, 0.0, 20.0, 180.0], [50.0, 90.0, 10.0, 270.0]])
    session_runner.capture_sim(tmp_path / "s", sample={"model": "diffuse", "params": {"reflectance": 0.5}},
                               plan=plan, seed=SEED, settings=settings, progress=False)
    with xr.open_dataset(export(tmp_path / "s")) as ds:
        stage = np.stack([ds[k].values for k in ("yaw", "tilt", "azimuth", "lamp")], -1)
        last = np.array([[0.0, 0.0, 0.0, 0.0], np.sign(stage[1] - stage[0])])   # the journal's order: plan order here
        want = C.calibrated_angles(cal, stage, last_dir=last)
        assert np.allclose(ds["theta_i"].values, want[:, 0], atol=1e-9)
        assert np.allclose(ds["theta_o"].values, want[:, 2], atol=1e-9)
        # the second point: each axis's measured lost motion -b/2 x (direction of its move) is
        # corrected; the first point (no move seen in the journal) is not
        plain = C.calibrated_angles(cal, stage)
        assert np.allclose(ds["theta_i"].values[0], plain[0, 0], atol=1e-9)
        shift = C.lost_motion(cal, last)
        assert np.allclose(shift[1], -0.5 * np.abs([cal["alignment"]["backlash_yaw_deg"], cal["alignment"]["backlash_tilt_deg"],
                                                    0.0, cal["alignment"]["backlash_lamp_deg"]]) * last[1])
        assert abs(ds["theta_i"].values[1] - plain[1, 0]) > 1e-4
        assert np.allclose(ds["theta_i_nominal"].values, [30.0, 50.0], atol=1e-3)
        assert np.all(ds["theta_i_u"].values > 0)
        assert ds.attrs["aperture_source_half_deg"] == 0.5
        assert float(np.max(np.abs(ds["theta_i"].values - [30.0, 50.0]))) > 0.05     # the calibration moved them


def test_capture_refuses_a_calibration_that_does_not_fit(run, tmp_path, capsys):
    """--calibration of the simulator for another seed or error model, a damaged file, or
    --errors on hardware: one line, exit 2, no session folder."""
    _, cal, _ = run
    good = C.write_calibration(tmp_path / "cal.toml", cal)
    (tmp_path / "junk.toml").write_text("not = [toml")
    out = tmp_path / "session"
    cases = [(["--sim", "--seed", str(SEED + 1), "--errors", "typical", "--calibration", str(good)], "seed"),
             (["--sim", "--seed", str(SEED), "--errors", "poor", "--calibration", str(good)], "error model"),
             (["--sim", "--seed", str(SEED), "--calibration", str(tmp_path / "junk.toml")], "not a calibration"),
             (["--port", "sim://nowhere/zaber", "--meter-port", "x", "--camera", "y", "--errors", "typical"], "--sim")]
    for args, words in cases:
        rc = main(["capture", "--plan", "quick", "--out", str(out), "--quiet", *args])
        err = capsys.readouterr().err
        assert rc == 2 and words in err and len(err.strip().splitlines()) == 1, err
        assert not out.exists()


def test_driver_bench_sees_what_the_physics_bench_sees(tmp_path):
    """DriverBench (the production drivers over the simulator's sim:// ports, what hardware runs)
    and SimBench measure the same squares at the same pose: their means agree within 5 combined
    standard errors of the frame noise (false alarm 6e-7)."""
    from gonio.bench.drivers.rig import Bench

    s = default_settings()
    s["errors"] = {"preset": "typical"}
    sim_bench, _ = C._sim_bench(s, SEED)
    phys = C._sim_bench(s, SEED)[0]
    inst = sim_bench.inst.register("test-calibrate-drivers")
    try:
        rig = Bench(s, inst.url("zaber"), inst.url("meter"), inst.url("camera"), sleep=inst.clock.advance)
        try:
            drv = C.DriverBench(rig, s, tmp_path / "scratch")
            pose = (20.0, 0.0, 0.0, 50.0)
            got = []
            for b in (drv, phys):
                b.move(pose)
                got.append(np.array([C._squares(b, pose, s, 0.004)[:2] for _ in range(6)]))
        finally:
            rig.close()
    finally:
        inst.unregister()
    mean = [g.mean(0) for g in got]
    se = np.sqrt(sum(g.var(0, ddof=1) / len(g) for g in got))
    assert drv.full_scale == phys.full_scale
    assert np.all(np.abs(mean[0] - mean[1]) < 5 * se + 1e-9), (mean, se)
    assert not list((tmp_path / "scratch").iterdir())               # RAW scratch files removed
