"""The likelihood for real data (issue 16): solid-angle weights in every loss, the log loss
as the default for files without a measured sigma, its sandwich covariance, and the
``gonio bench fit --real`` table's metrics."""

from pathlib import Path

import numpy as np
import pytest

import gonio.models as gm
from gonio.fitting import Measurements, default_loss, fit
from gonio.perf.fit import simulate_capture

RGL = Path(__file__).resolve().parents[3] / "shared" / "data" / "rgl"
needs_rgl = pytest.mark.skipif(not (RGL / "vch_golden_yellow_rgb.bsdf").exists(), reason="no RGL data here")
TRUTH = {"diffuse_reflectance": np.array([0.6, 0.3, 0.15]), "alpha": 0.15, "int_ior": 1.6}


def test_weight_is_a_multiplicity():
    """A solid-angle weight of 2 is the same sample measured twice: the weighted fit of the
    data equals the unweighted fit of the data with those rows duplicated (both losses, to
    the optimiser's precision), so weights enter chi2 and log alike."""
    model = gm.get("roughplastic", distribution="ggx")
    meas, _ = simulate_capture(model, TRUTH, 300, np.random.default_rng(3), 0.05)
    w = np.where(np.arange(meas.n_points) % 3 == 0, 2.0, 1.0)
    weighted = Measurements(meas.wi, meas.wo, meas.brdf, meas.brdf_std, meas.use, weight=w)
    dup = np.concatenate([np.arange(meas.n_points), np.arange(0, meas.n_points, 3)])
    for loss in ("chi2", "log"):
        a = fit(weighted, model, rng=np.random.default_rng(0), loss=loss)
        b = fit(meas.subset(dup), model, rng=np.random.default_rng(0), loss=loss)
        assert np.allclose(a.x, b.x, rtol=2e-4, atol=2e-5), (loss, a.x, b.x)


def test_default_loss_by_data():
    """dataset.nc (measured sigma) keeps chi2; a file without sigma gets the log loss."""
    model = gm.get("diffuse")
    meas, _ = simulate_capture(model, {"reflectance": np.array([0.5, 0.4, 0.3])}, 50, np.random.default_rng(0))
    assert default_loss(meas) == "chi2"
    meas.attrs["nominal_sigma"] = True
    assert default_loss(meas) == "log"


def test_log_sandwich_matches_the_spread_over_noise():
    """On simulated captures (fixed geometry, 5 % Gaussian noise) the log loss's sandwich
    sigma of alpha matches the spread of 24 refits: the ratio of the empirical standard
    deviation to the mean reported sigma lies within the 99 % range of a sample standard
    deviation of 24 draws (chi2_23 quantiles: 0.62-1.43); the chi2 Fisher sigma at the log
    optimum (what the log fit reported before) is about half of it."""
    from scipy.stats import chi2 as chi2_dist

    model = gm.get("roughplastic", distribution="ggx")
    xs, stds = [], []
    for k in range(24):
        meas, _ = simulate_capture(model, TRUTH, 400, np.random.default_rng([5, k]), 0.05)
        r = fit(meas, model, rng=np.random.default_rng(k), loss="log", n_local=1)
        xs.append(r.x)
        stds.append(r.std)
    i = r.space.names.index("alpha")
    ratio = np.std(np.array(xs)[:, i], ddof=1) / np.mean(np.array(stds)[:, i])
    lo, hi = np.sqrt(chi2_dist.ppf([0.005, 0.995], 23) / 23)
    print(f"empirical / sandwich sigma of alpha: {ratio:.2f} (99 % range {lo:.2f}-{hi:.2f})")
    assert lo <= ratio <= hi
    assert "sandwich" in r.method


def test_metrics_reference_values():
    """Ngan's relative L2: f_model = 1.1 f gives exactly 0.1; Loew's log error of a model
    equal to the data is 0 and of f + c / cos is ln-exact; the dense grid's pairs are equal
    solid-angle cells within 80 deg."""
    from gonio.perf.real import dense_grid, metrics

    wi, wo = dense_grid()
    assert np.degrees(np.arccos(min(wi[:, 2].min(), wo[:, 2].min()))) <= 80.0
    cz = np.cos(np.radians(80.0))
    assert np.allclose(np.mean(wi[:, 2]), 0.5 * (1 + cz), rtol=1e-9)    # uniform in cos theta
    f = np.abs(np.random.default_rng(0).normal(1.0, 0.5, (len(wi), 3)))
    assert metrics(1.1 * f, f, wi)["ngan"] == pytest.approx(0.1, rel=1e-12)
    assert metrics(f, f, wi)["log"] == 0.0
    cos = wi[:, 2:3]
    g = (np.e * (1 + f * cos) - 1) / cos                 # ln(1 + g cos) = 1 + ln(1 + f cos)
    assert metrics(g, f, wi)["log"] == pytest.approx(1.0, rel=1e-9)
    with pytest.raises(FloatingPointError):
        metrics(f * np.nan, f, wi)


def test_bench_real_bad_input_is_one_line(tmp_path, capsys):
    from gonio.cli.main import main

    bad = tmp_path / "x.txt"
    bad.write_text("no")
    for args in (["bench", "fit", "--real", str(tmp_path / "missing.bsdf")], ["bench", "fit", "--real", str(bad)]):
        assert main(args) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "--real" in err


def test_perf_real_bad_input_is_one_line(tmp_path, capsys):
    """``gonio perf real DIR...``: a missing path, a folder without a measured file, a file of
    another kind, an unknown peer family: one line each, exit 2, nothing written."""
    from gonio.cli.main import main

    (tmp_path / "empty").mkdir()
    bad = tmp_path / "x.txt"
    bad.write_text("no")
    out = tmp_path / "out.csv"
    cases = ((["perf", "real", str(tmp_path / "missing")], "missing"), (["perf", "real", str(tmp_path / "empty")],
             "no RGL"), (["perf", "real", str(bad)], "x.txt"),
             (["perf", "real", str(RGL), "--peer", "nonsense", "--out", str(out)], "--peer"))
    for args, what in cases:
        assert main(args) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and what in err, err
    assert not out.exists()


@needs_rgl
@pytest.mark.slow
def test_bench_real_gonio_beats_the_peer(tmp_path):
    """paper_white (RGL-EPFL): gonio's chosen fit beats the scipy log-loss peer (Mitsuba's
    roughplastic, issue 35) on both the Ngan and the log metric of the dense grid, and its
    render is within CIEDE2000 1 of the measured file's; the table is written as CSV. (The speed ratio is printed, never asserted.)"""
    import csv

    from gonio.perf.fit import run_real

    rows = run_real([RGL / "paper_white_rgb.bsdf"], out=tmp_path / "real.csv")
    r = rows[0]
    assert r["gonio_ngan"] < r["peer_ngan"] and r["gonio_log"] < r["peer_log"]
    assert all(np.isfinite(r[k]) for k in ("gonio_ngan", "gonio_log", "peer_ngan", "peer_log", "speedup",
                                           "speedup_cpu", "gonio_cpu_s", "peer_cpu_s", "alone_s",
                                           "choice_per_fit"))
    # the speed columns compare the whole choice: the peer's time over it, and it over the chosen
    # family's own fit (issue 35's two ratios)
    assert r["speedup"] == pytest.approx(r["peer_time_s"] / r["gonio_select_s"])
    assert r["choice_per_fit"] == pytest.approx(r["gonio_select_s"] / r["alone_s"])
    # rendered against the measured file with matched seeds: at most 1 CIEDE2000 (issue 16;
    # measured 0.88, noise floor 0.33 at 64 px, 256 spp)
    assert r["de00_noise"] < 0.5 and r["gonio_de00"] <= 1.0
    # at 16x the samples the noise's upward bias shrinks (measured 0.71 -> 0.49, 2026-12-05)
    assert r["gonio_de00_converged"] < r["gonio_de00"] - 0.1
    # the fit on the file's own grid through `measured`: both renders draw the same directions,
    # so its noise floor is a fraction of gonio's plugin's (measured 0.044 against 0.389) and
    # the grid holds the fit (Ngan relative L2 0.058); within the limit (0.39)
    assert r["grid_noise"] < r["de00_noise"] / 4 and r["grid_l2"] < 0.1 and r["gonio_de00_grid"] <= 1.0
    # matte by ASTM D523 (60 deg gloss below 10 GU; 2.78 GU measured 2026-12-05), so its limit is 1
    assert r["gloss_60"] < 10 and r["de00_limit"] == 1
    with open(tmp_path / "real.csv") as fh:
        assert next(csv.DictReader(fh))["material"] == "paper_white_rgb"


def test_fit_loss_help_lists_every_loss():
    from gonio.cli.main import build_parser
    from gonio.fitting import LOSSES

    fit_parser = build_parser()._subparsers._group_actions[0].choices["fit"]
    text = next(a.help for a in fit_parser._actions if "--loss" in a.option_strings)
    assert all(name in text for name in LOSSES), text


@needs_rgl
@pytest.mark.long      # 27 s: the suite's 10 minutes on 2 cores (make test-long runs it)
def test_auto_on_the_golden_paint_falls_back_to_the_data_driven_ndf():
    """vch_golden_yellow (RGL-EPFL): no --model auto candidate renders within CIEDE2000 1 of the
    measured file in the product-shot scene (BIC's roughconductor2: preview CIEDE2000 3.66, its
    lobe one colour where the data's core is orange and its halo and body yellow-green), so the
    rendered check's fallback fits ``tabulated`` from the data and chooses it: a preview clearly
    closer to the measured file than BIC's choice (CIEDE2000 at 64 px, 256 spp: measured 1.98,
    its matched-seed floor 0.56 from the tabulated plugin's own sampling, against 3.66) and a better Ngan and log error on the dense grid than
    BIC's choice (0.152 / 0.0224 against 0.328 / 0.0326). In the product-shot scene (32 px,
    128 spp): tabulated 2.47 (floor 0.47), cooktorrance 3.54, roughconductor2-GGX 4.97.
    2.5 minutes at load 6-9 on the shared 2-core machine: the selection, the tabulated fit
    (57 s) and the renders. The candidates are the RGB ones (``CANDIDATES``): the file is
    goniochromic (``by_data.goniochromism``), and with the flake paint offered BIC chooses
    flakepaint, which renders as close as tabulated (product shot 2.49 against 2.47; measured
    2026-12-04), so BIC's choice stands and there is no bad choice for the fallback to mend."""
    from gonio.fitting import REAL_DEFAULT_LOSS, select
    from gonio.fitting.selection.by_data import CANDIDATES
    from gonio.perf.real import dense_grid, measured_on_grid, metrics, rendered_delta_e
    from gonio.fitting.realdata import rgl_samples
    from gonio.fitting.selection.by_scene import data_driven, rendered_choice

    path = RGL / "vch_golden_yellow_rgb.bsdf"
    meas = rgl_samples(path)
    by_bic, ranking = select(meas, rng=np.random.default_rng(0), loss=REAL_DEFAULT_LOSS, candidates=CANDIDATES)
    best, ranking, note = rendered_choice(ranking, str(path), seed=0, fallback=data_driven(meas, seed=0))
    print(note, [(r.name, r.k, r.delta_e) for r in ranking])
    assert best.model.name == "tabulated" and "fallback" in note
    wi, wo = dense_grid()
    f = measured_on_grid(path, wi, wo)
    g, b = metrics(best.model.eval(wi, wo, best.params), f, wi), metrics(by_bic.model.eval(wi, wo, by_bic.params), f, wi)
    assert g["ngan"] < b["ngan"] and g["log"] < b["log"]
    de, floor = rendered_delta_e(best.model, best.params, path, seed=0)
    de_bic, floor_bic = rendered_delta_e(by_bic.model, by_bic.params, path, seed=0)
    print(g, b, de, floor, de_bic, floor_bic)
    # Clearly closer than BIC's choice in the preview (1.98 against 3.66, floors 0.56 and 0.41).
    # Issue 16's bound of 2 is met here (1.98) but not asserted: its margin, 0.02, is below what
    # another CPU's floating-point order may move a 42-parameter fit (gonio bench fit --real
    # prints it).
    assert floor < 0.65 and de + floor + floor_bic < de_bic


@pytest.mark.slow        # Mitsuba loads the BSDF at every residual call: about 10 s
def test_the_peer_fits_the_same_optimum_through_mitsuba_as_through_gonio():
    """`gonio perf real --peer-eval mitsuba` is issue 35's plain fit as written (Mitsuba's own
    roughplastic, loaded and evaluated at every residual call); it reaches the optimum the
    compiled-kernel peer reaches (Mitsuba evaluates in float32, so its differences take a 1e-3
    step: the parameters agree to 1e-3 relative, well inside the 2 % noise; with scipy's default
    step the fit never left its start), and an unknown evaluation is refused."""
    from gonio.fitting.measurements import Measurements
    from gonio.perf.real import peer_fit

    rng = np.random.default_rng(11)
    model = gm.get("roughplastic")
    n = 300
    ti, to, po = np.radians(rng.uniform(5, 75, n)), np.radians(rng.uniform(5, 75, n)), rng.uniform(0, 2 * np.pi, n)
    wi = np.stack([np.sin(ti), np.zeros(n), np.cos(ti)], 1)
    wo = np.stack([np.sin(to) * np.cos(po), np.sin(to) * np.sin(po), np.cos(to)], 1)
    truth = {"diffuse_reflectance": np.array([0.6, 0.4, 0.2]), "alpha": 0.2, "int_ior": 1.5}
    f = model.eval(wi, wo, truth) * (1 + 0.02 * rng.standard_normal((n, 3)))
    meas = Measurements(wi, wo, f, 0.02 * f, True, {"source": "test"})
    fits = {e: peer_fit(meas, model, np.random.default_rng(1), n_starts=1, evaluate=e) for e in ("gonio", "mitsuba")}
    np.testing.assert_allclose(fits["mitsuba"][1], fits["gonio"][1], rtol=1e-3)
    np.testing.assert_allclose(fits["gonio"][1][:3], truth["diffuse_reflectance"], rtol=0.02)
    with pytest.raises(ValueError, match="choose one of mitsuba, gonio"):
        peer_fit(meas, model, np.random.default_rng(1), n_starts=1, evaluate="numpy")
