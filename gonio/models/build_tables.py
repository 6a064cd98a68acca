"""Build ``models/data/roughplastic_tables.npz``: the roughplastic tables on a grid.

Run ``python -m gonio.models.build_tables [--out PATH] [--jobs N]``. For each distribution
(beckmann, ggx) it computes :func:`gonio.models.physics.rough_tables.rough_tables` (exact,
float64) at alpha log-spaced over the model's declared bounds [1e-4, 1] (``N_ALPHA`` nodes) and
eta over the declared ``int_ior`` bounds [1.0001, 4], uniform in ``y = log(eta - 1 +
ETA_SHIFT)`` (``N_ETA`` nodes: dense near eta = 1, where the tables change fastest, sparser
toward 4), and at the centre of every cell, where it records the error of the interpolant of
:func:`gonio.models.physics.rough_tables.rough_tables_interp` (cells above ``INTERP_TOL`` are
evaluated exactly at run time). Stored arrays (float64 unless noted):

``log_alpha`` (N_ALPHA,), ``y_eta`` (N_ETA,), ``eta_shift`` (), ``t_<kind>``
(N_ALPHA, N_ETA, 64), ``r_<kind>`` (N_ALPHA, N_ETA), ``err_<kind>`` (N_ALPHA - 1,
N_ETA - 1) float32, ``version`` ().
"""

from __future__ import annotations

import argparse
import ctypes
import os
import time
from multiprocessing import get_context
from pathlib import Path

import numpy as np

from gonio.core.atomic import atomic_open

from gonio.models.physics import rough_tables as rt
from gonio.models.catalogue.roughplastic import RoughPlastic

KINDS = ("beckmann", "ggx")
N_ALPHA = 57  # 14 nodes per decade over [1e-4, 1]
N_ETA = 49
ETA_SHIFT = 0.1
VERSION = 1


def grid():
    """(log alpha nodes, y nodes) from the model's declared parameter bounds."""
    par = {p.name: p for p in RoughPlastic().parameters}
    a, e = par["alpha"], par["int_ior"]
    x = np.linspace(np.log(a.lower), np.log(a.upper), N_ALPHA)
    y = np.linspace(np.log(e.lower - 1.0 + ETA_SHIFT), np.log(e.upper - 1.0 + ETA_SHIFT), N_ETA)
    return x, y


def _eta(y):
    return float(np.exp(y) - ETA_SHIFT + 1.0)


def _init_worker():
    # numpy's large temporaries are mmap-ed and unmapped on every call by default; keeping
    # them in the heap avoids the page faults (2.5x faster tables, build only).
    try:
        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt(-3, 1 << 30)  # M_MMAP_THRESHOLD
        libc.mallopt(-1, 1 << 30)  # M_TRIM_THRESHOLD
    except (OSError, AttributeError):
        pass


def _node(args):
    kind, x, y = args
    t, r = rt.rough_tables(kind, float(np.exp(x)), _eta(y))
    rt.rough_tables.cache_clear()
    return np.concatenate([t, [r]])


def _compute(pool, kind, xs, ys):
    jobs = [(kind, x, y) for x in xs for y in ys]
    vals = pool.map(_node, jobs, chunksize=16)
    return np.array(vals).reshape(len(xs), len(ys), rt.RES + 1)


def diffuse_error(approx, exact):
    """Relative error of t(mu_i) t(mu_o) / (1 - R_int) bound from table errors (..., 65)."""
    t, r = exact[..., :-1], exact[..., -1]
    dt = np.abs(approx[..., :-1] - t) / np.maximum(t, 1e-300)
    return 2.0 * dt.max(axis=-1) + np.abs(approx[..., -1] - r) / (1.0 - r)


def build(out, jobs=2):
    x, y = grid()
    xc, yc = 0.5 * (x[1:] + x[:-1]), 0.5 * (y[1:] + y[:-1])
    data = {"log_alpha": x, "y_eta": y, "eta_shift": np.float64(ETA_SHIFT), "version": np.int64(VERSION)}
    centre = {}
    t0 = time.perf_counter()
    with get_context("fork").Pool(jobs, initializer=_init_worker) as pool:
        for kind in KINDS:
            nodes = _compute(pool, kind, x, y)
            data[f"t_{kind}"] = np.ascontiguousarray(nodes[..., :-1])
            data[f"r_{kind}"] = np.ascontiguousarray(nodes[..., -1])
            centre[kind] = _compute(pool, kind, xc, yc)
            print(f"{kind}: {time.perf_counter() - t0:.0f} s", flush=True)
    # interpolation error at the cell centres (tol = inf: no cell masked yet)
    g = rt._prepare_grid({**data, **{f"err_{k}": np.zeros((len(xc), len(yc))) for k in KINDS}})
    rt._GRID = g
    for kind in KINDS:
        approx = np.array([[np.concatenate(_interp_np(kind, a, b)) for b in yc] for a in xc])
        err = diffuse_error(approx, centre[kind])
        data[f"err_{kind}"] = err.astype(np.float32)
        q = np.quantile(err, [0.5, 0.9, 0.99])
        print(
            f"{kind}: cell-centre error of the diffuse term: median {q[0]:.1e}, 90% {q[1]:.1e}, "
            f"99% {q[2]:.1e}, max {err.max():.1e}; cells above INTERP_TOL={rt.INTERP_TOL:g}: "
            f"{np.mean(err > rt.INTERP_TOL):.1%}"
        )
    rt._GRID = None
    out = Path(out)
    with atomic_open(out, "wb") as fh:
        np.savez_compressed(fh, **data)
    print(f"wrote {out} ({out.stat().st_size / 1e6:.2f} MB) in {time.perf_counter() - t0:.0f} s")
    return data


def _interp_np(kind, alpha_log, y):
    t, r = rt._interp(kind, float(np.exp(alpha_log)), _eta(y), tol=np.inf)
    return t, [r]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(Path(__file__).parent / "data" / rt.GRID_FILE))
    ap.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1))
    args = ap.parse_args(argv)
    build(args.out, args.jobs)


if __name__ == "__main__":
    main()
