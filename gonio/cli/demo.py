"""``gonio demo``: the whole loop on the simulated instrument, as a lab runs it, timed step by step.

The virtual instrument has the ``typical`` systematic errors (gonio/sim/physics/errors.py: stage zero
offsets, repeatability and backlash, a tilted holder and a wedged sample, finite apertures,
stray light, a reference off its certificate and not Lambertian, a non-linear detector), so:

calibrate (``gonio calibrate --sim --errors typical``: specular cross-scans of a glossy
artefact, an exposure ladder, the reference over a grid; -> calibration.toml) -> capture with
the calibration (``gonio capture --sim --errors typical --calibration calibration.toml``: RAW
files, calibrated angles, linearised merge, the reference's factor table) -> export
(dataset.nc with its GUM budget) -> fit (the budget carried into every parameter, the
instrument's angular response modelled; Laplace, emcee) -> Mitsuba re-render at the measured
geometry -> HTML report. The sample's true BRDF is known, so the table compares what was
recovered with the truth, in units of the combined standard uncertainty u_c.
"""

from __future__ import annotations

import shutil
import time
import tomllib
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

import gonio.models as gm
from gonio.fitting import fit, load_dataset, versions, write_json_atomic
from gonio.perf.fit import scipy_lsq
from gonio.core.atomic import atomic_open
from gonio.models.mitsuba import mitsuba_variant

from gonio.cli.console import print_table
from gonio.cli.progress import Steps, on_terminal
from gonio.bench.report.fitdoc import truth_by_name
from gonio.core.preflight import check_output_dir
from gonio.bench.samples import load_sample
from gonio.core.errors import GonioError
from gonio.bench.dataset.export import export
from gonio.cli.fit import fit_dataset, open_budget, print_fit, render_closure, render_previews
from gonio.fitting.pipeline import data_as_fitted
from gonio.bench import calibrate
from gonio.bench.plan.plans import load_plan
from gonio.bench.report import write_report
from gonio.cli.capture import capture_sim

#: The demo's instrument: a lab bench before its alignment procedure (gonio/sim/physics/errors.py PRESETS).
DEMO_ERRORS = "typical"

__all__ = ["run_demo"]


def _clear_previous_demo(session: Path):
    """Remove a previous demo's session folder; refuse to touch anything else."""
    if not session.exists():
        return
    marker = session / "session.toml"
    try:
        is_demo = marker.exists() and tomllib.loads(marker.read_text()).get("meta", {}).get("demo", False)
    except (tomllib.TOMLDecodeError, UnicodeDecodeError, OSError):
        is_demo = False
    if not is_demo:
        raise GonioError(f"{session} exists and is not a previous demo session; choose another --out")
    shutil.rmtree(session)


def _truth_bsdf(model, params):
    """The simulated sample's true BSDF as a Mitsuba dict (the 'measured' side of the preview)."""
    import mitsuba as mi

    with mi.scoped_set_variant(mitsuba_variant()):
        return model.to_mitsuba(params)


def _noise_floor(preview: dict) -> float:
    values = [v["noise_mean"] for v in (preview.get("delta_e") or {}).values() if v.get("noise_mean") is not None]
    return max(values) if values else float("nan")


def _speed_vs_error(meas, result, sample, seed, doc=None) -> dict:
    """Time and error of gonio's fit and of scipy's least_squares (the peer) on this capture.

    Both minimise the same chi^2; the error is the largest |fit - truth| / sigma over the
    parameters (sigma: the fit document's combined u_c where it has a budget, else gonio's
    Laplace 1-sigma; with systematic errors the statistical sigma alone says nothing of the
    truth), so a value below ~3 is at the uncertainty's limit.
    """
    truth = result.space.from_params({k: np.asarray(v, dtype=float) for k, v in sample["params"].items()})
    unc = ((doc or {}).get("uncertainty") or {}).get("parameters") or {}
    sigma = np.array([unc[n]["u_combined"] if n in unc else s for n, s in zip(result.space.names, result.std)])
    x_lsq, t_lsq, n_lsq = scipy_lsq(meas, result.model)
    # gonio's fit once more, now that the first one has compiled its kernels in this process:
    # the optimiser's own time, as the peer's numpy has nothing to compile (the first fit's
    # time, compilation included, is the "fit" line of the wall-time table)
    warm = fit(meas, result.model, rng=np.random.default_rng([seed, 7]))
    rows = []
    for name, x, seconds, evals in (("gonio (global + LM + Laplace)", warm.x, warm.time_s, warm.n_evals),
                                    ("scipy least_squares (TRF, finite differences)", x_lsq, t_lsq, n_lsq)):
        fr = result.model.eval(meas.wi, meas.wo, result.space.to_params(x))
        r = ((fr - meas.brdf) / meas.brdf_std)[meas.use]
        rows.append({"optimiser": name, "time_s": float(seconds), "evaluations": int(evals),
                     "chi2": float(r @ r), "max_pull": float(np.max(np.abs((x - truth) / sigma))),
                     "rmse_fr": float(np.sqrt(np.mean(((fr - meas.brdf)[meas.use]) ** 2)))})
    return {"points": int(meas.n_points), "model": result.model.name, "rows": rows, "seed": seed,
            "versions": versions()}


def run_demo(out: Path, seed: int = 1, plan: str = "standard", posterior: bool = True, quiet: bool = False) -> dict:
    """Run the loop; returns a summary dict (the figures printed).

    ``out`` receives ``calibration.toml``, ``session/``, ``dataset.nc``, ``fit.json``,
    ``speed.json``, ``render/`` and ``report.html``; the seed is the virtual instrument's (its
    drawn errors), the calibration's and the fit's. On a terminal each step shows its progress
    (gonio/cli/progress.py) unless ``quiet``.
    """
    console = Console()
    out = Path(out)
    plan_obj = load_plan(plan)          # a bad plan is refused before anything is written
    # RAW files (about 150 kB a point with the calibration frames), dataset, fit, renders
    check_output_dir(out, "demo output folder (--out)", need_bytes=len(plan_obj) * 256 * 1024 + 32 * 2 ** 20)
    out.mkdir(parents=True, exist_ok=True)
    session = out / "session"
    _clear_previous_demo(session)
    sample = load_sample(None)
    run = _run_stages(out, session, sample, plan_obj, seed, posterior, console, quiet=quiet)
    return _print_summary(console, out, session, sample, plan, seed, run)


def _step(console, k: int, text: str) -> None:
    console.print(f"[bold]step {k}/6[/bold] {text}", highlight=False)


def _calibration_lines(cal) -> list[str]:
    """What the calibration found, briefly (values +- standard uncertainties)."""
    a, ref = cal["alignment"], cal["reference"]
    return [f"  found: {calibrate.summary(cal)}",
            f"  backlash yaw {a['backlash_yaw_deg']:.3f} +- {a['u_backlash_yaw_deg']:.3f} deg, tilt "
            f"{a['backlash_tilt_deg']:.3f} +- {a['u_backlash_tilt_deg']:.3f} deg; reference factor a = "
            f"{ref['factor_a']:.4f}, b = {ref['factor_b']:.4f} (1 = Lambertian at a = b = 0); the lamp arm's zero "
            f"is not identifiable from specular scans: its surveyed u {a['lamp_zero_u_deg']} deg is carried into "
            "every point's angle budget"]


def _run_stages(out, session, sample, plan_obj, seed, posterior, console=None, quiet=False) -> dict:
    """Calibrate, capture, export, fit, benchmark, re-render, preview and report, timing each stage."""
    from gonio.bench.settings import load_settings
    from gonio.cli.capture import with_errors_and_calibration

    console = console or Console()
    timings = {}

    cal_path = out / "calibration.toml"
    t = time.perf_counter()
    _step(console, 1, f"calibrate: gonio calibrate --sim --errors {DEMO_ERRORS} --seed {seed} --out {cal_path} "
                      "(specular cross-scans of a glossy artefact at 4 azimuths, up and down; an exposure ladder; "
                      "the reference over a 5 x 5 grid)")
    settings = load_settings(None)
    settings["errors"] = {"preset": DEMO_ERRORS}
    with Steps("calibrate", enabled=not quiet) as progress:
        cal = calibrate.run_calibration(settings, sim=True, seed=seed, progress=progress)
    calibrate.write_calibration(cal_path, cal)
    timings["calibrate (simulated instrument)"] = time.perf_counter() - t
    for line in _calibration_lines(cal):
        console.print(line, highlight=False)

    _step(console, 2, f"capture: gonio capture --sim --errors {DEMO_ERRORS} --seed {seed} --calibration {cal_path} "
                      f"--plan {plan_obj.name} ({len(plan_obj)} points; the calibration corrects the angles, the "
                      "detector's linearity and the reference's factor)")
    t = time.perf_counter()
    settings = with_errors_and_calibration(load_settings(None), sim=True, seed=seed, errors=DEMO_ERRORS,
                                           calibration=cal_path)
    capture_sim(session, sample=sample, plan=plan_obj, seed=seed, settings=settings,
                progress=not quiet and on_terminal(), demo=True)
    timings["capture (simulated instrument)"] = time.perf_counter() - t

    _step(console, 3, "export: dataset.nc (calibrated angles and their u, each value's GUM budget by component)")
    t = time.perf_counter()
    with Steps("export", enabled=not quiet):
        dataset = export(session)
    with open(dataset, "rb") as src, atomic_open(out / "dataset.nc", "wb") as dst:
        shutil.copyfileobj(src, dst)
    timings["export dataset.nc"] = time.perf_counter() - t
    _step(console, 4, f"fit: {sample['model']} by chi2 with the budget carried into every parameter (u_stat, u_c, "
                      "U), the instrument's angular response modelled and its shared angle errors estimated with it"
                      + ("; emcee posterior" if posterior else ""))

    meas = load_dataset(dataset)
    with Steps("fit", enabled=not quiet) as progress:
        budget = open_budget(dataset, meas)
        result, doc, post = fit_dataset(meas, model=sample["model"], options=sample["options"], seed=seed,
                                        posterior=posterior, posterior_budget_s=30.0, dataset_path=dataset,
                                        budget=budget, progress=progress)
    timings["fit (nlopt + Laplace)"] = doc["optimiser"]["time_s"]
    if post is not None:
        timings["posterior (emcee)"] = post.time_s
    write_json_atomic(out / "fit.json", doc)

    fitted = data_as_fitted(meas, budget, result)[0]       # the apertures' c, the shared-angle estimate's geometry
    with Steps("fit speed against scipy", enabled=not quiet):
        speed = _speed_vs_error(fitted, result, sample, seed, doc)
    write_json_atomic(out / "speed.json", speed)

    _step(console, 5, "render: Mitsuba re-render at every measured pose, and sphere previews (fit vs truth)")
    t = time.perf_counter()
    with Steps("render at the measured poses", enabled=not quiet):
        closure = render_closure(out / "fit.json", fitted, out / "render")
    timings[f"Mitsuba re-render ({closure['variant']})"] = time.perf_counter() - t

    t = time.perf_counter()
    truth_model = gm.get(sample["model"], **sample["options"])
    with Steps("render previews", enabled=not quiet):
        with_truth = render_previews(out / "fit.json", out / "render",
                                     measured=_truth_bsdf(truth_model, sample["params"]), size=96, spp=128)
    timings["preview renders (sphere, 2 lightings)"] = time.perf_counter() - t

    _step(console, 6, "report: report.html (identification with the calibration applied, status, results with "
                      "u_c and U, figures, appendix)")
    t = time.perf_counter()
    with Steps("report", enabled=not quiet):
        report = write_report(out, out / "report.html")
    timings["report"] = time.perf_counter() - t
    return {"timings": timings, "meas": meas, "doc": doc, "speed": speed, "closure": closure,
            "with_truth": with_truth, "report": report, "calibration": cal, "calibration_path": cal_path}


def _print_summary(console, out, session, sample, plan, seed, run) -> dict:
    """The demo's table and figures on the console; returns the summary dict."""
    timings, meas, doc, speed, closure = run["timings"], run["meas"], run["doc"], run["speed"], run["closure"]
    with_truth, report = run["with_truth"], run["report"]
    console.rule("gonio demo")
    console.print(f"sample: {sample['model']} {sample['options']}  plan: {plan}  points: {meas.n_points}  seed: {seed}  "
                  f"instrument errors: {DEMO_ERRORS}, calibrated ({run['calibration_path'].name})")
    print_fit(doc, truth=sample, console=console)
    s = closure["summary"]
    console.print(f"Mitsuba ({closure['variant']}) vs measurement: rms residual {s['residual_rms_sigma']:.3f} sigma, "
                  f"max {s['residual_max_sigma']:.2f} sigma; export check (render vs model) max rel "
                  f"{s['export_max_rel']:.2e}")
    table = Table(title="wall time per stage")
    table.add_column("stage")
    table.add_column("seconds", justify="right")
    for stage, seconds in timings.items():
        table.add_row(stage, f"{seconds:.2f}")
    table.add_row("total", f"{sum(timings.values()):.2f}")
    console.print(table)
    print_table(console, [("optimiser", "left"), ("time (s)", "right"), ("evals", "right"), ("chi2", "right"),
                          ("max pull", "right")],
                [[row["optimiser"], f"{row['time_s']:.3f}", str(row["evaluations"]), f"{row['chi2']:.2f}",
                  f"{row['max_pull']:.2f}"] for row in speed["rows"]], title="fit speed against error",
                caption="max pull = max |fit - truth| / u_c over the parameters")
    if with_truth.get("delta_e_mean") is not None:
        console.print(f"preview: fit vs the true sample, mean CIEDE2000 {with_truth['delta_e_mean']:.2f} "
                      f"(Monte Carlo noise floor {_noise_floor(with_truth):.2f})")

    truths = truth_by_name(sample, list(doc["parameters"]))
    # z in the combined standard uncertainty u_c (the budget's; the statistical sigma where none)
    unc = (doc.get("uncertainty") or {}).get("parameters") or {}
    sig = {n: unc[n]["u_combined"] if n in unc else p["std"] for n, p in doc["parameters"].items()}
    z = {n: (p["value"] - truths[n]) / sig[n] for n, p in doc["parameters"].items() if n in truths and sig[n] > 0}
    worst = max(abs(v) for v in z.values()) if z else float("nan")
    verdict = "within" if worst <= 3 else "NOT within"
    console.print(f"every recovered parameter is {verdict} 3 sigma of the truth (sigma: u_c, combined; "
                  f"largest |z| = {worst:.2f})")
    console.print(f"wrote {run['calibration_path']}, {session}/, {out / 'dataset.nc'}, {out / 'fit.json'}, {out / 'render' / 'render.json'}, {report}")
    return {"timings": timings, "z": z, "closure": s, "fit": doc, "calibration": run["calibration"]}

