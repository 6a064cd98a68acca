"""``gonio fit`` and ``gonio render``: dataset -> fit file -> Mitsuba loop closure."""

from __future__ import annotations

import json
import sys
from pathlib import Path


from gonio.cli.console import print_table
from gonio.cli.progress import Steps
from gonio.bench.report.fitdoc import energy_text, truth_for
from gonio.core.errors import GonioError
from gonio.fitting.display import inadequate_text, shared_angles_line
from gonio.bench.dataset.reader import open_budget, open_dataset as _open_dataset, open_fit_input  # noqa: F401  (the CLI's names)
from gonio.fitting.pipeline import (check_estimate_angles, fit_dataset, load_fit_file,  # noqa: F401
                                    model_error as _model_error, parse_options, resolve_candidates)
from gonio.fitting.render.closure import (check_measured as _check_measured, check_preview_options, check_variant,  # noqa: F401
                                          render_closure, render_previews)

__all__ = ["fit_dataset", "fit_cli", "render_cli", "parse_options", "print_fit"]


def print_fit(doc, truth=None, console=None):
    """The fit file's one uncertainty statement as a table (gonio.fitting.display.uncertainty_rows:
    value, u_stat, u_c, U, k, unit, flags), the 90 % interval where it says more than
    value +- 1.645 u_c, and the truth with z = (value - truth) / u_c where it is known."""
    from rich.console import Console

    from gonio.fitting.display import UNCERTAINTY_HEADER, interval_column, uncertainty_rows, uncertainty_values

    console = console or Console()
    values = uncertainty_values(doc)
    truths = truth_for(truth, doc["model"]["name"], list(values))
    intervals, interval_caption = interval_column(doc)
    ks = sorted({v["k"] for v in values.values()})
    k_text = f" (k={ks[0]:g})" if len(ks) == 1 else ""
    caption = "; ".join([f"value ± u_c; u_stat statistical, u_c combined (budget), U = k u_c{k_text}", interval_caption]
                        + (["z = (value - truth) / u_c"] if truths else []))
    # at 80 columns the table continues below instead of cutting values (gonio/cli/console.py)
    columns = [(h, "left" if h in ("parameter", "unit", "flags") else "right") for h in UNCERTAINTY_HEADER] \
        + ([("90 % interval", "right")] if intervals else []) + ([("truth", "right"), ("z", "right")] if truths else [])
    rows = []
    for row in uncertainty_rows(doc):
        name, v = row[0], values[row[0]]
        cells = list(row) + ([intervals.get(name, "-")] if intervals else [])
        if truths:
            t = truths.get(name)
            cells += [f"{t:.5g}" if t is not None else "-",
                      f"{(v['value'] - t) / v['u_c']:+.2f}" if (t is not None and v["u_c"] > 0) else "-"]
        rows.append(cells)
    print_table(console, columns, rows, title=f"fit: {doc['model']['name']} {json.dumps(doc['model']['options'])}",
                caption=caption)
    g = doc["goodness"]
    console.print(f"chi2/dof = {g['chi2_dof']:.3f} ({g['dof']} dof), RMSE f_r = {g['rmse_fr']:.3g} 1/sr, "
                  f"energy {energy_text(doc['constraints']['energy'])}, "
                  f"{doc['optimiser']['evaluations']} evaluations in {doc['optimiser']['time_s']:.2f} s")
    if g.get("warning"):
        console.print(f"[yellow]{g['warning']}[/yellow]")
    elif not g.get("model_adequate", True):
        console.print(f"[yellow]{inadequate_text(g)}[/yellow]")
    dominant = budget_line(doc)
    if dominant:
        console.print(dominant)
    angles = shared_angles_line(doc)
    if angles:
        from rich.markup import escape

        console.print(angles if doc["shared_angles"].get("applied") else f"[yellow]{escape(angles)}[/yellow]")
    if doc.get("posterior") and doc["posterior"].get("advice"):
        console.print(f"[yellow]{doc['posterior']['advice']}[/yellow]")


def budget_line(doc) -> str:
    """One line: each parameter's largest share of u_c^2 (the fit file's uncertainty budget)."""
    unc = (doc.get("uncertainty") or {}).get("parameters") or {}
    parts = []
    for name, u in unc.items():
        if u.get("budget"):
            comp, frac = max(u["budget"].items(), key=lambda kv: kv[1])
            parts.append(f"{name} {comp} {100 * frac:.0f} %")
    return ("largest term of u_c^2: " + ", ".join(parts)) if parts else ""


def print_selection(doc, console=None) -> None:
    """The BIC ranking of a fit document as a table (80 columns: gonio/cli/console.print_table)."""
    from rich.console import Console

    sel = doc["selection"]
    loss = sel[0].get("loss", "chi2")
    rendered = any("delta_e" in r for r in sel)
    print_table(console or Console(), [("model and options", "left"), ("k", "right"), (f"-2 ln L ({loss})", "right"),
                                       ("delta BIC", "right")] + ([("dE00", "right")] if rendered else []) + [("", "left")],
                [[f"{r['model']} {json.dumps(r['options'])}" if r["options"] else r["model"], str(r["k"]),
                  f"{r.get('neg2_loglik', r['chi2']):.4g}",
                  f"{r['delta_bic']:.2f}" if abs(r["delta_bic"]) < 1e4 else f"{r['delta_bic']:.4g}"]
                 + ([f"{r['delta_e']:.2f}" if "delta_e" in r else ""] if rendered else [])
                 + ["*" if r["chosen"] else ""] for r in sel],
                title="model selection (BIC" + (", and the rendered difference in the default scene)" if rendered else ")"),
                caption="* chosen")


def fit_cli(dataset: Path, *, model, options, out: Path, seed, loss, posterior, colour_space="srgb", quiet=False,
            estimate_angles=None):
    from gonio.fitting import write_json_atomic

    from gonio.core.preflight import check_output_file, writing

    from gonio.fitting import COLOUR_SPACES

    if colour_space not in COLOUR_SPACES:
        raise GonioError(f"unknown --colour-space {str(colour_space)[:40]!r}: choose one of {', '.join(COLOUR_SPACES)}")
    check_output_file(out, "fit file (--out)")
    inp = open_fit_input(dataset, seed, colour_space)
    meas = inp.meas
    if estimate_angles:             # the inputs stated; the loss is checked by fit_measurements, before the fit
        check_estimate_angles(inp.budget, "chi2", dataset.name)
    # a bar on a terminal: the candidates of --model auto (or of an open distribution) and their
    # renders, with the time left; one model alone: the time it has taken
    with Steps("fit" if model == "auto" else f"fit {model}", enabled=not quiet) as progress:
        _, doc, _ = fit_dataset(inp, model=model, options=parse_options(options), seed=seed, loss=loss,
                                posterior=posterior, dataset_path=dataset, progress=progress,
                                estimate_angles=estimate_angles)
    with writing(out):
        write_json_atomic(out, doc)
    truth = meas.attrs.get("sample_truth") if isinstance(meas.attrs.get("sample_truth"), dict) else None
    if colour_space != "srgb":
        truth = None        # the simulated truth is in linear sRGB: no z against values in another space
    print_fit(doc, truth)
    opts = doc["model"]["options"]
    if model != "auto" and doc.get("selection") and "distribution" in opts:
        others = ", ".join(sorted({r["options"].get("distribution") for r in doc["selection"]} - {opts["distribution"]}))
        _wrapped(f"distribution: {opts['distribution']} (chosen by BIC over {others}; "
                 f"--option distribution=NAME fixes it)")
    if doc.get("selection"):
        print_selection(doc)
    if doc.get("selection_rule"):
        _wrapped(f"selection: {doc['selection_rule']}")
    print(f"wrote {out}")


def _wrapped(text: str) -> None:
    """A long line of prose: whole in a pipe, wrapped at 80 columns on a terminal (helptext.say)."""
    from gonio.cli.helptext import say

    say(text)


def fit_batch_cli(datasets, *, model, options, out: Path, seed, loss, scheduler, workers, dashboard=None,
                  quiet=False, estimate_angles=None):
    """Fit many datasets with one named model on Dask; one fit file per dataset in ``out``
    (`gonio.bench.dataset.fit_files.fit_files`; the warnings on stderr, so the lines on stdout
    stay machine-readable). On a terminal a bar says how long the batch has run (the cluster
    returns every fit at once: there is no count to show)."""
    from gonio.bench.dataset.fit_files import fit_files

    with Steps(f"fit {len(datasets)} datasets on Dask", enabled=not quiet):
        fit_files(datasets, model=model, options=options, out=out, seed=seed, loss=loss, scheduler=scheduler,
                  workers=workers, dashboard=dashboard, say=print, warn=lambda line: print(line, file=sys.stderr),
                  estimate_angles=estimate_angles)


def render_cli(fit_path: Path, dataset: Path, out_dir: Path, variant=None, preview=False, measured=None,
               size=128, spp=256, quiet=False):
    from gonio.core.preflight import check_output_dir

    # every option is checked before anything is rendered or written
    if preview or measured:
        check_preview_options(size, spp)
    check_output_dir(out_dir, "render output folder (--out)")
    if measured is not None:
        _check_measured(Path(measured))
    check_variant(variant)
    if not Path(fit_path).exists():
        raise GonioError(f"fit file {fit_path} does not exist; run `gonio fit DATASET --out FIT.json` first")
    meas = fitted_data(_open_dataset(dataset), dataset, fit_path)
    with Steps("render at the measured poses", enabled=not quiet):
        result = render_closure(fit_path, meas, out_dir, variant)
    s = result["summary"]
    _wrapped(f"Mitsuba {result['variant']}: {result['points']} poses rendered in {result['time_s']:.3f} s "
             f"(scene re-render of {result['scene_check']['poses']} poses agrees to "
             f"{result['scene_check']['max_rel']:.1e}); export check max rel {s['export_max_rel']:.2e}; render vs "
             f"measurement rms {s['residual_rms_sigma']:.3f} sigma (max {s['residual_max_sigma']:.2f}); wrote "
             f"{Path(out_dir) / 'render.json'}")
    if preview or measured:
        with Steps("render previews", enabled=not quiet):
            pv = render_previews(fit_path, out_dir, measured, size, spp)
        de = f"; mean CIEDE2000 vs measured {pv['delta_e_mean']:.2f}" if pv.get("delta_e_mean") is not None else ""
        _wrapped(f"previews in {Path(out_dir) / 'preview'} ({pv['time_s']:.1f} s){de}")


def fitted_data(meas, dataset, fit_path):
    """``meas`` (``dataset`` as opened) as the fit file's fit saw it: at the directions its
    shared-angle estimate gave the data, corrected for the apertures where it modelled them
    (gonio.bench.report.fitdoc.as_fitted; a fit file that cannot be read is left to its reader's
    refusal); a note on the terminal where the estimate does not fit the dataset."""
    from gonio.bench.report.fitdoc import as_fitted
    from gonio.fitting import load_fit

    try:
        loaded = load_fit(fit_path)
        ir = loaded.document.get("instrument_response")
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return meas
    response = (loaded.model, loaded.params, ir.get("source_half_deg"), ir.get("detector_half_deg")) \
        if isinstance(ir, dict) else None
    meas, note = as_fitted(meas, dataset, loaded.document.get("shared_angles"), response)
    if note:
        _wrapped(note)
    return meas
