"""Exchange formats: MERL .binary round trips, RGL .bsdf through Mitsuba, snippets, CSV.

MERL facts used (Matusik et al. 2003, the MERL distribution's BRDFRead.cpp): grid
90 x 90 x 180 over (theta_h, theta_d, phi_d), f_r = stored * (1/1500, 1.15/1500, 1.66/1500),
negative = no data, theta_h index floor(90 sqrt(theta_h / (pi/2))).
"""

import csv
import math
from pathlib import Path

import numpy as np
import pytest

import gonio.models as gm
from gonio.fitting import Measurements, direction, fit
from gonio.fitting.formats import (MERL_SCALE, MERL_SHAPE, MerlBRDF, RGLBRDF, dataset_to_csv, half_diff_angles,
                                   merl_bin_directions, merl_to_measurements, mitsuba_snippet, read_merl,
                                   resample_to_merl, rgl_measurements, write_merl)
from gonio.fitting.formats import _merl_indices

RGL = Path(__file__).resolve().parents[3] / "shared" / "data" / "rgl"
PAPER = RGL / "paper_white_rgb.bsdf"
GLOSSY = {"diffuse_reflectance": [0.5, 0.3, 0.2], "alpha": 0.2, "int_ior": 1.5}


def _random_pairs(rng, n, max_deg=80.0):
    wi = direction(np.radians(rng.uniform(0, max_deg, n)), rng.uniform(-np.pi, np.pi, n))
    wo = direction(np.radians(rng.uniform(0, max_deg, n)), rng.uniform(-np.pi, np.pi, n))
    return wi, wo


@pytest.fixture(scope="module")
def glossy_merl():
    model = gm.get("roughplastic", distribution="ggx")
    return model, resample_to_merl(model, GLOSSY)


def test_index_mapping_bin_centres_and_reciprocity():
    wi, wo = merl_bin_directions()
    th, _, td, pd = half_diff_angles(wi, wo)
    idx = _merl_indices(th, td, pd)
    assert np.array_equal(idx, np.arange(int(np.prod(MERL_SHAPE))))  # each centre looks up its own bin
    th2, _, td2, pd2 = half_diff_angles(wo, wi)
    assert np.array_equal(_merl_indices(th2, td2, pd2), idx)  # swapping wi and wo: same bin
    # square-root mapping of theta_h (BRDFRead.cpp): 22.5 deg is index floor(90 * sqrt(1/4)) = 45
    assert _merl_indices(np.array([math.radians(22.5) + 1e-9]), np.array([0.0]), np.array([0.0]))[0] == 45 * 90 * 180
    # phi_d < 0 folds onto phi_d + pi
    a = _merl_indices(np.array([0.3]), np.array([0.4]), np.array([-0.5]))
    b = _merl_indices(np.array([0.3]), np.array([0.4]), np.array([math.pi - 0.5]))
    assert a[0] == b[0]


def test_write_read_is_bit_exact(tmp_path):
    rng = np.random.default_rng(3)
    table = rng.uniform(0.0, 5.0, (3, *MERL_SHAPE))
    table[:, :, 80:, :] = -1.0  # a block of "no data"
    path = write_merl(tmp_path / "t.binary", table)
    raw = path.read_bytes()
    assert len(raw) == 12 + 3 * 8 * 90 * 90 * 180
    assert tuple(np.frombuffer(raw[:12], dtype="<i4")) == (90, 90, 180)
    merl = read_merl(path)
    assert isinstance(merl, MerlBRDF) and merl.path == str(path)
    expected_raw = table / MERL_SCALE[:, None, None, None]
    expected_raw[expected_raw < 0] = -1.0
    assert np.array_equal(merl.raw, expected_raw)  # stored values bit-exact
    assert np.array_equal(merl.table[merl.raw >= 0],
                          (expected_raw * MERL_SCALE[:, None, None, None])[merl.raw >= 0])
    # read -> write -> read: byte-identical file
    again = write_merl(tmp_path / "u.binary", merl)
    assert again.read_bytes() == raw
    assert not list(tmp_path.glob(".*.tmp"))  # atomic write leaves no temporary file
    # header checks
    bad = tmp_path / "bad.binary"
    bad.write_bytes(np.asarray([90, 90, 360], "<i4").tobytes() + raw[12:])
    with pytest.raises(ValueError, match="dimensions"):
        read_merl(bad)
    bad.write_bytes(raw[:-8])
    with pytest.raises(ValueError, match="bytes"):
        read_merl(bad)


def test_lambertian_table_round_trips(tmp_path):
    value = 0.5 / math.pi
    merl = resample_to_merl(lambda wi, wo: np.full((wi.shape[0], 3), value))
    wi_c, wo_c = merl_bin_directions()
    below = (wi_c[:, 2] <= 0) | (wo_c[:, 2] <= 0)
    assert np.all(merl.raw.reshape(3, -1)[:, below] < 0) and np.all(merl.raw.reshape(3, -1)[:, ~below] >= 0)
    back = read_merl(write_merl(tmp_path / "lambert.binary", merl))
    wi, wo = _random_pairs(np.random.default_rng(1), 5000, 75.0)
    f = back.eval(wi, wo)
    assert np.all(back.has_data(wi, wo))
    np.testing.assert_allclose(f, value, rtol=1e-15)
    # below the horizon: 0; a bin without data: NaN (or the caller's fill value)
    assert np.all(back.eval(wi, wo * [1, 1, -1]) == 0)
    # in-plane theta_h = 59.3, theta_d = 30.55 deg: theta_i = 89.85 deg is above the horizon,
    # but the bin's centre (60.025 + 30.5 deg) is below it, so the bin holds no data
    grazing_wi = direction(np.radians([59.3 + 30.55]), np.array([0.0]))
    grazing_wo = direction(np.radians([59.3 - 30.55]), np.array([0.0]))
    assert not back.has_data(grazing_wi, grazing_wo).any()
    assert np.isnan(back.eval(grazing_wi, grazing_wo)).all()
    assert np.all(back.eval(grazing_wi, grazing_wo, missing=0.0) == 0)


def test_roughplastic_resampled_to_merl_matches_model_away_from_peak(glossy_merl):
    """Nearest-bin discretisation error of a GGX alpha=0.2 roughplastic on the MERL grid.

    Measured (2e5 random pairs, theta_i, theta_o < 70 deg, theta_h > 5 deg): median 0.26 %,
    99th percentile 2.3 %, max 10 % relative (the max at theta_h ~ 18 deg, near-grazing,
    where the GGX tail and Fresnel change fastest across a 1-degree theta_d bin).
    """
    model, merl = glossy_merl
    wi, wo = _random_pairs(np.random.default_rng(2), 20000, 70.0)
    f = merl.eval(wi, wo)
    ref = model.eval(wi, wo, GLOSSY)
    theta_h = half_diff_angles(wi, wo)[0]
    away = np.degrees(theta_h) > 5.0
    rel = (np.abs(f - ref) / ref)[away]
    assert np.median(rel) < 0.005
    assert np.percentile(rel, 99) < 0.03
    assert rel.max() < 0.15
    # at the peak itself the sqrt mapping keeps bins narrow: still within 10 % there
    near = ~away & (np.degrees(np.arccos(np.minimum(wi[:, 2], wo[:, 2]))) < 60)
    assert np.median((np.abs(f - ref) / ref)[near]) < 0.02


def test_merl_file_fits_back_to_its_model(glossy_merl, tmp_path):
    model, merl = glossy_merl
    path = write_merl(tmp_path / "rp.binary", merl)
    meas = merl_to_measurements(path, n=1500, rng=0)
    assert isinstance(meas, Measurements) and meas.n_used == 3 * 1500
    assert meas.attrs["source"] == "MERL"
    result = fit(meas, model, rng=np.random.default_rng(0), n_starts=4, n_local=1)
    values = result.params
    np.testing.assert_allclose(values["alpha"], GLOSSY["alpha"], rtol=0.05)
    np.testing.assert_allclose(values["diffuse_reflectance"], GLOSSY["diffuse_reflectance"], rtol=0.05)
    # explicit directions: below-horizon and no-data pairs are flagged, not fitted
    wi, wo = _random_pairs(np.random.default_rng(5), 10)
    wo[0, 2] = -wo[0, 2]
    m2 = merl_to_measurements(merl, wi, wo)
    assert not m2.use[0].any() and m2.use[1:].all()


@pytest.mark.skipif(not PAPER.is_file(), reason=f"RGL sample data not found at {PAPER}")
def test_rgl_measurements_through_mitsuba_measured_plugin():
    wi, wo = _random_pairs(np.random.default_rng(4), 3000, 80.0)
    meas = rgl_measurements(PAPER, wi, wo)
    assert meas.brdf.shape == (3000, 3) and meas.use.all()
    # paper is close to Lambertian: f_r ~ albedo / pi with albedo ~ 0.83/0.84/0.98 (tech-facts)
    med = np.median(meas.brdf, axis=0) * math.pi
    assert np.all(np.abs(med - [0.83, 0.84, 0.98]) < 0.15), med
    # f_r is not the cosine-weighted value: dividing by cos(theta_i) was done
    rgl = RGLBRDF(PAPER)
    f = rgl.eval(wi[:5], wo[:5])
    np.testing.assert_allclose(f, meas.brdf[:5])
    # reciprocity of the measured data in gonio's convention (same bins either way): a few %
    swap = rgl.eval(wo, wi)
    rel = np.abs(swap - meas.brdf) / np.abs(meas.brdf)
    assert np.median(rel) < 0.05
    # an RGL file resampled to MERL
    merl = resample_to_merl(rgl)
    assert merl.valid.mean() > 0.7


@pytest.mark.parametrize("name,options,params", [
    ("roughplastic", {"distribution": "ggx"}, GLOSSY),
    ("roughconductor", {"distribution": "beckmann"}, {"eta": [0.2, 0.9, 1.1], "k": [3.9, 2.4, 2.2], "alpha": 0.3}),
    ("diffuse", {}, {"reflectance": [0.6, 0.5, 0.4]}),
    ("cooktorrance", {}, {"diffuse_reflectance": 0.3, "specular_reflectance": 0.2, "roughness": 0.3, "f0": 0.04}),
])
def test_mitsuba_snippet_xml_equals_dict(name, options, params):
    import mitsuba as mi

    from gonio.models.mitsuba import eval_cos as eval_bsdf_cos

    xml, d = mitsuba_snippet(name, options, params)
    assert xml.lstrip().startswith("<!--") and '<bsdf type="' in xml and xml.rstrip().endswith("</bsdf>")
    variant = gm.mitsuba_variant()
    with mi.scoped_set_variant(variant):
        scene = mi.load_string(f'<scene version="3.0.0">\n{xml}<shape type="rectangle"><ref id="gonio_fit"/></shape>\n</scene>')
        bsdf_xml = scene.shapes()[0].bsdf()
        wi, wo = _random_pairs(np.random.default_rng(6), 500)
        a = eval_bsdf_cos(bsdf_xml, wi, wo, variant)
        b = eval_bsdf_cos(d, wi, wo, variant)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_allclose(b / wi[:, 2:3], gm.get(name, **options).eval(wi, wo, params), rtol=1e-4, atol=1e-7)


def _write_dataset(path, meas, saturated):
    import xarray as xr

    def ang(w):
        return np.degrees(np.arccos(w[:, 2])), np.degrees(np.arctan2(w[:, 1], w[:, 0]))

    ti, pi_ = ang(meas.wi)
    to, po = ang(meas.wo)
    deg = {"units": "degree"}
    ds = xr.Dataset(
        {"brdf": (("point", "channel"), meas.brdf, {"units": "1/sr"}),
         "brdf_std": (("point", "channel"), meas.brdf_std, {"units": "1/sr"}),
         "saturated": (("point",), saturated)},
        coords={"channel": ["R", "G", "B"], "theta_i": ("point", ti, deg), "phi_i": ("point", pi_, deg),
                "theta_o": ("point", to, deg), "phi_o": ("point", po, deg)},
        attrs={"gonio_version": "test", "seed": 1})
    ds.to_netcdf(path, engine="h5netcdf")


def test_dataset_to_csv(tmp_path):
    rng = np.random.default_rng(7)
    wi, wo = _random_pairs(rng, 20)
    f = gm.get("diffuse").eval(wi, wo, {"reflectance": [0.5, 0.4, 0.3]})
    meas = Measurements(wi, wo, f, 0.01 * f, np.ones(f.shape, bool))
    sat = np.zeros(20, bool)
    sat[3] = True
    _write_dataset(tmp_path / "dataset.nc", meas, sat)
    out = dataset_to_csv(tmp_path / "dataset.nc", tmp_path / "out" / "dataset.csv")
    with open(out, newline="") as fh:
        rows = list(csv.reader(fh))
    header, body = rows[0], rows[1:]
    assert header[:4] == ["theta_i [deg]", "phi_i [deg]", "theta_o [deg]", "phi_o [deg]"]
    assert "brdf_R [1/sr]" in header and "brdf_std_B [1/sr]" in header and "use_G [0/1]" in header
    assert len(body) == 20
    table = np.array([[float(x) for x in r] for r in body])
    np.testing.assert_allclose(table[:, 0], np.degrees(np.arccos(wi[:, 2])), atol=1e-6)
    np.testing.assert_allclose(table[:, 4:7], f, rtol=1e-15)
    assert table[3, header.index("use_R [0/1]")] == 0 and table[4, header.index("use_R [0/1]")] == 1
    # from Measurements directly
    out2 = dataset_to_csv(meas, tmp_path / "m.csv")
    assert out2.read_text().splitlines()[0] == ",".join(header)


def test_dataset_binned_into_merl_keeps_measured_values_and_marks_the_rest(tmp_path):
    """Each measured point lands in its own MERL bin (the bin it indexes to) with its value;
    bins without a point read back as no data."""
    from gonio.fitting import Measurements, direction
    from gonio.fitting.formats import dataset_to_merl, read_merl, write_merl

    rng = np.random.default_rng(4)
    n = 200
    wi = direction(np.radians(rng.uniform(5, 80, n)), rng.uniform(-np.pi, np.pi, n))
    wo = direction(np.radians(rng.uniform(5, 80, n)), rng.uniform(-np.pi, np.pi, n))
    f = rng.uniform(0.05, 2.0, (n, 3))
    meas = Measurements(wi, wo, f, 0.01 * f, np.ones((n, 3), bool))
    merl = read_merl(write_merl(tmp_path / "m.binary", dataset_to_merl(meas)))
    idx = merl.indices(wi, wo)
    unique, first = np.unique(idx, return_index=True)
    assert merl.valid.sum() == unique.size
    alone = np.bincount(idx)[idx[first]] == 1        # bins holding exactly one point
    got = merl.eval(wi[first][alone], wo[first][alone])
    # the file stores float64 of f / scale: the value comes back to rounding
    np.testing.assert_allclose(got, f[first][alone], rtol=1e-12)
