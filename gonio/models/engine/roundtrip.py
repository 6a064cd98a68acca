"""The numpy round trip of the public ``Model.eval``: (N, 3) directions in, f_r (N, 3) out.

float64 or float32 (the type of the directions: the kernel runs in it), through a compiled
kernel that gathers from numpy's memory mapped without a copy (:func:`eval_gathered`) or, on
CPUs whose vector gathers are slow, through one that reads and writes contiguous arrays that
numpy copies (:func:`eval_blocks`). Which one a batch takes:
:func:`gonio.models.engine.fast.takes_copies`, from a race of the two run once per process and
precision (:func:`gonio.models.engine.fast.round_trip_race`): the gathers' cost depends on the
CPU, not on its vector width alone. Every value is the same kernel's on the same inputs either
way, equal bit for bit (tested), so the choice is speed alone, and a race that a loaded machine
decides wrongly costs speed, never a value. float32 directions travel as uint64 words of two
rows each (:func:`packed_kernel`); with more than one Dr.Jit thread the copies are spread over
that many Python threads (numpy releases the GIL while it copies).
"""

# The copies (eval_blocks): numpy copies each direction component into an array that Dr.Jit
# allocated (its allocator keeps freed blocks: no fresh pages to fault in on every call, which
# cost as much as the copy itself), the model's kernel reads them as contiguous arrays, and
# numpy interleaves the three channels into an output that Dr.Jit allocated as well (handed to
# numpy without a further copy). float32 (N, 3) directions go through the same copies as uint64
# words of two rows each, (x0, y0), (z0, x1), (y1, z1): numpy's strided copies cost about the
# same per element whatever its size, so half the elements cost half the time; packed_kernel
# splits and packs the words exactly. Per-CPU measurements (gathers against copies, SOA_MIN_PAIRS,
# what was tried and was slower): docs/performance.md, gonio.models.engine.roundtrip.

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from functools import lru_cache

import numpy as np

from gonio.core.channels import CHANNELS

__all__ = ["SOA_MIN_PAIRS", "COPIES", "types", "soa_kernel", "packed_kernel", "gather_kernel", "to_components",
           "interleave", "eval_blocks", "eval_gathered", "word_gather_kernel", "gather_into_kernel",
           "word_gather_into_kernel", "SOA_BLOCK"]

#: Pairs from which :func:`gonio.models.engine.fast.eval` takes the copies where they are taken at
#: all (:func:`gonio.models.engine.fast.takes_copies`); below it the gathering kernel's fixed cost
#: is lower (one mapped input per direction, no copies). Measured on the Zen 5 (CPU time, one
#: thread, min of 41): diffuse 32/57 us (gathering/copies) at 1024 pairs, 142/139 us at 16384, 455/325 us at
#: 65536; roughplastic GGX 45/69, 183/183, 675/544 us.
SOA_MIN_PAIRS = 1 << 14

#: Which round trip a batch of :data:`SOA_MIN_PAIRS` pairs or more takes
#: (:func:`gonio.models.engine.fast.takes_copies`): ``"auto"`` (the faster of the two on this
#: machine, raced once per process and precision: :func:`gonio.models.engine.fast.round_trip_race`),
#: ``"copies"`` or ``"gathers"``. The results
#: are the same bit for bit; the tests set it to check both.
COPIES = "auto"


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
    """The kernel of :func:`eval_gathered`: one lane per pair gathers its two rows from the
    flat (3N) numpy-mapped inputs, non-finite rows become degenerate geometry, the model's
    three channels are evaluated and scattered as one row of the flat (3N) output, so that
    numpy sees an (N, 3) array without a copy in either direction.

    One fused kernel: Dr.Jit 1.5 keeps a 3-vector gather and scatter (``dr.gather(V3, ...)``,
    ``dr.scatter(out, V3(...), ...)``) in the kernel that computes the values, where three
    scatters of one channel each into the same output launch a kernel each, and the channels
    had to be evaluated first (written to memory and read back). Measured on the AVX2 Zen 3
    (wall time, 2 threads, 1e6 pairs, best of 15, 2026-12-03), the whole ``Model.eval``, ms,
    channels evaluated then interleaved by further kernels -> one fused kernel: float64
    diffuse 4.82 -> 2.90, orennayar 5.73 -> 3.32, roughplastic GGX 10.68 -> 7.98,
    roughconductor GGX 11.57 -> 9.77, cooktorrance 7.38 -> 5.98; float32 (as words,
    :func:`word_gather_kernel`) 2.25 -> 1.70, 2.83 -> 2.11, 5.26 -> 4.51, 5.42 -> 4.54,
    4.04 -> 3.36. The float64 round trip now moves its 72 bytes a pair at about numpy's
    speed for an ``np.add`` of two such arrays (2.2 ms against 2.3 ms for 1e6 rows, the data
    alone). Tried: Dr.Jit's packet gathers (2, 4 or 6 words a lane) gain ~25 % of the data's
    time only where numpy's memory is 64-byte aligned (numpy's large arrays start 16 bytes
    past it); not taken."""
    dr, F = _types_of(flat_i)[:2]
    out = dr.empty(F, dr.width(flat_i))
    gather_into_kernel(kernel, model, flat_i, flat_o, out, lanes, P)
    return out


def word_gather_kernel(kernel, model, words_i, words_o, lanes, P):
    """float32 :func:`gather_kernel` on rows taken two at a time: each direction's (2M, 3)
    float32 rows, mapped from numpy as 3M uint64 words ``(x0, y0), (z0, x1), (y1, z1)``,
    gathered three words a lane (half the gathers of a float each), split, evaluated and
    packed by :func:`packed_kernel`, and the three words of a row pair scattered into the
    output, (2M, 3) float32 to numpy; one fused kernel, as :func:`gather_kernel` (which
    has the figures). Against a float per gather (both with the channels evaluated first;
    AVX2 Zen 3, wall time, 2 threads, 2**20 pairs, best of 15; ms, the whole ``Model.eval``):
    diffuse 3.77 -> 2.46, roughplastic GGX 8.60 -> 6.46, orennayar 4.36 -> 3.05. The same
    values bit for bit (tested)."""
    import drjit as dr
    from drjit.llvm.ad import UInt64

    out = dr.empty(UInt64, dr.width(words_i))
    word_gather_into_kernel(kernel, model, words_i, words_o, out, lanes, P)
    return out


def gather_into_kernel(kernel, model, flat_i, flat_o, out, lanes, P):
    """:func:`gather_kernel`'s work, its rows written into ``out``: a new array there, and,
    for the blocks of a large batch (:func:`eval_gathered`), a Dr.Jit array mapped from a
    slice of numpy's output (the scatter writes numpy's memory in place), so that each block
    lands where it belongs, with no copy. For the blocks it is traced, not replayed: a
    recording's scatter into an input did not reach the mapped memory (Dr.Jit 1.5.0), and a
    block's trace (~0.1 ms) is small against its ~1e5 pairs."""
    dr, F, V3, U = _types_of(flat_i)
    # sizes only through dr.arange(U, dr.width(input)): a replayed recording follows the new
    # inputs' widths (``lanes`` has one lane per pair), never a traced Python integer
    idx = dr.arange(U, dr.width(lanes))
    vi = dr.gather(V3, flat_i, idx)
    vo = dr.gather(V3, flat_o, idx)
    chans = kernel(model, *_degenerate(dr, V3, vi, vo), P)
    dr.scatter(out, V3(*chans), idx)


def word_gather_into_kernel(kernel, model, words_i, words_o, out, lanes, P):
    """:func:`word_gather_kernel`'s work, its words written into ``out`` (a new array, or
    uint64 words mapped from a slice of numpy's float32 output), as
    :func:`gather_into_kernel`."""
    import drjit as dr
    from drjit.llvm.ad import Array3u64, UInt32

    idx = dr.arange(UInt32, dr.width(lanes))
    a = dr.gather(Array3u64, words_i, idx)
    b = dr.gather(Array3u64, words_o, idx)
    dr.scatter(out, Array3u64(*packed_kernel(kernel, model, *a, *b, P)), idx)


def _word_rows(a) -> bool:
    """Whether float32 rows ``a`` (C order) can be read as uint64 words: an even number of
    them, starting 8-byte aligned."""
    return a.dtype == np.float32 and a.shape[0] % 2 == 0 and a.ctypes.data % 8 == 0 and a.flags.c_contiguous


def _output(F, n):
    """An (n, 3) numpy view of a new, evaluated Dr.Jit array of type F: Dr.Jit's allocator
    reuses freed blocks, so a large output's pages are not faulted in again on every call."""
    import drjit as dr

    buf = dr.empty(F, CHANNELS * n)
    dr.eval(buf)
    return np.asarray(buf).reshape(n, CHANNELS)


#: Above ``block`` pairs :func:`eval_gathered` launches blocks of ``block // BLOCK_SPLIT``.
BLOCK_SPLIT = 4


def eval_gathered(runs, wi, wo, P, lock, block):
    """f_r (N, 3) from ``runs`` on numpy's C-contiguous (N, 3) arrays mapped into Dr.Jit
    without a copy: ``(run, run_words, into, into_words)``, the frozen :func:`gather_kernel`
    of a model and, for float32, its frozen :func:`word_gather_kernel` (or None), and their
    traced :func:`gather_into_kernel` and :func:`word_gather_into_kernel`. Up to ``block``
    pairs one replay, whose output numpy takes without a copy; above, blocks of ``block //
    BLOCK_SPLIT`` pairs, each written by its kernel straight into its rows of one output (so
    that memory stays bounded). float32 rows go as words where they can (:func:`_word_rows`);
    an odd batch as its even part and its last row."""
    dr, F, V3, U = types(wi.dtype)
    run, run_words, into, into_words = runs

    def one(a, b):
        k = a.shape[0]
        with lock, dr.suspend_grad():  # one recording replayed at a time (threads)
            if run_words is not None and _word_rows(a) and _word_rows(b):
                from drjit.llvm.ad import UInt64

                f = run_words(UInt64(a.reshape(-1).view(np.uint64)), UInt64(b.reshape(-1).view(np.uint64)),
                              dr.empty(U, k // 2), P)
                dr.eval(f)
                return np.asarray(f).view(np.float32).reshape(k, CHANNELS)
            f = run(F(a.reshape(-1)), F(b.reshape(-1)), dr.empty(U, k), P)
            dr.eval(f)
        return np.asarray(f).reshape(k, CHANNELS)

    n = wi.shape[0]
    if n <= block:
        if run_words is None or n % 2 == 0 or n == 1:
            return one(wi, wo)
        # an odd float32 batch: its even part as words, its last row alone, both replayed
        # (through the traced blocks below, a trace each: roughplastic GGX, 1001 pairs,
        # 407 us a call against 83 us; 100001 pairs 723 against 409 us; 2026-12-03)
        out = np.empty((n, CHANNELS), wi.dtype)
        out[:-1] = one(wi[:-1], wo[:-1])
        out[-1:] = one(wi[-1:], wo[-1:])
        return out
    # in blocks, a large batch needs its output and little more (peak RSS over what was
    # resident before the call, 1e7 diffuse float64 pairs, 2026-12-03: 1.05x the output;
    # 1.27x when each block had its own output, copied into place); the output in memory
    # that Dr.Jit allocated, as in eval_blocks (no fresh pages faulted in a call), each
    # block's kernel scattering into its rows. Measured (Intel Xeon, AVX-512, 2 Dr.Jit
    # threads, 2026-12-03, 4M pairs, best of 7, ms a call), each block's own output copied
    # into place -> written in place (one launch): diffuse float32 11.1-12.2 -> 5.9 (4.6),
    # float64 21.4 -> 11.4 (10.1); roughplastic GGX float32 17.4 -> 11.8 (9.0), float64
    # 32.0 -> 18.4 (16.4)
    out = _output(F, n)
    step = max(2, (block // BLOCK_SPLIT) & ~1)  # even: blocks stay word-aligned
    with lock, dr.suspend_grad():
        for s in range(0, n, step):
            a, b, o = wi[s:s + step], wo[s:s + step], out[s:s + step]
            k = a.shape[0]
            if into_words is not None and _word_rows(a) and _word_rows(b) and _word_rows(o):
                from drjit.llvm.ad import UInt64

                dst = UInt64(o.reshape(-1).view(np.uint64))
                into_words(UInt64(a.reshape(-1).view(np.uint64)), UInt64(b.reshape(-1).view(np.uint64)), dst,
                           dr.empty(U, k // 2), P)
            else:
                dst = F(o.reshape(-1))
                into(F(a.reshape(-1)), F(b.reshape(-1)), dst, dr.empty(U, k), P)
            dr.eval(dst)
        dr.sync_thread()    # every block written before numpy reads the output
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


def packed_kernel(kernel, model, a0, a1, a2, b0, b1, b2, P):
    """float32 :func:`soa_kernel` on rows taken two at a time: each direction's block of
    rows, (2M, 3) float32, read as (M, 3) uint64 words ``(x0, y0), (z0, x1), (y1, z1)``
    (:func:`to_components` copies 8-byte words: half the elements of a float32 copy, which
    costs numpy the same per element). The kernel splits each word into its two float32
    values (integer shifts and reinterpretations, exact), evaluates the model on the even
    and on the odd rows (two halves of one fused kernel) and packs the six channels of a
    row pair back into three words ``(r0, g0), (b0, r1), (g1, b1)``: f_r (2M, 3) in C
    order once :func:`interleave` writes them into the (M, 3) word view of the output."""
    import drjit as dr
    from drjit.llvm.ad import Float32, UInt32, UInt64

    def split(w):
        return dr.reinterpret_array(Float32, UInt32(w & 0xFFFFFFFF)), dr.reinterpret_array(Float32, UInt32(w >> 32))

    def join(lo, hi):
        return UInt64(dr.reinterpret_array(UInt32, lo)) | (UInt64(dr.reinterpret_array(UInt32, hi)) << 32)

    (ix0, iy0), (iz0, ix1), (iy1, iz1) = split(a0), split(a1), split(a2)
    (ox0, oy0), (oz0, ox1), (oy1, oz1) = split(b0), split(b1), split(b2)
    e = soa_kernel(kernel, model, ix0, iy0, iz0, ox0, oy0, oz0, P)
    o = soa_kernel(kernel, model, ix1, iy1, iz1, ox1, oy1, oz1, P)
    return join(e[0], e[1]), join(e[2], o[0]), join(o[1], o[2])


def _words(w):
    """The (N, 3) view :func:`to_components` copies columns of: float64 rows as they are,
    float32 rows (N even) two at a time as uint64 words (:func:`packed_kernel`)."""
    return w if w.dtype == np.float64 else w.reshape(-1).view(np.uint64).reshape(-1, CHANNELS)


def _buffers(n, k, dtype):
    """k evaluated Dr.Jit arrays of n entries of ``dtype`` (float64, or uint64 words for
    float32 rows) and numpy views of them (writable)."""
    import drjit as dr
    from drjit.llvm.ad import Float64, UInt64

    T = Float64 if np.dtype(dtype) == np.float64 else UInt64
    bufs = [dr.empty(T, n) for _ in range(k)]
    dr.eval(*bufs)
    return bufs, [np.asarray(b) for b in bufs]


def to_components(wi, wo, into=None):
    """The six component columns of :func:`_words` of two (N, 3) arrays as contiguous Dr.Jit
    arrays (float64 components, or uint64 words of two float32 rows), written into ``into``
    (the ``(bufs, views)`` of :func:`_buffers`, of the right size) or into new ones."""
    wi, wo = _words(wi), _words(wo)
    bufs, views = into if into is not None else _buffers(wi.shape[0], 2 * CHANNELS, wi.dtype)
    _run([(views[k], w[:, j]) for k, (w, j) in enumerate((w, j) for w in (wi, wo) for j in range(CHANNELS))])
    return bufs


def interleave(chans, out):
    """Write the three evaluated channels (or packed words) into ``out`` (n, 3) (numpy, C
    order)."""
    src = [np.asarray(c) for c in chans]
    out = _words(out)
    _run([(out[:, c], src[c]) for c in range(CHANNELS)])


def _padded(w):
    """An odd float32 block with one row (0, 0, 1) more (f_r of it is dropped)."""
    return np.concatenate([w, np.array([[0.0, 0.0, 1.0]], w.dtype)]) if w.shape[0] % 2 else w


def eval_blocks(run, wi, wo, P, lock):
    """f_r (N, 3), of the directions' type, from ``run`` (the frozen :func:`soa_kernel` of a
    model in float64, :func:`packed_kernel` in float32) in blocks of :data:`SOA_BLOCK` pairs,
    one replay at a time under ``lock``, written into an output that Dr.Jit allocated (handed
    to numpy without a copy; Dr.Jit's allocator reuses freed blocks, so a new output's pages
    are not faulted in on every call). The full blocks share one set of component buffers.
    Peak memory: the output plus one block's components and channels (72 bytes a pair in
    float64, 36 in float32)."""
    import drjit as dr

    F = types(wi.dtype)[1]
    n = wi.shape[0]
    per = 1 if wi.dtype == np.float64 else 2  # rows per word
    out = _output(F, n)
    full = _buffers(SOA_BLOCK // per, 2 * CHANNELS, wi.dtype) if n >= SOA_BLOCK else None
    for s in range(0, n, SOA_BLOCK):
        a, b = _padded(wi[s:s + SOA_BLOCK]), _padded(wo[s:s + SOA_BLOCK])
        comps = to_components(a, b, full if a.shape[0] == SOA_BLOCK else None)
        with lock, dr.suspend_grad():
            chans = run(*comps, P)
            dr.eval(*chans)
        del comps  # (a short last block's) before the next block's are allocated
        dst = out[s:s + SOA_BLOCK]
        if dst.shape[0] == a.shape[0]:
            interleave(chans, dst)
        else:  # the padded last block of an odd N
            tmp = np.empty(a.shape, a.dtype)
            interleave(chans, tmp)
            dst[...] = tmp[:dst.shape[0]]
        del chans
    return out
