"""Spectral capture (issue 39): the monochromator as an optional declared port, opened,
identified and recorded only where a capture is given one; a capture without it is unchanged."""

from __future__ import annotations

import tomllib

import numpy as np
import pytest

from gonio.bench.plan.plans import Plan
from gonio.bench.samples import DEMO_SAMPLE, check_sample
from gonio.bench.session.simulated import capture_sim
from gonio.bench.settings import default_settings
from gonio.core.devices import OPTIONAL_PORTS, REQUIRED_PORTS, port_spec

TWO = [[30, 0, 30, 180], [30, 0, 50, 180]]


def test_the_monochromator_is_an_optional_declared_port():
    assert REQUIRED_PORTS == ("zaber", "meter", "camera")
    assert OPTIONAL_PORTS == ("monochromator",)
    assert port_spec("monochromator").table == "monochromator"


@pytest.mark.parametrize("with_mono", [True, False])
def test_a_capture_records_the_monochromator_only_where_it_has_one(tmp_path, with_mono):
    st = default_settings()
    st["capture"] = {**st["capture"], "flat_frames": 16}
    if with_mono:
        st["monochromator"] = {}
    s = capture_sim(tmp_path / "s", sample=check_sample(DEMO_SAMPLE), plan=Plan("two", TWO), seed=3, settings=st,
                    progress=False)
    assert s.complete and s.n_done == 2
    doc = tomllib.loads((tmp_path / "s" / "session.toml").read_text())
    if with_mono:
        # the twin's INFO? answer (gonio/sim/devices/monochromator.py)
        assert doc["devices"]["monochromator"] == "CORNERSTONE 260 VER 2.31 TWIN"
        assert doc["ports"]["monochromator"].endswith("/monochromator")
    else:
        assert "monochromator" not in doc["devices"] and "monochromator" not in doc["ports"]


# -- a spectral capture on the simulator ---------------------------------------------------------

LACQUER = "gonio/cli/samples/red-lacquer.toml"
SPECTRAL = {"name": "short", "points": [[30, 0, 30, 180], [30, 0, 50, 180]],
            "spectral": {"from_nm": 450, "to_nm": 650, "step_nm": 200}}


@pytest.fixture(scope="module")
def spectral_session(tmp_path_factory):
    """Two geometries x 450 and 650 nm (two gratings) of the red lacquer (instant clock, seed 4)."""
    from gonio.bench.plan.plans import plan_from_dict
    from gonio.bench.samples import load_sample

    folder = tmp_path_factory.mktemp("spectral") / "s"
    st = {**default_settings(), "monochromator": {}}
    st["capture"] = {**st["capture"], "flat_frames": 16}        # 512 took 1.6 s of the 2.1 s
    sample = load_sample(LACQUER)
    summary = capture_sim(folder, sample=sample, plan=plan_from_dict(SPECTRAL), seed=4, settings=st, progress=False)
    return folder, summary, sample, st


def test_each_point_is_measured_at_its_wavelength(spectral_session):
    import gonio.sim as gs
    from gonio.bench.plan.kinematics import directions
    from gonio.bench.session.journal import Journal

    folder, summary, sample, st = spectral_session
    assert summary.complete and summary.n_done == 4
    assert summary.spectral.startswith("wavelength the ")         # the capture's summary says the axis
    doc = tomllib.loads((folder / "session.toml").read_text())
    assert doc["order"]["wavelength_axis"] in ("fastest", "slowest")
    inst = gs.Instrument(st, sample=sample)
    with Journal(folder / "journal.sqlite") as j:
        rows = j.points()
        p_refs = [e for e in j.events() if e[1] == "p_ref_nm"]
    assert len(p_refs) == 2                   # the monitor's reference once per wavelength
    seen = set()
    for r in rows:
        nm = doc["plan"]["wavelength_nm"][r["idx"]]
        assert r["detail"]["wavelength_nm"] == pytest.approx(nm, abs=0.01)     # WAVE? read back, 2 decimals
        seen.add(nm)
        truth = inst.truth_at(nm).eval(directions(r["theta_i"], r["phi_i"])[None],
                                       directions(r["theta_o"], r["phi_o"])[None])[0]
        # the lacquer's spectrum at nm, through the roughplastic model: the capture within 4 sigma + 0.3 %
        np.testing.assert_allclose(r["brdf"], truth, atol=4 * max(r["brdf_std"]) + 3e-3 * truth[0])
    assert seen == {450.0, 650.0}
    by_nm = {doc["plan"]["wavelength_nm"][r["idx"]]: r["brdf"][1] for r in rows if r["theta_o"] == 50}
    assert by_nm[650.0] > 3 * by_nm[450.0]   # red: its albedo 0.05 at 450 nm, 0.63 at 650 nm


def test_the_dataset_has_a_wavelength_dimension_that_follows_the_spectrum(spectral_session):
    import xarray as xr

    import gonio.sim as gs
    from gonio.bench.dataset.export import export
    from gonio.fitting import load_dataset

    folder, _, sample, st = spectral_session
    path = export(folder)
    with xr.open_dataset(path, engine="h5netcdf") as ds:
        assert ds["brdf"].dims == ("point", "wavelength") and ds.sizes["point"] == 2
        assert ds["wavelength"].values.tolist() == [450.0, 650.0]
        assert dict(ds["wavelength"].attrs, long_name=None) == {"standard_name": "radiation_wavelength",
                                                                "units": "nm", "long_name": None}
        np.testing.assert_allclose(ds["wavelength_read"].values, [[450.0, 650.0]] * 2, atol=0.01)
        f, sd = ds["brdf"].values, ds["brdf_std"].values
        assert not ds["saturated"].values.any()
    meas = load_dataset(path)
    assert meas.n_channels == 2 and meas.attrs["wavelengths_nm"] == [450.0, 650.0]
    assert meas.channels == ("450nm", "650nm")
    inst = gs.Instrument(st, sample=sample)
    for j, nm in enumerate((450.0, 650.0)):
        truth = inst.truth_at(nm).eval(meas.wi, meas.wo)[:, 0]
        # one f_r per (point, wavelength), the Bayer channels combined: within 4 sigma + 0.3 % of the truth
        assert np.all(np.abs(f[:, j] - truth) <= 4 * sd[:, j] + 3e-3 * truth), (nm, f[:, j], truth)
    # the lacquer's diffuse albedo (red-lacquer.toml): 0.05 at 450 nm, 0.63 at 650 nm; at theta_o 50 deg
    # (off the specular peak) f_r follows it
    off = int(np.argmax(np.degrees(np.arccos(meas.wo[:, 2]))))
    assert f[off, 1] > 3 * f[off, 0]


def test_gonio_devices_identifies_the_monochromator():
    import gonio.sim as gs
    from gonio.bench.drivers.probe import probe_ports

    inst = gs.Instrument({"monochromator": {}}, seed=1).register("spectral-devices")
    try:
        lines = probe_ports({"monochromator": inst.url("monochromator")}, {}, 115200)
    finally:
        inst.unregister()
    # the twin at power-on: INFO? "CORNERSTONE 260 VER 2.31 TWIN", grating 1, the drive at 0 nm (zero order)
    assert lines == ["monochromator sim://spectral-devices/monochromator: CORNERSTONE 260 VER 2.31 TWIN, grating 1, "
                     "0 nm"]


def test_the_report_lists_the_monochromator(spectral_session):
    from gonio.bench.report.inputs import Folder
    from gonio.bench.report.meta import _devices

    folder = spectral_session[0]
    rows = {d["role"]: d["text"] for d in _devices(Folder(folder), folder / "journal.sqlite")}
    assert rows["monochromator (INFO?)"] == "CORNERSTONE 260 VER 2.31 TWIN"


def test_a_spectral_run_closes_the_shutter_it_opened(tmp_path):
    """The simulator lights the sample through the monochromator only while its shutter is open:
    a white-light capture after a spectral one on the same instrument must see the LED again."""
    import gonio.sim as gs
    from gonio.bench.plan.plans import plan_from_dict
    from gonio.bench.session.capture import capture

    st = {**default_settings(), "monochromator": {}}
    st["capture"] = {**st["capture"], "flat_frames": 16}
    inst = gs.Instrument(st, sample=check_sample(DEMO_SAMPLE), seed=2).register("spectral-shutter")
    try:
        plan = plan_from_dict({"name": "one", "points": [[30, 0, 30, 180]],
                               "spectral": {"from_nm": 500, "to_nm": 600, "step_nm": 100}})
        s = capture(tmp_path / "s", plan, st, inst.url("zaber"), inst.url("meter"), inst.url("camera"),
                    progress=False, sleep=inst.clock.advance, monochromator=inst.url("monochromator"))
        assert s.complete
        assert inst.monochromator.drive.shutter_open is False and inst.wavelength_nm is None
    finally:
        inst.unregister()


def test_a_simulated_spectral_capture_gets_the_twin_by_default(tmp_path):
    from gonio.bench.plan.plans import plan_from_dict

    st = default_settings()
    st["capture"] = {**st["capture"], "flat_frames": 16}
    assert "monochromator" not in st
    plan = plan_from_dict({"name": "one", "points": [[30, 0, 30, 180]],
                           "spectral": {"from_nm": 500, "to_nm": 600, "step_nm": 100}})
    s = capture_sim(tmp_path / "s", sample=check_sample(DEMO_SAMPLE), plan=plan, seed=1, settings=st, progress=False)
    assert s.complete and s.n_done == 2
    doc = tomllib.loads((tmp_path / "s" / "session.toml").read_text())
    assert doc["settings"]["monochromator"] == {} and doc["devices"]["monochromator"].startswith("CORNERSTONE")


def test_a_spectral_fits_truth_comes_from_the_samples_spectrum():
    from gonio.bench.report.fitdoc import truth_by_name
    from gonio.bench.samples import load_sample

    sample = load_sample(LACQUER)
    got = truth_by_name(sample, ["diffuse_reflectance[600nm]", "diffuse_reflectance[612.5nm]", "alpha"])
    # red-lacquer.toml: 0.42 at 600 nm, 0.58 at 625 nm (linear between), alpha 0.12
    assert got == {"diffuse_reflectance[600nm]": pytest.approx(0.42), "diffuse_reflectance[612.5nm]": pytest.approx(0.50),
                   "alpha": pytest.approx(0.12)}


def test_sim_serve_hints_name_the_monochromator_port():
    from gonio.cli.capture import serve_hints

    paths = {"zaber": "/r/zaber", "meter": "/r/meter", "camera": "/r/camera", "monochromator": "/r/monochromator"}
    devices = {k: f"/dev/pts/{i}" for i, k in enumerate(paths)}
    lines = serve_hints(paths, devices)
    assert "monochromator /r/monochromator -> /dev/pts/3" in lines
    assert ("  gonio capture --port /r/zaber --meter-port /r/meter --camera /r/camera --monochromator-port "
            "/r/monochromator --out my-session") in lines
    assert not any("monochromator" in ln for ln in serve_hints({k: paths[k] for k in list(paths)[:3]}, devices))


def test_gonio_export_counts_a_spectral_sessions_points(spectral_session, capsys):
    from gonio.cli.main import main

    folder = spectral_session[0]
    assert main(["export", str(folder)]) in (0, None)
    out = capsys.readouterr().out
    # 2 geometries x 2 wavelengths, all measured: not PARTIAL (it said "2 of 4 planned points")
    assert out.strip() == f"wrote {folder / 'dataset.nc'} (4 points)", out


@pytest.mark.parametrize("spectral_table, says", [
    ("from_nm = 1300\nto_nm = 1500\nstep_nm = 100\n", "1500 nm is outside the monochromator's ranges"),
    ("from_nm = 400\nto_nm = 700\nstep_nm = 0\n", "step_nm = 0 must be positive"),
    ("from_nm = nan\nto_nm = 700\nstep_nm = 100\n", "not a finite number"),
])
def test_bad_wavelengths_are_one_line_exit_2_before_anything_is_written(tmp_path, capsys, spectral_table, says):
    from gonio.cli.main import main

    (tmp_path / "settings.toml").write_text("[monochromator]\ngratings = [[1, 200, 650], [2, 650, 1400]]\n")
    (tmp_path / "plan.toml").write_text('name = "bad"\n[spectral]\n' + spectral_table
                                        + '[[scan]]\nkind = "points"\npoints = [[30, 0, 30, 180]]\n')
    rc = main(["capture", "--sim", "--settings", str(tmp_path / "settings.toml"), "--plan", str(tmp_path / "plan.toml"),
               "--out", str(tmp_path / "s"), "--quiet"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and says in err and "\n" not in err, err
    assert not (tmp_path / "s").exists()


def test_a_spectral_session_resumes_only_with_a_monochromator(spectral_session, tmp_path, monkeypatch):
    import shutil

    import gonio.bench.session.capture as cap
    from gonio.core.errors import SessionError

    copy = tmp_path / "s"
    shutil.copytree(spectral_session[0], copy)
    real = cap._integrity.load_session

    def without_port(folder):              # session.toml as if it recorded no monochromator port
        data, doc, why = real(folder)
        return data, {**doc, "ports": {k: v for k, v in doc["ports"].items() if k != "monochromator"}}, why

    monkeypatch.setattr(cap._integrity, "load_session", without_port)
    with pytest.raises(SessionError, match="the plan is spectral; give the monochromator's port"):
        cap.resume(copy, progress=False)   # refused before any port opens (its sim:// URLs name no instrument)
