"""The instrument's angular response in the forward model (issue 15; gonio/fitting/likelihood/aperture.py)."""

import dataclasses

import numpy as np
import pytest

import gonio.models as gm
from gonio.fitting import Measurements, fit, with_instrument_response
from gonio.fitting.likelihood.aperture import aperture_mean, aperture_ratio, cone, disk_rule

from _simdata import cone_directions, directions


def test_disk_rule_is_exact_to_degree_five():
    """Stroud S2 5-1 on the unit disk: mean of 1, x^2, x^4, x^2 y^2 = 1, 1/4, 1/8, 1/24;
    odd moments 0 (the uniform disk's moments)."""
    p, w = disk_rule()
    x, y = p.T
    for value, expected in ((1.0, 1.0), (x ** 2, 0.25), (x ** 4, 0.125), (x ** 2 * y ** 2, 1 / 24),
                            (x, 0.0), (x ** 3 * y, 0.0), (x * y ** 2, 0.0)):
        assert np.sum(w * value) == pytest.approx(expected, abs=1e-15)


def test_cone_directions_are_unit_and_within_the_half_angle():
    rng = np.random.default_rng(0)
    w, _ = directions(rng, 50)
    d = cone(w, np.radians(1.0))
    assert np.allclose(np.linalg.norm(d, axis=2), 1.0)
    ang = np.degrees(np.arccos(np.clip(np.einsum("knc,nc->kn", d, w), -1, 1)))
    assert ang[0].max() < 1e-6 and np.allclose(ang[1:], np.degrees(np.arctan(np.tan(np.radians(1)) * np.sqrt(2 / 3))))


def test_a_lambertian_is_unchanged_and_a_narrow_lobe_is_lowered():
    rng = np.random.default_rng(1)
    wi, wo = directions(rng, 40, specular_fraction=0.0)
    lam = gm.get("diffuse")
    np.testing.assert_allclose(aperture_ratio(lam, wi, wo, {"reflectance": 0.5}, 0.5, 0.5), 1.0, atol=1e-12)
    m = gm.get("roughplastic", distribution="ggx")
    truth = {"diffuse_reflectance": 0.3, "alpha": 0.02, "int_ior": 1.5}
    wi1 = gm.geometry.directions(np.radians([30.0]), [0.0])
    wo1 = gm.geometry.directions(np.radians([30.0]), [np.pi])
    # at the mirror direction the averaged peak is lower, more so for the wider aperture
    c05, c15 = (aperture_ratio(m, wi1, wo1, truth, h, h)[0, 0] for h in (0.5, 1.5))
    assert 0.5 < c15 < c05 < 0.95
    assert aperture_mean(m, wi1, wo1, truth, 0.0, 0.0) == pytest.approx(m.eval(wi1, wo1, truth))


@pytest.fixture(scope="module")
def convolved():
    """A glossy session (alpha 0.05) measured through 0.5 deg source and detector disks."""
    m = gm.get("roughplastic", distribution="ggx")
    truth = {"diffuse_reflectance": np.array([0.5, 0.35, 0.2]), "alpha": 0.05, "int_ior": 1.5}
    rng = np.random.default_rng(11)
    wi, wo = directions(rng, 300, spread=0.05)
    f = aperture_mean(m, wi, wo, truth, 0.5, 0.5)
    sigma = 0.01 * f + 1e-3
    y = f + sigma * rng.standard_normal(f.shape)
    attrs = {"aperture_source_half_deg": 0.5, "aperture_detector_half_deg": 0.5}
    return m, Measurements(wi, wo, y, sigma, np.ones(f.shape, bool), attrs)


def test_the_response_removes_the_bias_of_a_narrow_lobe(convolved):
    """The point model's alpha is > 10 sigma off (figure: tests/fitting/aperture_effect.py);
    with the response it is within 3 sigma, and the correction is said."""
    m, meas = convolved
    refit = lambda d: fit(d, m, rng=np.random.default_rng(0))  # noqa: E731
    point = refit(meas)
    i = point.space.names.index("alpha")
    assert abs(point.x[i] - 0.05) / point.std[i] > 10
    res, m2, _ = with_instrument_response(meas, None, point, refit)
    assert abs(res.x[i] - 0.05) / res.std[i] < 3
    info = res.response
    assert info["source_half_deg"] == 0.5 and 0.01 < info["max_correction"] < 0.5 and info["last_change"] < 0.05
    assert m2.attrs["aperture_corrected"] and np.all(m2.brdf_std > 0)


def test_the_corrected_data_keep_every_other_field(convolved):
    """``corrected`` divides f_r, sigma and the budget's components by c and keeps the rest: the
    solid-angle weights and the clusters the cluster-robust sandwich sums over (it dropped the
    clusters before)."""
    from gonio.fitting.likelihood.aperture import corrected

    _, meas = convolved
    n = meas.n_points
    meas = dataclasses.replace(meas, weight=np.linspace(0.5, 1.5, n), cluster=np.arange(n) // 3)
    c = np.full(meas.brdf.shape, 1.25)
    m2, _ = corrected(meas, None, c)
    np.testing.assert_array_equal(m2.cluster, meas.cluster)
    np.testing.assert_array_equal(m2.weight, meas.weight)
    np.testing.assert_allclose(m2.brdf * 1.25, meas.brdf, rtol=1e-15)
    np.testing.assert_allclose(m2.brdf_std * 1.25, meas.brdf_std, rtol=1e-15)
    assert m2.attrs["aperture_corrected"] and "aperture_corrected" not in meas.attrs


@pytest.mark.parametrize("bad", [-0.1, float("nan"), 45.0])
def test_impossible_apertures_are_refused(convolved, bad):
    m, meas = convolved
    broken = Measurements(meas.wi, meas.wo, meas.brdf, meas.brdf_std, meas.use,
                          {"aperture_source_half_deg": bad, "aperture_detector_half_deg": 0.5})
    with pytest.raises(ValueError, match="aperture half-angles"):
        with_instrument_response(broken, None, None, None)


def test_the_mean_across_a_transmission_cutoff_is_the_uniform_disks_mean():
    """Where f_r jumps to 0 inside the cones the mean is still over the uniform disks (Nicodemus
    et al. 1977). The frosted glass (GGX 0.3, eta 1.5) at theta_i 39.613 / theta_o 120.396 /
    phi_o 180 (seed 5's true pair in tests/bench/transmission_adequacy.py): f_r is 0 at the pair
    (the half-vector below the surface) and about 0.19 just across; the degree-5 rule put 4 of
    its 49 pairs past the jump (2.1x the mean). It must equal a 400 000-sample Monte Carlo of
    <f cos theta_i> / <cos theta_i> within 5 of its standard errors."""
    model, p = gm.get("roughdielectric", distribution="ggx"), {"alpha": 0.3, "int_ior": 1.5}
    ti, to = np.radians(39.613), np.radians(120.396)
    wi = np.array([[np.sin(ti), 0.0, np.cos(ti)]])
    wo = np.array([[-np.sin(to), 0.0, np.cos(to)]])
    assert model.eval(wi, wo, p)[0, 0] == 0.0
    got = aperture_mean(model, wi, wo, p, 0.5, 0.5)[0, 0]
    rng, n, d = np.random.default_rng(15), 400_000, np.radians(0.5)
    a, b = cone_directions(wi[0], d, n, rng), cone_directions(wo[0], d, n, rng)
    x, c = model.eval(a, b, p)[:, 0] * a[:, 2], a[:, 2]
    ratio = x.mean() / c.mean()
    se = x.std() / np.sqrt(n) / c.mean()                 # the cosine's own spread is 1e-4 of it
    assert ratio > 20 * se
    assert abs(got - ratio) < 5 * se


@pytest.mark.long       # a glossy capture, two fits and the report's page without figures: about 20 s
def test_render_and_report_compare_the_fit_with_the_data_corrected_as_it_was(tmp_path, monkeypatch):
    """Where the dataset declares apertures the fit is of the data divided by c = <f_r>/f_r (at
    the shared-angle estimate's directions where it was made). `gonio render` (cli.fit
    .fitted_data) and the report (fitdoc.as_fitted) re-opened the dataset, moved it where the
    estimate put it and left c out: on a typical capture of a glossy sample (0.5 deg apertures,
    GGX alpha 0.05, seed 500100) rms (data - fit) / sigma 8.6 where the fit's chi2/dof is 6.3
    (rms 2.5); without the estimate as well. c is taken again at the fitted parameters and the
    directions the data are drawn at."""
    import json

    import gonio.bench.report as report
    from gonio.bench.dataset.export import export
    from gonio.bench.dataset.reader import open_dataset, open_fit_input
    from gonio.bench.report.inputs import Folder
    from gonio.bench.settings import default_settings
    from gonio.cli.capture import capture_sim
    from gonio.cli.fit import fitted_data
    from gonio.fitting import load_fit, write_json_atomic
    from gonio.fitting.pipeline import fit_dataset

    seed, settings = 500100, default_settings()
    settings["errors"] = {"preset": "typical"}
    sample = {"model": "roughplastic", "options": {"distribution": "ggx"},
              "params": {"diffuse_reflectance": [0.5, 0.35, 0.2], "alpha": 0.05, "int_ior": 1.5}}
    capture_sim(tmp_path / "s", sample=sample, plan="glossy", seed=seed, settings=settings, progress=False)
    dataset = export(tmp_path / "s")
    inp = open_fit_input(dataset, seed=seed)
    assert inp.meas.attrs["aperture_source_half_deg"] == 0.5

    def rms(m, fit_path):
        loaded = load_fit(fit_path)
        z = ((m.brdf - loaded.model.eval(m.wi, m.wo, loaded.params)) / m.brdf_std)[m.use]
        return float(np.sqrt(np.mean(z ** 2))), float(np.sqrt(loaded.goodness["chi2_dof"]))

    for estimate in (None, False):
        doc = fit_dataset(inp, model="roughplastic", options={"distribution": "ggx"}, seed=seed,
                          estimate_angles=estimate)[1]
        assert doc["instrument_response"]["max_correction"] > 0.01
        assert (doc["shared_angles"] or {}).get("applied", False) is (estimate is None)
        write_json_atomic(tmp_path / "fit.json", doc)
        got, fitted = rms(fitted_data(open_dataset(dataset, seed=seed), dataset, tmp_path / "fit.json"),
                          tmp_path / "fit.json")
        assert got < 1.1 * fitted, (estimate, got, fitted)
    # the report, with the estimate (the default)
    doc = fit_dataset(inp, model="roughplastic", options={"distribution": "ggx"}, seed=seed)[1]
    folder = tmp_path / "r"
    folder.mkdir()
    (folder / "dataset.nc").write_bytes(dataset.read_bytes())
    write_json_atomic(folder / "fit.json", doc)
    seen = {}

    def no_figures(meas, model, params, *args, fitted=None, **kw):
        seen.update(fitted=fitted if fitted is not None else meas)
        return {}

    monkeypatch.setattr(report, "_draw_all", no_figures)
    monkeypatch.setattr(report, "view_data", lambda meas, *a: {})
    report.build_page(folder, report.find_outputs(folder), Folder(folder))
    got, fitted = rms(seen["fitted"], folder / "fit.json")
    assert got < 1.1 * fitted, (got, fitted)
    assert json.loads((folder / "fit.json").read_text())["shared_angles"]["applied"] is True
