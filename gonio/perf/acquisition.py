"""``gonio perf acquisition``: instrument time against fit error, plan by plan (issue 38's front).

Every plan captures the same virtual sample on the simulated instrument (instant clock, the same
seed and error model); its instrument time is the dataset's ``instrument_time_s`` (motion,
settling, exposures and preparation on the simulator's clock, as journalled). The capture is
exported, fitted by chi2 with the dataset's budget (a sequential plan's points weighted by their
design weights unless ``-unweighted``): the sample's own family (roughplastic GGX for a measured
file), ``model``, or the family each capture's data choose (:data:`CHOOSE`), and
the fit scored against the truth on :func:`gonio.perf.real.dense_grid` (Ngan and log errors,
:func:`gonio.perf.real.metrics`) and by the preview's rendered CIEDE2000. The front: the plans
no other plan beats on both instrument time and Ngan error. Over several seeds
(:func:`run_seeds`), each plan is set against the dense grid of the same seed (:func:`paired`).
The sequential plans' peer at the same time is :data:`THINNED`: the dense plan thinned uniformly,
fitted as the dense grid is.
"""

from __future__ import annotations

import csv
import math
import tempfile
import time
from pathlib import Path

import numpy as np

from gonio.core.atomic import atomic_open
from gonio.core.errors import GonioError

__all__ = ["PLANS", "SEQUENTIAL", "THINNED", "CHOOSE", "thinned_stride", "front", "paired", "parse_seeds", "run",
           "run_seeds", "score", "strategy_table"]

#: plans compared by default (``adaptive``: the sequential design drawing from ``dense``; ``alc``
#: and ``ndf`` on request)
PLANS = ("quick", "standard", "adaptive")
#: the plans drawn from ``dense`` by a strategy: ``adaptive`` (D-optimal), ``alc`` (the adaptive
#: plan with ``criterion = "alc"``), ``ndf``; each fitted with its design weights
#: (gonio.bench.plan.design_weights), or without them as ``adaptive-unweighted``, ``alc-unweighted``
SEQUENTIAL = ("adaptive", "alc", "ndf", "adaptive-unweighted", "alc-unweighted")
#: the sequential plans' peer: every k-th point of the dense plan (from point seed mod k), fitted
#: without design weights as the dense grid is (the dense grid's own estimator on a k-th of its
#: points); k by :func:`thinned_stride` within the budget, or round(len(dense) / points) without one
THINNED = "thinned"
#: the suffix of a sequential plan fitted without its design weights
UNWEIGHTED = "-unweighted"
#: the adaptive plan's point budget by default
ADAPTIVE_POINTS = 24
#: ``model``: every plan's data (the dense grid's too) choose their family among the sequential
#: plans' candidates by weighted cross-validation (gonio.bench.plan.family.choose_cv); not the
#: default: on held-out materials it raised the dense grid's bar more than the plans followed
#: (docs/performance.md, "The family chosen from the data")
CHOOSE = "choose"


def truth_on_grid(sample: dict, wi, wo) -> np.ndarray:
    """The sample's true f_r at the grid: its model, or the measured file it was given as."""
    import gonio.models as gm

    from gonio.perf.real import measured_on_grid

    if "bsdf_file" in sample:
        return measured_on_grid(sample["bsdf_file"], wi, wo)
    model = gm.get(sample["model"], **sample.get("options", {}))
    return np.asarray(model.eval(wi, wo, model.validate(sample["params"])), dtype=np.float64)


def _truth_bsdf(sample: dict):
    import gonio.models as gm

    if "bsdf_file" in sample:
        return Path(sample["bsdf_file"])
    model = gm.get(sample["model"], **sample.get("options", {}))
    return model.to_mitsuba(model.validate(sample["params"]))


def score(result, sample: dict, *, render=True, seed=0) -> dict:
    """Ngan and log errors of a fit against the truth on the dense grid; the preview's mean
    CIEDE2000 against the truth rendered with the same seeds (NaN without ``render``)."""
    from gonio.perf.real import dense_grid, metrics

    wi, wo = dense_grid()
    m = metrics(result.model.eval(wi, wo, result.params), truth_on_grid(sample, wi, wo), wi)
    m["de00"] = float("nan")
    if render:
        from gonio.fitting.render.preview import preview

        with tempfile.TemporaryDirectory() as tmp:
            out = preview(result.model, result.params, tmp, measured=_truth_bsdf(sample), size=48, spp=128,
                          seed=seed)
        m["de00"] = float(out["delta_e_mean"])
    return m


def front(rows) -> list:
    """The rows no other row beats on both instrument time and Ngan error."""
    return [r for r in rows if not any((o["time_s"] <= r["time_s"] and o["ngan"] < r["ngan"])
                                       or (o["time_s"] < r["time_s"] and o["ngan"] <= r["ngan"]) for o in rows)]


def strategy_table(plan: str, seed: int, points: int, budget_s: float = 0.0) -> dict:
    """session.toml's ``[strategy]`` of a :data:`SEQUENTIAL` plan: at most ``points``, or as many
    as ``budget_s`` of instrument time allows where it is > 0."""
    base = plan.removesuffix(UNWEIGHTED)
    table = {"name": "ndf" if base == "ndf" else "adaptive", "seed": int(seed), "points": int(points)}
    if base == "alc":
        table["criterion"] = "alc"
    if plan.endswith(UNWEIGHTED):
        table["design_weights"] = False
    if budget_s > 0:
        table.update(budget_s=float(budget_s), points=0)
    return table


def _one(plan: str, sample: dict, model: str, options: dict, folder: Path, seed: int, points: int,
         settings: dict, budget_s: float = 0.0, estimate_angles: bool = False, dense_s: float = 0.0) -> dict:
    import xarray as xr

    from gonio.bench.dataset.export import export
    from gonio.bench.dataset.reader import open_budget, open_dataset
    from gonio.bench.session.simulated import capture_sim
    from gonio.fitting.pipeline import fit_measurements

    sequential = plan in SEQUENTIAL
    strategy = strategy_table(plan, seed, points, budget_s) if sequential else None
    t0 = time.perf_counter()
    if plan == THINNED:
        dataset = _thinned(folder, sample, seed, settings, points, budget_s, dense_s)
    else:
        session = folder / plan
        capture_sim(session, sample=sample, plan="dense" if sequential else plan, seed=seed, progress=False,
                    strategy=strategy, settings=settings)
        dataset = export(session)
    with xr.open_dataset(dataset) as ds:
        instrument_s = float(ds.attrs["instrument_time_s"])
        n_points = int(ds.sizes.get("point", 0))
    meas = open_dataset(Path(dataset), seed=seed)
    if model == CHOOSE:                 # the same rule on every plan's data: the family that predicts best
        from gonio.bench.plan.family import choose_cv

        model, options, _ = choose_cv(meas, _candidates(), seed=seed, n_local=1)
    result = fit_measurements(meas, model=model, options=options, seed=seed, budget=open_budget(Path(dataset), meas),
                              dataset_path=dataset, estimate_angles=estimate_angles)[0]
    from gonio.bench.plan.family import label

    row = {"plan": plan, "points": n_points, "time_s": instrument_s,
           "model": label(result.model.name, result.model.options), "estimate_angles": bool(estimate_angles),
           # whether the estimate was applied (it refuses itself where the model's misfit passes for
           # angle errors): "" where it was not asked for or the dataset states no inputs
           "angles_applied": (result.shared_angles or {}).get("applied", "")}
    row.update(score(result, sample, seed=seed))
    row["wall_s"] = time.perf_counter() - t0
    return row


def _thinned(folder: Path, sample: dict, seed: int, settings: dict, points: int, budget_s: float,
             dense_s: float) -> Path:
    """Capture :data:`THINNED` into ``folder``: its exported dataset. The captures of the other
    strides tried stay beside it, each named by its stride."""
    import xarray as xr

    from gonio.bench.dataset.export import export
    from gonio.bench.plan.plans import load_plan, thin
    from gonio.bench.session.simulated import capture_sim

    dense = load_plan("dense")
    done: dict[int, tuple[Path, float]] = {}

    def spent(k: int) -> float:
        session = folder / f"{THINNED}-{k}"
        capture_sim(session, sample=sample, plan=thin(dense, k, seed % k), seed=seed, progress=False,
                    settings=settings)
        dataset = export(session)
        with xr.open_dataset(dataset) as ds:
            done[k] = dataset, float(ds.attrs["instrument_time_s"])
        return done[k][1]

    if budget_s <= 0:
        k = max(1, round(len(dense) / max(1, int(points))))
        spent(k)
        return done[k][0]
    k = thinned_stride(math.ceil(min(dense_s / budget_s, len(dense)) - 1e-9), budget_s, spent, len(dense))
    if done[k][1] > budget_s:
        raise GonioError(f"--budget-fraction: {budget_s:.0f} s is less than one point of the dense plan takes "
                         f"({done[k][1]:.0f} s); give a larger fraction")
    return done[k][0]


def thinned_stride(start: int, budget_s: float, spent, most: int) -> int:
    """:data:`THINNED`'s stride: a k whose ``spent(k)`` (the capture's instrument time, s) is at
    most ``budget_s`` next to one over it (``start``'s where it fits; ``most`` where nothing does).
    The search goes up from ``start``, each next k from the line through the last two captures'
    times against their points (``most / k`` each; the first line through the origin): the stride
    whose points that line puts at ``budget_s``, at least one more than the last; then it bisects
    between the largest stride found over the budget and the least found within it. A capture
    has a fixed cost (its preparation) and a point's time grows as the points thin out (longer
    moves), not smoothly (each stride is another tour): the time is measured, not predicted once."""
    k = max(1, min(int(start), most))
    times = {k: spent(k)}
    while times[k] > budget_s and k < most:
        (n0, t0), (n1, t1) = ((0.0, 0.0) if len(times) == 1 else (most / prev, times[prev])), (most / k, times[k])
        slope = (t1 - t0) / (n1 - n0) if n1 != n0 else 0.0
        fits = (budget_s - (t1 - slope * n1)) / slope if slope > 0 else 0.0     # the points the line allows
        prev, k = k, min(most, max(k + 1, math.ceil(min(most / fits if fits >= 1.0 else most, most) - 1e-9)))
        times[k] = spent(k)
    if times[k] > budget_s:
        return k
    lo = max((j for j, t in times.items() if t > budget_s), default=k)   # over the budget
    hi = min(j for j, t in times.items() if t <= budget_s and j > lo) if lo < k else k
    while hi - lo > 1:                                 # the strides the line jumped over
        mid = (lo + hi) // 2
        times[mid] = spent(mid)
        lo, hi = (mid, hi) if times[mid] > budget_s else (lo, mid)
    return hi


def _candidates():
    """The sequential plans' default candidate families (or gonio.bench.plan.family's where
    their default is the plan's model alone)."""
    from gonio.bench.plan import family
    from gonio.bench.plan.adaptive import DEFAULTS

    return family.parse(DEFAULTS["candidates"]) or family.FAMILIES


def run(plans=PLANS, sample=None, *, model=None, options=None, seed=0, points=ADAPTIVE_POINTS, errors="typical",
        out=None, folder=None, budget_fraction=None, estimate_angles=True) -> list[dict]:
    """Capture, fit and score ``sample`` (a :func:`gonio.bench.samples.load_sample` dict; the demo
    sample by default) with each plan; print the table and the front; with ``out`` write the
    CSV there. ``model``: the family fitted (default the sample's own; roughplastic GGX for a
    measured file; :data:`CHOOSE`: each plan's data choose); ``errors``: the simulator's error preset (every plan the same instrument);
    ``budget_fraction``: the sequential plans stop at that fraction of the ``dense`` plan's
    instrument time (``dense`` must be among ``plans``; it runs first) instead of ``points``;
    ``estimate_angles`` (default on; off to reproduce the studies before 2026-12-05): every
    plan's fit estimates the shared angle errors (gonio.fitting's ``estimate_angles``)."""
    plans = tuple(plans)
    if budget_fraction is not None:
        f = budget_fraction
        if isinstance(f, bool) or not isinstance(f, (int, float)) or not 0 < f <= 1:
            raise GonioError(f"--budget-fraction {f!r}: give a fraction of the dense plan's time in (0, 1]")
        if "dense" not in plans:
            raise GonioError("--budget-fraction needs dense among --plans: the budget is a fraction of its time")
        plans = ("dense",) + tuple(p for p in plans if p != "dense")
    from gonio.bench.calibrate import with_errors_and_calibration
    from gonio.bench.samples import load_sample
    from gonio.bench.settings import load_settings

    settings = with_errors_and_calibration(load_settings(None), sim=True, seed=seed, errors=errors, calibration=None)

    sample = load_sample(None) if sample is None else sample
    if model is None:
        model, options = (("roughplastic", {"distribution": "ggx"}) if "bsdf_file" in sample
                          else (sample["model"], dict(sample.get("options", {}))))
    rows = []
    with tempfile.TemporaryDirectory(prefix="gonio-acq-") as tmp:
        base = Path(folder) if folder is not None else Path(tmp)
        for plan in plans:
            timed = budget_fraction and (plan in SEQUENTIAL or plan == THINNED)
            budget_s = budget_fraction * rows[0]["time_s"] if timed else 0.0
            rows.append(_one(plan, sample, model, dict(options or {}), base, seed, points, settings, budget_s,
                             estimate_angles, dense_s=rows[0]["time_s"] if timed else 0.0))
            _print(rows[-1:], head=len(rows) == 1)
    on_front = {id(r) for r in front(rows)}
    print(f"front (no plan both faster and closer): "
          f"{', '.join(r['plan'] for r in sorted(rows, key=lambda r: r['time_s']) if id(r) in on_front)}")
    print(f"fitted {'the family each plan chose (cross-validated)' if model == CHOOSE else model}"
          f"{', the shared angle errors estimated' if estimate_angles else ', the shared angle errors not estimated'}; simulator errors {errors!r}, seed {seed}; time: instrument_time_s of the simulated capture (motion, settling, exposures, "
          "preparation); Ngan, log: against the truth on the dense grid (theta <= 80 deg); dE00: preview, 48 px, "
          "128 spp, matched seeds; wall: capture, export, fit and scoring on this machine")
    if out is not None:
        _write(out, [{**r, "seed": seed} for r in rows], errors)
    return rows


def _write(out, rows, errors) -> None:
    """The rows (each with its ``seed``) as CSV at ``out`` (a .csv file or a folder), with the
    error preset and gonio's version."""
    path = Path(out) if Path(out).suffix.lower() == ".csv" else Path(out) / "acquisition.csv"
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]) + ["errors", "gonio"])
        w.writeheader()
        w.writerows([{**r, "errors": errors, "gonio": _version()} for r in rows])
    print(f"wrote {path}")


def parse_seeds(text: str) -> tuple:
    """``--seeds 10-13`` or ``10,12,15`` (or both, ``0-3,8``): the seeds in the order given, at
    least two, each once, from 0 to 2**63 - 1; one line otherwise."""
    seeds = []
    for part in str(text).split(","):
        a, dash, b = part.strip().partition("-")
        try:
            lo, hi = int(a), int(b) if dash else int(a)
        except ValueError:
            raise GonioError(f"--seeds {str(text)[:40]!r}: give seeds as 10-13 or 10,12,15") from None
        if not 0 <= lo <= hi < 2 ** 63 or hi - lo >= 1000:
            raise GonioError(f"--seeds {str(text)[:40]!r}: give ranges low-high from 0 to 2**63 - 1, at most 1000 seeds")
        seeds += range(lo, hi + 1)
    if len(seeds) < 2 or len(set(seeds)) != len(seeds) or len(seeds) > 1000:
        raise GonioError(f"--seeds {str(text)[:40]!r}: give at least two different seeds, each once (one: --seed)")
    return tuple(seeds)


def paired(rows, *, time_fraction=0.1, level=0.95) -> list[dict]:
    """Each plan against the dense grid captured with the same seed, over the seeds: how often
    both its errors are at most the dense grid's and its time at most ``time_fraction`` of it
    (``passes`` of ``n``), and each error's ratio to the dense grid's (``ngan``, ``log``: the
    geometric mean and its ``level`` interval, Student's t on the log ratios, as a ratio's
    spread is multiplicative; the interval NaN with one seed; all three NaN where a ratio is not
    finite and positive, counted in ``not_finite``); ``time``: the mean of the plan's time over
    the dense grid's. ``dense_cv``: the dense grid's own seed-to-seed spread (sd over mean) of
    each error. [] without dense rows."""
    from scipy import stats

    dense = {r["seed"]: r for r in rows if r["plan"] == "dense"}
    dense_cv = {}
    for m in ("ngan", "log"):
        d = np.array([r[m] for r in dense.values()], float)
        dense_cv[m] = float(d.std(ddof=1) / d.mean()) if len(d) > 1 else float("nan")
    out = []
    for plan in dict.fromkeys(r["plan"] for r in rows if r["plan"] != "dense" and r["seed"] in dense):
        mine = [r for r in rows if r["plan"] == plan and r["seed"] in dense]
        entry = {"plan": plan, "n": len(mine), "passes": sum(
            r["ngan"] <= dense[r["seed"]]["ngan"] and r["log"] <= dense[r["seed"]]["log"]
            and r["time_s"] <= time_fraction * dense[r["seed"]]["time_s"] for r in mine), "dense_cv": dense_cv}
        for m in ("ngan", "log"):
            with np.errstate(divide="ignore", invalid="ignore"):
                ratio = (np.array([r[m] for r in mine], float)
                         / np.array([dense[r["seed"]][m] for r in mine], float))
            entry.setdefault("not_finite", {})[m] = int(np.sum(~(np.isfinite(ratio) & (ratio > 0))))
            if entry["not_finite"][m]:          # a dense error of 0, an error NaN: no ratio to average
                entry[m] = (float("nan"),) * 3
                continue
            q = np.log(ratio)
            half = (stats.t.ppf(0.5 + level / 2, len(q) - 1) * q.std(ddof=1) / np.sqrt(len(q))
                    if len(q) > 1 else float("nan"))
            entry[m] = tuple(float(v) for v in np.exp([q.mean(), q.mean() - half, q.mean() + half]))
        entry["time"] = float(np.mean([r["time_s"] / dense[r["seed"]]["time_s"] for r in mine]))
        out.append(entry)
    return out


def run_seeds(plans, sample, seeds, *, out=None, errors="typical", **kw) -> tuple[list, list]:
    """:func:`run` once per seed, then :func:`paired`'s summary printed; with ``out`` one CSV of
    every seed's rows. Returns (rows, summary)."""
    rows = []
    for s in seeds:
        print(f"-- seed {s}", flush=True)
        rows += [{**r, "seed": s} for r in run(plans, sample, seed=s, errors=errors, **kw)]
    summary = paired(rows)
    if summary:
        print(f"over {len(seeds)} seeds, each plan against the dense grid of the same seed (ratio: geometric mean "
              f"[95 % interval]; passes: both errors at most the dense grid's, time at most 10 % of it):")
        print(f"{'plan':<20}{'passes':>8}{'Ngan ratio':>26}{'log ratio':>26}{'time':>8}")
        for e in summary:
            cells = "".join(f"{e[m][0]:>10.3f} [{e[m][1]:.3f}, {e[m][2]:.3f}]" if not e["not_finite"][m] else
                            f"{'n/a: ' + str(e['not_finite'][m]) + ' not finite':>26}" for m in ("ngan", "log"))
            print(f"{e['plan']:<20}{e['passes']:>5d}/{e['n']:<2d}{cells}{100 * e['time']:>7.2f}%")
        cv = summary[0]["dense_cv"]
        print(f"the dense grid's own spread over the seeds (sd / mean): Ngan {100 * cv['ngan']:.2f} %, "
              f"log {100 * cv['log']:.2f} %")
    if out is not None:
        _write(out, rows, errors)
    return rows, summary


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("gonio")
    except PackageNotFoundError:
        return "unknown"


def _print(rows, head=True):
    if head:
        print(f"{'plan':<20}{'points':>7}{'time s':>9}{'Ngan':>8}{'log':>9}{'dE00':>7}{'wall s':>8}  model")
    for r in rows:
        print(f"{r['plan']:<20}{r['points']:>7d}{r['time_s']:>9.1f}{r['ngan']:>8.4f}{r['log']:>9.5f}"
              f"{r['de00']:>7.2f}{r['wall_s']:>8.1f}  {r['model']}", flush=True)


def check_plans(text: str) -> tuple:
    """``--plans quick,standard,adaptive``: known presets or ``adaptive``; one line otherwise."""
    from gonio.bench.plan.plans import PRESETS

    names = tuple(p.strip() for p in str(text).split(",") if p.strip())
    bad = [p for p in names if p not in SEQUENTIAL and p not in PRESETS and p != THINNED]
    if not names or bad:
        raise GonioError(f"--plans {text!r}: give plan presets separated by commas "
                         f"({', '.join(PRESETS + SEQUENTIAL + (THINNED,))})")
    return names
