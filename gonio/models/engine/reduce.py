"""In-kernel sums of many terms over all lanes, in float64, for the compiled gradients and
normal equations of :mod:`gonio.models.engine.fast` (issue 18): :func:`_reduced` inside a kernel,
:func:`_collect` after it."""

from __future__ import annotations

import numpy as np

from gonio.models.engine.jit import _dr

__all__ = ["SLOTS", "_reduced", "_collect"]


#: Partial sums per term kept by :func:`_reduced`: lane j of the kernel adds into slot
#: j mod SLOTS, so the 16 lanes of an AVX-512 packet (8 of an AVX2 one) hit distinct addresses.
SLOTS = 16


#: Terms per packet (:func:`_groups`): 16, one masked read-add-write per lane for up to 16
#: terms. Each packet costs every lane a test of its mask bit and a branch in Dr.Jit's
#: scatter besides the transposes, so cooktorrance's 11 chi^2-gradient terms in one packet of
#: 16 instead of 8 + 4 take 492 instead of 662 instructions a 16-lane iteration of its float32
#: kernel (static count of the AVX-512 code LLVM makes of Dr.Jit's IR: issue 18), 592 instead
#: of 764 in float64; measured on AVX2 (8 lanes, CPU time, load 9): even to 6 % faster, its
#: float64 normal equations 19.4-21.2 ms against 22.6-23.6 ms at 1e6 pairs.
_PACKET = {"float32": 16, "float64": 16}


def _groups(n_terms, width=16):
    """Packet sizes :func:`_reduced` scatters ``n_terms`` terms in: ``width`` at a time, the
    rest in one packet of 2, 4, 8 or 16 (zero padded)."""
    if width == 1:
        return [1] * n_terms
    out = [width] * (n_terms // width)
    r = n_terms % width
    if r:
        out.append(next(p for p in (2, 4, 8, 16) if p >= r))
    return out


def _reduced(terms):
    """The sums over the lanes of each term, reduced inside the kernel into float64 partial
    sums (:func:`_collect` adds them up): the terms are packed 16 to a packet (:data:`_PACKET`;
    8 until issue 18's last change, when the measurements below were made) and each lane adds
    its packet into slot (lane mod :data:`SLOTS`) of its thread's copy of the target
    (``scatter_reduce`` of a 16-wide float64 array, ``ReduceMode.Expand``: one 16-double
    read-add-write per lane, to distinct addresses within a SIMD packet, so nothing waits
    on the previous packet's store; merged across threads at the end). Every addition is in
    float64; only the order differs from a sequential sum.

    Measured (CPU time, one thread, AVX-512, 1e6 lanes): 8 float64 sums cost 0.88 ms this way
    against 3.49 ms as 8 scalar ``scatter_reduce`` calls (Expand: a horizontal reduction and a
    dependent scalar read-add-write per term and packet), 4.27 ms with ``ReduceMode.Local``.
    In the models' chi^2-gradient kernels (min of 21, 1e6 pairs; old -> new ratio to
    ``Bound.eval``) float32 gains everywhere (roughconductor beckmann 4.79 -> 2.77, cooktorrance
    4.86 -> 4.11); float64 gains on most, is even on roughconductor ggx (2.83 -> 2.96, within
    the noise). Where the ratio stays above 3 (float32 roughconductor ggx, cooktorrance) the
    kernel with all terms summed into ONE reduction already costs 3.2-3.4x: the derivative
    arithmetic and the wider reads (y, w), not the sums. Rejected: each lane taking k pairs
    (gathers: 1.6-4x slower; zero-copy views: k = 4 saved 25 % in float32 but was slower in
    float64), ``ReduceMode.Local`` (0.53 ms a term), ``NoConflicts`` into per-lane slots
    (25 ms for 8 terms), float32 partial sums (precision).
    (A 1-element target per term, each read back on its own, measured 133 us a call against
    43 us for one target at 100 pairs: the transfers, not the kernel.)"""
    import drjit as dr
    import drjit.llvm.ad as L

    _, F64, _, U = _dr()
    sizes = _groups(len(terms), _PACKET[_precision(terms[0])])
    target = dr.zeros(F64, SLOTS * sum(sizes))
    slot = dr.arange(U, dr.width(terms[0])) & (SLOTS - 1)
    vals = [F64(t) for t in terms]
    vals += [dr.zeros(F64, 1)] * (sum(sizes) - len(vals))
    packet = {2: L.Array2f64, 4: L.Array4f64, 8: L.ArrayXf64, 16: L.ArrayXf64}
    start = 0  # in doubles; each group's SLOTS packets of its size are contiguous
    for size in sizes:
        chunk = vals[start // SLOTS:start // SLOTS + size]
        if size == 1:  # all lanes into one address (a horizontal sum per SIMD packet)
            dr.scatter_reduce(dr.ReduceOp.Add, target, chunk[0], dr.zeros(U, 1) + start, mode=dr.ReduceMode.Expand)
        else:
            v = packet[size](*chunk) if size < 8 else L.ArrayXf64(chunk)
            dr.scatter_reduce(dr.ReduceOp.Add, target, v, slot + start // size, mode=dr.ReduceMode.Expand)
        start += SLOTS * size
    return target


def _precision(x):
    import drjit as dr

    return "float32" if dr.type_v(x) == dr.VarType.Float32 else "float64"


def _collect(target, dtype):
    """The per-term sums (float64 numpy) from :func:`_reduced`'s partial sums for terms of
    ``dtype`` (the batch's), added in float64 (padding terms, 0, at the end)."""
    a = np.asarray(target, dtype=np.float64)
    out, start = [], 0
    for size in _groups(a.size // SLOTS, _PACKET[np.dtype(dtype).name]):
        out.append(a[start:start + SLOTS * size].reshape(SLOTS, size).sum(axis=0))
        start += SLOTS * size
    return np.concatenate(out)
