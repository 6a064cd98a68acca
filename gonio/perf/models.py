"""Throughput benchmark of the models against Mitsuba 3's own ``bsdf.eval``.

``gonio bench models`` calls :func:`run`. Not a test: figures depend on the machine. For each
model (default options plus GGX variants) at one *coloured* parameter set and one batch of
``n`` random direction pairs on the upper hemisphere it times, best of ``repeat``: ``numpy``
(the reference), ``eval`` and ``eval32`` (the public ``Model.eval`` on float64 / float32 numpy
directions, numpy round trip included), ``drjit32`` (:meth:`gonio.models.engine.fast.Bound.eval`
on a resident float32 batch), ``jac32``, ``grad32``, ``chi32``, ``evp32`` (Jacobian, chi^2
gradient, chi^2, prepared evaluation on that batch), ``mitsuba`` (``bsdf.eval`` on resident
Mitsuba arrays, no numpy round trip) and ``mi+np`` (a Mitsuba user's numpy-to-numpy path). The
figure of merit is ``drjit32`` over ``mitsuba``, timed head to head, with ratios such as
``ev/mi``, ``ev32/mi``, ``jac/ev``, ``grad/ev``, ``grad/chi``, ``e64/mi``; the memory-bandwidth
limits (:func:`copy_bandwidth`) are printed beside them. With one Dr.Jit thread
(``GONIO_THREADS=1``) times are the process's CPU time (:func:`clock`). Definitions: the
comment below; measurements: docs/performance.md.
"""

# What each timing is:
# * parameters: the defaults with the per-channel values spread, so no path can evaluate one
#   channel for three.
# * numpy: the reference implementation, model.eval_reference (float64).
# * eval: the public API, model.eval(wi, wo, p) on the numpy arrays: the compiled float64 kernel
#   with the numpy round trip (gonio.models.engine.fast.eval; also reported as drjit64).
# * eval32: the public API on the same directions as float32 numpy arrays (converted once,
#   before timing): model.eval(wi32, wo32, p), the compiled float32 kernel with the numpy round
#   trip, float32 (N, 3) out (the fast path).
# * drjit32: gonio.models.engine.fast.Bound.eval (parameters loaded once, as Mitsuba's
#   load_dict) on a float32 gonio.models.engine.fast.Directions batch loaded once, results left
#   in Dr.Jit.
# * jac32: gonio.models.engine.fast.jacobian, the same batch: f_r and its derivative with
#   respect to every parameter (N x 3 values per parameter, left in Dr.Jit).
# * grad32: gonio.models.engine.fast.chi2_grad, the same batch with resident data and weights:
#   chi^2 and its gradient with respect to every parameter (reduced in the kernel). Where the
#   model declares its parameter-independent geometry (structure.geometry: cooktorrance,
#   diffuse, orennayar, roughconductor with an isotropic roughness) it reads that geometry,
#   prepared once per batch (Directions.geometry, before timing, as a fit prepares it once),
#   instead of the directions; the others read the directions.
# * chi32 (not printed as a rate): gonio.models.engine.fast.weighted_sse, the chi^2 alone on the
#   same data and the same inputs as grad32 (prepared geometry or directions): the function whose
#   gradient grad32 is (grad/chi; both read y and w and sum in the kernel, where drjit32 writes
#   f_r).
# * evp32 (not printed as a rate): Bound.eval(prepared=True), the evaluation on the same prepared
#   geometry (the directions where the model declares none: then drjit32's kernel), f_r left in
#   Dr.Jit: grad/evp is grad32 over it, grad/ev over drjit32, the evaluation on the directions.
# * mitsuba: bsdf.eval in the variant chosen by mitsuba_variant, on the same batch already
#   converted to Mitsuba arrays (float32), results left in Dr.Jit: Mitsuba's kernel alone, with
#   NO numpy round trip (the hardest peer: gonio's side pays its numpy round trip, Mitsuba's
#   does not).
# * mi+np (mitsuba_np): what a Mitsuba user writes to get f_r from numpy, the peer of the public
#   eval32: the float32 (N, 3) numpy directions through gonio.models.mitsuba.interaction (a
#   transposed numpy copy and a Dr.Jit copy of each), bsdf.eval, np.asarray(f).T (a copy to
#   numpy, seen as (N, 3) through a transposed view: Fortran order, one interleave fewer than
#   gonio's C-order output).
#
# Ratios: drjit32 and mitsuba run under the same conditions (float32, resident inputs, one fused
# kernel, outputs evaluated) and are timed head to head, taking turns; their ratio is the figure
# of merit, with ev/mi and ev32/mi (the public eval, float64 and float32 directions, numpy round
# trip included, over Mitsuba's rate), jac/ev and grad/ev (the Jacobian's and the chi^2
# gradient's times over drjit32's), grad/ev64 (the chi^2 gradient over the evaluation, both
# float64 and resident: the fitter's precision), grad/chi and grad/chi64 (the gradient over the
# chi^2 it differentiates) and e64/mi (the resident float64 kernel over Mitsuba's rate: the
# public float64 eval does that kernel's work plus the numpy round trip, so ev/mi cannot exceed
# it). Each timing ends with dr.sync_thread() (the LLVM backend launches asynchronously). With
# one Dr.Jit thread the CPU times are robust to the other processes of a shared machine.
#
# Physical limit: a resident evaluation reads the two directions and writes f_r, so it can go no
# faster than the machine's memory bandwidth over the bytes it moves per pair (36 in float32:
# Mitsuba's and drjit32's; 72 in float64 with numpy in and out: eval's and numpy's). The
# bandwidth is measured in the same run (copy_bandwidth: a large copy, read + write, on every
# thread) and the limits are printed beside the figures.

from __future__ import annotations

import os
import sys
import time

import numpy as np

from gonio.models.engine import fast
from gonio.models.base import get
from gonio.models.mitsuba import interaction, mitsuba_variant

__all__ = ["run", "CASES", "coloured_params"]

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


def coloured_params(model):
    """The model's defaults with per-channel values scaled by (1.2, 1.0, 0.8) (kept inside
    the bounds), so the three channels differ."""
    p = model.defaults()
    for par in model.parameters:
        if par.per_channel:
            v = np.asarray(p[par.name], dtype=np.float64) * np.array([1.2, 1.0, 0.8])
            p[par.name] = np.clip(v, par.lower, par.upper)
    return model.validate(p)


def clock():
    """The benchmark's clock: the process's CPU time when Dr.Jit runs on one thread
    (``GONIO_THREADS=1``: every timed path, Mitsuba's included, then runs on one core, and
    CPU time does not count the time other processes of a shared machine take that core),
    the wall clock otherwise (CPU time would add the threads up)."""
    if fast.available():
        import drjit as dr

        if dr.thread_count() <= 1:
            return time.process_time
    return time.perf_counter


def _interleaved_best(timed, repeat):
    """Best time of each callable over ``repeat`` rounds, the callables taking turns within
    a round so that all of them see the same machine (a shared host's load drifts); one
    untimed call first (JIT compilation, table caches)."""
    now = clock()
    for fn in timed.values():
        fn()
    best = dict.fromkeys(timed, float("inf"))
    for _ in range(repeat):
        for key, fn in timed.items():
            t0 = now()
            fn()
            best[key] = min(best[key], now() - t0)
    return best


def _mitsuba_timer(model, params, wi, wo):
    """Callables running Mitsuba's bsdf.eval on the batch: ``(resident, with_numpy)``, and
    the variant (None, None without Mitsuba).

    ``resident``: the batch already converted to Mitsuba's arrays (float32), results left in
    Dr.Jit (evaluated): Mitsuba's kernel alone. ``with_numpy``: what a Mitsuba user writes to
    get the same from numpy, the counterpart of the public ``model.eval``: float32 (N, 3)
    numpy directions in (:func:`gonio.models.mitsuba.interaction`: numpy's transposed copy
    of each into a (3, N) array, Dr.Jit's copy of that into a ``Vector3f``), ``bsdf.eval``,
    and numpy out: ``np.asarray(v).T``, Dr.Jit's copy of the (3, N) result into numpy seen
    as (N, 3) through a transposed view (Fortran order; gonio's ``eval`` returns C order, so
    this peer does one interleave less)."""
    try:
        variant = mitsuba_variant()
        import drjit as dr
        import mitsuba as mi
    except Exception:  # pragma: no cover - environment dependent
        return None, None, None
    if not variant.startswith(("llvm", "cuda")):
        return None, None, variant
    bsdf = mi.load_dict(model.to_mitsuba(params))
    si, w = interaction(wi, wo)
    ctx = mi.BSDFContext()
    dr.eval(si, w)
    wi32, wo32 = wi.astype(np.float32), wo.astype(np.float32)

    def go():
        v = bsdf.eval(ctx, si, w)
        dr.eval(v)
        dr.sync_thread()

    def go_numpy():
        s, d = interaction(wi32, wo32)
        return np.asarray(bsdf.eval(ctx, s, d)).T

    return go, go_numpy, variant


COLUMNS = ("numpy", "eval", "eval32", "drjit32", "jac32", "grad32", "mitsuba", "mitsuba_np")
#: COLUMNS as printed
HEADERS = {"mitsuba_np": "mi+np"}
EXTRA = ("32/mi", "ev/mi", "ev32/mi", "ev/mnp", "ev32/mnp", "e64/mi", "jac/ev", "grad/ev", "grad/ev64", "grad/chi", "grad/chi64",
         "grad/evp", "grad/evp64", "32/lim", "ev/lim")
#: Bytes a resident evaluation moves per direction pair: two directions in, f_r out (RGB).
BYTES_PER_PAIR = {"float32": 3 * 4 * 3, "float64": 3 * 8 * 3}


def copy_bandwidth(nbytes=256 << 20, repeat=9):
    """The machine's copy bandwidth in bytes/s (read + write counted), best of ``repeat``:
    a copy moving ``nbytes`` in all (half read, half written) by Dr.Jit on all its threads
    (as the kernels run), or by numpy where the compiled path is unavailable. Measured on a
    working set of the benchmark batch's size, the limit sees the same caches."""
    if fast.available():
        import drjit as dr
        from drjit.llvm.ad import Float

        x = dr.zeros(Float, max(nbytes // 8, 1))  # read half the bytes, write the other half
        dr.make_opaque(x)  # in memory, not a literal

        def go():
            y = x + 1.0
            dr.eval(y)
            dr.sync_thread()
    else:
        x = np.zeros(max(nbytes // 16, 1))
        y = np.empty_like(x)

        def go():
            np.copyto(y, x)
    go()
    best = min(_timed(go) for _ in range(repeat))
    return float(nbytes) / best


def _limits(bw32, bw64):
    """Evaluations/s each column could reach at the copy bandwidth measured on a working set
    of its own size (None where no bound is stated: the Jacobian's output depends on the
    model). A model that reads fewer components (the diffuse ones need only the two
    cosines) can pass the limit: it is the bound for reading every component once."""
    b32, b64 = BYTES_PER_PAIR["float32"], BYTES_PER_PAIR["float64"]
    return {"bandwidth": bw32, "bandwidth64": bw64, "numpy": bw64 / b64, "eval": bw64 / b64, "eval32": bw32 / b32,
            "drjit32": bw32 / b32,
            "mitsuba": bw32 / b32, "mitsuba_np": bw32 / b32, "grad32": bw32 / b32 * (b32 / 48), "jac32": None}


def _timed(fn):
    now = clock()
    t0 = now()
    fn()
    return now() - t0


def _resident(fn):
    """A timer of a resident-batch call: the call, then wait for Dr.Jit's kernels."""
    import drjit as dr

    def go():
        fn()
        dr.sync_thread()

    return go


def _compiled_timers(model, p, wi, wo, dirs, dirs64, rng):
    """The compiled paths' timers for one model (``drjit64`` ... ``grad64``)."""
    wi32, wo32 = wi.astype(np.float32), wo.astype(np.float32)
    timed = {"eval": lambda: model.eval(wi, wo, p), "eval32": lambda: model.eval(wi32, wo32, p)}
    bound = fast.Bound(model, p, np.float32)
    timed["drjit32"] = _resident(lambda: bound.eval(dirs, numpy=False))
    timed["jac32"] = _resident(lambda: fast.jacobian(model, dirs, p, numpy=False))
    f_true = model.eval(wi, wo, p)
    y_np = f_true * (1.0 + 0.01 * rng.standard_normal(f_true.shape))
    w_np = 1.0 / (0.01 * np.maximum(f_true, 1e-3)) ** 2
    y32, w32 = dirs.channels(y_np), dirs.channels(w_np)
    y64, w64 = dirs64.channels(y_np), dirs64.channels(w_np)
    timed["evalp32"] = _resident(lambda: bound.eval(dirs, numpy=False, prepared=True))
    timed["grad32"] = lambda: fast.chi2_grad(model, dirs, p, y32, w32)
    timed["chi32"] = lambda: fast.weighted_sse(model, dirs, p, y32, w32)
    bound64 = fast.Bound(model, p, np.float64)
    timed["eval64"] = _resident(lambda: bound64.eval(dirs64, numpy=False))
    timed["evalp64"] = _resident(lambda: bound64.eval(dirs64, numpy=False, prepared=True))
    timed["grad64"] = lambda: fast.chi2_grad(model, dirs64, p, y64, w64)
    timed["chi64"] = lambda: fast.weighted_sse(model, dirs64, p, y64, w64)
    return timed


def _head_to_head(timed, t, repeat):
    """drjit32 against mitsuba timed alone, taking turns which goes first: next to the numpy
    columns (hundreds of MB through the caches between timings) the ratio moved by up to
    30 % with the order."""
    if "drjit32" in timed and "mitsuba" in timed:
        pair = {"drjit32": timed["drjit32"], "mitsuba": timed["mitsuba"]}
        flip = {"mitsuba": timed["mitsuba"], "drjit32": timed["drjit32"]}
        h2h = [_interleaved_best(pair if r % 2 == 0 else flip, 2) for r in range(2 * repeat)]
        return {k: min(h[k] for h in h2h) for k in pair}
    return {"drjit32": t["drjit32"], "mitsuba": t["mitsuba"]}


def _row(name, options, t, head, n):
    row = {"model": name, "options": dict(options)}
    row.update({k: (n / v if v else None) for k, v in t.items() if k in COLUMNS})
    row["ratio"] = (head["mitsuba"] / head["drjit32"]) if (head["mitsuba"] and head["drjit32"]) else None
    row["eval_ratio"] = (t["mitsuba"] / t["eval"]) if (t.get("mitsuba") and t.get("eval")) else None
    row["eval32_ratio"] = (t["mitsuba"] / t["eval32"]) if (t.get("mitsuba") and t.get("eval32")) else None
    row["eval64_ratio"] = (t["mitsuba"] / t["eval64"]) if (t.get("mitsuba") and t.get("eval64")) else None
    row["eval_np_ratio"] = (t["mitsuba_np"] / t["eval"]) if (t.get("mitsuba_np") and t.get("eval")) else None
    row["eval32_np_ratio"] = (t["mitsuba_np"] / t["eval32"]) if (t.get("mitsuba_np") and t.get("eval32")) else None
    row["drjit64"] = row.get("eval")
    row.update({f"{k}_h2h": (n / v if v else None) for k, v in head.items()})
    for key, num, den in (("jac_cost", "jac32", "drjit32"), ("grad_cost", "grad32", "drjit32"),
                          ("grad_cost64", "grad64", "eval64"), ("grad_chi", "grad32", "chi32"),
                          ("grad_chi64", "grad64", "chi64"), ("grad_cost_p", "grad32", "evalp32"),
                          ("grad_cost_p64", "grad64", "evalp64")):
        row[key] = (t[num] / t[den]) if (t.get(num) and t.get(den)) else None
    return row


def _round_trips_here(n):
    """Which numpy round trip the public eval of ``n`` pairs takes on this machine, float64
    and float32 (:func:`gonio.models.engine.fast.takes_copies`: a race run once per process)."""
    from gonio.models.engine.fast import takes_copies

    def which(dtype):
        return "numpy copies in, kernel, interleave out" if takes_copies(n, dtype) else \
            "numpy memory gathered by the kernel, channels interleaved"
    f64, f32 = which(np.float64), which(np.float32)
    return f64 if f64 == f32 else f"float64: {f64}; float32: {f32}"


def _print_row(row, name, options, out):
    def fmt(x, width, scale=1e-6, digits=1):
        return f"{x * scale:{width}.{digits}f}" if x is not None else f"{'-':>{width}}"

    label = name + "".join(f" {v}" for v in options.values())
    print(f"{label:<26}" + "".join(fmt(row[c], 9) for c in COLUMNS)
          + "".join(fmt(row[k], 11, 1, 2) for k in ("ratio", "eval_ratio", "eval32_ratio", "eval_np_ratio", "eval32_np_ratio",
                                                     "eval64_ratio", "jac_cost", "grad_cost",
                                                     "grad_cost64", "grad_chi", "grad_chi64", "grad_cost_p",
                                                     "grad_cost_p64", "of_limit32", "of_limit64")), file=out)


def _print_goals(rows, out):
    """Issue 18's goals in words, from this run's rows: the public eval of its example model
    (roughplastic) over Mitsuba's resident kernel (>= 0.5) for float32 and float64
    directions, with the float64 kernel's own ratio (the ceiling for float64 directions),
    and the largest gradient/evaluation ratio (<= 3)."""
    def span(key, sel=lambda r: True):
        vals = [r[key] for r in rows if r.get(key) is not None and sel(r)]
        return (min(vals), max(vals)) if vals else None

    plastic = span("eval32_ratio", lambda r: r["model"] == "roughplastic")
    if plastic is None:
        return
    p64, e64 = span("eval_ratio", lambda r: r["model"] == "roughplastic"), \
        span("eval64_ratio", lambda r: r["model"] == "roughplastic")
    g32, g64 = span("grad_cost"), span("grad_cost64")
    if None in (p64, e64, g32, g64):
        return

    def verdict(lo, goal, above=True):
        return "met" if (lo >= goal if above else lo <= goal) else "NOT met"
    print(f"issue 18, gm.get('roughplastic').eval(wi, wo, p) over Mitsuba's resident kernel (goal >= 0.5, numpy "
          f"round trip included): float32 directions (Mitsuba's own precision) {plastic[0]:.3f}-{plastic[1]:.3f}, "
          f"{verdict(plastic[0], 0.5)}; float64 directions {p64[0]:.3f}-{p64[1]:.3f}, {verdict(p64[0], 0.5)} "
          f"(the resident float64 kernel alone reaches {e64[0]:.3f}-{e64[1]:.3f} of Mitsuba's float32 one: the "
          f"ceiling for float64 directions on this CPU). Gradient over evaluation (goal <= 3): float32 at most "
          f"{g32[1]:.2f}, float64 at most {g64[1]:.2f}, {verdict(max(g32[1], g64[1]), 3.0, above=False)}.", file=out)


def run(n=1_000_000, repeat=9, cases=CASES, file=None, seed=0):
    """Print evaluations per second per model and return the figures.

    Parameters
    ----------
    n : int
        Direction pairs per batch.
    repeat : int
        Rounds of timings (the best is kept; a first, JIT-compiling call is extra).
    cases : sequence of (name, options)
    file : text stream
        Where to print (default stdout).
    seed : int
        Seed of the direction batch.

    Returns
    -------
    list of dict
        One dict per case: ``model``, ``options``, and evaluations/s ``numpy``,
        ``drjit64`` (= ``eval``), ``eval32``, ``drjit32``, ``jac32``, ``mitsuba`` (None where
        unavailable), ``eval_ratio`` and ``eval32_ratio`` (mitsuba's time over the public
        eval's, float64 and float32 directions), ``ratio``
        (drjit32 / mitsuba, head to head; their rates there in ``drjit32_h2h`` and
        ``mitsuba_h2h``), ``jac_cost`` and ``grad_cost`` (time of the Jacobian and of
        chi2_grad / time of drjit32) and ``grad_cost64`` (the same in float64).
    """
    out = file or sys.stdout
    rng = np.random.default_rng(seed)

    def hemi(k):
        v = rng.normal(size=(k, 3))
        v[:, 2] = np.abs(v[:, 2])
        return v / np.linalg.norm(v, axis=1)[:, None]

    wi, wo = hemi(n), hemi(n)
    compiled = fast.available()
    if compiled:
        dirs = fast.Directions(wi, wo, np.float32)
        dirs64 = fast.Directions(wi, wo, np.float64)
    rows = []
    print(f"gonio.models benchmark: N = {n:,} pairs, Mevals/s (best of {repeat}; load average "
          f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores at the start)", file=out)
    print(f"{'model':<26}" + "".join(f"{HEADERS.get(c, c):>9}" for c in COLUMNS) + "".join(f"{c:>11}" for c in EXTRA), file=out)
    # the copy of a working set of the batch's own size (the same caches as the timed paths)
    limits = _limits(copy_bandwidth(n * BYTES_PER_PAIR["float32"]), copy_bandwidth(n * BYTES_PER_PAIR["float64"]))
    print(f"{'limit (memory bandwidth)':<26}" + "".join(f"{limits[c] * 1e-6:9.0f}" if limits.get(c) else f"{'-':>9}"
                                                      for c in COLUMNS), file=out)
    variant = None
    for name, options in cases:
        model = get(name, **options)
        p = coloured_params(model)
        model.eval_reference(wi[:1000], wo[:1000], p)  # warm caches (tables)
        timed = {"numpy": lambda: model.eval_reference(wi, wo, p)}
        if compiled:
            timed.update(_compiled_timers(model, p, wi, wo, dirs, dirs64, rng))
        go, go_numpy, variant = _mitsuba_timer(model, p, wi, wo)
        if go is not None:
            timed["mitsuba"] = go
            timed["mitsuba_np"] = go_numpy
        t = dict.fromkeys(COLUMNS)
        t.update(_interleaved_best(timed, repeat))
        row = _row(name, options, t, _head_to_head(timed, t, repeat), n)
        row["limits"] = limits
        row["of_limit32"] = row["drjit32"] / limits["drjit32"] if row.get("drjit32") else None
        row["of_limit64"] = row["eval"] / limits["eval"] if row.get("eval") else None
        rows.append(row)
        _print_row(row, name, options, out)
    print(f"times: {'CPU time of the process (one Dr.Jit thread)' if clock() is time.process_time else 'wall clock'}, "
          f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores at the end", file=out)
    print("columns: numpy = model.eval_reference (float64 numpy); eval, eval32 = the public model.eval(wi, wo, p) "
          "on float64 / float32 numpy (N, 3) directions, numpy (N, 3) f_r out (numpy round trip included: "
          f"{_round_trips_here(n)} here, the faster of the two in a race on this machine: "
          "gonio/models/engine/fast.takes_copies); drjit32 = gonio's float32 kernel on a resident batch, f_r left in Dr.Jit; jac32, "
          "grad32 = its Jacobian and chi^2 gradient, resident; mitsuba = Mitsuba's bsdf.eval on a resident batch "
          "(already Mitsuba arrays), result left in Dr.Jit: Mitsuba's kernel alone, NO numpy round trip; mi+np = "
          "Mitsuba with its own numpy round trip from the same float32 (N, 3) numpy directions (interaction(): a "
          "transposed numpy copy and a Dr.Jit copy of each direction; bsdf.eval; np.asarray(f).T: a copy to numpy, "
          "(N, 3) as a transposed view, no interleave)", file=out)
    print("32/mi: drjit32 against mitsuba timed head to head (the columns: all paths in turn); ev/mi, ev32/mi: the "
          "public model.eval over resident mitsuba (issue 18's goal >= 0.5; gonio's numpy round trip included, "
          "Mitsuba's not): float64 directions (float64 kernel and out) and float32 ones "
          "(float32 kernel and out: the fast path), timed in the same rounds; ev/mnp, ev32/mnp: the same over "
          "mi+np (both sides with their numpy round trip); e64/mi: the resident "
          "float64 kernel alone over mitsuba, the most ev/mi can reach; jac/ev, grad/ev: against "
          "drjit32 in turn (the evaluation on the directions); grad/ev64: float64; grad/chi, grad/chi64: chi2_grad "
          "over weighted_sse, the chi^2 whose gradient it is (same inputs, same reads of y and w, in-kernel sums); "
          "grad32 and chi32 read the geometry prepared once per batch where the model declares it (cooktorrance, "
          "diffuse, orennayar, isotropic roughconductor; the directions for the others); grad/evp, grad/evp64: "
          "chi2_grad over the evaluation on that same prepared geometry (Bound.eval(prepared=True)); "
          "32/lim, ev/lim: fraction of the "
          "memory-bandwidth limit "
          f"(copy bandwidth {limits['bandwidth'] * 1e-9:.1f} GB/s on a float32 batch's working set, "
          f"{limits['bandwidth64'] * 1e-9:.1f} GB/s on a float64 one, measured in this run, read + write; "
          f"{BYTES_PER_PAIR['float32']} B/pair float32 (eval32 with numpy in and out too), "
          f"{BYTES_PER_PAIR['float64']} B/pair float64 with numpy in and out; grad32 on the directions reads y "
          "and w too: 48 B/pair; on prepared geometry 4 (diffuse), 8 (orennayar), 16 (cooktorrance) or 28 B "
          "(roughconductor) of it with y and w: 28-52 B/pair)", file=out)
    if variant is not None:
        print(f"Mitsuba variant: {variant}", file=out)
    _print_goals(rows, out)
    if not compiled:
        print("Dr.Jit LLVM backend unavailable: compiled paths not timed", file=out)
    return rows


if __name__ == "__main__":  # pragma: no cover
    run()
