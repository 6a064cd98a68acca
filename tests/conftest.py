"""Session-wide setup of the suite.

``GONIO_LLVM_TARGET`` (``native``, ``avx2``, ``avx2-4``) pins the machine code Dr.Jit's LLVM
backend generates for the whole run, before any kernel is compiled, so that one machine
can run the numerical tests under another machine's code generation (issue 12;
``make test-avx2``). The header of the run says which target was in effect.

Under pytest-xdist each worker gets its share of the cores for Dr.Jit's thread pool
(``GONIO_THREADS``, inherited by the gonio commands a test starts) and for OpenBLAS:
two workers on two cores, each with Dr.Jit's default of a thread a core, ran the emcee
coverage captures 2x slower than with one thread each (1.63-1.73 s against 0.83 s a
capture, measured 2026-12-02). A value set by the caller is kept.
"""

from __future__ import annotations

import pytest


def _share_the_cores():
    import os

    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "0") or 0)
    if not os.environ.get("PYTEST_XDIST_WORKER") or workers < 1:
        return
    share = str(max(1, len(os.sched_getaffinity(0)) // workers))
    os.environ.setdefault("GONIO_THREADS", share)
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS"):  # the commands a test starts
        os.environ.setdefault(var, share)
    from threadpoolctl import threadpool_limits

    threadpool_limits(int(os.environ["OPENBLAS_NUM_THREADS"]))  # this worker's numpy and scipy
    try:
        from gonio.models.engine.target import apply_threads

        apply_threads()  # this worker's Dr.Jit, also where a test starts Mitsuba itself
    except ImportError:
        pass  # no Dr.Jit: nothing to share


def _sigint_as_python_starts_it():
    """SIGINT's default handler (KeyboardInterrupt) where this process was started with it
    ignored: a test run launched as a background job of a non-interactive shell (``make test
    &`` in a script) ignores it, as POSIX has the shell do; every child a test starts would
    inherit that, a child Python then never installs KeyboardInterrupt, and the tests that stop
    ``gonio sim serve`` with SIGINT saw it run on (2026-12-02, two failures in such a run). A
    handler set here does not survive a child's exec: the children get the default."""
    import signal

    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


def _allocator_as_gonio_runs_it():
    """glibc's allocator set as the ``gonio`` command sets it (``gonio.fitting.tune_allocator``):
    the suite's processes fit as the command does, their numpy temporaries kept on the heap.
    tests/fitting/test_malloc.py runs its own processes, with and without."""
    try:
        from gonio.fitting import tune_allocator
    except ImportError:
        return
    tune_allocator()


def pytest_configure(config):
    import os

    _share_the_cores()
    _sigint_as_python_starts_it()
    _allocator_as_gonio_runs_it()
    if os.environ.get("GONIO_LLVM_TARGET"):
        from gonio.models.engine.target import apply_env

        config._gonio_llvm_target = apply_env()


def pytest_report_header(config):
    import os

    target = getattr(config, "_gonio_llvm_target", None)
    if target is None:
        return "gonio: Dr.Jit LLVM target native (GONIO_LLVM_TARGET unset)"
    return f"gonio: Dr.Jit LLVM target {os.environ['GONIO_LLVM_TARGET']} = {target[0]}, {target[1]} float32 lanes"



@pytest.hookimpl(trylast=True)      # after ``-m`` has deselected: the list the workers will run
def pytest_collection_modifyitems(session, config, items):
    """Hand every xdist worker its share of the long tests at the start of its queue.

    pytest-xdist's ``worksteal`` gives worker i the next ``len(pending) // (workers - i)``
    tests of the collection, in order, and an idle worker steals from the end of another's
    queue. The tests marked ``slow`` (tens of seconds to two minutes each, about half the
    suite's time) are dealt out in turn, one to each worker's chunk, each chunk filled up with
    the other tests in their usual order; so no worker starts a long test near the end while
    the other stands idle (on 2026-12-02 the emcee coverage test, 128 s, started last, at
    834 s, on one worker while the other had finished at 852 s). Without xdist the long tests
    simply run first. Deterministic: every worker computes the same order, as xdist requires."""
    import itertools
    import os

    slow = [it for it in items if it.get_closest_marker("slow") is not None]
    rest = [it for it in items if it.get_closest_marker("slow") is None]
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "0") or 0)
    if workers < 2:
        items[:] = slow + rest
        return
    sizes, left = [], len(items)
    for i in range(workers):                # worksteal's first split (xdist.scheduler.worksteal)
        sizes.append(left // (workers - i))
        left -= sizes[-1]
    chunks = [slow[w::workers] for w in range(workers)]
    fill = iter(rest)
    for chunk, size in zip(chunks, sizes):
        chunk.extend(itertools.islice(fill, max(0, size - len(chunk))))
    items[:] = [it for chunk in chunks for it in chunk] + list(fill)


@pytest.fixture
def flat_sample_luminance():
    """``render(bsdf, wi, wo, spp=256)``: the luminance a radiance meter toward ``wo`` reads off a
    flat sample (``bsdf``: a dict or a loaded BSDF) lit by a directional lamp of irradiance 1
    from ``wi``, direct integrator, in the active Mitsuba variant: f_r cos(theta_i) where every
    spectrum is flat (the spectral twins' render checks; gonio's VirtualGonio is RGB only)."""
    def render(bsdf, wi, wo, spp=256):
        import mitsuba as mi
        import numpy as np

        scene = mi.load_dict({
            "type": "scene", "integrator": {"type": "direct"},
            "sample": {"type": "rectangle", "bsdf": bsdf},
            "lamp": {"type": "directional", "direction": (-wi).tolist(),
                     "irradiance": {"type": "spectrum", "value": 1.0}},
            "meter": {"type": "radiancemeter", "origin": (5.0 * wo).tolist(), "direction": (-wo).tolist(),
                      "film": {"type": "hdrfilm", "width": 1, "height": 1, "rfilter": {"type": "box"},
                               "pixel_format": "luminance"},
                      "sampler": {"type": "independent", "sample_count": spp}}})
        return float(np.array(mi.render(scene)).ravel()[0])
    return render
