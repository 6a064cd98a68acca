"""glibc's allocator for processes that fit.

A fit on 1e5 points makes and drops numpy temporaries of a few MiB each iteration (the
residuals, their weights, the Jacobian's columns); glibc by default serves each from a fresh
``mmap`` and hands the heap's free top back to the kernel, so their pages fault in again.
The settings (mallopt(3)): blocks under :data:`MMAP_THRESHOLD` come from the heap, and up to
:data:`TRIM_THRESHOLD` of free heap top is kept for the next allocation instead of handed
back. The price: a process keeps up to that much memory it no longer uses (released when it
exits). gonio applies them where the process is its own: the ``gonio`` command
(:func:`tune`, before any work) and the worker processes of ``fit_batch``'s local cluster
(:data:`MALLOC_ENV` in their environment, read by glibc when the process starts). A
program that imports gonio keeps its allocator as it is unless it calls :func:`tune` itself.
"""

# glibc's defaults: each such block comes from a fresh mmap until the adaptive mmap threshold
# has grown past it, and the heap's free top goes back to the kernel once it exceeds twice
# that threshold; every such block's pages then fault in again (zeroed by the kernel) the
# next time. Figures: docs/performance.md, gonio.fitting.batch.malloc.

from __future__ import annotations

import ctypes

#: blocks below this many bytes come from the heap (glibc's largest allowed value on 64-bit)
MMAP_THRESHOLD = 32 << 20
#: free heap top kept for reuse before it is handed back to the kernel
TRIM_THRESHOLD = 256 << 20

#: the same settings as environment variables, for a process about to be started
MALLOC_ENV = {"MALLOC_MMAP_THRESHOLD_": str(MMAP_THRESHOLD), "MALLOC_TRIM_THRESHOLD_": str(TRIM_THRESHOLD)}

_M_TRIM_THRESHOLD = -1   # glibc malloc.h
_M_MMAP_THRESHOLD = -3

_TUNED: bool | None = None


def _startup_environ() -> dict:
    """The environment this process started with (what glibc read), from
    ``/proc/self/environ``: ``os.environ`` may have changed since (Dask's nanny writes its
    workers' ``pre-spawn-environ`` into the process that starts them). Empty where there is
    no such file."""
    try:
        with open("/proc/self/environ", "rb") as fh:
            raw = fh.read()
    except OSError:
        return {}
    out = {}
    for item in raw.split(b"\0"):
        key, sep, value = item.partition(b"=")
        if sep:
            out[key.decode("utf-8", "replace")] = value.decode("utf-8", "replace")
    return out


def tune() -> bool:
    """Apply :data:`MMAP_THRESHOLD` and :data:`TRIM_THRESHOLD` to this process's glibc
    allocator (``mallopt``). Returns whether they are in effect: False where the C library
    is not glibc (musl, macOS, Windows) or where the process was started with
    ``MALLOC_MMAP_THRESHOLD_`` or ``MALLOC_TRIM_THRESHOLD_`` set to other values (the user's
    choice is kept). Idempotent."""
    global _TUNED
    if _TUNED is not None:
        return _TUNED
    _TUNED = False
    started = _startup_environ()
    if any(k in started and started[k] != v for k, v in MALLOC_ENV.items()):
        return False
    try:
        libc = ctypes.CDLL(None)
        libc.gnu_get_libc_version    # glibc's own: mallopt's numbers below are glibc's
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    _TUNED = bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD))
    return _TUNED


def tuned() -> bool:
    """Whether :func:`tune` has put gonio's settings in effect in this process."""
    return bool(_TUNED)
