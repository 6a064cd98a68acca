"""Throughput benchmark of the models against Mitsuba 3's own ``bsdf.eval``.

``gonio bench models`` calls :func:`run`. Not a test: figures depend on the machine.
For each model (default parameters, default options, plus GGX variants) and one batch
of ``n`` random direction pairs on the upper hemisphere it times, best of ``repeat``:

* ``numpy``: the reference implementation, ``model.eval``;
* ``drjit``: the compiled path, :func:`gonio.models._fast.eval` (if LLVM works);
* ``grad``: :func:`gonio.models._fast.value_and_grad` (f_r and the gradient with respect
  to every parameter, one reverse-mode pass);
* ``mitsuba``: ``bsdf.eval`` in the variant chosen by :func:`mitsuba_variant`, on the
  same batch already converted to Mitsuba arrays (float32, its native precision).

and prints millions of evaluations per second and the ratios drjit / mitsuba and
grad / drjit cost. All timings include the conversion from and to numpy of the gonio
paths; Mitsuba's excludes it (its inputs are built once).
"""

from __future__ import annotations

import sys
import time

import numpy as np

__all__ = ["run", "CASES"]

#: (model name, options) benchmarked by default.
CASES = (
    ("diffuse", {}),
    ("roughconductor", {"distribution": "beckmann"}),
    ("roughconductor", {"distribution": "ggx"}),
    ("roughplastic", {"distribution": "beckmann"}),
    ("roughplastic", {"distribution": "ggx"}),
    ("cooktorrance", {}),
    ("orennayar", {}),
)


def _best(fn, repeat):
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def _mitsuba_timer(model, params, wi, wo):
    """A callable running Mitsuba's bsdf.eval on the batch, or None without Mitsuba."""
    try:
        from ._mitsuba import mitsuba_variant

        variant = mitsuba_variant()
        import drjit as dr
        import mitsuba as mi
    except Exception:  # pragma: no cover - environment dependent
        return None, None
    if not variant.startswith(("llvm", "cuda")):
        return None, variant
    bsdf = mi.load_dict(model.to_mitsuba(params))
    n = wi.shape[0]
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.wi = mi.Vector3f(np.ascontiguousarray(wo.T.astype(np.float32)))
    si.sh_frame = mi.Frame3f(mi.Normal3f(0.0, 0.0, 1.0))
    w = mi.Vector3f(np.ascontiguousarray(wi.T.astype(np.float32)))
    ctx = mi.BSDFContext()
    dr.eval(si, w)

    def go():
        v = bsdf.eval(ctx, si, w)
        dr.eval(v)
        dr.sync_thread()  # the LLVM backend launches asynchronously

    return go, variant


def run(n=1_000_000, repeat=3, cases=CASES, file=None, seed=0):
    """Print evaluations per second per model and return the figures.

    Parameters
    ----------
    n : int
        Direction pairs per batch.
    repeat : int
        Timings per figure (the best is kept; the first, JIT-compiling call is extra).
    cases : sequence of (name, options)
    file : text stream
        Where to print (default stdout).
    seed : int
        Seed of the direction batch.

    Returns
    -------
    list of dict
        One dict per case: ``model``, ``options``, ``numpy``, ``drjit``, ``grad``,
        ``mitsuba`` (evaluations/s, None where unavailable), ``ratio`` (drjit / mitsuba)
        and ``grad_cost`` (time of value_and_grad / time of drjit eval).
    """
    from . import _fast, get

    out = file or sys.stdout
    rng = np.random.default_rng(seed)

    def hemi(k):
        v = rng.normal(size=(k, 3))
        v[:, 2] = np.abs(v[:, 2])
        return v / np.linalg.norm(v, axis=1)[:, None]

    wi, wo = hemi(n), hemi(n)
    fast = _fast.available()
    rows = []
    header = f"{'model':<34}{'numpy':>10}{'drjit':>10}{'grad':>10}{'mitsuba':>10}{'drjit/mi':>10}{'grad/eval':>10}"
    print(f"gonio.models benchmark: N = {n:,} pairs, Mevals/s (best of {repeat})", file=out)
    print(header, file=out)
    variant = None
    for name, options in cases:
        model = get(name, **options)
        p = model.defaults()
        model.eval(wi[:1000], wo[:1000], p)  # warm caches (tables)
        t_np = _best(lambda: model.eval(wi, wo, p), repeat)
        t_dr = t_gr = None
        if fast:
            cot = np.ones((n, 3))
            _fast.eval(model, wi, wo, p)
            t_dr = _best(lambda: _fast.eval(model, wi, wo, p), repeat)
            _fast.value_and_grad(model, wi, wo, p, cot)
            t_gr = _best(lambda: _fast.value_and_grad(model, wi, wo, p, cot), repeat)
        go, variant = _mitsuba_timer(model, p, wi, wo)
        t_mi = None
        if go is not None:
            go()
            t_mi = _best(go, repeat)
        row = {
            "model": name,
            "options": dict(options),
            "numpy": n / t_np,
            "drjit": n / t_dr if t_dr else None,
            "grad": n / t_gr if t_gr else None,
            "mitsuba": n / t_mi if t_mi else None,
        }
        row["ratio"] = (t_mi / t_dr) if (t_mi and t_dr) else None
        row["grad_cost"] = (t_gr / t_dr) if (t_gr and t_dr) else None
        rows.append(row)

        def fmt(x, scale=1e-6):
            return f"{x * scale:10.1f}" if x is not None else f"{'-':>10}"

        label = name + "".join(f" {v}" for v in options.values())
        print(
            f"{label:<34}{fmt(row['numpy'])}{fmt(row['drjit'])}{fmt(row['grad'])}{fmt(row['mitsuba'])}"
            f"{fmt(row['ratio'], 1)}{fmt(row['grad_cost'], 1)}",
            file=out,
        )
    if variant is not None:
        print(f"Mitsuba variant: {variant}", file=out)
    if not fast:
        print("Dr.Jit LLVM backend unavailable: compiled path not timed", file=out)
    return rows


if __name__ == "__main__":  # pragma: no cover
    run()
