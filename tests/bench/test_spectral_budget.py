"""A spectral dataset.nc carries the RGB export's uncertainty budget on (point, wavelength)
(issue 39; gonio/bench/dataset/spectral.py `spectral_budget`, docs/interfaces.md 5.1).

Each row (a geometry at one wavelength) has three Bayer channels combined by inverse variance,
f = sum_c a_c f_c with a_c = sigma_c^-2 / sum sigma^-2; the budget of the rows
(`budget_variables`, as the RGB export) maps through it: a shared, signed line as sum_c a_c u_c,
an independent one as sqrt(sum_c a_c^2 u_c^2) (JCGM 100:2008 5.1.2, 5.2.2), so the type-A lines
add up to brdf_std exactly; the angle shifts are per geometry. The fast tests use journal rows
made here; the long ones capture on the simulator, check CF and fit.
"""

import math
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from gonio.bench import calibrate
from gonio.bench.dataset.budget import budget_variables
from gonio.bench.dataset.spectral import combine, spectral_budget
from gonio.bench.settings import default_settings

GEOMETRIES = [(10.0, 60.0), (26.0, 64.0), (42.0, 70.0)]         # (yaw, lamp) of three in-plane points
SIGMA = np.array([1.2e-3, 0.8e-3, 1.5e-3])                       # relative 1-sigma of the three sites


def rows(order="fastest", skip=()):
    """Journal rows of 3 geometries x 2 wavelengths, each with region statistics and exposures;
    ``order``: wavelength the fastest axis (a geometry's two wavelengths in a row) or the
    slowest (the geometry tour at each wavelength: the stage revisits each geometry);
    ``skip``: (geometry, wavelength) cells not measured."""
    cells = [(g, w) for g in range(3) for w in range(2)] if order == "fastest" else \
        [(g, w) for w in range(2) for g in range(3)]
    out = []
    for t, (g, w) in enumerate(cells):
        if (g, w) in skip:
            continue
        yaw, lamp = GEOMETRIES[g]
        ang = calibrate.calibrated_angles({}, [yaw, 0.0, 0.0, lamp])[0]
        ratio = (80.0 + 20 * g + 5 * w) / 150.0
        d = {"wavelength_nm": 450.0 + 200 * w, "exposures": [{"seconds": 40.0, "power": 1.0}]}
        for name, mean in (("sample", 150.0 * ratio), ("reference", 150.0)):
            d.update({f"{name}_mean": [mean] * 3, f"{name}_se_model": list(0.4 * SIGMA * mean),
                      f"{name}_se": list(0.5 * SIGMA * mean), f"{name}_n": [200] * 3})
        f = ratio * 0.99 / math.pi
        out.append({"idx": 2 * g + w, "detail": d, "yaw": yaw, "tilt": 0.0, "azimuth": 0.0, "lamp": lamp,
                    "finished": float(t), "theta_i": ang[0], "phi_i": ang[1], "theta_o": ang[2], "phi_o": ang[3],
                    "brdf": [f * (1 + 1e-4 * c) for c in range(3)], "brdf_std": list(f * SIGMA), "saturated": 0})
    return out


def cells_and_brdf(rs):
    cell = np.array([[r["idx"] // 2, r["idx"] % 2] for r in rs], int)
    brdf = np.full((3, 2), np.nan)
    std = np.full((3, 2), np.nan)
    for (i, j), r in zip(cell, rs):
        brdf[i, j], std[i, j] = combine(r["brdf"], r["brdf_std"])
    return cell, brdf, std


def weights(rs):
    w = 1.0 / np.array([r["brdf_std"] for r in rs]) ** 2
    return w / w.sum(axis=1, keepdims=True)


def test_type_a_lines_add_up_to_brdf_std():
    rs = rows()
    cell, brdf, std = cells_and_brdf(rs)
    v = spectral_budget(rs, default_settings(), cell, brdf)
    var = v["u_shot_read"][1] ** 2 + v["u_fixed_pattern"][1] ** 2
    if "u_dark_frame" in v:
        var = var + (v["u_dark_frame"][1] ** 2).sum(axis=2)
    np.testing.assert_allclose(np.sqrt(var), std, rtol=1e-12)
    for name in ("u_shot_read", "u_fixed_pattern", "u_linearity", "u_stray_light", "u_reference_certificate",
                 "u_combined"):
        assert v[name][0] == ("point", "wavelength"), name
    assert v["u_shot_read"][2]["gum_type"] == "A" and v["u_shot_read"][2]["correlation"] == "none"
    # u_combined is the root sum of squares of every line (JCGM 100 5.1.2)
    total = sum((np.asarray(v[n][1]) ** 2).reshape(3, 2, -1).sum(axis=2) for n in v
                if n.startswith("u_") and n != "u_combined" and not n.endswith("_group"))
    np.testing.assert_allclose(v["u_combined"][1], np.sqrt(total), rtol=1e-12)
    assert set(v["u_combined"][2]["components"].split()) == {n[2:] for n in v if n.startswith("u_")} - {"combined"}


def test_shared_lines_map_by_the_channel_weights():
    """A shared line moves each site's value by u_c for +1 sigma of its input: the combined value
    moves by sum_c a_c u_c (signed), not by the root sum of squares."""
    rs = rows()
    cell, brdf, _ = cells_and_brdf(rs)
    settings = default_settings()
    v = spectral_budget(rs, settings, cell, brdf)
    per_row = budget_variables(rs, settings, np.array([r["brdf"] for r in rs]), np.array([r["brdf_std"] for r in rs]))
    a = weights(rs)
    for name in ("u_linearity", "u_stray_light"):
        want = np.full((3, 2), np.nan)
        want[cell[:, 0], cell[:, 1]] = (a * per_row[name][1]).sum(axis=1)
        np.testing.assert_allclose(v[name][1], want, rtol=1e-12)
        assert np.any(v[name][1] != 0) and v[name][2]["correlation"] == "full" and v[name][2]["gum_type"] == "B"
        assert v[name][2]["source"] == per_row[name][2]["source"]
    want = np.full((3, 2), np.nan)
    want[cell[:, 0], cell[:, 1]] = np.sqrt(((a * per_row["u_fixed_pattern"][1]) ** 2).sum(axis=1))
    np.testing.assert_allclose(v["u_fixed_pattern"][1], want, rtol=1e-12)


def test_the_certificate_is_per_wavelength_and_says_its_correlation():
    rs = rows()
    cell, brdf, _ = cells_and_brdf(rs)
    s = default_settings()
    rel = float(s["reference"]["rel_std"])
    assert rel > 0
    v = spectral_budget(rs, s, cell, brdf)["u_reference_certificate"]
    np.testing.assert_allclose(v[1], brdf * rel, rtol=1e-12)
    assert v[2]["correlation"] == "full" and "every wavelength" in v[2]["source"]
    s2 = {**s, "reference": {**s["reference"], "rel_std": [0.004, 0.007], "rel_std_correlation": "channel"}}
    v = spectral_budget(rs, s2, cell, brdf)["u_reference_certificate"]
    np.testing.assert_allclose(v[1], brdf * [0.004, 0.007], rtol=1e-12)
    assert v[2]["correlation"] == "channel" and "per wavelength" in v[2]["source"]
    # hostile: a certificate for three colour channels on two wavelengths
    bad = {**s, "reference": {**s["reference"], "rel_std": [0.004, 0.005, 0.006]}}
    with pytest.raises(ValueError, match="one number or one per wavelength"):
        spectral_budget(rs, bad, cell, brdf)
    none = {**s, "reference": {**s["reference"], "rel_std": 0.0}}
    assert "u_reference_certificate" not in spectral_budget(rs, none, cell, brdf)


@pytest.mark.parametrize("order", ["fastest", "slowest"])
def test_angle_shifts_are_per_geometry_or_per_visit(order):
    """A geometry's angle shifts and move labels are its first-measured row's, as the RGB export
    computes them from the rows' stage poses and move history, except where the tour revisited
    every geometry (wavelength the slowest axis): there each (point, wavelength) cell keeps its
    own row's shifts and labels, one move error per visit, and the shared inputs' shifts as that
    visit moved them (its lost-motion signs: 57 of the lacquer's 120 cells differ from their first
    visit's). With the first visit's move errors standing for all, the red lacquer's budget check
    rejected its fit (553 on 114 dof, seed 0; 96 with them)."""
    rs = rows(order)
    cell, brdf, _ = cells_and_brdf(rs)
    settings = default_settings()
    v = spectral_budget(rs, settings, cell, brdf)
    per_row = budget_variables(rs, settings, np.array([r["brdf"] for r in rs]), np.array([r["brdf_std"] for r in rs]))
    first = [min((k for k in range(len(rs)) if cell[k, 0] == g), key=lambda k: rs[k]["finished"]) for g in range(3)]
    for name in ("angle_shift_shared", "irradiance_shift_shared", "angle_shift_independent",
                 "angle_shift_independent_group"):
        dims, value, attrs = v[name]
        row_dims, row_value = per_row[name][0], np.asarray(per_row[name][1])
        if order == "slowest":
            assert dims == (row_dims[0], "point", "wavelength") + tuple(row_dims[2:]), name
            assert np.shape(value)[1:3] == (3, 2) and "own move errors" in attrs.get("source", "own move errors")
            np.testing.assert_array_equal(np.asarray(value)[:, cell[:, 0], cell[:, 1]], row_value)
        else:
            assert dims == row_dims and np.shape(value)[1] == 3, name
            np.testing.assert_array_equal(value, row_value[:, first])
    shared = v["angle_shift_shared"][1]
    assert np.all(np.isfinite(shared)) and np.any(shared != 0)
    assert ("do not depend on the wavelength" if order == "fastest" else "own move errors") in \
        v["angle_shift_shared"][2]["source"]
    labels = np.asarray(per_row["angle_shift_independent_group"][1])
    if order == "slowest":       # the tour revisits every geometry: a new move at each wavelength
        assert np.any(labels[:, :3] != labels[:, 3:])


def test_a_cell_never_measured_has_no_uncertainty_but_its_geometry_keeps_its_angles():
    rs = rows(skip={(1, 1)})
    cell, brdf, _ = cells_and_brdf(rs)
    v = spectral_budget(rs, default_settings(), cell, brdf)
    assert np.isnan(brdf[1, 1]) and np.isnan(v["u_combined"][1][1, 1]) and np.isnan(v["u_linearity"][1][1, 1])
    assert np.all(np.isfinite(np.delete(v["u_combined"][1].ravel(), 3)))
    assert np.all(np.isfinite(v["angle_shift_shared"][1]))


def test_a_row_without_a_usable_site_has_no_value_and_no_uncertainty():
    rs = rows()
    rs[1]["brdf_std"] = [float("nan")] * 3          # geometry 0 at 650 nm: every site's sigma lost
    cell, brdf, _ = cells_and_brdf(rs)
    v = spectral_budget(rs, default_settings(), cell, brdf)
    assert np.isnan(brdf[0, 1])
    for name in ("u_shot_read", "u_linearity", "u_reference_certificate", "u_combined"):
        assert np.isnan(v[name][1][0, 1]) and np.all(np.isfinite(np.delete(v[name][1].ravel(), 1))), name


def test_load_budget_refuses_a_line_on_neither_channel_nor_wavelength(tmp_path):
    from types import SimpleNamespace

    from gonio.fitting.uncertainty.budget import load_budget

    path = tmp_path / "odd.nc"
    xr.Dataset({"u_odd": (("point", "band"), np.ones((2, 2)), {"gum_type": "B", "correlation": "full"})}).to_netcdf(
        path, engine="h5netcdf")
    meas = SimpleNamespace(brdf=np.ones((2, 2)), use=np.ones((2, 2), bool), n_points=2, n_channels=2,
                           attrs={"colour": {"space": "spectral", "variable": "brdf"}})
    with pytest.raises(ValueError, match="u_odd has dimensions"):
        load_budget(path, meas)


def test_per_visit_move_errors_are_read_and_made_one_error_per_visit(tmp_path):
    """A file whose per-move angle shifts are per (point, wavelength) (the spectral export where
    the stage revisited its geometries): load_budget reads them with their labels, and each axis's
    line is the model's slope times that cell's own shift, grouped by the cell's own move label;
    labels that do not match the shifts' cells are refused in one line."""
    from types import SimpleNamespace

    import gonio.models as gm
    from gonio.core.channels import spectral
    from gonio.fitting.measurements import Measurements
    from gonio.fitting.uncertainty.budget import angle_components, load_budget, per_point, slope

    rng = np.random.default_rng(4)
    n, m = 3, 4
    shifts = rng.normal(0, 0.01, (4, n, m, 4))
    labels = rng.integers(0, 5, (4, n, m))
    path = tmp_path / "visits.nc"
    xr.Dataset({"angle_shift_independent": (("angle_input", "point", "wavelength", "angle"), shifts),
                "angle_shift_independent_group": (("angle_input", "point", "wavelength"), labels)}).to_netcdf(
        path, engine="h5netcdf")
    ti = np.radians([20.0, 35.0, 50.0])
    wi = np.stack([np.sin(ti), np.zeros(n), np.cos(ti)], 1)
    wo = np.stack([-np.sin(ti + 0.1), np.zeros(n), np.cos(ti + 0.1)], 1)
    wl = [450.0, 500.0, 550.0, 600.0]
    meas = Measurements(wi, wo, np.ones((n, m)), np.full((n, m), 0.01), True, {"wavelengths_nm": wl},
                        spectral(wl).names)
    budget = load_budget(path, meas)
    assert budget.angles["independent"].shape == (4, n, m, 4) and budget.angles["independent_groups"].shape == (4, n, m)
    # the second-order term and the adequacy refit take each geometry's mean over its measured visits
    shared = np.zeros((2, n, m, 4))
    shared[:, :, :2] = rng.normal(0, 0.01, (2, n, 2, 4))           # wavelengths 3 and 4 not measured
    mean = per_point({"shared": shared, "shared_irradiance": shared[..., 0]})
    np.testing.assert_allclose(mean["shared"], shared[:, :, :2].mean(axis=2), rtol=1e-12)
    np.testing.assert_allclose(mean["shared_irradiance"], shared[:, :, :2, 0].mean(axis=2), rtol=1e-12)
    model = gm.get("roughplastic", distribution="ggx")
    params = {"diffuse_reflectance": np.full(m, 0.3), "alpha": 0.1, "int_ior": 1.5}
    comps = angle_components(SimpleNamespace(model=model, params=params), meas, budget.angles)
    S = slope(model, params, wi, wo)
    for k, c in enumerate(comps):
        assert c.correlation == "group" and c.name == f"angle_repeatability_{('yaw', 'tilt', 'azimuth', 'lamp')[k]}"
        np.testing.assert_allclose(c.value, np.einsum("nca,nca->nc", S, shifts[k]), rtol=1e-12)
        np.testing.assert_array_equal(c.groups, labels[k])
    # the shared inputs per visit stay one error each across every cell ('full'): as 'none' (each
    # value its own error) their lines over-covered the lacquer's spectral fit (T 22-105 on 114 dof)
    line = angle_components(SimpleNamespace(model=model, params=params), meas, {"shared": shared})
    assert [(c.name, c.correlation) for c in line] == [("angle_shared", "full")]
    np.testing.assert_allclose(line[0].value, np.einsum("nca,knca->knc", S, shared), rtol=1e-12)
    xr.Dataset({"angle_shift_independent": (("angle_input", "point", "wavelength", "angle"), shifts),
                "angle_shift_independent_group": (("angle_input", "point"), labels[:, :, 0])}).to_netcdf(
        tmp_path / "bad.nc", engine="h5netcdf")
    with pytest.raises(ValueError, match="must be integer labels") as err:
        load_budget(tmp_path / "bad.nc", meas)
    assert "\n" not in str(err.value)


# ----------------------------------------------------------------------------- on the simulator
LACQUER = Path(__file__).parents[2] / "gonio/cli/samples/red-lacquer.toml"


def _capture(root, plan, seed):
    from gonio.bench.dataset.export import export
    from gonio.bench.samples import load_sample
    from gonio.bench.session.simulated import capture_sim

    settings = {**default_settings(), "monochromator": {}, "errors": {"preset": "typical"}}
    capture_sim(root, sample=load_sample(LACQUER), plan=plan, seed=seed, settings=settings, progress=False)
    return export(root)


@pytest.mark.long        # a capture, an export and both CF checks: about 12 s
def test_a_captured_spectral_dataset_has_the_budget_and_is_cf(tmp_path):
    pytest.importorskip("compliance_checker")
    from compliance_checker.runner import CheckSuite

    from gonio.bench.plan.plans import plan_from_dict
    from gonio.fitting import load_dataset
    from gonio.fitting.uncertainty.budget import load_budget

    plan = plan_from_dict({"name": "sb", "points": [[30, 0, 30, 180], [30, 0, 50, 180], [45, 0, 20, 0]],
                           "spectral": {"from_nm": 450, "to_nm": 650, "step_nm": 200}})
    path = _capture(tmp_path / "s", plan, seed=3)
    with xr.open_dataset(path, engine="h5netcdf") as ds:
        for name in ("u_shot_read", "u_fixed_pattern", "u_linearity", "u_reference_certificate", "u_combined"):
            assert ds[name].dims == ("point", "wavelength"), name
        assert ds["angle_shift_shared"].dims == ("angle_input", "point", "angle")
        type_a = ds["u_shot_read"] ** 2 + ds["u_fixed_pattern"] ** 2
        if "u_dark_frame" in ds:
            type_a = type_a + (ds["u_dark_frame"] ** 2).sum("dark_input")
        np.testing.assert_allclose(np.sqrt(type_a.values), ds["brdf_std"].values, rtol=1e-12)
        assert "u_reference_certificate" in ds["brdf"].attrs["ancillary_variables"]
    suite = CheckSuite()
    suite.load_all_available_checkers()
    results, errors = suite.run_all(suite.load_dataset(str(path)), ["cf:1.8"], skip_checks=[])["cf:1.8"]
    failed = [(r.name, r.msgs) for r in results
              if r.value is False or (isinstance(r.value, tuple) and r.value[0] < r.value[1])]
    assert errors == {} and failed == []
    meas = load_dataset(path)
    budget = load_budget(path, meas)
    names = {c.name for c in budget.components}
    assert {"reference_certificate", "linearity", "shot_read", "fixed_pattern"} <= names
    assert budget.angles["shared"].shape[1:] == (3, 4)


@pytest.mark.long        # 210 points and a 7-wavelength fit: about 20 s
def test_a_spectral_fit_of_the_lacquer_under_typical_errors_states_the_angles():
    """The red lacquer (GGX alpha 0.12) through the spectral preset on the typical simulator:
    the fit's budget has the angle and certificate lines, alpha's u_c is at least its
    statistical u, and the truth lies within U = 2 u_c (a ~5 % false alarm for a coverage of
    95 %; before, chi2/dof 1490 against brdf_std alone and the Birge ratio 39 made the interval).
    Measured, seeds 0-3 (the apertures declared, 0dbfc20): z = (alpha - 0.12) / u_c = -0.42,
    0.30, 0.22, -1.06, the budget's chi-square p 0.25, 0.50, 0.09, 0.50 (201 dof); before the
    file's budget (brdf_std and scale_rel_std, Birge-inflated) z = 0.35, 2.18, 6.23, -0.49."""
    import tempfile

    from gonio.bench.dataset.reader import open_fit_input
    from gonio.bench.plan.plans import load_plan
    from gonio.bench.samples import load_sample
    from gonio.cli.fit import fit_dataset

    sample = load_sample(LACQUER)
    with tempfile.TemporaryDirectory() as tmp:       # as `gonio fit dataset.nc`: the file's budget
        given = open_fit_input(_capture(Path(tmp) / "s", load_plan("spectral"), seed=0), seed=0)
        _, doc, _ = fit_dataset(given, model=sample["model"], options=sample["options"], seed=0)
    lines = doc["uncertainty"]["components"]
    assert "reference_certificate" in lines and any(n.startswith("angle") for n in doc["uncertainty"]["parameters"]
                                                    ["alpha"]["budget"])
    alpha = doc["parameters"]["alpha"]
    u = doc["uncertainty"]["parameters"]["alpha"]
    assert u["u_combined"] >= u["u_stat"]
    assert max(u["budget"], key=u["budget"].get).startswith("angle")     # the angles dominate alpha's u_c
    assert abs(alpha["value"] - 0.12) <= alpha["U"], alpha
