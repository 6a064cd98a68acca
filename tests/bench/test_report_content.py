"""`gonio report` reads like a calibration lab's measurement report (issue 19).

Identification first (sample, operator, date, instrument with serials, reference and its
certificate, plan, band), a status box that says what is incomplete, inadequate or violated,
the results with u_c and U rounded by JCGM 100:2008 7.2.6, figures with captions and no
overlapping labels, an offline interactive view, an appendix, and a print stylesheet that
headless Chromium turns into a PDF. Without a fit the measured BRDF is still shown.
"""

from __future__ import annotations

import base64
import hashlib
import json
import re
import shutil
import sqlite3
import subprocess

import pytest

import report_folder
from gonio.bench.report import figures as figs
from gonio.bench.report.meta import gum
from gonio.bench.report import write_report

SCRIPT = "<script>alert(1)</script>"


@pytest.fixture(scope="module")
def pristine(tmp_path_factory):
    return report_folder.build(tmp_path_factory.mktemp("content") / "out")


@pytest.fixture
def out(pristine, tmp_path):
    return report_folder.copy(pristine, tmp_path)


@pytest.fixture
def no_figures(monkeypatch):
    """Tests of the text skip matplotlib (seconds a report); the figures have their own tests."""
    monkeypatch.setattr(figs, "draw", lambda images, notes, name, fn, *args: None)


def edit_fit(folder, change):
    doc = json.loads((folder / "fit.json").read_text())
    change(doc)
    (folder / "fit.json").write_text(json.dumps(doc))


def edit_attrs(folder, **attrs):
    import xarray as xr

    with xr.open_dataset(folder / "dataset.nc", engine="h5netcdf") as ds:
        ds.load()
    ds.attrs.update(attrs)
    (folder / "dataset.nc").unlink()
    ds.to_netcdf(folder / "dataset.nc", engine="h5netcdf")
    return ds


def journal(folder, ident) -> None:
    """A session journal holding one identification event, as gonio/bench/drivers/identify.record writes it."""
    (folder / "session").mkdir(exist_ok=True)
    db = sqlite3.connect(folder / "session" / "journal.sqlite")
    db.execute("CREATE TABLE events (id INTEGER PRIMARY KEY AUTOINCREMENT, time REAL NOT NULL, kind TEXT NOT NULL, "
               "text TEXT NOT NULL)")
    db.execute("INSERT INTO events (time, kind, text) VALUES (1, 'identification', ?)", (json.dumps(ident),))
    db.commit()
    db.close()


def section(page: str, start: str, end: str) -> str:
    return page[page.index(start):page.index(end)]


@pytest.mark.parametrize("value, u, want", [
    (100.02147, 0.00035, ("100.02147", "0.00035")),     # JCGM 100:2008 7.2.2: m_s = 100.02147 g, u_c = 0.35 mg
    (100.02147, 0.00079, ("100.02147", "0.00079")),     # JCGM 100:2008 7.2.4: U = 0.79 mg (k = 2.26)
    (0.5500496, 7.696e-05, ("0.550050", "0.000077")),   # the issue's `0.55 +- 7.7e-05`, now to u's digit
    (0.15, 9.96e-05, ("0.15000", "0.00010")),           # u rounds up to the next decade
    (1234.5, 123.4, ("1230", "120")),                   # whole numbers rounded to u's place
    (-0.3, 0.012, ("-0.300", "0.012")),
    (1.23456e-12, 3.4e-15, ("1.2346e-12", "0.0034e-12")),  # one shared power of ten
    (3e-65, 1.511e-62, ("0.0e-62", "1.5e-62")),          # a value far inside u (at a bound of 0): u's power
    (-4e-20, 1e-15, ("0.0e-15", "1.0e-15")),              # ... rounded to zero, without a sign
    (0.55, float("nan"), ("0.55", "nan")),
])
def test_gum_rounding(value, u, want):
    assert gum(value, u) == want


def test_the_report_opens_with_identification_status_and_results(out, no_figures):
    journal(out, {"zaber_port": "/dev/ttyUSB0", "meter": "Thorlabs,PM100USB,P2001234,1.7.0",
                  "camera": "Nikon D5100 " + SCRIPT, "meter_port": "USB0::0x1313",
                  "zaber": [{"address": 1, "device_id": "30342", "serial": "91001", "firmware": "7.38", "build": "18426",
                             "axes": 4, "peripheral_ids": []}]})
    settings = {"session": {"sample_id": "S-0042", "sample_description": "white PTFE tile, lot 7", "operator": "A. Tester"},
                "reference": {"reflectance": 0.99, "rel_std": 0.005, "certificate": "NPL-2026-117"},
                "meter": {"wavelength_nm": 550}}
    edit_attrs(out, settings=json.dumps(settings), versions=json.dumps({"created": "2026-11-30T10:00:00+00:00"}))
    edit_fit(out, lambda d: d.pop("uncertainty", None))      # a fit file without a budget
    page = write_report(out).read_text()
    head = section(page, "<h1>", "<h2>Results")
    for text in ("S-0042", "white PTFE tile, lot 7", "A. Tester", "2026-11-30T10:00:00+00:00", "NPL-2026-117",
                 "serial 91001", "firmware 7.38", "Thorlabs,PM100USB,P2001234,1.7.0", "source monitor at 550 nm",
                 "quick: 40 planned points", "Complete: 40 of 40 planned points", "Model adequate"):
        assert text in head, text
    assert "&lt;script&gt;" in head and SCRIPT not in page          # device text is hostile text
    assert "<title>BRDF measurement report: sample S-0042" in page
    # results: value and u_c by the GUM rule, U = 2 u_c; the statement of what u leaves out
    fit = json.loads((out / "fit.json").read_text())
    p = next(iter(fit["parameters"].values()))
    value, u = gum(p["value"], p["std"])
    results = section(page, "<h2>Results", "Appendix A")
    assert f'<td class="num">{value}</td><td class="num">{u}</td><td class="num">{gum(p["value"], 2 * p["std"])[1]}' \
        in results
    assert "statistical standard uncertainty only" in results and "0.5 % relative" in results
    # the optimiser benchmark and the internals are in the appendix, after the results
    appendix = page[page.index('<div class="appendix">'):]
    for text in ("Optimiser benchmark", "optimiser ", "Model selection", "Mitsuba re-render"):
        assert text in appendix and text not in results, text
    assert "white-space:pre-wrap" in page and "@media print" in page


def test_combined_uncertainty_from_the_fit_file_is_used(out, no_figures):
    def add(doc):
        doc["uncertainty"] = {"k": 2, "components": {"reference_certificate": {"gum_type": "B", "correlation": "full"}},
                              "parameters": {n: {"u_stat": p["std"], "u_combined": 0.0031, "U": 0.0062, "k": 2,
                                                 "budget": {"statistical": 0.02, "reference_certificate": 0.98}}
                                             for n, p in doc["parameters"].items()}}
    edit_fit(out, add)
    page = write_report(out).read_text()
    results = section(page, "<h2>Results", "Appendix A")
    p = next(iter(json.loads((out / "fit.json").read_text())["parameters"].values()))
    assert f'<td class="num">{gum(p["value"], 0.0031)[0]}</td><td class="num">0.0031</td><td class="num">0.0062' \
        in results
    assert "combined standard uncertainty" in results
    # the budget as a table (issue 41): a row per component, its share of u_c^2 and contribution
    budget = results[results.index('<table class="budget"'):]
    name = next(iter(json.loads((out / "fit.json").read_text())["parameters"]))
    cell = '<td class="num" data-parameter="' + re.escape(name) + '"><span class="u">{}</span> <span class="share">\\({}\\)'
    assert re.search(r'data-component="reference_certificate"><td>reference_certificate</td><td>B</td><td>full</td>'
                     r'<td>[^<]*</td>' + cell.format("0.0031", "98 %"), budget)
    assert re.search(r'data-component="statistical"><td>statistical</td><td>A</td><td>none</td><td>[^<]*</td>'
                     + cell.format("0.00044", "2 %"), budget)


def test_the_status_box_says_what_is_incomplete_inadequate_or_violated(out, no_figures):
    import numpy as np

    ds = edit_attrs(out, plan=json.dumps({"name": "dense", "points": [[0, 0, 0, 0]] * 1053}), complete=0)
    brdf = ds["brdf"].values.copy()
    brdf[1] = brdf[0] * 3.0                                  # partners 0 and 1 disagree by many sigma
    ds["brdf"] = (("point", "channel"), brdf)
    (out / "dataset.nc").unlink()
    ds.to_netcdf(out / "dataset.nc", engine="h5netcdf")
    edit_fit(out, lambda d: (d["goodness"].update(model_adequate=False, chi2_dof=3.8e5),
                             d["constraints"]["energy"].update(holds=False, max_albedo=1.2)))
    page = write_report(out).read_text()
    box = section(page, '<div class="status bad">', "<h2>Results")
    bad = re.findall(r'<li class="bad">([^<]*)</li>', box)
    assert any("Incomplete: 40 of 1053 planned points" in b for b in bad), bad
    assert any("Inadequate model: chi2/dof = 3.8e+05" in b for b in bad), bad
    # the verdict names its test and level (issue 34)
    assert any("budget chi-square test" in b and "alpha = 0.001" in b for b in bad), bad
    assert any("Energy violated" in b and "1.2 &gt; 1" in b for b in bad), bad
    assert any("Reciprocity violated" in b for b in bad), bad
    assert np.isfinite(brdf).all()


def test_without_a_fit_the_measured_brdf_is_shown(out):
    for name in ("fit.json", "speed.json"):
        (out / name).unlink()
    shutil.rmtree(out / "render")
    page = write_report(out).read_text()
    assert 'alt="measured.png' in page and "No fit in this folder" in page and "Not fitted" in page
    assert 'alt="coverage.png' in page and 'alt="inplane.png' not in page
    view = json.loads(re.search(r'<script type="application/json" id="view-data">(.*?)</script>', page, re.S)[1])
    assert view["fitted"] is False and all(g["lobe"] is None for g in view["incidences"])
    assert sum(len(g["points"]) for g in view["incidences"]) == 40


def test_the_interactive_view_is_offline_and_escaped(out, no_figures):
    import xarray as xr

    with xr.open_dataset(out / "dataset.nc", engine="h5netcdf") as ds:
        ds.load()
    ds = ds.assign_coords(channel=[SCRIPT, "G", "</script><b>"])
    (out / "dataset.nc").unlink()
    ds.to_netcdf(out / "dataset.nc", engine="h5netcdf")
    page = write_report(out).read_text()
    raw = re.search(r'<script type="application/json" id="view-data">(.*?)</script>', page, re.S)[1]
    assert "<" not in raw and ">" not in raw                 # tojson's \u003c escapes: nothing closes the element
    view = json.loads(raw)
    assert view["channels"] == [SCRIPT, "G", "</script><b>"] and view["fitted"] is True
    lobe = view["incidences"][0]["lobe"]
    assert len(lobe) == 3 and len(lobe[0]) == len(view["theta_o_grid"]) * len(view["phi_o_grid"])
    # the one executable script is allowed by its hash, nothing is fetched
    code = re.findall(r"<script>(.*?)</script>", page, re.S)
    assert len(code) == 1
    digest = base64.b64encode(hashlib.sha256(code[0].encode()).digest()).decode()
    assert f"script-src 'sha256-{digest}'" in page and "default-src 'none'" in page
    assert not re.search(r"(src|href)=\"(https?:)?//", page) and "fetch(" not in code[0]


def test_no_figure_has_overlapping_labels_and_the_report_prints(out, monkeypatch, tmp_path):
    """matplotlib's tight bounding boxes of the drawn text artists do not intersect, in every
    figure of the report (the issue found them in polar, mitsuba_vs_measured and corner); and
    headless Chromium prints the report to an A4 PDF through its print stylesheet."""
    seen = {}
    original = figs._save

    def check(fig):                  # the figure as saved: its texts made legible in print first
        seen[len(seen)] = figs.text_overlaps(fig)
        return original(fig)

    monkeypatch.setattr(figs, "_save", check)
    path = write_report(out)
    assert len(seen) == 7, seen                              # every drawn figure (the preview PNG is not drawn)
    assert all(not v for v in seen.values()), seen
    # the check itself sees an overlap when there is one
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots()
    ax.text(0.5, 0.5, "f_r G (1/sr)")
    ax.text(0.52, 0.5, "180 deg")
    assert figs.text_overlaps(fig) == [("f_r G (1/sr)", "180 deg")]
    plt.close(fig)

    # print (the view and the executed script are checked by tests/e2e/test_loop.py's browser test)
    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    if browser is None:
        pytest.skip("Debian's chromium is not installed (`make chromium`)")
    pdf = tmp_path / "report.pdf"
    proc = subprocess.run([browser, "--headless", "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-sync",
                           "--disable-background-networking", "--disable-component-update",
                           f"--user-data-dir={tmp_path / 'p'}", "--no-pdf-header-footer", f"--print-to-pdf={pdf}",
                           path.as_uri()], capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 0 and pdf.read_bytes().startswith(b"%PDF"), proc.stderr[-2000:]
    pages = len(re.findall(rb"/Type\s*/Page[^s]", pdf.read_bytes()))
    assert 2 <= pages <= 12, pages                          # A4, the appendix from a new page


def test_a_damaged_journal_is_said_not_fatal(out, no_figures):
    (out / "session").mkdir()
    (out / "session" / "journal.sqlite").write_bytes(b"SQLite format 3\x00" + b"\xff" * 4000)
    page = write_report(out).read_text()
    assert "the session journal cannot be read (damaged database)" in page
    (out / "session" / "journal.sqlite").unlink()
    journal(out, {"zaber": "not a list of devices", "meter": ["x"], "camera": 7})
    page = write_report(out).read_text()
    assert "<th>Zaber device" not in page and "<th>camera</th><td>7</td>" in page


def test_the_band_row_names_the_colour_space_of_the_values():
    """The report's values are in the space the dataset was read in (linear sRGB by default,
    issue 15), not 'raw RGB': the identification table says which, and from which matrix."""
    from types import SimpleNamespace

    from gonio.bench.report.meta import _band

    def meas(colour):
        return SimpleNamespace(attrs={"colour": colour}, channels=("R", "G", "B"))

    srgb = _band(meas({"space": "srgb", "matrix": {"source": "chart"}}))
    assert "linear sRGB" in srgb and "ColorChecker" in srgb and "raw" not in srgb
    assert "camera's own RGB" in _band(meas({"space": "camera", "matrix": None}))
    assert "XYZ" in _band(meas({"space": "xyz", "matrix": {"source": "dng"}}))
    assert "not recorded" in _band(meas(None)) and "not recorded" in _band(meas({"space": "lab"}))


def test_the_calibration_row_says_what_was_applied_or_that_nothing_was():
    """The identification names the calibration a session applied (`gonio capture --calibration`;
    issue 15: the report must show it), its estimates with their u, the lamp-arm zero carried as a
    prior, what it corrects; without one it says none was applied. Values are hostile text."""
    from gonio.bench.report.meta import _calibration

    assert "none applied" in _calibration({})
    settings = {"calibration": {"sim": True, "seed": 3, "errors": {"preset": "typical"}},
                "alignment": {"yaw_zero_deg": 0.1234, "u_yaw_zero_deg": 0.0102, "tilt_zero_deg": -0.05,
                              "u_tilt_zero_deg": 0.003, "holder_tilt_x_deg": 0.2, "u_holder_tilt_x_deg": 0.004,
                              "holder_tilt_y_deg": float("nan"), "u_holder_tilt_y_deg": SCRIPT,
                              "lamp_zero_u_deg": 0.02},
                "linearity": {"gamma": 0.003, "u_gamma": 0.0001}, "reference": {"factor": [[1.0]]}}
    text = _calibration(settings)
    for want in ("gonio calibrate on the simulated instrument (typical errors), seed 3", "yaw zero 0.1234 ± 0.0102 deg",
                 "holder tilt x 0.2000 ± 0.0040 deg, y ?", "surveyed u 0.02 deg carried", "gamma 0.00300 ± 0.00010",
                 "every point's angles", "the HDR merge's linearisation", "non-Lambertian factor table"):
        assert want in text, (want, text)
    assert SCRIPT not in text
    hostile = _calibration({"calibration": {"sim": False, "seed": SCRIPT * 100}, "alignment": {}})
    assert "on this instrument" in hostile and len(hostile) <= 900


def test_the_shared_angle_estimate_is_one_sentence_or_nothing():
    """The fit file's ``shared_angles`` in the report: applied (inputs, the largest estimate,
    the posterior range, the largest direction change), not applied (its reason, cut), absent
    (nothing); a wrong type is refused in one line like every other fit-file value."""
    from gonio.bench.report import _shared_angles_text
    from gonio.bench.report.inputs import Doc
    from gonio.core.errors import GonioError

    def text(sa):
        return _shared_angles_text(Doc({"shared_angles": sa}, "fit.json", fix="re-run gonio fit").sub("shared_angles"))

    applied = text({"inputs": 11, "applied": True, "estimate_sigma": [0.05, -1.18, 0.4],
                    "posterior_sigma": [0.99, 0.053, 0.7], "max_direction_change_deg": 0.0604})
    assert applied == ("Shared angle errors estimated: 11 inputs, the largest 1.18 sigma of its stated error, "
                       "posterior 0.05-0.99 sigma; directions moved up to 0.060 deg.")
    older = text({"inputs": 3, "applied": True, "estimate_sigma": [0.1], "posterior_sigma": [0.5]})
    assert older.endswith("posterior 0.50-0.50 sigma.")    # a fit file from before the direction change was recorded
    refused = text({"inputs": 10, "applied": False, "reason": "the inputs' estimate lies 15.6 sigma " + "x" * 900})
    assert refused.startswith("Shared angle errors not estimated: the inputs' estimate lies 15.6 sigma")
    assert len(refused) < 700 and "\n" not in refused
    assert text(None) == ""
    with pytest.raises(GonioError, match="estimate_sigma must be a list"):
        text({"inputs": 3, "applied": True, "estimate_sigma": "1.2", "posterior_sigma": [0.5]})
    with pytest.raises(GonioError, match="posterior_sigma must be a non-empty list"):
        text({"inputs": 3, "applied": True, "estimate_sigma": [0.1], "posterior_sigma": []})
    with pytest.raises(GonioError, match="inputs must be a whole number"):
        text({"inputs": -1, "applied": True, "estimate_sigma": [0.1], "posterior_sigma": [0.5]})
