"""Kernels replayed from their recordings (``dr.freeze``), shared by :mod:`gonio.models.engine.fast` and
:mod:`gonio.models.engine.affine`, and the lock every replay holds (a recording is not re-entrant)."""

from __future__ import annotations

import gc
import threading
from functools import lru_cache

_FREEZE_LOCK = threading.Lock()


#: Recordings kept per frozen function (least recently used dropped). Dr.Jit records again
#: when the inputs' configuration changes, and a public ``Model.eval`` of numpy-mapped arrays
#: of a new size is often one (measured: 40 sizes, 40 recordings): without a limit the kernels
#: of every size ever seen stay in memory, and from the 11th Dr.Jit printed a warning
#: addressed to the developer of the frozen function to the user of ``Model.eval``.
FREEZE_LIMIT = 24
_NEVER = 2 ** 31 - 1


@lru_cache(maxsize=256)
def _frozen(fn, name, options, threads=None):
    """``fn(model, *inputs)`` for one model configuration under ``dr.freeze``: the first call
    per input layout traces and records the kernel launch, later calls replay it with the new
    inputs (parameters are opaque inputs), for any N, skipping Python tracing and Dr.Jit's code
    generation and hashing (~0.1 ms a call). One recording per (fn, model configuration,
    size of Dr.Jit's thread pool): see :func:`_frozen_for`."""
    import drjit as dr

    from gonio.models.registry import get

    model = get(name, **dict(options))
    return _GcPaused(dr.freeze(lambda *inputs: fn(model, *inputs), limit=FREEZE_LIMIT, warn_after=_NEVER))


class _GcPaused:
    """A frozen function called with Python's cyclic garbage collector paused. A collection
    that starts while a kernel is being recorded frees whatever unreachable Dr.Jit arrays
    other code left in reference cycles, and Dr.Jit 1.5.0 aborted the process there (SIGABRT,
    "Garbage-collecting" inside principled's kernel as ``normal_equations`` recorded it, one
    suite run in a clean clone, 2026-12-02); the collection runs at the next allocation after
    the call instead. Attributes (``n_cached_recordings``, ...) are the frozen function's."""

    def __init__(self, frozen):
        self._frozen = frozen

    def __call__(self, *inputs):
        if not gc.isenabled():
            return self._frozen(*inputs)
        gc.disable()
        try:
            return self._frozen(*inputs)
        finally:
            gc.enable()

    def __getattr__(self, name):
        return getattr(self._frozen, name)


def _frozen_for(fn, model):
    """The frozen ``fn`` of ``model``'s configuration (:func:`_frozen`) for the present size
    of Dr.Jit's thread pool. A recording keeps the per-thread copies that the in-kernel sums
    (:func:`gonio.models.engine.reduce._reduced`, ``ReduceMode.Expand``) were given for the pool it was recorded
    with: replayed after ``dr.set_thread_count`` had enlarged the pool (recorded on one thread,
    replayed on two) it segfaulted (Dr.Jit 1.5.0, 2 of 3 runs of a roughconductor fit at 1e5
    points)."""
    import drjit as dr

    return _frozen(fn, model.name, tuple(sorted(model.options.items())), dr.thread_count())
