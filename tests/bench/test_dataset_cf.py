"""dataset.nc follows CF-1.8, checked by the IOOS compliance checker's ``cf:1.8`` suite
(compliance-checker, offline: it ships CF standard name table v93), and its stated
conventions are the ones the reader uses.

The checker's power is shown on the pre-CF encoding (variable-length string labels, 64-bit
integers, no long_name): it must report failures there. Cross-check done by hand (not in the
suite, it needs Debian's libudunits2-0 and the CF tables from the network): cfchecker 4.1.0
``cfchecks -v 1.8`` on the same export reported 0 errors (warnings: a char variable named
like its dimension "possible incorrect declaration of a coordinate variable").
"""

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


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    from gonio.bench.plan import plans
    from gonio.bench.samples import load_sample
    from gonio.bench.dataset.export import export
    from gonio.cli.capture import capture_sim

    root = tmp_path_factory.mktemp("cf")
    plan = plans.Plan("cf", plans.with_reciprocal([[30, 0, 40, 180], [45, 0, 20, 0], [20, 0, 50, 90]]))
    capture_sim(root / "session", sample=load_sample(None), plan=plan, seed=3, progress=False)
    return export(root / "session")


def test_cf_checker_reports_nothing(dataset):
    failed, errors = cf_failures(dataset)
    assert errors == {} and failed == []


def test_cf_checker_fails_the_old_encoding(tmp_path):
    """The same layout as before CF: the checker is not blind to what was wrong."""
    ds = xr.Dataset({"brdf": (("point", "channel"), np.ones((4, 3)), {"units": "sr^-1"}),
                     "plan_index": ("point", np.arange(4, dtype=np.int64))},
                    coords={"point": np.arange(4), "channel": np.array(["R", "G", "B"], dtype=object),
                            "theta_i": ("point", np.full(4, 30.0), {"units": "degree"})})
    ds.to_netcdf(tmp_path / "old.nc", engine="h5netcdf")
    failed, _ = cf_failures(tmp_path / "old.nc")
    names = " ".join(str(f) for f in failed)
    assert failed and "int64" in names and "long_name" in names


def test_attributes_flags_and_labels(dataset):
    import netCDF4

    with netCDF4.Dataset(dataset) as nc:
        assert nc.getncattr("Conventions") == CF_CONVENTIONS == "CF-1.8"
        for key in ("title", "institution", "source", "history", "references", "angle_convention", "colour_space"):
            assert str(nc.getncattr(key)).strip(), key
        ch = nc.variables["channel"]
        assert ch.dtype == np.dtype("S1") and ch.dimensions == ("channel", "string1")
        sat = nc.variables["saturated"]
        assert sat.dtype == np.int8 and list(sat.flag_values) == [0, 1]
        assert sat.flag_meanings.split() == ["not_saturated", "saturated"]
        for name in ("point", "reciprocal_partner", "plan_index"):
            assert nc.variables[name].dtype == np.int32, name
        assert all("long_name" in nc.variables[v].ncattrs() for v in nc.variables)


def test_stated_conventions_are_the_readers(dataset):
    """The phi convention written in the file, applied to the stored angles, gives the reader's
    directions; the flag decodes to the reader's mask; the labels read back as text."""
    meas = load_dataset(dataset)
    with xr.open_dataset(dataset, engine="h5netcdf") as ds:
        assert "w = (sin theta cos phi, sin theta sin phi, cos theta)" in ds.phi_i.attrs["comment"]
        np.testing.assert_allclose(directions_deg(ds.theta_i.values, ds.phi_i.values), meas.wi, atol=1e-12)
        np.testing.assert_allclose(directions_deg(ds.theta_o.values, ds.phi_o.values), meas.wo, atol=1e-12)
        assert list(ds.channel.values) == ["R", "G", "B"] == list(meas.channels)
        assert np.array_equal(~ds.saturated.values.astype(bool), meas.use.all(axis=1))
