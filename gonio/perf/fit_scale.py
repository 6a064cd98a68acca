"""``gonio bench fit``'s scale row (issue 18): a 1e6-point fit in a fresh process, its time and
its peak memory against the data's own size."""

from __future__ import annotations

import numpy as np

import gonio.models as gm

from gonio.perf.fit_data import MODELS, simulate_capture


def _rss_peak_reset() -> bool:
    """Reset this process's peak resident set size (Linux: ``5`` into ``/proc/self/clear_refs``);
    False where that cannot be done (the peak then includes what came before)."""
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        return True
    except OSError:
        return False


def _rss_peak() -> int:
    """This process's peak resident set size in bytes (``VmHWM``; ``ru_maxrss`` elsewhere)."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass        # no /proc (not Linux): ru_maxrss below
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def _scale_child(n, seed):
    """In a fresh process: simulate ``n`` points of roughconductor (MODELS[1]), fit them,
    print one JSON line: the fit's time, the process's peak RSS during the fit (the peak
    reset after the simulation, where Linux allows it) against the RSS before it and the
    data's size, and, from a second, identical fit under ``tracemalloc``, the peak of the
    fit's own numpy and Python allocations (Dr.Jit's arrays are not traced: they are in the
    RSS)."""
    import json
    import tracemalloc

    from gonio.fitting.optimise.mle import fit

    name, options, truth = MODELS[1]
    model = gm.get(name, **options)
    truth = {k: np.asarray(v, dtype=np.float64) if isinstance(v, list) else v for k, v in truth.items()}
    meas, _ = simulate_capture(model, truth, n, np.random.default_rng([seed, 13]), 0.02)
    reset = _rss_peak_reset()
    rss0 = _rss_peak()
    res = fit(meas, model, rng=np.random.default_rng(seed))
    rss = _rss_peak()
    tracemalloc.start()
    fit(meas, model, rng=np.random.default_rng(seed))
    traced = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    x_true = res.space.from_params(model.validate(truth))
    data = sum(a.nbytes for a in (meas.wi, meas.wo, meas.brdf, meas.brdf_std, meas.use))
    print(json.dumps({"points": n, "time_s": res.time_s, "n_evals": res.n_evals, "chi2_dof": res.chi2_dof,
                      "peak_rss_bytes": rss, "rss_before_fit_bytes": rss0, "peak_reset": reset,
                      "traced_peak_bytes": traced, "data_bytes": int(data),
                      "max_err_sigma": float(np.max(np.abs(res.x - x_true) / res.std)), "method": res.method}))


def bench_scale(n=1_000_000, seed=0):
    """A fit of ``n`` points (roughconductor, the general path: Levenberg-Marquardt on normal
    equations reduced in the compiled kernel, no N x P Jacobian per iteration) in a child
    process (:func:`_scale_child`): wall time, the peak resident memory during the fit and
    the peak of its numpy allocations (tracemalloc), against the data's own size (wi, wo,
    f_r, sigma: 4 x 24 bytes a point, mask 3)."""
    import json
    import subprocess
    import sys

    code = f"from gonio.perf.fit_scale import _scale_child; _scale_child({int(n)}, {int(seed)})"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=1800)
    if out.returncode != 0:
        print(f"\nscale: the {n}-point fit failed: {out.stderr.strip().splitlines()[-1:]}")
        return {"points": n, "failed": True}
    row = json.loads(out.stdout.strip().splitlines()[-1])
    print(f"\nscale, roughconductor {n:,} points: fit {row['time_s']:.1f} s ({row['n_evals']} evaluations, "
          f"chi2/dof {row['chi2_dof']:.3f}, worst parameter {row['max_err_sigma']:.1f} sigma from the truth), "
          f"peak RSS during the fit {row['peak_rss_bytes'] / 2**20:.0f} MiB ("
          f"{row['rss_before_fit_bytes'] / 2**20:.0f} MiB before it, "
          f"{'peak reset after the simulation' if row['peak_reset'] else 'peak NOT reset: includes the simulation'}), "
          f"{(row['peak_rss_bytes'] - row['rss_before_fit_bytes']) / 2**20:.0f} MiB more than before = "
          f"{(row['peak_rss_bytes'] - row['rss_before_fit_bytes']) / row['data_bytes']:.2f}x the data "
          f"({row['data_bytes'] / 2**20:.0f} MiB: wi, wo, f_r, sigma, mask); numpy + Python allocations of the fit "
          f"(tracemalloc peak, a second identical fit) {row['traced_peak_bytes'] / 2**20:.0f} MiB = "
          f"{row['traced_peak_bytes'] / row['data_bytes']:.2f}x the data; {row['method']}")
    return row
