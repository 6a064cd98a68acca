"""Colour end to end (issue 15): a saturated sample through a real camera's colour, fitted in
linear sRGB, exported to Mitsuba, renders its true colour.

The virtual sample is Lambertian with rho = (0.6, 0.1, 0.05) in linear sRGB; the simulated
camera has the NPL-measured Nikon D5100 sensitivities (gonio/sim/physics/colour.py), so its white-balanced
RGB of that sample is about (0.42, 0.12, 0.07). The bench takes the camera -> sRGB matrix from
the DNG's ColorMatrix1 (gonio/bench/measure/colour_matrix.py), the fit runs on ``brdf_srgb``, and Mitsuba
renders the fitted material on the preview sphere (``env`` lighting) beside the true one, with
the same sampler seed: the mean CIEDE2000 over the sphere is 0.01 measured (bound 1). The same
pipeline fitted in camera RGB (no matrix applied, as before issue 15) gives 5.9 measured (the
issue's "about 10" was for a stronger mixing than the D5100's): it must stay above 3, so the
matrix is what makes the difference.

The noise is seeded, so the result is one fixed draw; the z bound of 3 per channel would
fail a correct pipeline with probability 1 - 0.9973^3 = 0.8 % over seeds.
"""

import json

import numpy as np
import pytest
import xarray as xr

from gonio.bench.plan import plans
from gonio.bench.settings import default_settings
from gonio.bench.measure.colour_matrix import matrix_from_dng
from gonio.bench.dataset.export import export
from gonio.cli.capture import capture_sim
from gonio.fitting import fit, load_dataset
from gonio.fitting.render.preview import delta_e_2000, render_sphere, sphere_mask
import gonio.models as gm
from gonio.sim.physics.colour import camera_colour

RHO = np.array([0.6, 0.1, 0.05])
SAMPLE = {"model": "diffuse", "params": {"reflectance": RHO.tolist()}}
PLAN = plans.Plan("colour", [[0, 0, 30, 0], [30, 0, 0, 0], [45, 0, 20, 180], [20, 0, 45, 90],
                             [60, 0, 10, 0], [10, 0, 60, 180]])
SIZE, SPP = 32, 8


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    out = tmp_path_factory.mktemp("colour")
    settings = default_settings()
    settings["capture"]["flat_frames"] = 0
    capture_sim(out / "s", sample=SAMPLE, plan=PLAN, seed=11, progress=False, settings=settings)
    path = export(out / "s")
    model = gm.get("diffuse")
    truth = render_sphere(model.to_mitsuba({"reflectance": RHO}), "env", size=SIZE, spp=SPP, seed=1)
    return {"path": path, "folder": out / "s", "model": model, "truth": truth}


def _fit_and_render(session, space):
    meas = load_dataset(session["path"], colour_space=space)
    result = fit(meas, session["model"], rng=np.random.default_rng(0))
    image = render_sphere(session["model"].to_mitsuba(result.params), "env", size=SIZE, spp=SPP, seed=1)
    de = float(delta_e_2000(image, session["truth"])[sphere_mask(SIZE)].mean())
    return meas, result, de


def test_dataset_says_which_space_and_which_matrix(session):
    with xr.open_dataset(session["path"], engine="h5netcdf") as ds:
        assert ds.brdf.attrs["colour_space"] == "camera" and ds.brdf_srgb.attrs["colour_space"] == "srgb"
        assert ds.brdf_xyz.attrs["colour_space"] == "xyz"
        matrix = json.loads(ds.attrs["colour_matrix"])
        corr = ds.brdf_srgb_corr.values
    assert matrix["source"] == "dng"
    # the DNG's ColorMatrix1 gives back the simulated camera's A^-1 (1e-7 rationals)
    np.testing.assert_allclose(matrix["srgb_from_cam"], camera_colour().srgb_from_cam, atol=1e-6)
    raw = next(p for p in sorted((session["folder"] / "raw").glob("*.dng")) if not p.name.startswith("."))
    assert matrix_from_dng(raw).source == "dng"
    # the matrix mixes independent camera channels: sRGB noise is correlated (R-G strongly, negatively)
    assert np.all(np.abs(corr) <= 1) and corr[:, 2].max() < -0.3


def test_fit_in_srgb_renders_the_true_colour(session):
    meas, result, de = _fit_and_render(session, "srgb")
    assert meas.attrs["colour"]["space"] == "srgb" and "not in its covariance" in meas.attrs["colour"]["left_out"]
    z = (result.params["reflectance"] - RHO) / result.std
    assert np.all(np.abs(z) < 3), (result.params["reflectance"], result.std)
    assert de < 1.0, de


def test_without_the_matrix_the_colour_is_visibly_wrong(session):
    meas, result, de = _fit_and_render(session, "camera")
    assert meas.attrs["colour"]["space"] == "camera"
    # camera RGB is A rho, not rho: red reads about 0.42 instead of 0.6
    np.testing.assert_allclose(result.params["reflectance"], camera_colour().balanced @ RHO, rtol=0.01)
    assert de > 3.0, de


def test_a_chart_capture_gives_the_matrix_and_its_uncertainty(session, tmp_path):
    """``gonio export --colour-chart``: the matrix from a ColorChecker capture by the same camera,
    its source and uncertainty recorded; the sample's sRGB lies within it (k = 2)."""
    from gonio.bench.measure.colour_matrix import colour_matrix_uncertainty, matrix_from_chart_dng
    from gonio.bench.dataset.export import to_dataset
    from gonio.sim import Instrument
    from gonio.sim.devices.camera_port import CameraPort

    inst = Instrument(seed=5)
    inst.lamp.switch(inst.clock.now(), True)
    assert CameraPort(inst).handle(f"CHART 0.01 {tmp_path / 'chart.dng'}")[0].startswith("OK ")
    ds = to_dataset(session["folder"], tmp_path / "chart.dng")
    matrix = json.loads(ds.attrs["colour_matrix"])
    assert matrix["source"] == "chart" and matrix["chart_file"].endswith("chart.dng")
    assert matrix["uncertainty"] == "row covariance of the chart fit" and len(matrix["prediction_rel"]) == 3
    f_cam = ds.brdf.values * np.pi                                   # Lambertian: rho = pi f_r
    u = colour_matrix_uncertainty(f_cam, matrix_from_chart_dng(tmp_path / "chart.dng"))
    z = (ds.brdf_srgb.values * np.pi - RHO) / np.hypot(u, ds.brdf_srgb_std.values * np.pi)
    assert np.all(np.abs(z) < 2.0), z
    # the chart's budget lines reach an sRGB fit's budget (gonio/fitting/uncertainty/budget.py), none a camera-RGB one
    from gonio.fitting import load_budget

    path = tmp_path / "chart.nc"
    ds.to_netcdf(path, engine="h5netcdf")
    names = [c.name for c in load_budget(path, load_dataset(path)).components]
    assert sum(n.startswith("colour_matrix_") for n in names) == 12
    assert not any(n.startswith("colour_matrix_") for n in
                   (c.name for c in load_budget(path, load_dataset(path, colour_space="camera")).components))


def test_capture_takes_the_chart_when_asked(tmp_path):
    """``[capture] colour_chart = true``: the session journals one chart frame and export fits
    the colour matrix to it (source "chart" in dataset.nc; the settings in session.toml say so)."""
    from gonio.bench.session.journal import Journal, read_session
    from gonio.bench.dataset.export import to_dataset

    settings = default_settings()
    settings["capture"].update(flat_frames=0, colour_chart=True)
    capture_sim(tmp_path / "s", sample=SAMPLE, plan=plans.Plan("one", PLAN.angles[:2]), seed=12,
                progress=False, settings=settings)
    assert read_session(tmp_path / "s")["settings"]["capture"]["colour_chart"] is True
    with Journal(tmp_path / "s" / "journal.sqlite") as j:
        (seconds, file, _), = j.frames("chart").values()
    assert file.endswith("colour_chart.dng") and seconds <= settings["capture"]["probe_s"]
    matrix = json.loads(to_dataset(tmp_path / "s").attrs["colour_matrix"])
    assert matrix["source"] == "chart" and matrix["chart_file"].endswith("colour_chart.dng")


def test_a_bad_colour_chart_setting_is_refused_before_anything_is_written(tmp_path):
    from gonio.core.errors import GonioError

    settings = default_settings()
    settings["capture"].update(flat_frames=0, colour_chart="yes")
    with pytest.raises(GonioError, match="colour_chart"):
        capture_sim(tmp_path / "s", sample=SAMPLE, plan=PLAN, seed=12, progress=False, settings=settings)
    assert not (tmp_path / "s" / "session.toml").exists()
