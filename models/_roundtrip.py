"""The numpy round trip of the public ``Model.eval`` (issue 18): (N, 3) directions in, f_r
(N, 3) out, float64 or float32 (the type of the directions: the kernel runs in it), through a
compiled kernel that reads and writes contiguous arrays only (large batches, :func:`eval_blocks`)
or that gathers from numpy's memory mapped without a copy (small ones, :func:`eval_gathered`).

Why not gathers inside the kernel (what :func:`gather_kernel` does for small batches): on this project's AVX-512 machine (AMD Zen 5, measured 2026-12-02, CPU time, one
thread, 1e6 pairs) the three stride-3 float64 gathers that de-interleave one (N, 3) array cost
3.5-3.9 ms (1.0 ms when the same kernel is compiled for AVX2, where LLVM does not use the
vector gather instruction), and the kernel that interleaves the three channels back 4.7 ms:
~12 ms of a ~19 ms call, for a model whose float64 kernel costs 1-4 ms. numpy's strided copies
do the same in ~2.0 ms per (N, 3) array.

So here numpy copies each direction component into an array that Dr.Jit allocated (its
allocator keeps freed blocks: no fresh pages to fault in on every call, which cost as much as
the copy itself), the model's kernel reads them as contiguous arrays, and numpy interleaves
the three channels into an output that Dr.Jit allocated as well (handed to numpy without a
further copy). Every value is the same kernel's on the same inputs: equal, bit for bit, to
the gathering path (tested), in either precision.

With more than one Dr.Jit thread the copies are spread over that many Python threads (numpy
releases the GIL while it copies).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from functools import lru_cache

import numpy as np

from ._base import CHANNELS

__all__ = ["SOA_MIN_PAIRS", "types", "soa_kernel", "gather_kernel", "to_components", "interleave", "eval_blocks",
           "eval_gathered", "SOA_BLOCK"]

#: Pairs from which :func:`gonio.models._fast.eval` takes this path; below it the gathering
#: kernel's fixed cost is lower (one mapped input per direction, no copies). Measured (CPU
#: time, one thread, min of 41): diffuse 32/57 us (gathering/here) at 1024 pairs, 142/139 us
#: at 16384, 455/325 us at 65536; roughplastic GGX 45/69, 183/183, 675/544 us.
SOA_MIN_PAIRS = 1 << 14

#: Pairs per launch (a block's components and channels stay in the caches between numpy's
#: copies and the kernel; see :func:`eval_blocks`).
SOA_BLOCK = 1 << 16


def types(dtype):
    """``(dr, F, V3, U)``: Dr.Jit and its LLVM float array, 3-vector and uint32 array types for
    numpy's float32 or float64."""
    import drjit as dr
    from drjit.llvm.ad import Array3f, Array3f64, Float32, Float64, UInt32

    return (dr, Float32, Array3f, UInt32) if np.dtype(dtype) == np.float32 else (dr, Float64, Array3f64, UInt32)


def _degenerate(dr, V3, vi, vo):
    """Non-finite directions made degenerate geometry (f_r = 0), as in the reference."""
    finite = dr.isfinite(vi.x) & dr.isfinite(vi.y) & dr.isfinite(vi.z)
    finite &= dr.isfinite(vo.x) & dr.isfinite(vo.y) & dr.isfinite(vo.z)
    down = V3(0.0, 0.0, -1.0)
    return dr.select(finite, vi, down), dr.select(finite, vo, down)


def _types_of(x):
    import drjit as dr

    return types(np.float32 if dr.type_v(x) == dr.VarType.Float32 else np.float64)


def soa_kernel(kernel, model, ix, iy, iz, ox, oy, oz, P):
    """``kernel(model, wi, wo, P)`` (the model's f_r) on six contiguous component arrays (of
    either precision); non-finite directions become degenerate geometry (f_r = 0)."""
    dr, F, V3, U = _types_of(ix)
    return kernel(model, *_degenerate(dr, V3, V3(ix, iy, iz), V3(ox, oy, oz)), P)


def gather_kernel(kernel, model, flat_i, flat_o, lanes, P):
    """The kernels of :func:`eval_gathered`: directions de-interleaved from the flat (3N)
    numpy-mapped inputs by gathers, non-finite rows made degenerate, then f_r interleaved
    into one flat (3N) output by a second, gathering kernel, so that numpy sees an (N, 3)
    array without a copy in either direction. (Scattering the channels from the model's
    kernel instead measured 2-3x slower than the model's kernel alone on roughplastic at 1e6
    pairs; the second kernel costs ~1.5 ms there.)"""
    dr, F, V3, U = _types_of(flat_i)
    # sizes only through dr.arange(U, dr.width(input)): a replayed recording follows the new
    # inputs' widths (``lanes`` has one lane per pair), never a traced Python integer
    idx = dr.arange(U, dr.width(lanes)) * 3
    vi = V3(*(dr.gather(F, flat_i, idx + k) for k in range(3)))
    vo = V3(*(dr.gather(F, flat_o, idx + k) for k in range(3)))
    c0, c1, c2 = kernel(model, *_degenerate(dr, V3, vi, vo), P)
    dr.eval(c0, c1, c2)
    j = dr.arange(U, dr.width(flat_i))
    q = j // 3
    r = j - 3 * q
    return dr.select(r == 0, dr.gather(F, c0, q), dr.select(r == 1, dr.gather(F, c1, q), dr.gather(F, c2, q)))


def eval_gathered(run, wi, wo, P, lock, block):
    """f_r (N, 3) from ``run`` (the frozen :func:`gather_kernel` of a model) on numpy's
    C-contiguous (N, 3) arrays mapped into Dr.Jit without a copy; above ``block`` pairs in
    blocks of that many, copied into one array (24 or 12 bytes a pair more, so that memory
    stays bounded)."""
    dr, F, V3, U = types(wi.dtype)

    def one(a, b):
        with lock, dr.suspend_grad():  # one recording replayed at a time (threads)
            f = run(F(a.reshape(-1)), F(b.reshape(-1)), dr.empty(U, a.shape[0]), P)
            dr.eval(f)
        return np.asarray(f).reshape(a.shape[0], CHANNELS)

    n = wi.shape[0]
    if n <= block:
        return one(wi, wo)
    # the kernel's channels and its interleaved output are one output's worth each: in
    # blocks, a large batch needs its output plus two blocks (measured peak RSS over the
    # inputs, 1e7 diffuse pairs: 2.03x the output in one launch, 1.27x in blocks)
    out = np.empty((n, CHANNELS), wi.dtype)
    for s in range(0, n, block):
        out[s:s + block] = one(wi[s:s + block], wo[s:s + block])
    return out


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


def _buffers(n, k, dtype):
    """k evaluated Dr.Jit arrays of n entries of ``dtype`` and numpy views of them (writable)."""
    dr, F = types(dtype)[:2]
    bufs = [dr.empty(F, n) for _ in range(k)]
    dr.eval(*bufs)
    return bufs, [np.asarray(b) for b in bufs]


def to_components(wi, wo):
    """The six components of two (N, 3) arrays (float32 or float64) as contiguous Dr.Jit
    arrays of that type."""
    n = wi.shape[0]
    bufs, views = _buffers(n, 2 * CHANNELS, wi.dtype)
    _run([(views[k], w[:, j]) for k, (w, j) in enumerate((w, j) for w in (wi, wo) for j in range(CHANNELS))])
    return bufs


def interleave(chans, out):
    """Write the three evaluated channels into ``out`` (n, 3) (numpy, C order)."""
    src = [np.asarray(c) for c in chans]
    _run([(out[:, c], src[c]) for c in range(CHANNELS)])


def eval_blocks(run, wi, wo, P, lock):
    """f_r (N, 3), of the directions' type, from ``run`` (the frozen :func:`soa_kernel` of a
    model) in blocks of :data:`SOA_BLOCK` pairs, one replay at a time under ``lock``, written
    into an output that Dr.Jit allocated (handed to numpy without a copy; Dr.Jit's allocator
    reuses freed blocks, so a new output's pages are not faulted in on every call). Peak
    memory: the output plus one block's components and channels (72 bytes a pair in float64,
    36 in float32)."""
    dr, F = types(wi.dtype)[:2]
    n = wi.shape[0]
    buf = dr.empty(F, CHANNELS * n)
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
