"""``gonio bench fit``: speed against error of the fitter and of its peer.

A fixed matrix -- models x number of points {100, 1e3, 1e4, 1e5} x relative noise x optimiser --
on simulated captures with known truth: directions drawn with the seeded rng (half of them near
the mirror direction, where the lobe is), f_r from the model, Gaussian noise sigma = rel * f_r +
floor. Optimisers: ``gonio`` (:func:`gonio.fitting.fit` as shipped: stratified global stage,
variable projection + Levenberg-Marquardt, compiled kernels, Laplace covariance);
``gonio-local`` (the same from the declared defaults only, ``n_starts=0``); ``nlopt-mma``,
``nlopt-slsqp`` (LD_MMA, LD_SLSQP from the defaults on the same chi^2 with its exact in-kernel
gradient); ``scipy-lsq`` (``scipy.optimize.least_squares``, trust-region reflective, 2-point
finite differences, bounds, numpy ``model.eval``, from the defaults). Per cell (mean over
``reps`` captures; below 1e5 points each time is the median of :data:`REPEAT` runs after one
untimed run per optimiser): wall time, parameter error (RMS of (x - truth) / CRLB, ~1 at the
noise limit), RMSE of f_r against the noiseless truth, chi^2/dof, the efficiency CRLB^2 / MSE
(worst parameter, :mod:`gonio.fitting.uncertainty.crlb`). :func:`run_real`: :mod:`gonio.perf.real`.
"""

# The peers: nlopt's local optimisers are the peers of gonio's local stage; scipy-lsq on the same
# chi^2 residuals is what a user of scipy would write. run_real (gonio bench fit --real FILES) is
# the measured-material table: gonio's chosen fit beside a scipy log-loss peer on a dense grid.

from __future__ import annotations

import csv
import time
from pathlib import Path

import numpy as np

import gonio.models as gm
from gonio.models import fast

from gonio.perf.fit_dask import bench_dask
from gonio.perf.fit_scale import bench_scale
from gonio.perf.fit_data import MODELS, simulate_capture
from gonio.perf.real import run_real

__all__ = ["run", "run_real", "simulate_capture"]

POINTS = (100, 1000, 10000, 100000)
NOISE = (0.01, 0.05)
OPTIMISERS = ("gonio", "gonio-local", "nlopt-mma", "nlopt-slsqp", "scipy-lsq")
#: nlopt algorithms benchmarked as local stages (exact gradients from the compiled kernel)
NLOPT_LOCAL = {"nlopt-mma": "LD_MMA", "nlopt-slsqp": "LD_SLSQP"}


def scipy_lsq(meas, model):
    import scipy.optimize

    from gonio.fitting.likelihood import loss as _loss
    from gonio.fitting.optimise.space import ParameterSpace

    space = ParameterSpace(model, meas.n_channels)
    t0 = time.perf_counter()
    res = scipy.optimize.least_squares(
        lambda x: _loss.residuals("chi2", model.eval(meas.wi, meas.wo, space.to_params(x)), meas),
        space.default(), bounds=(space.lower, space.upper))
    return res.x, time.perf_counter() - t0, res.nfev + res.njev * space.size


def _nlopt_local(meas, model, algorithm):
    """nlopt's gradient-based local optimisers (LD_MMA, LD_SLSQP) on the same chi^2 from the
    declared defaults, with the exact gradient of the compiled kernel
    (:func:`gonio.models.fast.chi2_grad`, float64) chained into the unit box: the peers of
    gonio's Levenberg-Marquardt local stage. Returns (x, seconds, evaluations)."""
    import nlopt

    from gonio.fitting.optimise.space import ParameterSpace

    space = ParameterSpace(model, meas.n_channels)
    t0 = time.perf_counter()
    dirs = fast.Directions(meas.wi, meas.wo, np.float64)
    y = dirs.channels(np.where(meas.use, meas.brdf, 0.0), "y")
    w = dirs.channels(np.where(meas.use, 1.0 / meas.brdf_std ** 2, 0.0), "w")
    n_evals = [0]
    best = [np.inf, None]  # nlopt raises on a round-off stop without handing back its point

    def chi2_u(u, grad):
        x = space.from_unit(u)
        chi2, g = fast.chi2_grad(model, dirs, space.to_params(x), y, w)
        n_evals[0] += 1
        if chi2 < best[0]:
            best[:] = [chi2, np.array(u)]
        if grad.size:
            grad[:] = space.from_params(g) * space.dx_du(x) / norm
        return chi2 / norm

    u0 = space.to_unit(space.default())
    norm = 1.0
    norm = max(chi2_u(u0, np.zeros(0)), 1e-300)  # objective of order 1 (SLSQP's line search)
    opt = nlopt.opt(getattr(nlopt, algorithm), space.size)
    opt.set_lower_bounds(np.zeros(space.size))
    opt.set_upper_bounds(np.ones(space.size))
    opt.set_min_objective(chi2_u)
    opt.set_ftol_rel(1e-10)
    opt.set_xtol_rel(1e-8)
    opt.set_maxeval(1000)
    try:
        opt.optimize(u0)
    except nlopt.RoundoffLimited:
        pass
    return space.from_unit(best[1]), time.perf_counter() - t0, n_evals[0]


def run(quick: bool = False, out: Path | None = None, reps: int | None = None, seed: int = 0) -> list[dict]:
    """Run the matrix, print the table; with ``out``, write ``fit_bench.csv`` and ``fit_bench.png``.

    ``quick`` (the test's setting, < 1 min): roughplastic only, 100 and 1000 points, one
    noise level, 2 captures per cell, each optimiser run once per capture with no untimed
    run before it (with the tables uncached every run pays for its own: nlopt MMA's ~70
    evaluations of ~40 ms each made the full repeats 55 s of the suite).
    """
    from gonio.fitting.uncertainty.crlb import crlb, efficiency
    from gonio.fitting.optimise.mle import fit

    models = MODELS[:1] if quick else MODELS
    points = POINTS[:2] if quick else POINTS
    noise = NOISE[:1] if quick else NOISE
    reps = reps or (2 if quick else 5)
    rows = []
    for name, options, truth in models:
        model = gm.get(name, **options)
        truth = {k: np.asarray(v, dtype=np.float64) if isinstance(v, list) else v for k, v in truth.items()}
        for n in points:
            for rel in noise:
                n_reps = reps if n < 100_000 else max(2, reps // 2)  # the 1e5 cells: fewer captures
                caps = [simulate_capture(model, truth, n, np.random.default_rng([seed, n, int(rel * 1e4), r]), rel)
                        for r in range(n_reps)]
                names, bound = crlb(caps[0][0], model, truth)
                for opt in OPTIMISERS:
                    xs, times, rmses, chi, evals = [], [], [], [], []
                    repeat = 1 if quick else (REPEAT if n < 100_000 else 1)
                    if n < 100_000 and not quick:  # untimed: the kernels recorded for this size (every optimiser)
                        _run_one(opt, caps[0][0], model, 0, fit)
                    for r, (meas, f_true) in enumerate(caps):
                        runs = [_run_one(opt, meas, model, r, fit) for _ in range(repeat)]
                        x, _, ne, fr, c, space = runs[0]
                        dt = float(np.median([run[1] for run in runs]))  # a shared machine's load: the median
                        chi.append(c)
                        x_true = space.from_params(model.validate(truth))
                        xs.append(x)
                        times.append(dt)
                        evals.append(ne)
                        rmses.append(float(np.sqrt(np.mean((fr - f_true) ** 2))))
                    x_true = space.from_params(model.validate(truth))
                    err = np.sqrt(np.mean(((np.array(xs) - x_true) / bound) ** 2))
                    eff = efficiency(xs, x_true, bound)["efficiency"]
                    rows.append({"model": name, "points": n, "noise": rel, "optimiser": opt,
                                 "time_s": float(np.mean(times)), "evals": float(np.mean(evals)),
                                 "param_err_crlb": float(err), "rmse_fr": float(np.mean(rmses)),
                                 "chi2_dof": float(np.mean(chi)), "efficiency_min": float(np.min(eff)),
                                 "reps": n_reps})
    _print(rows)
    _print_verdicts(cell_verdicts(rows))
    extra = {} if quick else {"crossover": bench_crossover(seed=seed), "emcee": bench_emcee(seed=seed),
                              "dask": bench_dask(seed=seed), "scale": bench_scale(seed=seed)}
    if out is not None:
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        with open(out / "fit_bench.csv", "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
        _plot(rows, out / "fit_bench.png")
        if extra:
            import json

            (out / "fit_bench_extra.json").write_text(json.dumps(extra, indent=1, default=float))
    return rows


#: runs of each optimiser on each capture below 1e5 points, the median time kept (the results
#: are the same run to run): on a shared machine one run's wall time is mostly others' load
REPEAT = 3


def _run_one(opt, meas, model, r, fit):
    """One optimiser on one capture: (x, seconds, evaluations, f_r at x, chi2/dof, space).

    Every run starts with the per-parameter table caches empty (:func:`gonio.models.fast.
    clear_parameter_caches`): a run repeated on the same capture (:data:`REPEAT`) would
    otherwise find every roughplastic table it needs computed by the run before it. A
    deterministic peer revisits the same (alpha, eta) each time, so its repeats cost nothing
    but the data kernel (nlopt SLSQP at 1e3 points: 0.010 s with the caches warm, ~1 s cold
    at 40 ms a new table), while gonio's affine path makes its tables in the kernel and had
    no such discount: before this, every roughplastic cell up to 1e4 points read "peer ahead"
    (gonio/SLSQP 3.9-8.3, 2026-12-02)."""
    from gonio.fitting.optimise.space import ParameterSpace

    fast.clear_parameter_caches()
    if opt == "scipy-lsq" or opt in NLOPT_LOCAL:
        x, dt, ne = scipy_lsq(meas, model) if opt == "scipy-lsq" else _nlopt_local(meas, model, NLOPT_LOCAL[opt])
        space = ParameterSpace(model, meas.n_channels)
        fr = model.eval(meas.wi, meas.wo, space.to_params(x))
        return x, dt, ne, fr, float(np.sum(((fr - meas.brdf) / meas.brdf_std) ** 2)) / (meas.n_used - len(x)), space
    kw = {"n_starts": 0, "n_local": 1} if opt == "gonio-local" else {}
    res = fit(meas, model, rng=np.random.default_rng(r), **kw)
    return res.x, res.time_s, res.n_evals, model.eval(meas.wi, meas.wo, res.params), res.chi2_dof, res.space


#: a peer's error counts as equal to gonio's within this factor (err/CRLB, mean over captures)
EQUAL_ERROR = 1.1


def cell_verdicts(rows):
    """Per (model, points, noise) cell: gonio's time over the fastest peer's whose parameter
    error is at most ``EQUAL_ERROR`` x gonio's (issue 18: no peer ahead at equal error);
    peers with a larger error do not count (they did not solve the same problem)."""
    cells = {}
    for r in rows:
        cells.setdefault((r["model"], r["points"], r["noise"]), {})[r["optimiser"]] = r
    out = []
    for (model, n, noise), by in cells.items():
        ours = by.get("gonio")
        if ours is None:
            continue
        peers = [r for k, r in by.items() if not k.startswith("gonio")
                 and r["param_err_crlb"] <= EQUAL_ERROR * ours["param_err_crlb"]]
        best = min(peers, key=lambda r: r["time_s"]) if peers else None
        out.append({"model": model, "points": n, "noise": noise, "gonio_s": ours["time_s"],
                    "best_peer": best["optimiser"] if best else None, "peer_s": best["time_s"] if best else None,
                    "ratio": (ours["time_s"] / best["time_s"]) if best else None})
    return out


def _print_verdicts(verdicts):
    print(f"\n{'model':<15}{'N':>7}{'noise':>7}  gonio s   fastest peer at equal error (<= {EQUAL_ERROR} x gonio's err)")
    for v in verdicts:
        peer = (f"{v['best_peer']:<12} {v['peer_s']:.3f} s  gonio/peer {v['ratio']:.2f}"
                + ("  PEER AHEAD" if v["ratio"] > 1.0 else "")) if v["best_peer"] else "none at equal error"
        print(f"{v['model']:<15}{v['points']:>7}{v['noise']:>7.2f}  {v['gonio_s']:7.3f}   {peer}")


def _print(rows):
    head = f"{'model':<15}{'N':>7}{'noise':>7}  {'optimiser':<12}{'time s':>9}{'evals':>8}{'err/CRLB':>10}{'RMSE f_r':>11}{'chi2/dof':>9}{'eff min':>9}"
    print(head)
    print("-" * len(head))
    for r in rows:
        print(f"{r['model']:<15}{r['points']:>7}{r['noise']:>7.2f}  {r['optimiser']:<12}{r['time_s']:>9.3f}"
              f"{r['evals']:>8.0f}{r['param_err_crlb']:>10.2f}{r['rmse_fr']:>11.2e}{r['chi2_dof']:>9.3f}"
              f"{r['efficiency_min']:>9.2f}")


def _plot(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for opt, marker in zip(OPTIMISERS, "osvD^"):
        sel = [r for r in rows if r["optimiser"] == opt]
        for ax, key, label in ((axes[0], "param_err_crlb", "parameter error / CRLB"), (axes[1], "rmse_fr", "RMSE f_r (sr^-1)")):
            ax.scatter([r["time_s"] for r in sel], [r[key] for r in sel], marker=marker, label=opt)
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xlabel("wall time (s)")
            ax.set_ylabel(label)
    axes[0].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def bench_emcee(n=10000, n_walkers=32, seed=0):
    """Posterior of a roughplastic RGB fit to ``n`` points: wall time, tau, independent
    samples, and log-probability evaluations per second against plain emcee on the same
    data with the numpy reference model (all 5 parameters, walkers looped), the issue's peer."""
    import emcee

    from gonio.fitting.optimise.mle import fit
    from gonio.fitting.uncertainty.posterior import sample_posterior
    from gonio.fitting.optimise.space import ParameterSpace

    name, options, truth = MODELS[0]
    model = gm.get(name, **options)
    truth = {k: np.asarray(v, dtype=np.float64) if isinstance(v, list) else v for k, v in truth.items()}
    meas, _ = simulate_capture(model, truth, n, np.random.default_rng([seed, 7]), 0.01)
    res = fit(meas, model, rng=np.random.default_rng(seed))
    post = sample_posterior(meas, res, rng=np.random.default_rng(seed), n_walkers=n_walkers, max_steps=6000, chunk=250)
    ours = post.n_steps * post.n_walkers / post.time_s
    space = ParameterSpace(model, 3)

    def log_prob(x):
        if np.any(x < space.lower) or np.any(x > space.upper):
            return -np.inf
        r = (model.eval(meas.wi, meas.wo, space.to_params(x)) - meas.brdf) / meas.brdf_std
        return -0.5 * float(np.sum(r[meas.use] ** 2))

    rng = np.random.default_rng(seed)
    p0 = res.x + 1e-3 * res.std * rng.standard_normal((32, space.size))
    sampler = emcee.EnsembleSampler(32, space.size, log_prob)
    t0 = time.perf_counter()
    sampler.run_mcmc(p0, 5, progress=False)
    peer = 5 * 32 / (time.perf_counter() - t0)
    row = {"points": n, "walkers": post.n_walkers, "steps": post.n_steps, "time_s": post.time_s,
           "tau_max": float(np.max(post.tau)), "n_independent": post.n_independent, "converged": post.converged,
           "evals_per_s": ours, "peer_evals_per_s": peer, "surrogate_error": post.surrogate_error}
    print(f"\nemcee, roughplastic RGB, {n} points, {post.n_walkers} walkers: {post.n_steps} steps in "
          f"{post.time_s:.1f} s, tau {np.max(post.tau):.0f}, {post.n_independent:.0f} independent samples "
          f"({post.n_independent / post.time_s:.0f}/s), converged {post.converged}")
    print(f"log-probability evaluations/s: gonio {ours:,.0f}, plain emcee + numpy model {peer:,.0f} "
          f"(ratio {ours / peer:.0f}); table surrogate error {post.surrogate_error}")
    return row


#: the sizes of :func:`bench_crossover`
CROSSOVER_POINTS = (30, 100, 300, 1000, 3000, 10000)


def bench_crossover(seed=0, reps=3, points=CROSSOVER_POINTS, model_index=1):
    """Where the problem's shape moves gonio's choices (issue 18), roughconductor (``MODELS[1]``,
    1 % noise) at each N:

    * the fit: gonio's default (compiled: Levenberg-Marquardt steps from the compiled normal
      equations at every N, :data:`gonio.fitting.likelihood.problem.NORMAL_LOSSES`), the same loop on
      the numpy evaluator (``use_fast=False``: what gonio ran below ``FAST_MIN_POINTS``
      before), and nlopt LD_SLSQP with the compiled gradient (the best peer at small N);
      each the mean over ``reps`` captures of the best of 3 runs, in CPU seconds of every
      thread (:func:`_cpu`: a shared machine's load lengthens wall time, not this);
    * one call: the sum of squares against the normal equations (the trial step is costed
      by the normal equations up to :data:`gonio.fitting.likelihood.problem.TRIAL_NORMAL_MAX` points,
      so that an accepted step brings the next step's equations), best of 50."""
    from gonio.fitting.optimise.mle import fit
    from gonio.fitting.likelihood.problem import FAST_MIN_POINTS, TRIAL_NORMAL_MAX

    name, options, truth = MODELS[model_index]
    model = gm.get(name, **options)
    truth = {k: np.asarray(v, dtype=np.float64) if isinstance(v, list) else v for k, v in truth.items()}
    rows = []
    print(f"\ncrossover, {name} {options}, 1 % noise: fit CPU seconds, all threads (mean over {reps} captures of "
          "the best of 3; CPU time, not wall: load-independent), and one kernel call (wall, best of 50)")
    print(f"{'N':>7}  {'gonio':>8} {'numpy path':>11} {'slsqp':>8} {'gonio/slsqp':>12} {'numpy/gonio':>12}   "
          f"{'sse us':>8} {'normal us':>10}  trial costed by")
    for n in points:
        caps = [simulate_capture(model, truth, n, np.random.default_rng([seed, 17, n, r]), 0.01)[0] for r in range(reps)]
        fits = {"gonio": lambda m, r: fit(m, model, rng=np.random.default_rng(r)),
                "numpy": lambda m, r: fit(m, model, rng=np.random.default_rng(r), use_fast=False),
                "slsqp": lambda m, r: _nlopt_local(m, model, "LD_SLSQP")}
        best = {k: [] for k in fits}
        for r, meas in enumerate(caps):
            for k, fn in fits.items():
                fn(meas, r)  # kernels compiled, tables cached
                best[k].append(min(_cpu(fn, meas, r) for _ in range(3)))
        t = {k: float(np.mean(v)) for k, v in best.items()}
        meas = caps[0]
        dirs = fast.Directions(meas.wi, meas.wo, np.float64)
        y, w = dirs.channels(meas.brdf, "y"), dirs.channels(1.0 / meas.brdf_std ** 2, "w")
        p = model.validate(truth)
        calls = {"sse": lambda: fast.weighted_sse(model, dirs, p, y, w),
                 "normal": lambda: fast.normal_equations(model, dirs, p, y, w)}
        call = {}
        for k, fn in calls.items():
            fn()
            call[k] = min(_clocked(fn) for _ in range(50))
        row = {"points": n, "gonio_s": t["gonio"], "numpy_path_s": t["numpy"], "slsqp_s": t["slsqp"],
               "sse_call_s": call["sse"], "normal_call_s": call["normal"],
               "trial": "normal equations" if n <= TRIAL_NORMAL_MAX else "sum of squares"}
        rows.append(row)
        print(f"{n:>7}  {t['gonio']:8.4f} {t['numpy']:11.4f} {t['slsqp']:8.4f} {t['gonio'] / t['slsqp']:12.2f} "
              f"{t['numpy'] / t['gonio']:12.2f}   {call['sse'] * 1e6:8.0f} {call['normal'] * 1e6:10.0f}  {row['trial']}")
    print(f"gonio fits on the compiled path at every N (chi2 without variable projection); below {FAST_MIN_POINTS} "
          f"points it used the numpy path (the 'numpy path' column). Trials are costed by the normal equations up to "
          f"{TRIAL_NORMAL_MAX} points, by the sum of squares above (1e5 pairs: ~0.4 ms against ~1.3 ms a call).")
    return rows


def _cpu(fn, *args):
    """CPU seconds of ``fn(*args)``, every thread of the process (Dr.Jit's included): unlike
    wall time, not lengthened by other processes' load on a shared machine."""
    c0 = time.process_time()
    fn(*args)
    return time.process_time() - c0


def _clocked(fn):
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0
