"""The whole loop on the simulated instrument: capture -> export -> fit -> Mitsuba -> report.

The virtual sample's BRDF is known, so the fit must recover it within its reported
uncertainty, and Mitsuba, given the exported fit, must render what gonio's own model
evaluates (tech-facts: the flat-sample/directional/radiancemeter scene renders
f_r E cos(theta_i) exactly).
"""

import json
import subprocess
import sys

import numpy as np
import pytest

from gonio.bench.samples import DEMO_SAMPLE, check_sample
from gonio.bench.dataset.export import export
from gonio.cli.fit import fit_dataset, render_closure
from gonio.bench.report.fitdoc import truth_by_name as _truth_by_name
from gonio.bench.report import write_report
from gonio.cli.capture import capture_sim
from gonio.fitting import load_dataset, write_json_atomic

from capture_process import start_capture


@pytest.fixture(scope="module")
def loop(tmp_path_factory):
    out = tmp_path_factory.mktemp("loop")
    sample = check_sample(DEMO_SAMPLE)
    summary = capture_sim(out / "session", sample=sample, plan="quick", seed=7, progress=False)
    dataset = export(out / "session")
    meas = load_dataset(dataset)
    result, doc, _ = fit_dataset(meas, model=sample["model"], options=sample["options"], seed=7,
                                 dataset_path=dataset)
    write_json_atomic(out / "fit.json", doc)
    closure = render_closure(out / "fit.json", meas, out / "render")
    return {"out": out, "sample": sample, "summary": summary, "meas": meas, "result": result, "doc": doc,
            "closure": closure}


def test_capture_is_complete_and_dataset_is_clean(loop):
    s, meas = loop["summary"], loop["meas"]
    assert s.complete and s.n_done == s.n_points == meas.n_points
    assert np.all(np.isfinite(meas.brdf)) and np.all(meas.brdf_std > 0)
    assert meas.attrs["sample_truth"]["model"] == "roughplastic"
    assert "seed" in meas.attrs and "gonio_version" in meas.attrs


def test_recovered_parameters_within_reported_uncertainty(loop):
    doc, sample = loop["doc"], loop["sample"]
    truths = _truth_by_name(sample, list(doc["parameters"]))
    assert len(truths) == 5
    for name, p in doc["parameters"].items():
        z = (p["value"] - truths[name]) / p["std"]
        assert abs(z) < 3.0, (name, p["value"], truths[name], p["std"])
        assert p["ci90"][0] < p["value"] < p["ci90"][1]
    assert 0.3 < doc["goodness"]["chi2_dof"] < 2.0
    assert doc["constraints"]["energy"]["holds"]


def test_mitsuba_renders_what_the_model_evaluates(loop):
    s = loop["closure"]["summary"]
    assert s["export_max_rel"] < 1e-4
    # the render of the fit agrees with the measurement at the noise level
    assert s["residual_rms_sigma"] < 2.0


def test_report_is_self_contained(loop):
    path = write_report(loop["out"], loop["out"] / "report.html")
    text = path.read_text()
    assert text.count("data:image/png;base64,") >= 4
    assert "Mitsuba re-render" in text and "roughplastic" in text
    assert (loop["out"] / "report_files" / "inplane.png").stat().st_size > 1000


@pytest.mark.slow
def test_demo_command_end_to_end(tmp_path):
    """`gonio demo` as a user runs it (quick plan to keep the suite short): the typical errors,
    a calibration step first, its file recorded in session.toml and dataset.nc and named in the
    report, and every parameter within 3 u_c of the truth."""
    import tomllib

    import xarray as xr

    proc = subprocess.run([sys.executable, "-m", "gonio.cli.main", "demo", "--out", str(tmp_path / "out"),
                           "--plan", "quick", "--seed", "3", "--no-posterior"],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "within 3 sigma" in proc.stdout
    out = tmp_path / "out"
    for name in ("calibration.toml", "dataset.nc", "fit.json", "report.html", "render/render.json",
                 "session/journal.sqlite"):
        assert (out / name).exists(), name
    fit = json.loads((out / "fit.json").read_text())
    assert fit["provenance"]["seed"] == 3
    # the calibration step ran first, on the typical instrument of this seed, and said what it found
    text = " ".join(proc.stdout.split())
    for k, step in enumerate(("calibrate", "capture", "export", "fit", "render", "report"), 1):
        assert f"step {k}/6 {step}" in text, step
    assert text.index("step 1/6 calibrate") < text.index("holder tilt") < text.index("step 2/6 capture")
    assert "--errors typical" in text and "--calibration" in text
    # the fit estimated the shared angle errors (on by default) and its summary says so, once
    assert fit["shared_angles"]["applied"] is True
    assert text.count("shared angle errors estimated:") == 1
    cal = tomllib.loads((out / "calibration.toml").read_text())
    assert cal["calibration"]["sim"] is True and cal["calibration"]["seed"] == 3
    assert cal["calibration"]["errors"]["preset"] == "typical"
    # ... and the capture used it: session.toml, dataset.nc (calibrated angles, their u), the report
    session = tomllib.loads((out / "session" / "session.toml").read_text())
    settings = session.get("settings", session)
    assert settings["errors"]["preset"] == "typical"
    assert settings["alignment"]["holder_tilt_x_deg"] == cal["alignment"]["holder_tilt_x_deg"]
    assert settings["linearity"]["gamma"] == cal["linearity"]["gamma"]
    assert settings["calibration"]["seed"] == 3
    with xr.open_dataset(out / "dataset.nc") as ds:
        assert "angle_calibration" in ds.attrs and np.all(ds["theta_i_u"].values > 0)
        assert json.loads(ds.attrs["angle_calibration"])["holder_tilt_y_deg"] == cal["alignment"]["holder_tilt_y_deg"]
        assert float(np.max(np.abs(ds["theta_o"].values - ds["theta_o_nominal"].values))) > 0.01
    report = (out / "report.html").read_text()
    assert "<th>Calibration</th>" in report or ">Calibration<" in report
    assert "gonio calibrate on the simulated instrument (typical errors), seed 3" in report
    assert "the HDR merge&#39;s linearisation" in report or "the HDR merge's linearisation" in report
    # a second run replaces the previous demo session instead of refusing
    proc = subprocess.run([sys.executable, "-m", "gonio.cli.main", "demo", "--out", str(tmp_path / "out"),
                           "--plan", "quick", "--seed", "3", "--no-posterior"],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]


def test_report_renders_in_headless_chromium(loop, tmp_path):
    """The report opens in a real browser, every embedded image decodes, no script error."""
    import shutil

    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    if browser is None:
        pytest.skip("Debian's chromium is not installed (`make test` installs it where apt-get runs as root)")
    path = write_report(loop["out"], loop["out"] / "report.html")
    proc = subprocess.run(
        [browser, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         f"--user-data-dir={tmp_path / 'profile'}", "--enable-logging=stderr", "--v=0",
         "--virtual-time-budget=5000", "--dump-dom", path.as_uri()],
        capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "<h1>BRDF measurement report" in proc.stdout
    assert '<section id="view" hidden' not in proc.stdout      # the view's script ran under the CSP
    decoded = proc.stdout.split('data-images-decoded="')[1].split('"')[0]
    ok, total = (int(v) for v in decoded.split("/"))
    assert total >= 5 and ok == total, decoded
    assert "Uncaught" not in proc.stderr


def test_cli_sim_capture_killed_then_resumed(tmp_path):
    """`gonio capture --sim` SIGKILLed mid-run; `gonio capture --resume` rebuilds the same
    virtual instrument from session.toml, re-homes it and finishes: every point once."""
    import signal
    import sqlite3

    session = tmp_path / "s"
    proc, done = start_capture(session, timeout_s=120)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert 3 <= done < 30
    res = subprocess.run([sys.executable, "-m", "gonio.cli.main", "capture", "--resume", str(session), "--quiet"],
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "30/30 points" in res.stdout
    rows = sqlite3.connect(session / "journal.sqlite").execute("SELECT idx FROM points ORDER BY idx").fetchall()
    assert [r[0] for r in rows] == list(range(30))
    assert not list(session.rglob("*.tmp")) and not list((session / "raw").glob(".*"))
    meas = load_dataset(export(session))
    assert meas.n_points == 30 and np.all(np.isfinite(meas.brdf))
