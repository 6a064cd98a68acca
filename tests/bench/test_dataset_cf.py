"""dataset.nc and a fit's NetCDF follow CF-1.8, checked by both CF checkers of PyPI: the IOOS
compliance checker's ``cf:1.8`` suite (compliance-checker, offline: it ships CF standard name
table v93) and, where it runs, the CF Checker of NCAS (cfchecker, ``cfchecks -v 1.8``); each
must report nothing (no error, no warning, no information message). The stated conventions are
the ones the reader uses; every value is linked to its uncertainties (``ancillary_variables``),
and the caller's global attributes (``institution``, ...) are accepted, a misspelt one refused.

cfchecker needs UDUNITS-2 (Debian's libudunits2-0) and, offline, the CF tables given as files:
the standard name table is compliance-checker's copy; the area type and standardized region
tables are given empty (these files use neither an area type nor a region, so their contents
cannot matter). Without UDUNITS-2 its test is skipped, saying so.

The checkers' power is shown on the pre-CF encoding (variable-length string labels, 64-bit
integers, no long_name, labels named like their dimension): they must report it.
"""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

pytest.importorskip("compliance_checker")
# compliance-checker 6.1 deprecates its ioos_sos checker when it loads every checker
pytestmark = pytest.mark.filterwarnings("ignore:The ioos_sos checker is deprecated:DeprecationWarning")

from gonio.bench.dataset.cf import CF_CONVENTIONS
from gonio.fitting import load_dataset
from gonio.core.geometry import directions_deg


def cf_failures(path):
    """(failed results as (weight, name, messages), checker exceptions) of the cf:1.8 suite."""
    from compliance_checker.runner import CheckSuite

    suite = CheckSuite()
    suite.load_all_available_checkers()
    results, errors = suite.run_all(suite.load_dataset(str(path)), ["cf:1.8"], skip_checks=[])["cf:1.8"]
    failed = [(r.weight, r.name, r.msgs) for r in results
              if r.value is False or (isinstance(r.value, tuple) and r.value[0] < r.value[1])]
    return failed, errors


def cfchecks(path, tmp_path):
    """cfchecker's report on ``path`` as its lines (ERROR, WARN, INFO and the counts), offline."""
    import compliance_checker

    tables = Path(compliance_checker.__file__).parent / "data" / "cf-standard-name-table.xml"
    area, region = tmp_path / "area-types.xml", tmp_path / "regions.xml"
    area.write_text('<?xml version="1.0"?><area_type_table><version_number>none</version_number>'
                    "<date>none</date></area_type_table>\n")
    region.write_text('<?xml version="1.0"?><standardized_region_list><version_number>none</version_number>'
                      "<date>none</date></standardized_region_list>\n")
    proc = subprocess.run([sys.executable, "-c", "import sys; from cfchecker.cfchecks import main; sys.exit(main())",
                           "-v", "1.8", "-s", str(tables), "-a", str(area), "-r", str(region), str(path)],
                          capture_output=True, text=True, timeout=120)
    return proc.stdout + proc.stderr


def cfchecker_or_skip():
    pytest.importorskip("cfchecker", reason="cfchecker is not installed (pip install cfchecker)")
    try:
        import cfunits  # noqa: F401  (loads UDUNITS-2)
    except (OSError, FileNotFoundError, ImportError) as exc:
        pytest.skip(f"cfchecker cannot run here: {' '.join(str(exc).split())[:120]} "
                    "(Debian: apt-get install libudunits2-0)")


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    from gonio.bench.plan import plans
    from gonio.bench.samples import load_sample
    from gonio.bench.dataset.export import export
    from gonio.cli.capture import capture_sim

    root = tmp_path_factory.mktemp("cf")
    plan = plans.Plan("cf", plans.with_reciprocal([[30, 0, 40, 180], [45, 0, 20, 0], [20, 0, 50, 90]]))
    capture_sim(root / "session", sample=load_sample(None), plan=plan, seed=3, progress=False)
    return export(root / "session", attrs={"institution": "Physikalisch-Technische Bundesanstalt, Braunschweig",
                                          "summary": "a simulated orange plastic", "history": "captured by hand"})


@pytest.fixture(scope="module")
def fit_nc(dataset, tmp_path_factory):
    """A fit of the dataset, written as NetCDF by `gonio convert --to netcdf`."""
    from gonio.cli.main import main

    root = tmp_path_factory.mktemp("fitnc")
    assert main(["fit", str(dataset), "--model", "roughplastic", "--option", "distribution=ggx",
                 "--out", str(root / "fit.json")]) == 0
    assert main(["convert", str(root / "fit.json"), "--to", "netcdf", "--out", str(root / "fit.nc"),
                 "--attr", "institution=NPL, Teddington"]) == 0
    return root / "fit.nc"


def test_cf_checker_reports_nothing(dataset, fit_nc):
    for path in (dataset, fit_nc):
        failed, errors = cf_failures(path)
        assert errors == {} and failed == [], path


def test_cfchecker_reports_nothing(dataset, fit_nc, tmp_path):
    cfchecker_or_skip()
    for path in (dataset, fit_nc):
        report = cfchecks(path, tmp_path)
        assert "ERRORS detected: 0" in report and "WARNINGS given: 0" in report, report[-3000:]
        assert "INFORMATION messages: 0" in report, report[-3000:]


def _old_encoding(path):
    ds = xr.Dataset({"brdf": (("point", "channel"), np.ones((4, 3)), {"units": "sr^-1"}),
                     "plan_index": ("point", np.arange(4, dtype=np.int64))},
                    coords={"point": np.arange(4), "channel": np.array(["R", "G", "B"], dtype=object),
                            "theta_i": ("point", np.full(4, 30.0), {"units": "degree"})})
    ds.to_netcdf(path, engine="h5netcdf")
    return path


def test_cf_checker_fails_the_old_encoding(tmp_path):
    """The same layout as before CF: the checker is not blind to what was wrong."""
    failed, _ = cf_failures(_old_encoding(tmp_path / "old.nc"))
    names = " ".join(str(f) for f in failed)
    assert failed and "int64" in names and "long_name" in names


def test_cfchecker_fails_the_old_encoding(tmp_path):
    cfchecker_or_skip()
    report = cfchecks(_old_encoding(tmp_path / "old.nc"), tmp_path)
    assert "ERRORS detected: 0" not in report, report[-2000:]


def test_attributes_flags_and_labels(dataset):
    import netCDF4

    with netCDF4.Dataset(dataset) as nc:
        # an ACDD attribute was given: both conventions named
        assert nc.getncattr("Conventions").split() == [CF_CONVENTIONS, "ACDD-1.3"] and CF_CONVENTIONS == "CF-1.8"
        for key in ("title", "institution", "source", "history", "references", "comment", "angle_convention",
                    "colour_space"):
            assert str(nc.getncattr(key)).strip(), key
        assert nc.getncattr("institution") == "Physikalisch-Technische Bundesanstalt, Braunschweig"
        assert nc.getncattr("summary") == "a simulated orange plastic"
        history = nc.getncattr("history").splitlines()          # gonio's export first, the caller's after
        assert "exported from the journal of session session" in history[0] and history[1] == "captured by hand"
        # labels apart from their dimension (CF-1.8 chapter 5), named in the coordinates attribute
        assert "channel" not in nc.variables
        ch = nc.variables["channel_label"]
        assert ch.dtype == np.dtype("S1") and ch.dimensions == ("channel", "string1")
        assert "channel_label" in nc.variables["brdf"].coordinates.split()
        sat = nc.variables["saturated"]
        assert sat.dtype == np.int8 and list(sat.flag_values) == [0, 1]
        assert sat.flag_meanings.split() == ["not_saturated", "saturated"]
        for name in ("point", "reciprocal_partner", "plan_index"):
            assert nc.variables[name].dtype == np.int32, name
        assert all("long_name" in nc.variables[v].ncattrs() for v in nc.variables)


def test_every_value_is_linked_to_its_uncertainty(dataset, fit_nc):
    """``ancillary_variables``: brdf -> brdf_std, u_combined, every u_ component of the budget and
    the saturation flag; the sRGB and XYZ values -> theirs; each named variable exists and each
    uncertainty among them says so in its long_name."""
    import netCDF4

    with netCDF4.Dataset(dataset) as nc:
        links = {name: nc.variables[name].ancillary_variables.split() for name in nc.variables
                 if "ancillary_variables" in nc.variables[name].ncattrs()}
        budget = nc.variables["u_combined"].components.split()
        assert links["brdf"][:2] == ["brdf_std", "u_combined"] and "saturated" in links["brdf"]
        assert {f"u_{c}" for c in budget} <= set(links["brdf"])
        assert links["brdf_srgb"][0] == "brdf_srgb_std" and links["brdf_xyz"][0] == "brdf_xyz_std"
        for value, linked in links.items():
            for name in linked:
                var = nc.variables[name]
                assert var.dimensions[0] == "point", (value, name)
                if "flag_values" not in var.ncattrs() and not name.endswith("_corr"):
                    assert "uncertainty" in var.long_name, (name, var.long_name)
    with netCDF4.Dataset(fit_nc) as nc:
        linked = nc.variables["value"].ancillary_variables.split()
        assert linked[:4] == ["std", "u_stat", "u_combined", "U"] and "at_bound" in linked
        assert all("uncertainty" in nc.variables[n].long_name for n in linked[:4])
        assert nc.getncattr("institution") == "NPL, Teddington" and nc.getncattr("Conventions") == "CF-1.8"
        labels = [str(v) for v in nc.variables["parameter_label"][:]]      # chars with _Encoding: text
        assert labels[:2] == ["diffuse_reflectance[R]", "diffuse_reflectance[G]"]


def test_global_attributes_are_checked(tmp_path, capsys):
    from gonio.bench.dataset.cf import check_global_attributes
    from gonio.cli.main import main

    assert check_global_attributes({"institution": "NPL", "creator_name": "A. Tester"}) == {
        "institution": "NPL", "creator_name": "A. Tester"}
    for bad, says in (({"instituion": "NPL"}, "did you mean institution?"), ({"title": "a\x1b[2Jb"}, "control"),
                      ({"comment": ""}, "1 to 4000"), ({"title": 7}, "give text")):
        with pytest.raises(ValueError, match=says):
            check_global_attributes(bad)
    # through the command line: one line, exit 2, before anything is read
    assert main(["export", str(tmp_path), "--attr", "instituion=NPL"]) == 2
    err = capsys.readouterr().err
    assert "did you mean institution?" in err and len(err.strip().splitlines()) == 1


def test_stated_conventions_are_the_readers(dataset):
    """The phi convention written in the file, applied to the stored angles, gives the reader's
    directions; the flag decodes to the reader's mask; the labels read back as text."""
    meas = load_dataset(dataset)
    with xr.open_dataset(dataset, engine="h5netcdf") as ds:
        assert "w = (sin theta cos phi, sin theta sin phi, cos theta)" in ds.phi_i.attrs["comment"]
        np.testing.assert_allclose(directions_deg(ds.theta_i.values, ds.phi_i.values), meas.wi, atol=1e-12)
        np.testing.assert_allclose(directions_deg(ds.theta_o.values, ds.phi_o.values), meas.wo, atol=1e-12)
        assert list(ds.channel_label.values) == ["R", "G", "B"] == list(meas.channels)
        assert list(ds.brdf.set_xindex("channel_label").sel(channel_label="G").values) == list(ds.brdf[:, 1].values)
        assert np.array_equal(~ds.saturated.values.astype(bool), meas.use.all(axis=1))


@pytest.fixture(scope="module")
def spectral_dataset(tmp_path_factory):
    """dataset.nc of a simulated spectral capture (issue 39): two geometries x 450, 650 nm."""
    from gonio.bench.dataset.export import export
    from gonio.bench.plan.plans import plan_from_dict
    from gonio.bench.samples import load_sample
    from gonio.bench.settings import default_settings
    from gonio.cli.capture import capture_sim

    root = tmp_path_factory.mktemp("cf-spectral")
    settings = {**default_settings(), "monochromator": {}}
    settings["capture"] = {**settings["capture"], "flat_frames": 16}      # the PRNU's precision is not tested here
    plan = plan_from_dict({"name": "cf-spectral", "points": [[30, 0, 30, 180], [30, 0, 50, 180]],
                           "spectral": {"from_nm": 450, "to_nm": 650, "step_nm": 200}})
    capture_sim(root / "session", sample=load_sample(Path(__file__).parents[2] / "gonio/cli/samples/red-lacquer.toml"),
                plan=plan, seed=3, settings=settings, progress=False)
    return export(root / "session")


def test_a_spectral_dataset_is_cf_with_a_wavelength_coordinate(spectral_dataset, tmp_path):
    with xr.open_dataset(spectral_dataset, engine="h5netcdf") as ds:
        assert ds["brdf"].dims == ("point", "wavelength")
        assert ds["wavelength"].values.tolist() == [450.0, 650.0]
        assert ds["wavelength"].attrs["standard_name"] == "radiation_wavelength"     # CF standard name table v93
        assert ds["wavelength"].attrs["units"] == "nm"
    failed, errors = cf_failures(spectral_dataset)
    assert errors == {} and failed == []
    try:
        cfchecker_or_skip()
    except pytest.skip.Exception:
        return
    report = cfchecks(spectral_dataset, tmp_path)
    assert "ERRORS detected: 0" in report and "WARNINGS given: 0" in report, report[-3000:]
    assert "INFORMATION messages: 0" in report, report[-3000:]
