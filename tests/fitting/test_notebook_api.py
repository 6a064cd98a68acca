"""The notebook face of fits and datasets: short reprs (no raw arrays), escaped HTML tables,
``to_xarray()`` holding the same numbers, ``load_fit``'s FitFile, and the plotting helpers.

Rounding reference: the GUM (JCGM 100:2008, 7.2.6) gives the uncertainty to at most two
significant digits and the value to the same decimal place.
"""

import matplotlib

matplotlib.use("Agg")

import numpy as np
import pytest

import gonio.models as gm
from gonio.fitting import FitFile, Measurements, fit, fit_document, load_fit, write_json_atomic
from gonio.fitting import plots
from gonio.fitting.display import value_pm
from gonio.perf.fit import simulate_capture
from gonio.core.geometry import directions_deg

TRUTH = {"diffuse_reflectance": np.array([0.6, 0.4, 0.2]), "alpha": 0.15, "int_ior": 1.5}


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    model = gm.get("roughplastic", distribution="ggx")
    meas, _ = simulate_capture(model, TRUTH, 150, np.random.default_rng(1))
    result = fit(meas, model, rng=np.random.default_rng(0))
    path = write_json_atomic(tmp_path_factory.mktemp("nb") / "fit.json", fit_document(result, meas, seed=0))
    return meas, result, path


@pytest.mark.parametrize("x,u,text", [(0.549918, 7.7e-5, "0.549918 ± 0.000077"), (0.55, 0.0123, "0.550 ± 0.012"),
                                      (123.456, 1.5, "123.5 ± 1.5"), (1.2e-5, 3.4e-7, "(1.200 ± 0.034)e-05"),
                                      (2.0e6, 3.0e4, "(2.000 ± 0.030)e+06"), (3.0, 0.0, "3"),
                                      (3e-65, 1.511e-62, "(0.0 ± 1.5)e-62"), (-4e-20, 1e-15, "(0.0 ± 1.0)e-15")])
def test_values_rounded_to_their_uncertainty(x, u, text):
    assert value_pm(x, u) == text


def test_fit_result_repr_html_and_xarray(fitted):
    meas, result, _ = fitted
    text = repr(result)
    assert "array(" not in text and len(text.splitlines()) < 15
    for name, x, s in zip(result.space.names, result.x, result.std):
        assert f"{name}  " in text and value_pm(x, s) in text
    assert f"chi2/dof = {result.chi2_dof:.4g}" in text
    html = result._repr_html_()
    assert html.startswith("<div><table>") and value_pm(result.x[0], result.std[0]) in html
    ds = result.to_xarray()
    np.testing.assert_array_equal(ds.value.values, result.x)
    np.testing.assert_array_equal(ds["std"].values, result.std)
    assert list(ds.parameter.values) == result.space.names and ds.attrs["dof"] == result.dof
    c = ds.correlation.values
    np.testing.assert_allclose(np.diag(c), 1.0)
    np.testing.assert_allclose(c, c.T)


def test_load_fit_returns_a_fit_file(fitted):
    meas, result, path = fitted
    loaded = load_fit(path)
    assert isinstance(loaded, FitFile) and loaded.model.name == "roughplastic"
    np.testing.assert_allclose(loaded.eval(meas.wi, meas.wo), result.model.eval(meas.wi, meas.wo, result.params))
    ds = loaded.to_xarray()
    np.testing.assert_allclose(ds.value.values, result.x)
    assert (ds.ci90_low.values < ds.value.values).all() and (ds.value.values < ds.ci90_high.values).all()
    assert value_pm(result.x[-1], loaded.parameters["int_ior"]["std"]) in repr(loaded)
    assert 'version="3.0.0"' in loaded.to_mitsuba_xml() and loaded.to_mitsuba()["type"] == "roughplastic"


def test_measurements_repr_and_escaped_html():
    wi = directions_deg(np.full(4, 30.0), np.zeros(4))
    wo = directions_deg(np.array([10.0, 20.0, 30.0, 40.0]), np.full(4, 180.0))
    meas = Measurements(wi, wo, np.full((4, 2), 0.1), 0.01, True, attrs={"title": "<script>x</script>"},
                        channels=("<b>R</b>", "G&"))
    text = repr(meas)
    assert text.startswith("Measurements: 4 direction pairs x 2 channels, 8 values used") and "array(" not in text
    html = meas._repr_html_()
    assert "<script>" not in html and "&lt;script&gt;" in html and "&lt;b&gt;R&lt;/b&gt;" in html and "G&amp;" in html
    ds = meas.to_xarray()
    np.testing.assert_allclose(ds.theta_o.values, [10, 20, 30, 40])
    np.testing.assert_array_equal(ds.brdf.values, meas.brdf)


def test_plot_in_plane_draws_the_data_and_the_model():
    """An in-plane scan of a Lambertian 0.5: the curve is 0.5 / pi everywhere; every point is drawn."""
    model, params = gm.get("diffuse"), {"reflectance": np.array([0.5, 0.5, 0.5])}
    theta_o = np.array([-60.0, -30.0, 10.0, 40.0, 70.0])
    wi = directions_deg(np.full(5, 30.0), np.zeros(5))
    wo = directions_deg(np.abs(theta_o), np.where(theta_o < 0, 0.0, 180.0))
    f = model.eval(wi, wo, params)
    meas = Measurements(wi, wo, f, 0.01 * f, True)
    fig = plots.plot_in_plane(meas, model, params)
    ax = fig.axes[0]
    assert ax.get_title() == "theta_i = 30 deg"
    curves = [line for line in ax.get_lines() if len(line.get_xdata()) == 241]
    assert len(curves) == 3 and all(np.allclose(line.get_ydata(), 0.5 / np.pi) for line in curves)
    points = [line for line in ax.get_lines() if len(line.get_xdata()) == 5]
    np.testing.assert_allclose(sorted(points[0].get_xdata()), sorted(theta_o))
    fig_r = plots.plot_residuals(meas, model, params)
    assert sum(p.get_height() for p in fig_r.axes[0].patches) == meas.n_used


def test_in_plane_panels_follow_the_measured_incidences_however_they_were_moved():
    """The in-plane panels group the points' theta_i where they lie: a set of points moved
    together by a shared-angle estimate (30 -> 30.52, the uncalibrated quick capture seed 13)
    stays one panel titled at its own angle, its curve drawn there, not rounded to 31; one
    incidence whose points straddle 29.5 (29.46, 29.54) is one panel, not two."""
    import numpy as np

    from gonio.fitting import Measurements
    from gonio.fitting import plots
    from gonio.core.geometry import directions

    assert [g.tolist() for g in plots.incidence_groups([45.52, 30.52, 30.53, 45.5, 30.54])] == \
        [[30.52, 30.53, 30.54], [45.5, 45.52]]
    assert plots.incidence_groups([]) == []
    ti = np.radians(np.r_[np.full(5, 29.46), np.full(5, 29.54), np.full(5, 45.0)])
    to = np.radians(np.tile(np.linspace(-60, 60, 5), 3))
    wi = directions(ti, np.zeros_like(ti))
    wo = directions(np.abs(to), np.where(to < 0, 0.0, np.pi))
    meas = Measurements(wi, wo, np.ones((15, 3)), np.full((15, 3), 0.1), np.ones((15, 3), bool))
    fig = plots.plot_in_plane(meas)
    titles = [ax.get_title() for ax in fig.axes if ax.get_title()]
    assert titles == ["theta_i = 29.5 deg", "theta_i = 45 deg"]
    # every point of each incidence in its panel: 10 and 5 points, 3 channels each
    markers = [sum(len(line.get_xdata()) for line in ax.lines if line.get_marker() == "o") for ax in fig.axes[:2]]
    assert markers == [30, 15]
