"""Every exchange-format writer writes every point or says which it left out and why, counts what
it wrote, and fails with one line and no file when the count is not what it had (issue 34).

The incident angles below are those of a simulated calibrated capture (``gonio calibrate --sim
--errors typical``, then ``gonio capture --sim --plan standard --calibration``): the calibration
moves each point's incidence by a few hundredths of a degree, so incidences that a 0.1-degree
file name cannot tell apart are distinct directions.
"""

import numpy as np
import pytest

import gonio.models as gm
from gonio.cli import main as cli
from gonio.core.geometry import directions_deg
from gonio.fitting import Measurements
from gonio.fitting.formats import ExportError, export_pabopto
from gonio.fitting.formats import pabopto as pab

#: (theta_i, phi_i) of a calibrated capture's first points (degrees)
CALIBRATED = [(15.0068, -0.471), (15.0026, -0.4712), (14.9883, -0.6745), (14.9862, -0.6746), (15.0287, -0.4703),
              (44.9876, -0.1806), (44.9615, -0.1808), (44.9876, -0.1895), (59.94, 44.95), (59.97, 44.99)]


def _meas(n_per=3, use=None, theta_o=None):
    rng = np.random.default_rng(34)
    ti, pi_ = (np.repeat(np.array(c), n_per) for c in zip(*CALIBRATED))
    to = rng.uniform(5, 80, ti.size) if theta_o is None else np.asarray(theta_o, float)
    wi, wo = directions_deg(ti, pi_), directions_deg(to, rng.uniform(-180, 180, ti.size))
    f = gm.get("diffuse").eval(wi, wo, {"reflectance": [0.6, 0.4, 0.2]})
    return Measurements(wi, wo, f, 0.01 * f, np.ones(f.shape, bool) if use is None else use)


def _records(folder):
    return sum(pab._read_records(p.read_text())[1].shape[0] for p in folder.glob("*.dat"))


def test_close_incidences_of_a_calibrated_capture_are_all_written(tmp_path):
    meas = _meas()
    done = export_pabopto(tmp_path, meas)
    assert _records(tmp_path) == meas.n_points == done.n_written == 30
    assert len(done.paths) == len(list(tmp_path.glob("*.dat"))) == len(CALIBRATED)
    assert done.left_out == {} and not (tmp_path / pab.LEFT_OUT_NAME).exists()
    assert done.summary().startswith("30 of 30 points in 10 PAB-Opto files")


def test_left_out_points_are_listed_with_their_reason(tmp_path):
    use = np.ones((30, 3), bool)
    use[[2, 7], 1] = False                                    # saturated in one channel
    theta_o = np.full(30, 40.0)
    theta_o[11] = 90.0                                        # grazing: a dataset allows it, PAB-Opto does not
    done = export_pabopto(tmp_path, _meas(use=use, theta_o=theta_o))
    assert done.n_written == _records(tmp_path) == 27
    assert {k: v.tolist() for k, v in done.left_out.items()} == {"flagged": [2, 7], "horizon": [11]}
    rows = (tmp_path / pab.LEFT_OUT_NAME).read_text().splitlines()
    assert [r.split("\t")[0] for r in rows[2:]] == ["2", "7", "11"]
    assert "saturated" in rows[2] and "horizon" in rows[4]
    assert "27 of 30 points" in done.summary() and "3 left out" in done.summary()


def test_a_file_that_does_not_hold_what_the_writer_had_is_refused_and_nothing_written(tmp_path, monkeypatch):
    """A writer that loses a record (as the one-decimal file names did: two incidences, one name)."""
    real = pab.pabopto_files

    def lossy(*args, **kwargs):
        files = real(*args, **kwargs)
        name = next(iter(files))
        files[name] = files[name].rsplit("\n", 2)[0] + "\n"   # the last record dropped
        return files

    monkeypatch.setattr(pab, "pabopto_files", lossy)
    with pytest.raises(ExportError, match="had 30, the file holds 29"):
        export_pabopto(tmp_path / "out", _meas())
    assert list((tmp_path / "out").iterdir()) == []


def test_convert_prints_the_true_count(tmp_path, capsys):
    import xarray as xr
    from gonio.core.geometry import angles_deg

    meas = _meas()
    sat = np.zeros(30, np.int8)
    sat[4] = 1
    (ti, pi_), (to, po) = angles_deg(meas.wi), angles_deg(meas.wo)
    deg = {"units": "degree"}
    xr.Dataset({"brdf": (("point", "channel"), meas.brdf, {"units": "1/sr"}),
                "brdf_std": (("point", "channel"), meas.brdf_std, {"units": "1/sr"}),
                "saturated": (("point",), sat)},
               coords={"channel": ["R", "G", "B"], "theta_i": ("point", ti, deg), "phi_i": ("point", pi_, deg),
                       "theta_o": ("point", to, deg), "phi_o": ("point", po, deg)},
               attrs={"gonio_version": "test", "seed": 1}).to_netcdf(tmp_path / "dataset.nc", engine="h5netcdf")
    out = tmp_path / "pab"
    assert cli.main(["convert", str(tmp_path / "dataset.nc"), "--to", "pabopto", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "29 of 30 points in 10 PAB-Opto files" in printed and "1 left out" in printed, printed
    assert _records(out) == 29


def test_merl_csv_and_mitsuba_writers_refuse_a_file_that_differs(tmp_path, monkeypatch, capsys):
    """Each writer reads its file back: a value lost on the way (simulated here) is one line, exit 2
    at the command line, and no file."""
    import csv

    from gonio.fitting import fit_document, fit, write_json_atomic
    from gonio.fitting import formats
    from gonio.fitting.formats import mitsuba_xml

    merl = formats.resample_to_merl(gm.get("diffuse"), {"reflectance": [0.5, 0.4, 0.3]})
    real_read = formats.read_merl

    def damaged(path):
        back = real_read(path)
        back.raw[0, 10, 10, 10] = -1.0                       # one bin lost
        return back

    monkeypatch.setattr(formats, "read_merl", damaged)
    with pytest.raises(ExportError, match="MERL bins with data"):
        formats.write_merl(tmp_path / "m.binary", merl)
    monkeypatch.setattr(formats, "read_merl", real_read)

    real_writer = csv.writer

    class Lossy:
        def __init__(self, fh):
            self.w = real_writer(fh)

        def writerow(self, row):
            self.w.writerow(row)

        def writerows(self, rows):
            self.w.writerows(rows[:-1])                      # the last point lost

    monkeypatch.setattr(csv, "writer", Lossy)
    with pytest.raises(ExportError, match="CSV rows"):
        formats.dataset_to_csv(_meas(), tmp_path / "d.csv")
    monkeypatch.setattr(csv, "writer", real_writer)

    real_lines = mitsuba_xml._xml_lines
    monkeypatch.setattr(mitsuba_xml, "_xml_lines", lambda d, indent: real_lines(d, indent)[:-1])  # a property lost
    with pytest.raises(ExportError, match="Mitsuba XML properties"):
        mitsuba_xml.write_mitsuba_document(tmp_path / "r.xml", "roughplastic", {}, {})
    meas = _meas()
    fit_path = write_json_atomic(tmp_path / "fit.json", fit_document(
        fit(meas, gm.get("diffuse"), rng=np.random.default_rng(0), n_starts=2), meas, seed=0))
    capsys.readouterr()
    assert cli.main(["convert", str(fit_path), "--to", "mitsuba-xml", "--out", str(tmp_path / "x.xml")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "Mitsuba XML properties: had 1, the file holds 0" in err[0], err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fit.json"]
