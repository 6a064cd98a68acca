"""Frozen kernels and Python's garbage collector (gonio/models/engine/freeze.py)."""

import subprocess
import sys
import textwrap

# Cyclic garbage holding Dr.Jit arrays, collected (threshold 5) while principled's normal
# equations and sum of squares are recorded for new batch sizes: a free inside a recording
# made Dr.Jit 1.5.0 abort the process ("RecordThreadState::enqueue_host_func(): this function
# cannot be recorded!"; one clean-clone suite run, 2026-12-02).
SCRIPT = textwrap.dedent("""
    import gc
    import numpy as np
    import gonio.models as gm
    from gonio.models import fast
    from drjit.llvm.ad import Float64

    class Cyc:
        pass

    m = gm.get("principled", distribution="ggx")
    p = m.validate(m.defaults())
    rng = np.random.default_rng(0)
    gc.set_threshold(5, 1, 1)

    def hemisphere(n):
        v = rng.standard_normal((n, 3))
        v[:, 2] = np.abs(v[:, 2])
        return v / np.linalg.norm(v, axis=1)[:, None]

    for it in range(N):
        n = 50 + it
        dirs = fast.Directions(hemisphere(n), hemisphere(n), np.float64)
        y, w = np.abs(rng.standard_normal((n, 3))), np.ones((n, 3))
        for _ in range(20):
            a, b = Cyc(), Cyc()
            a.o, b.o = b, a
            a.x = Float64(np.arange(64.0)) * 2.0
        fast.normal_equations(m, dirs, p, y, w)
        fast.weighted_sse(m, dirs, p, y, w)
    print("recorded", N)
""")


def test_a_collection_never_runs_inside_a_recording():
    """Every new batch size records the kernels again; with the collector paused around each
    frozen call (_freeze._GcPaused) the process survives collections at every few allocations.
    Without it the same script aborted (SIGABRT) within its first iterations."""
    n = 12
    out = subprocess.run([sys.executable, "-c", f"N = {n}\n" + SCRIPT], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    assert f"recorded {n}" in out.stdout
