"""``gonio demo``: the whole loop on the simulated instrument, timed stage by stage.

capture (simulated instrument over its serial protocols, RAW files, calibration against the
reference on the holder) -> export (dataset.nc) -> fit (nlopt, Laplace, emcee) -> Mitsuba
re-render at the measured geometry -> HTML report. The sample's true BRDF is known, so the
table compares what was recovered with the truth, in units of the reported uncertainty.
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
from gonio.fitting.speed import scipy_lsq
from gonio.models.atomic import atomic_open
from gonio.models.mitsuba import mitsuba_variant

from ._console import print_table
from ._fitdoc import truth_by_name
from ._preflight import check_output_dir
from ._samples import load_sample
from .errors import GonioError
from .export import export
from .fit_runner import fit_dataset, open_budget, print_fit, render_closure, render_previews
from .plans import load_plan
from .report import write_report
from .session_runner import capture_sim

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


def _speed_vs_error(meas, result, sample, seed) -> dict:
    """Time and error of gonio's fit and of scipy's least_squares (the peer) on this capture.

    Both minimise the same chi^2; the error is the largest |fit - truth| / sigma over the
    parameters (sigma: gonio's Laplace 1-sigma), so a value below ~3 is at the noise limit.
    """
    truth = result.space.from_params({k: np.asarray(v, dtype=float) for k, v in sample["params"].items()})
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
                     "chi2": float(r @ r), "max_pull": float(np.max(np.abs((x - truth) / result.std))),
                     "rmse_fr": float(np.sqrt(np.mean(((fr - meas.brdf)[meas.use]) ** 2)))})
    return {"points": int(meas.n_points), "model": result.model.name, "rows": rows, "seed": seed,
            "versions": versions()}


def run_demo(out: Path, seed: int = 1, plan: str = "standard", posterior: bool = True) -> dict:
    """Run the loop; returns a summary dict (the figures printed)."""
    console = Console()
    out = Path(out)
    plan_obj = load_plan(plan)          # a bad plan is refused before anything is written
    # RAW files (about 150 kB a point with the calibration frames), dataset, fit, renders
    check_output_dir(out, "demo output folder (--out)", need_bytes=len(plan_obj) * 256 * 1024 + 32 * 2 ** 20)
    out.mkdir(parents=True, exist_ok=True)
    session = out / "session"
    _clear_previous_demo(session)
    sample = load_sample(None)
    run = _run_stages(out, session, sample, plan_obj, seed, posterior)
    return _print_summary(console, out, session, sample, plan, seed, run)


def _run_stages(out, session, sample, plan_obj, seed, posterior) -> dict:
    """Capture, export, fit, benchmark, re-render, preview and report, timing each stage."""
    timings = {}

    t = time.perf_counter()
    capture_sim(session, sample=sample, plan=plan_obj, seed=seed, progress=True, demo=True)
    timings["capture (simulated instrument)"] = time.perf_counter() - t

    t = time.perf_counter()
    dataset = export(session)
    with open(dataset, "rb") as src, atomic_open(out / "dataset.nc", "wb") as dst:
        shutil.copyfileobj(src, dst)
    timings["export dataset.nc"] = time.perf_counter() - t

    meas = load_dataset(dataset)
    result, doc, post = fit_dataset(meas, model=sample["model"], options=sample["options"], seed=seed,
                                    posterior=posterior, posterior_budget_s=30.0, dataset_path=dataset,
                                    budget=open_budget(dataset, meas))
    timings["fit (nlopt + Laplace)"] = doc["optimiser"]["time_s"]
    if post is not None:
        timings["posterior (emcee)"] = post.time_s
    write_json_atomic(out / "fit.json", doc)

    speed = _speed_vs_error(meas, result, sample, seed)
    write_json_atomic(out / "speed.json", speed)

    t = time.perf_counter()
    closure = render_closure(out / "fit.json", meas, out / "render")
    timings[f"Mitsuba re-render ({closure['variant']})"] = time.perf_counter() - t

    t = time.perf_counter()
    truth_model = gm.get(sample["model"], **sample["options"])
    with_truth = render_previews(out / "fit.json", out / "render", measured=_truth_bsdf(truth_model, sample["params"]),
                                 size=96, spp=128)
    timings["preview renders (sphere, 2 lightings)"] = time.perf_counter() - t

    t = time.perf_counter()
    report = write_report(out, out / "report.html")
    timings["report"] = time.perf_counter() - t
    return {"timings": timings, "meas": meas, "doc": doc, "speed": speed, "closure": closure,
            "with_truth": with_truth, "report": report}


def _print_summary(console, out, session, sample, plan, seed, run) -> dict:
    """The demo's table and figures on the console; returns the summary dict."""
    timings, meas, doc, speed, closure = run["timings"], run["meas"], run["doc"], run["speed"], run["closure"]
    with_truth, report = run["with_truth"], run["report"]
    console.rule("gonio demo")
    console.print(f"sample: {sample['model']} {sample['options']}  plan: {plan}  points: {meas.n_points}  seed: {seed}")
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
                caption="max pull = max |fit - truth| / sigma over the parameters")
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
    console.print(f"wrote {session}/, {out / 'dataset.nc'}, {out / 'fit.json'}, {out / 'render' / 'render.json'}, {report}")
    return {"timings": timings, "z": z, "closure": s, "fit": doc}

