"""The CLI in an 80-column terminal, and what it says (issue 19, "the CLI never misleads").

Tables: values are never cut or wrapped (rich cut `diffuse_reflectance[…   0.5499…` before);
the progress bar keeps its count and ETA; unknown option values name their own choices once;
`fit --batch` warns like `fit`; an export of a partial session says so; `render` checks its
inputs before it writes.
"""

from __future__ import annotations

import io
import re
import json

import numpy as np
import pytest
from rich.console import Console

import report_folder
from gonio.cli.main import main

LONG = ["diffuse_reflectance[R]", "diffuse_reflectance[G]", "diffuse_reflectance[B]", "alpha", "int_ior"]


def _doc(uncertainty=True):
    """A fit document shaped as gonio fit writes it, with the widest columns (emcee intervals,
    the uncertainty budget's u_c and U, the truth)."""
    values = [0.5498598406268321, 0.30004553504938375, 0.11990647583637357, 0.14999366132551537, 1.5001066358210924]
    params = {n: {"value": v, "std": 1.4e-4 * (k + 1), "unit": "1", "method": "emcee", "at_bound": False,
                  "undetermined": False, "ci90": [v - 2.3e-4, v + 2.2e-4]} for k, (n, v) in enumerate(zip(LONG, values))}
    doc = {"model": {"name": "roughplastic", "options": {"distribution": "ggx", "nonlinear": False}},
           "parameters": params,
           "goodness": {"chi2_dof": 0.85, "dof": 85, "rmse_fr": 1.3e-4, "model_adequate": True, "warning": None},
           "constraints": {"energy": {"by_construction": True, "holds": True, "max_albedo": 0.6}},
           "optimiser": {"evaluations": 37, "time_s": 0.73}}
    if uncertainty:
        doc["uncertainty"] = {"k": 2, "components": {}, "parameters": {
            n: {"u_stat": p["std"], "u_combined": 3.1e-3 / (k + 1), "U": 6.2e-3 / (k + 1), "k": 2,
                "budget": {"statistical": 0.1, "reference_certificate": 0.9}}
            for k, (n, p) in enumerate(params.items())}}
    return doc


def _screen(width=80):
    return Console(width=width, file=io.StringIO(), record=True, color_system=None)


@pytest.mark.parametrize("uncertainty", [True, False])
def test_fit_table_at_80_columns_keeps_every_value_whole(uncertainty):
    from gonio.cli.fit import print_fit

    console = _screen()
    truth = {"model": "roughplastic", "options": {"distribution": "ggx"},
             "params": {"alpha": 0.15, "diffuse_reflectance": [0.55, 0.3, 0.12], "int_ior": 1.5}}
    print_fit(_doc(uncertainty), truth=truth, console=console)
    text = console.export_text()
    lines = text.splitlines()
    assert "…" not in text and max(len(line) for line in lines) <= 80, text
    for name in LONG:                                   # every name whole, in every table part
        assert sum(name in line for line in lines) >= 1, name
    # GUM rounding (JCGM 100 7.2.6): value to u_c's second significant digit; u_c to two digits
    assert ("0.5499" if uncertainty else "0.54986") in text
    assert ("0.0031" if uncertainty else "0.00014") in text
    assert "0.54963 .. 0.55008" in text                # the 90 % interval whole
    # and the same table at 200 columns is one table
    wide = _screen(200)
    print_fit(_doc(uncertainty), truth=truth, console=wide)
    assert "(continued)" not in wide.export_text() and "(continued)" in text


def test_print_table_continues_below_instead_of_cutting():
    from gonio.cli.console import print_table, table_width

    console = _screen()
    cols = [("key", "left")] + [(f"a long header {k}", "right") for k in range(6)]
    rows = [["x" * 20] + [f"{1.23456789012 * 10 ** k:.10g}" for k in range(6)]]
    print_table(console, cols, rows, title="t")
    text = console.export_text()
    assert "…" not in text and max(map(len, text.splitlines())) <= 80
    for v in rows[0]:
        assert v in text
    assert text.count("x" * 20) >= 2                    # the key column repeated in the continuation
    assert table_width([20, 10]) == 37


def test_progress_bar_keeps_count_and_eta_at_80_columns():
    from gonio.bench.measure.point import ProgressBar

    console = _screen()
    bar = ProgressBar(1053, 110, True, console=console)
    bar.advance(np.array([0.1234567, 0.07764, 0.03135]), {"rel": np.array([0.01, 0.02, 0.03])})
    bar.p.refresh()
    bar.close()
    text = console.export_text()
    assert "111/1053" in text and ("-:--:--" in text or ":" in text.split("111/1053")[1][:9]), text
    assert "0:00:…" not in text and max(map(len, text.splitlines())) <= 80


@pytest.mark.parametrize("argv, want, not_want", [
    (["--model", "nosuch"], "unknown model 'nosuch': choose one of", None),
    (["--model", "roughplastic", "--option", "distribution=nosuch"], "not one of ('beckmann', 'ggx')", "known models"),
])
def test_unknown_option_values_name_their_own_choices_once(tmp_path, capsys, argv, want, not_want):
    report_folder._dataset(tmp_path / "d.nc", n=8)
    assert main(["fit", str(tmp_path / "d.nc"), *argv, "--out", str(tmp_path / "fit.json")]) == 2
    err = capsys.readouterr().err
    assert want in err and err.count("known models") <= 1 and err.count("choose one of") <= 1, err
    if not_want:
        assert not_want not in err
    assert not (tmp_path / "fit.json").exists()


def test_fit_batch_warns_on_an_inadequate_fit(tmp_path, capsys, monkeypatch):
    """chi2/dof in the thousands (noise 1000x understated): `fit --batch` says so, like `fit`."""
    import xarray as xr

    import gonio.fitting
    from gonio.fitting import fit_serial

    good = tmp_path / "good.nc"
    report_folder._dataset(good, n=40)
    bad = tmp_path / "bad.nc"
    with xr.open_dataset(good, engine="h5netcdf") as ds:
        ds.load()
    ds["brdf_std"] = ds["brdf_std"] * 1e-3
    ds.to_netcdf(bad, engine="h5netcdf")

    def serial(metas, model, *, rng_seed, loss, **_):      # the Dask cluster's work, in this process
        # a local cluster is given a loader per file (called in the worker), and the model as
        # (name, options): each fitted as `gonio fit` fits it (fit_serial: the workers' code)
        return fit_serial(metas, model, rng_seed=rng_seed, loss=loss)

    monkeypatch.setattr(gonio.fitting, "fit_batch", serial)
    assert main(["fit", "--batch", str(good), str(bad), "--model", "diffuse", "--out", str(tmp_path / "fits")]) == 0
    out, err = capsys.readouterr()
    assert "good: chi2/dof" in out and "bad: chi2/dof" in out
    assert "warning: chi2/dof = " in err and "1 of 2 fits miss their data" in err and "bad" in err.split("fits miss")[1]
    assert json.loads((tmp_path / "fits" / "bad.fit.json").read_text())["goodness"]["model_adequate"] is False


def test_export_of_a_partial_session_says_partial(tmp_path, capsys, monkeypatch):
    import xarray as xr

    import gonio.bench.dataset.export

    path = tmp_path / "dataset.nc"
    report_folder._dataset(path, n=8)
    with xr.open_dataset(path, engine="h5netcdf") as ds:
        ds.load()
    ds.attrs.update(plan=json.dumps({"name": "dense", "points": [[0, 0, 0, 0]] * 1053}), complete=0)
    path.unlink()
    ds.to_netcdf(path, engine="h5netcdf")
    monkeypatch.setattr(gonio.bench.dataset.export, "export", lambda session, **options: path)
    assert main(["export", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "PARTIAL, 8 of 1053 planned points" in out and f"--resume {tmp_path}" in out


def test_render_checks_the_measured_file_before_writing(tmp_path, capsys):
    (tmp_path / "fit.json").write_text("{}")
    report_folder._dataset(tmp_path / "dataset.nc", n=8)
    out = tmp_path / "render"
    assert main(["render", str(tmp_path / "fit.json"), "--dataset", str(tmp_path / "dataset.nc"), "--out", str(out),
                 "--measured", str(tmp_path / "missing.binary")]) == 2
    assert "missing.binary does not exist" in capsys.readouterr().err
    assert not out.exists()


def test_capture_says_what_it_does_before_the_first_point(tmp_path, capsys, monkeypatch):
    """Darks and flats took ~5 s with a blank screen: on a terminal each preparation step is
    said (an updating status line; here, where the console is told it is on a terminal but
    writes to a captured stream, a line per step). In a pipe the capture says nothing while it
    works (issue 41: tests/bench/test_cli_progress.py)."""
    import gonio.cli.progress

    monkeypatch.setattr(gonio.cli.progress, "on_terminal", lambda stream=None: True)
    plan, settings = tmp_path / "two.toml", tmp_path / "s.toml"
    plan.write_text('name = "two"\npoints = [[30, 0, 20, 180], [30, 0, 40, 180]]\n')
    settings.write_text("[capture]\nflat_frames = 4\n")
    assert main(["capture", "--sim", "--plan", str(plan), "--settings", str(settings), "--out", str(tmp_path / "s")]) == 0
    err = capsys.readouterr().err
    steps = [line for line in err.splitlines() if line.startswith("capture: ")]
    assert steps[:2] == ["capture: checking the camera and the stages",
                         "capture: homing the stages (they lost their reference)"], err
    assert "capture: dark frames, lamp off" in steps and "capture: flat-field frames" in steps
    assert steps[-1] == "capture: lamp on, reading the source monitor"


def test_model_selection_table_fits_80_columns():
    from gonio.cli.fit import print_selection

    models = [("roughplastic", {"distribution": "ggx"}, 5, 72.21), ("roughplastic2", {"distribution": "beckmann"}, 7, 5798.0),
              ("cooktorrance", {}, 10, 2.384e5), ("roughconductor", {"distribution": "beckmann"}, 7, 6.977e6)]
    doc = {"selection": [{"model": m, "options": o, "k": k, "chi2": c, "neg2_loglik": c, "loss": "chi2",
                          "delta_bic": c - 72.21 + 4.0 * (k - 5), "chosen": m == "roughplastic"} for m, o, k, c in models]}
    console = _screen()
    print_selection(doc, console)
    table = console.export_text()
    assert "…" not in table and "(continued)" not in table and max(map(len, table.splitlines())) <= 80, table
    assert 'roughconductor {"distribution": "beckmann"}' in table and "6.977e+06" in table
    assert re.search(r'roughplastic \{"distribution": "ggx"\}.*\*\s*$', table, re.M), table


def test_progress_bar_names_a_transmitted_value_f_t():
    """A point behind the sample (the rear stop) is a BTDF value: the bar says f_t, not f_r."""
    from gonio.bench.measure.point import ProgressBar

    console = _screen()
    bar = ProgressBar(85, 40, True, console=console)
    bar.advance(np.array([30.6, 30.1, 29.8]), None, quantity="f_t")
    bar.p.refresh()
    bar.close()
    text = console.export_text()
    assert "f_t 30.6" in text and "f_r" not in text, text
