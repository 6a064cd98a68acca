"""The per-point uncertainty budget in dataset.nc (issue 15; gonio/bench/dataset/budget.py, docs/interfaces.md 5.1)
and how gonio fit reads it back (gonio/fitting/uncertainty/budget.py): components, their attributes, bad input."""

import json

import numpy as np
import pytest
import xarray as xr

from gonio.bench.dataset.budget import Component, budget_variables
from gonio.fitting import load_budget, load_dataset

N = 8


def rows(rng, se_ratio):
    """Journal rows' region statistics: se = se_ratio x se_model (fixed pattern when > 1)."""
    out = []
    for _ in range(N):
        d = {}
        for k in ("sample", "reference"):
            mean = 100 + 50 * rng.random(3)
            se_model = 0.1 * rng.random(3) + 0.05
            d.update({f"{k}_mean": mean.tolist(), f"{k}_se_model": se_model.tolist(),
                      f"{k}_se": (se_model * se_ratio).tolist()})
        out.append({"detail": d})
    return out


def brdf_of(rs):
    ratio = np.array([np.array(r["detail"]["sample_mean"]) / r["detail"]["reference_mean"] for r in rs])
    rel = np.sqrt(sum((np.array([r["detail"][f"{k}_se"] for r in rs]) /
                       np.array([r["detail"][f"{k}_mean"] for r in rs])) ** 2 for k in ("sample", "reference")))
    f = ratio * 0.99 / np.pi
    return f, f * rel


@pytest.mark.parametrize("se_ratio", [0.7, 1.0, 1.6])
def test_type_a_components_add_up_to_brdf_std(se_ratio):
    rs = rows(np.random.default_rng(1), se_ratio)
    f, s = brdf_of(rs)
    v = budget_variables(rs, {"reference": {"reflectance": 0.99, "rel_std": 0.005}}, f, s)
    shot, fixed = v["u_shot_read"][1], v["u_fixed_pattern"][1]
    np.testing.assert_allclose(shot ** 2 + fixed ** 2, s ** 2, rtol=1e-12)
    # the empirical scatter beyond the noise model is the fixed pattern: (1.6^2 - 1) / 1.6^2 of it
    np.testing.assert_allclose(fixed ** 2, s ** 2 * max(0.0, 1 - 1 / se_ratio ** 2), rtol=1e-9, atol=1e-30)
    assert v["u_shot_read"][2]["gum_type"] == "A" and v["u_shot_read"][2]["correlation"] == "none"
    cert = v["u_reference_certificate"]
    np.testing.assert_allclose(cert[1], f * 0.005, rtol=1e-15)            # signed: brdf x rel_std
    assert cert[2]["gum_type"] == "B" and cert[2]["correlation"] == "full" and "certificate" in cert[2]["source"]
    comb = v["u_combined"]
    np.testing.assert_allclose(comb[1], np.sqrt(s ** 2 + (f * 0.005) ** 2), rtol=1e-12)
    assert comb[2]["components"] == "fixed_pattern reference_certificate shot_read"


def test_certificate_per_channel_and_none():
    rs = rows(np.random.default_rng(2), 1.0)
    f, s = brdf_of(rs)
    v = budget_variables(rs, {"reference": {"rel_std": [0.004, 0.005, 0.006], "rel_std_correlation": "channel"}}, f, s)
    assert v["u_reference_certificate"][2]["correlation"] == "channel"
    np.testing.assert_allclose(v["u_reference_certificate"][1], f * [0.004, 0.005, 0.006])
    assert "u_reference_certificate" not in budget_variables(rs, {"reference": {"rel_std": 0.0}}, f, s)


def test_extra_components_and_groups():
    rs = rows(np.random.default_rng(3), 1.0)
    f, s = brdf_of(rs)
    g = np.arange(N) // 4
    extra = [Component("stray_light", 0.01 * f, "B", "group", "stray-light floor", groups=g)]
    v = budget_variables(rs, {"reference": {}}, f, s, extra=extra)
    assert v["u_stray_light"][2]["correlation"] == "group:u_stray_light_group"
    assert list(v["u_stray_light_group"][1]) == list(g)


@pytest.mark.parametrize("bad, needle", [
    (Component("Bad Name", None, "B", "full", ""), "lower-case"),
    (Component("x", None, "C", "full", ""), "gum_type"),
    (Component("x", None, "B", "sideways", ""), "correlation"),
    (Component("x", np.zeros((N, 2)), "B", "full", ""), "shape"),
    (Component("x", np.full((N, 3), np.nan), "B", "full", ""), "NaN"),
    (Component("x", None, "B", "group", ""), "groups"),
    (Component("shot_read", None, "A", "none", ""), "twice"),
])
def test_malformed_components_are_refused(bad, needle):
    rs = rows(np.random.default_rng(4), 1.0)
    f, s = brdf_of(rs)
    if bad.value is None:
        bad.value = np.zeros_like(f)
    with pytest.raises(ValueError, match=needle):
        budget_variables(rs, {"reference": {}}, f, s, extra=[bad])


def write(path, *, extra=None, scale=0.005):
    rng = np.random.default_rng(0)
    f = 0.1 + rng.random((N, 3))
    s = 0.01 * f
    deg = {"units": "degree"}
    coords = {"point": np.arange(N), "channel": ["R", "G", "B"],
              "theta_i": ("point", np.linspace(10, 60, N), deg), "phi_i": ("point", np.zeros(N), deg),
              "theta_o": ("point", np.linspace(20, 70, N), deg), "phi_o": ("point", np.full(N, 180.0), deg)}
    data = {"brdf": (("point", "channel"), f, {"units": "sr^-1"}),
            "brdf_std": (("point", "channel"), s, {"units": "sr^-1"}), **(extra or {})}
    xr.Dataset(data, coords=coords, attrs={"scale_rel_std": scale}).to_netcdf(path, engine="h5netcdf")
    return path


def test_load_budget_reads_the_variables_back(tmp_path):
    rs = rows(np.random.default_rng(5), 1.2)
    f, s = brdf_of(rs)
    g = (np.arange(N) % 2)
    v = budget_variables(rs, {"reference": {"rel_std": 0.005}}, f, s,
                         extra=[Component("angle", 0.001 * f, "B", "group", "zero offsets", groups=g)])
    path = write(tmp_path / "d.nc", extra=v)
    meas = load_dataset(path)
    b = load_budget(path, meas)
    by = {c.name: c for c in b.components}
    assert set(by) == {"shot_read", "fixed_pattern", "reference_certificate", "angle", "combined"} - {"combined"}
    assert by["angle"].correlation == "group" and by["angle"].groups.shape == (N, 3)
    assert by["shot_read"].statistical and not by["reference_certificate"].statistical
    # no u_ variables: brdf_std and the scale_rel_std attribute
    b0 = load_budget(write(tmp_path / "e.nc"), meas)
    assert [c.name for c in b0.components] == ["statistical", "reference_certificate"]


class Proc:
    def __init__(self, returncode, stdout, stderr):
        self.returncode, self.stdout, self.stderr = returncode, stdout, stderr


def gonio_fit(path, out, capsys, monkeypatch):
    """``gonio fit PATH --model diffuse --out OUT`` in this process (an 80-column terminal)."""
    from gonio.cli.main import main

    monkeypatch.setenv("COLUMNS", "80")
    rc = main(["fit", str(path), "--model", "diffuse", "--out", str(out)])
    got = capsys.readouterr()
    return Proc(rc, got.out, got.err)


@pytest.mark.parametrize("attrs, needle", [
    ({"gum_type": "C", "correlation": "full"}, "gum_type 'C'"),
    ({"gum_type": "B", "correlation": "sideways"}, "correlation 'sideways'"),
    ({"gum_type": "B", "correlation": "group:nowhere"}, "'nowhere', which is not in the dataset"),
])
def test_gonio_fit_refuses_a_malformed_budget_in_one_line(tmp_path, attrs, needle, capsys, monkeypatch):
    path = write(tmp_path / "d.nc", extra={"u_x": (("point", "channel"), np.full((N, 3), 1e-3), attrs)})
    proc = gonio_fit(path, tmp_path / "fit.json", capsys, monkeypatch)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0] and "u_x" in lines[0], proc.stderr
    assert not (tmp_path / "fit.json").exists()


def test_gonio_fit_reports_the_combined_uncertainty(tmp_path, capsys, monkeypatch):
    path = write(tmp_path / "d.nc")
    proc = gonio_fit(path, tmp_path / "fit.json", capsys, monkeypatch)
    assert proc.returncode == 0, proc.stderr
    doc = json.loads((tmp_path / "fit.json").read_text())
    u = doc["uncertainty"]
    assert u["k"] == 2.0 and u["budget_source"] == "scale_rel_std attribute"
    for c in "RGB":
        item = u["parameters"][f"reflectance[{c}]"]
        rho = doc["parameters"][f"reflectance[{c}]"]["value"]
        assert item["u_combined"] >= rho * 0.005 and item["U"] == pytest.approx(2 * item["u_combined"])
    assert "u_c" in proc.stdout and "(k=2)" in proc.stdout and "largest term" in proc.stdout
    # every line fits 80 columns except one that names a file: a path is a value, never cut
    # (under xdist pytest's tmp_path alone is over 60 characters)
    assert max(len(line) for line in proc.stdout.splitlines() if str(tmp_path) not in line) <= 80, proc.stdout


CAL = {"alignment": {"yaw_zero_deg": 0.05, "tilt_zero_deg": -0.03, "holder_tilt_x_deg": 0.1, "holder_tilt_y_deg": 0.0,
                     "cov_deg2": (np.diag([4e-4, 4e-4, 1e-4, 1e-4])).tolist(), "repeat_deg": 0.01,
                     "backlash_yaw_deg": 0.02, "backlash_tilt_deg": 0.02, "lamp_zero_u_deg": 0.02, "wedge_u_deg": 0.01},
       "reference": {"reflectance": 0.99, "rel_std": 0.005, "factor_theta_i": [0.0, 80.0], "factor_theta_o": [0.0, 80.0],
                     "factor": [[1.0, 0.98], [0.98, 0.95]], "u_factor": [[0.002, 0.004], [0.004, 0.008]]},
       "linearity": {"gamma": 0.003, "u_gamma": 0.0005}, "stray": {"floor": 1e-4}}


def calibrated_rows(rng):
    rs = rows(rng, 1.0)
    for k, r in enumerate(rs):
        r.update(theta_i=10.0 + 5 * k, theta_o=20.0 + 4 * k, yaw=10.0 + k, tilt=5.0, azimuth=0.0, lamp=50.0 + k)
        r["detail"]["exposures"] = [{"seconds": 0.01, "power": 1e-3}, {"seconds": 0.04, "power": 1e-3}]
    return rs


def test_a_calibrated_session_carries_its_calibrations_lines():
    """reference factor, linearity and stray light as brdf x their relative uncertainty (fully
    correlated), and the angles' shared and per-point shifts whose outer products are
    calibrate.angle_uncertainty's covariances."""
    from gonio.bench.calibrate import angle_uncertainty

    rs = calibrated_rows(np.random.default_rng(6))
    f, s = brdf_of(rs)
    v = budget_variables(rs, CAL, f, s)
    for name in ("reference_factor", "linearity", "stray_light"):
        assert v[f"u_{name}"][2]["gum_type"] == "B" and v[f"u_{name}"][2]["correlation"] == "full"
        assert np.all(np.isfinite(v[f"u_{name}"][1]))
    assert np.all(v["u_reference_factor"][1] >= 0)
    # linearity and the stray floor's bound are signed (one gamma, one floor moves values darker
    # than the reference up, brighter ones down); their magnitudes are calibrate's u_*_rel
    import math

    from gonio.bench.dataset.budget import _levels
    from gonio.bench.calibrate import u_linearity_rel, u_stray_rel
    from gonio.bench.measure.point import ReferenceModel

    cos_i = np.cos(np.radians([r["theta_i"] for r in rs]))[:, None]
    rho = ReferenceModel(CAL["reference"]).rho[None]
    np.testing.assert_allclose(np.abs(v["u_stray_light"][1]),
                               np.abs(f) * u_stray_rel(np.abs(f) * cos_i, rho / math.pi * cos_i, 1e-4), rtol=1e-9)

    lev_s, lev_r = _levels(rs, CAL, "sample"), _levels(rs, CAL, "reference")
    np.testing.assert_allclose(np.abs(v["u_linearity"][1]),
                               f * u_linearity_rel(lev_s, lev_r, CAL["linearity"]["u_gamma"]), rtol=1e-12)
    assert np.all(np.sign(v["u_linearity"][1]) == np.sign(f * (lev_r - lev_s)))
    # the factor's relative uncertainty at (10, 20) deg, bilinear over 0..80 deg (s = 1/8, t = 1/4):
    # u = 0.0028125 over the factor 0.9921875
    assert v["u_reference_factor"][1][0, 0] / f[0, 0] == pytest.approx(0.0028125 / 0.9921875, rel=1e-9)
    from gonio.bench.dataset.budget import move_history

    stage = np.array([[r[k] for k in ("yaw", "tilt", "azimuth", "lamp")] for r in rs])
    labels, last = move_history(rs)
    u = angle_uncertainty(CAL, stage, last_dir=last)
    # each axis's per-move error, shared by the points taken without moving the axis
    np.testing.assert_array_equal(v["angle_shift_independent_group"][1], labels.T)
    assert v["angle_shift_independent"][2]["correlation"].startswith("group:")
    shared = v["angle_shift_shared"][1]                       # (input, point, angle)
    np.testing.assert_allclose(np.einsum("kna,knb->nab", shared, shared), u["cov_shared"], atol=1e-12)
    indep = v["angle_shift_independent"][1]
    np.testing.assert_allclose(np.einsum("kna,knb->nab", indep, indep), u["cov_independent"], atol=1e-12)
    # with the shared inputs, the sample's own foreshortening: the wedge's inputs alone (here
    # degenerate with the holder tilt's, u 0.01 deg both: the modes mix them), d ln E =
    # -tan(theta_i) d theta_i, so its variance over the modes is tan^2 times the wedge's part of
    # theta_i's variance
    from gonio.bench.measure.calpoint import _jacobian, _p

    irr = v["irradiance_shift_shared"]
    assert irr[0] == ("angle_input", "point") and irr[1].shape == shared.shape[:2]
    Jw = _jacobian(stage, _p(CAL), ["wedge0", "wedge1"])[:, 0, :]           # d theta_i / d wedge
    ti = np.radians(u["angles"][:, 0])
    expected = np.tan(ti) ** 2 * np.sum(np.radians(Jw * 0.01) ** 2, axis=1)
    np.testing.assert_allclose(np.sum(irr[1] ** 2, axis=0), expected, rtol=1e-9)
    assert np.all(expected > 0)


def test_move_history_follows_the_order_the_points_were_taken():
    """Labels count each axis's moves in the order of ``finished`` (not the plan's); a point the
    axis was not moved to shares the previous one's label; last_dir is the last move's sign."""
    from gonio.bench.dataset.budget import move_history

    pos = [(10.0, 0.0, 0.0, 40.0), (20.0, 0.0, 0.0, 50.0), (20.0, 5.0, 0.0, 30.0), (15.0, 5.0, 0.0, 30.0)]
    finished = [3.0, 1.0, 2.0, 4.0]            # taken in the order 1, 2, 0, 3
    rows = [dict(zip(("yaw", "tilt", "azimuth", "lamp"), p), finished=t) for p, t in zip(pos, finished)]
    labels, last = move_history(rows)
    np.testing.assert_array_equal(labels[[1, 2, 0, 3]], [[0, 0, 0, 0], [0, 1, 0, 1], [1, 2, 0, 2], [2, 3, 0, 3]])
    np.testing.assert_array_equal(last[[1, 2, 0, 3]], [[0, 0, 0, 0], [0, 1, 0, -1], [-1, -1, 0, 1], [1, 1, 0, -1]])


# ---------------------------------------------------------------- the dark frames (issue 34)
def dark_rows(settings, rate=10.0):
    """Journal rows of dim points (zero signal: the darks matter most) whose regions the plan's
    geometry gives, their se_model the merge's noise model at dark level ``rate`` DN/s:
    points 0 and 1 one pose and one exposure (2.048 s: one dark frame, the same region), point 2
    another pose, the same exposure (regions that overlap in part), point 3 the first pose at
    1.024 s (another dark frame), point 4 bright."""
    from gonio.bench.measure.hdr import NoiseModel, dark_sensitivity
    from gonio.bench.plan.kinematics import inverse
    from gonio.bench.plan.markers import roi_masks_fast

    cam = settings["camera"]
    noise = NoiseModel(cam["gain_e_per_dn"], cam["read_noise_e"])
    n_raw = np.array([1.0, 2.0, 1.0])
    geo = [(30, 0, 50, 180), (30, 0, 50, 180), (30, 0, 60, 180), (30, 0, 50, 180), (30, 0, 30, 180)]
    times = [(2.048,), (2.048,), (2.048,), (1.024,), (0.008,)]
    level = [(5.0, 1e5)] * 4 + [(5e7, 5e7)]                # merged radiance (sample, reference), DN per s per W
    out = []
    for (ti, pi_, to, po), ts, (xs, x_ref) in zip(geo, times, level):
        stage = inverse(ti, pi_, to, po)
        sm, rm = roi_masks_fast(stage, settings)
        d = {"exposures": [{"seconds": t, "power": 0.01} for t in ts]}
        for k, x, m in (("sample", xs, sm), ("reference", x_ref, rm)):
            kk = np.array([t * 0.01 for t in ts])
            var, _ = dark_sensitivity(np.full(3, x), kk, rate * np.array(ts)[:, None], noise, n_raw)
            n = float(m.sum())
            d.update({f"{k}_mean": [x] * 3, f"{k}_n": [n] * 3, f"{k}_se_model": np.sqrt(var / n).tolist(),
                      f"{k}_se": np.sqrt(var / n).tolist()})
        out.append({"detail": d, "theta_i": ti, "phi_i": pi_, "theta_o": to, "phi_o": po,
                    **dict(zip(("yaw", "tilt", "azimuth", "lamp"), map(float, stage)))})
    return out


def test_the_dark_frames_are_a_shared_line():
    """One dark frame a rung is subtracted by every point that uses the rung: its noise (at zero
    signal half a value's variance) moves points whose regions overlap together. The budget
    carries it as ``dark_frame`` (type A, one fully shared input per correlated mode), taken out
    of shot_read so that the type-A lines still add up to brdf_std; the darks' level, which the
    journal does not hold, is found from the regions' se_model. Without it a glossy gold
    capture's chi2 scattered 1.8 times as widely as its budget said (T/dof sd 0.151 against
    0.083 over 24 seeded captures; 0.089 with it, 39 captures)."""
    from gonio.bench.settings import default_settings

    settings = default_settings()
    rs = dark_rows(settings)
    f, s = brdf_of(rs)
    v = budget_variables(rs, settings, f, s)
    dims, dark, attrs = v["u_dark_frame"]
    assert dims == ("point", "channel", "dark_input") and attrs["gum_type"] == "A" and attrs["correlation"] == "full"
    shot, fixed = v["u_shot_read"][1], v["u_fixed_pattern"][1]
    d2 = (dark ** 2).sum(axis=-1)
    np.testing.assert_allclose(shot ** 2 + fixed ** 2 + d2, s ** 2, rtol=1e-12)
    # at zero signal with one exposure the dark is half the sample region's variance (the
    # reference's share of these values is 1e-9 of it)
    np.testing.assert_allclose(d2[:4] / s[:4] ** 2, 0.5, rtol=0.02)
    assert np.all(d2[4] < 1e-3 * s[4] ** 2)                  # a bright point: its own shot noise
    dim = dark[:4]
    corr = np.einsum("ack,bck->abc", dim, dim) / np.sqrt(np.einsum("ack,ack->ac", dim, dim)[:, None]
                                                         * np.einsum("bck,bck->bc", dim, dim)[None])
    assert np.all(corr[0, 1] > 0.99)                         # one region, one dark frame
    assert np.all((0.05 < corr[0, 2]) & (corr[0, 2] < 0.95))   # overlapping regions
    assert np.all(np.abs(corr[0, 3]) < 1e-6)                 # another rung: another dark frame
    assert "u_dark_frame" not in budget_variables(rows(np.random.default_rng(1), 1.0), settings,
                                                  *brdf_of(rows(np.random.default_rng(1), 1.0)))


def test_load_budget_reads_a_line_of_several_shared_inputs(tmp_path):
    """A ``u_`` line with an input dimension (``dark_frame``): (K, N, C), fully shared each; and
    a fit takes it through the colour matrix as any shared line."""
    rng = np.random.default_rng(6)
    K = 4
    lines = 0.001 * rng.standard_normal((N, 3, K))
    extra = {"u_dark_frame": (("point", "channel", "dark_input"), lines,
                              {"units": "sr^-1", "gum_type": "A", "correlation": "full", "source": "dark frames"})}
    path = write(tmp_path / "d.nc", extra=extra)
    meas = load_dataset(path)
    by = {c.name: c for c in load_budget(path, meas).components}
    assert by["dark_frame"].value.shape == (K, N, 3) and by["dark_frame"].correlation == "full"
    np.testing.assert_allclose(by["dark_frame"].value, np.moveaxis(lines, -1, 0))
    bad = {"u_dark_frame": (("point", "channel", "dark_input"), lines,
                            {"units": "sr^-1", "gum_type": "A", "correlation": "none", "source": "dark frames"})}
    with pytest.raises(ValueError, match="fully shared line with several inputs"):
        load_budget(write(tmp_path / "e.nc", extra=bad), meas)
