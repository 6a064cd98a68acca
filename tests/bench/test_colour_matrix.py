"""Camera RGB -> sRGB (gonio/bench/measure/colour_matrix.py): from the DNG, from a ColorChecker capture, with
its uncertainty; the colour-space choice of load_dataset and gonio fit, and its refusals."""

import numpy as np
import pytest
import xarray as xr

from gonio.cli.main import main
from gonio.bench.measure.colour_matrix import (CHART_BORDER, CHART_BOX, CHART_GRID, chart_reference_srgb,
                                       colour_matrix_components, colour_matrix_uncertainty, convert,
                                       matrix_from_chart_dng, matrix_from_dng)
from gonio.core.errors import GonioError
from gonio.fitting import DataError, load_dataset
from gonio.sim import Instrument, SensorModel
from gonio.sim.physics import colour as simcolour
from gonio.sim.devices.camera_port import CameraPort
from gonio.sim.physics.sensor import encode_dng

RHO = np.array([0.6, 0.1, 0.05])


@pytest.fixture(scope="module")
def chart(tmp_path_factory):
    folder = tmp_path_factory.mktemp("chart")
    inst = Instrument(seed=5)
    inst.lamp.switch(inst.clock.now(), True)
    port = CameraPort(inst)
    assert port.handle(f"CHART 0.01 {folder / 'chart.dng'}")[0].startswith("OK ")
    assert port.handle(f"CHART 1.0 {folder / 'bright.dng'}")[0].startswith("OK ")
    return folder


def test_bench_and_simulator_declare_one_chart_slot():
    assert (CHART_BOX, CHART_GRID, CHART_BORDER) == (simcolour.CHART_BOX, simcolour.CHART_GRID, simcolour.CHART_BORDER)


def test_chart_fit_covers_the_truth_within_its_uncertainty(chart):
    """The chart's spectra (Ohta) are real surfaces; the virtual sample's are Mallett spectra, so
    a 3x3 fitted to the chart misses the sample's red by ~0.08 (metamerism): the prediction part
    of the uncertainty must cover it. Measured: z = 0.92, 0.07, 0.97 (R, G, B); bound k = 2."""
    m = matrix_from_chart_dng(chart / "chart.dng")
    assert m.source == "chart" and np.allclose(m.srgb_from_cam.sum(1), 1.0)
    f_cam = simcolour.camera_colour().balanced @ RHO
    u = colour_matrix_uncertainty(f_cam[None], m)[0]
    z = (m.srgb_from_cam @ f_cam - RHO) / u
    assert np.all(np.abs(z) < 2.0), z
    # the prediction part (metamerism) is larger than the estimate's own for the red channel
    parts = colour_matrix_components(f_cam[None], m)
    assert len(parts) == 12
    estimate = np.sqrt(sum(p[0] ** 2 for p in parts[:9]))
    assert parts[9][0, 0] > estimate[0]
    # the chart's reference values: white patch near neutral, dark skin reddish
    ref = chart_reference_srgb()
    assert ref[18].min() > 0.8 and ref[0, 0] > ref[0, 2]


def test_saturated_chart_and_bad_matrices_are_refused(chart, tmp_path):
    with pytest.raises(GonioError, match="saturated"):
        matrix_from_chart_dng(chart / "bright.dng")
    s = SensorModel(seed=0, camera="identity")
    raw = s.expose(np.full((s.height, s.width, 3), 0.1), 0.01, 0.01, np.random.default_rng(0))
    m = matrix_from_dng(data=encode_dng(raw, black=s.black, white=s.white, colour=s.colour))
    np.testing.assert_allclose(m.srgb_from_cam, np.eye(3), atol=1e-6)        # the identity camera
    bad = bytearray(encode_dng(raw, black=s.black, white=s.white, colour=s.colour))
    tag = (50778).to_bytes(2, "little") + (3).to_bytes(2, "little") + (1).to_bytes(4, "little")
    at = bytes(bad).index(tag) + len(tag)
    bad[at:at + 2] = (17).to_bytes(2, "little")                   # CalibrationIlluminant1 = Standard A
    with pytest.raises(GonioError, match="not D65"):
        matrix_from_dng(data=bytes(bad))


def test_channel_covariance_of_the_conversion():
    m = matrix_from_dng(data=_dng(SensorModel(seed=0)))
    f, sd, cov = convert(np.full((2, 3), 0.1), np.full((2, 3), 0.001), m, "srgb")
    s = m.srgb_from_cam
    np.testing.assert_allclose(cov[0], s @ np.diag([1e-6] * 3) @ s.T, rtol=1e-12)
    np.testing.assert_allclose(sd[0], np.sqrt(np.diag(cov[0])), rtol=1e-12)
    with pytest.raises(ValueError, match="unknown colour space"):
        convert(f, sd, m, "lab")


def _dng(s):
    raw = s.expose(np.full((s.height, s.width, 3), 0.1), 0.01, 0.01, np.random.default_rng(0))
    return encode_dng(raw, black=s.black, white=s.white, colour=s.colour)


def _dataset(path, declared=None, srgb=False):
    n = 4
    brdf = {"units": "sr^-1", **({"colour_space": declared} if declared else {})}
    data = {"brdf": (("point", "channel"), np.full((n, 3), 0.1), brdf),
            "brdf_std": (("point", "channel"), np.full((n, 3), 0.001), brdf)}
    if srgb:
        data["brdf_srgb"] = (("point", "channel"), np.full((n, 3), 0.2), {"colour_space": "srgb"})
        data["brdf_srgb_std"] = (("point", "channel"), np.full((n, 3), 0.002), {"colour_space": "srgb"})
    coords = {"channel": ["R", "G", "B"], **{k: ("point", np.full(n, 20.0), {"units": "degree"})
                                             for k in ("theta_i", "phi_i", "theta_o", "phi_o")}}
    xr.Dataset(data, coords=coords).to_netcdf(path, engine="h5netcdf")
    return path


def test_load_dataset_picks_and_states_the_colour_space(tmp_path):
    both = _dataset(tmp_path / "both.nc", "camera", srgb=True)
    assert load_dataset(both).brdf[0, 0] == 0.2                             # srgb by default
    cam = load_dataset(both, colour_space="camera")
    assert cam.brdf[0, 0] == 0.1 and cam.attrs["colour"]["space"] == "camera"
    with pytest.raises(DataError, match="--colour-space camera"):
        load_dataset(_dataset(tmp_path / "cam.nc", "camera"))                # camera RGB only
    with pytest.raises(DataError, match="unknown colour space"):
        load_dataset(both, colour_space="lab")
    plain = load_dataset(_dataset(tmp_path / "plain.nc"))                   # declares nothing
    assert "declares no colour space" in plain.attrs["colour"]["note"]


def test_gonio_fit_refuses_an_unknown_colour_space_in_one_line(tmp_path, capsys):
    path = _dataset(tmp_path / "d.nc", "camera", srgb=True)
    assert main(["fit", str(path), "--out", str(tmp_path / "f.json"), "--colour-space", "lab"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--colour-space" in err[0] and "srgb" in err[0]
    assert not (tmp_path / "f.json").exists()
    assert main(["fit", str(_dataset(tmp_path / "c.nc", "camera")), "--out", str(tmp_path / "f.json")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--colour-space camera" in err[0]
    assert not (tmp_path / "f.json").exists()


def test_opencv_mcc_finds_the_chart_in_a_large_frame(tmp_path):
    """In a 720 x 480 frame OpenCV's cv2.mcc detector finds the chart; its patch means agree with
    the slot geometry's to 0.3 % measured (bound 1 %), and the fit records how it was found."""
    import copy

    from gonio.bench.measure.colour_matrix import chart_patches, find_chart
    from gonio.bench.drivers.camera import decode_raw
    from gonio.sim import DEFAULT_SETTINGS

    settings = copy.deepcopy(DEFAULT_SETTINGS)
    settings["camera"]["width"], settings["camera"]["height"] = 720, 480
    inst = Instrument(settings, seed=5)
    inst.lamp.switch(inst.clock.now(), True)
    assert CameraPort(inst).handle(f"CHART 0.01 {tmp_path / 'c.dng'}")[0].startswith("OK ")
    planes = decode_raw(tmp_path / "c.dng").signal
    patches, how = find_chart(planes)
    assert how == "mcc"
    np.testing.assert_allclose(patches, chart_patches(planes), rtol=0.01)
    assert matrix_from_chart_dng(tmp_path / "c.dng").found_by == "mcc"
    assert find_chart(planes[:, :100, :150])[1] == "slot"            # too small for the detector
