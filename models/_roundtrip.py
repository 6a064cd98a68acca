"""The numpy round trip of the public ``Model.eval`` on large batches (issue 18): (N, 3)
float64 directions in, f_r (N, 3) float64 out, through a compiled kernel that reads and writes
contiguous arrays only.

Why not gathers inside the kernel (what :func:`gonio.models._fast._round_trip` does for small
batches): on this project's AVX-512 machine (AMD Zen 5, measured 2026-12-02, CPU time, one
thread, 1e6 pairs) the three stride-3 float64 gathers that de-interleave one (N, 3) array cost
3.5-3.9 ms (1.0 ms when the same kernel is compiled for AVX2, where LLVM does not use the
vector gather instruction), and the kernel that interleaves the three channels back 4.7 ms:
~12 ms of a ~19 ms call, for a model whose float64 kernel costs 1-4 ms. numpy's strided copies
do the same in ~2.0 ms per (N, 3) array.

So here numpy copies each direction component into an array that Dr.Jit allocated (its
allocator keeps freed blocks: no fresh pages to fault in on every call, which cost as much as
the copy itself), the model's kernel reads them as contiguous arrays, and numpy interleaves
the three channels into an output that Dr.Jit allocated as well (handed to numpy without a
further copy). Every value is the same kernel's on the same float64 inputs: equal, bit for
bit, to the gathering path (tested).

With more than one Dr.Jit thread the copies are spread over that many Python threads (numpy
releases the GIL while it copies).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from functools import lru_cache

import numpy as np

from ._base import CHANNELS
from ._jit import _dr

__all__ = ["SOA_MIN_PAIRS", "soa_kernel", "to_components", "interleave", "eval_blocks", "SOA_BLOCK"]

#: Pairs from which :func:`gonio.models._fast.eval` takes this path; below it the gathering
#: kernel's fixed cost is lower (one mapped input per direction, no copies). Measured (CPU
#: time, one thread, min of 41): diffuse 32/57 us (gathering/here) at 1024 pairs, 142/139 us
#: at 16384, 455/325 us at 65536; roughplastic GGX 45/69, 183/183, 675/544 us.
SOA_MIN_PAIRS = 1 << 14

#: Pairs per launch (a block's components and channels stay in the caches between numpy's
#: copies and the kernel; see :func:`eval_blocks`).
SOA_BLOCK = 1 << 16


def soa_kernel(kernel, model, ix, iy, iz, ox, oy, oz, P):
    """``kernel(model, wi, wo, P)`` (the model's f_r) on six contiguous component arrays;
    non-finite directions become degenerate geometry (f_r = 0), as in the reference."""
    dr, F, V3, U = _dr()
    vi, vo = V3(ix, iy, iz), V3(ox, oy, oz)
    finite = dr.isfinite(vi.x) & dr.isfinite(vi.y) & dr.isfinite(vi.z)
    finite &= dr.isfinite(vo.x) & dr.isfinite(vo.y) & dr.isfinite(vo.z)
    down = V3(0.0, 0.0, -1.0)
    return kernel(model, dr.select(finite, vi, down), dr.select(finite, vo, down), P)


@lru_cache(maxsize=1)
def _pool(workers):
    return ThreadPoolExecutor(max_workers=workers, thread_name_prefix="gonio-copy")


def _threads():
    import drjit as dr

    return dr.thread_count()


def _run(jobs):
    """Run the (destination, source) copies, on Dr.Jit's number of threads."""
    workers = min(_threads(), len(jobs))
    if workers <= 1:
        for dst, src in jobs:
            np.copyto(dst, src)
        return
    list(_pool(workers).map(lambda job: np.copyto(*job), jobs))


def _buffers(n, k):
    """k evaluated float64 Dr.Jit arrays of n entries and numpy views of them (writable)."""
    import drjit as dr

    F = _dr()[1]
    bufs = [dr.empty(F, n) for _ in range(k)]
    dr.eval(*bufs)
    return bufs, [np.asarray(b) for b in bufs]


def to_components(wi, wo):
    """The six components of two (N, 3) float64 arrays as contiguous Dr.Jit arrays."""
    n = wi.shape[0]
    bufs, views = _buffers(n, 2 * CHANNELS)
    _run([(views[k], w[:, j]) for k, (w, j) in enumerate((w, j) for w in (wi, wo) for j in range(CHANNELS))])
    return bufs


def interleave(chans, out):
    """Write the three evaluated channels into ``out`` (n, 3) (numpy, C order)."""
    src = [np.asarray(c) for c in chans]
    _run([(out[:, c], src[c]) for c in range(CHANNELS)])


def eval_blocks(run, wi, wo, P, lock):
    """f_r (N, 3) from ``run`` (the frozen :func:`soa_kernel` of a model) in blocks of
    :data:`SOA_BLOCK` pairs, one replay at a time under ``lock``, written into an output that
    Dr.Jit allocated (handed to numpy without a copy; Dr.Jit's allocator reuses freed blocks,
    so a new output's pages are not faulted in on every call). Peak memory: the output plus
    one block's components and channels (72 bytes a pair)."""
    import drjit as dr

    n = wi.shape[0]
    buf = dr.empty(_dr()[1], CHANNELS * n)
    dr.eval(buf)
    out = np.asarray(buf).reshape(n, CHANNELS)
    for s in range(0, n, SOA_BLOCK):
        comps = to_components(wi[s:s + SOA_BLOCK], wo[s:s + SOA_BLOCK])
        with lock, dr.suspend_grad():
            chans = run(*comps, P)
            dr.eval(*chans)
        del comps  # before the next block's are allocated
        interleave(chans, out[s:s + SOA_BLOCK])
        del chans
    return out
