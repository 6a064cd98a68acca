"""GONIO_LLVM_TARGET pins Dr.Jit's code generation (issue 12): the switch takes effect (the
kernels are compiled for the named width) and the results stay the float32/float64 results
of the same formulas. Run in child processes: the target is process-wide."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from gonio.models.engine import fast as _fast
from gonio.models.engine.target import _NEEDS, TARGETS, _host_flags, other_target, set_llvm_target

pytestmark = pytest.mark.skipif(not _fast.available(), reason="Dr.Jit LLVM backend unavailable")

_CHILD = r"""
import json, numpy as np, drjit as dr
import gonio.models as gm
from gonio.models import fast
from gonio.models.engine.target import llvm_target
assert fast.available()
rng = np.random.default_rng(5)
v = rng.normal(size=(2, 4096, 3)); v[..., 2] = np.abs(v[..., 2]); v /= np.linalg.norm(v, axis=-1)[..., None]
m = gm.get("roughconductor", distribution="ggx")
p = m.defaults()
ref = m.eval_reference(v[0], v[1], p)
f32 = fast.Bound(m, p, np.float32).eval(fast.Directions(v[0], v[1], np.float32))
f32 = np.asarray(f32, dtype=np.float64).reshape(ref.shape)
mask = ref * v[0][:, 2:3] > 1e-6
dr.set_flag(dr.JitFlag.PrintIR, False)
print(json.dumps({"target": llvm_target(), "rel": float(np.max(np.abs(f32 - ref)[mask] / ref[mask]))}))
"""


def _child(target):
    env = dict(os.environ)
    env.pop("GONIO_LLVM_TARGET", None)
    if target:
        env["GONIO_LLVM_TARGET"] = target
    r = subprocess.run([sys.executable, "-c", _CHILD], capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    return json.loads(r.stdout.strip().splitlines()[-1])


@pytest.mark.slow
def test_forced_target_changes_the_width_and_keeps_the_numbers():
    other = other_target()
    if not other:
        pytest.skip("this CPU has no second x86-64 code generation to force")
    native, forced = _child(None), _child(other)
    width = {"avx2": 8, "avx2-4": 4}[other]
    assert forced["target"][1] == width and native["target"][1] != width, (native, forced)
    # float32 kernels agree with the float64 reference under both code generations
    # (the resident float32 path's documented accuracy: <= 2e-5 where f_r cos > 1e-6)
    assert native["rel"] <= 2e-5 and forced["rel"] <= 2e-5, (native, forced)


@pytest.mark.slow
@pytest.mark.parametrize("target", [t for t in TARGETS if t != "native"])
def test_every_target_runs_the_kernels(target):
    """Each named target compiles and runs the float32 kernels (fused multiply-adds
    included) to their documented accuracy: a Nehalem (SSE4) target, the AVX2 host's second
    pass until 2026-12-02, aborted the process at the first kernel ("LLVM ERROR")."""
    missing = _NEEDS[target] - _host_flags()
    if missing:
        pytest.skip(f"this CPU cannot run the {target} target (it lacks {', '.join(sorted(missing))})")
    got = _child(target)
    assert tuple(got["target"]) == (TARGETS[target][0], TARGETS[target][2]) and got["rel"] <= 2e-5, got


def test_the_second_code_generation_suits_the_host(monkeypatch):
    """AVX-512 host: AVX2 (8 lanes); AVX2 host: AVX2 at 4 lanes; nothing below AVX2."""
    from gonio.models.engine import target as _jit_target

    avx2 = {"avx", "avx2", "fma", "f16c", "bmi1", "bmi2", "sse4_2", "popcnt"}
    for flags, want in ((avx2 | {"avx512f"}, "avx2"), (avx2, "avx2-4"), ({"sse4_2", "popcnt"}, ""), (set(), "")):
        monkeypatch.setattr(_jit_target, "_host_flags", lambda flags=flags: set(flags))
        assert other_target() == want, (flags, want)
    with pytest.raises(ValueError, match="unknown LLVM target 'sse4'"):
        set_llvm_target("sse4")


def test_unknown_or_unsupported_targets_are_refused(monkeypatch):
    with pytest.raises(ValueError, match="unknown LLVM target 'avx1024'"):
        set_llvm_target("avx1024")
    from gonio.models.engine.target import apply_env

    monkeypatch.setenv("GONIO_LLVM_TARGET", "avx1024")
    with pytest.raises(ValueError, match="^GONIO_LLVM_TARGET: unknown LLVM target 'avx1024'"):
        apply_env()


@pytest.mark.codegen
def test_this_run_compiles_for_the_requested_target():
    """Under GONIO_LLVM_TARGET (make test's second pass) this very process, an xdist worker
    included, compiles for that width: the pass is not a silent copy of the first one."""
    from gonio.models.engine.target import TARGETS, llvm_target

    name = os.environ.get("GONIO_LLVM_TARGET", "").strip().lower()
    cpu, width = llvm_target()
    if not name or TARGETS[name] is None:
        assert width >= 4
    else:
        assert (cpu, width) == (TARGETS[name][0], TARGETS[name][2])


def test_thread_count_from_the_environment(monkeypatch):
    """GONIO_THREADS sets Dr.Jit's pool; a bad value is one line before any work (exit 2)."""
    from gonio.models.engine.target import apply_threads, env_problem

    pytest.importorskip("drjit")
    import drjit as dr

    before = dr.thread_count()
    monkeypatch.setenv("GONIO_THREADS", "3")
    try:
        assert env_problem() is None and apply_threads() == 3 and dr.thread_count() == 3
    finally:
        dr.set_thread_count(before)
    for bad in ("0", "-2", "two", "1e3", "5000"):
        monkeypatch.setenv("GONIO_THREADS", bad)
        assert env_problem() == f"GONIO_THREADS = {bad!r}: give a whole number of threads from 1 to 1024; or unset it"
        with pytest.raises(ValueError, match="^GONIO_THREADS"):
            apply_threads()
    monkeypatch.setenv("GONIO_THREADS", "0")
    r = subprocess.run([sys.executable, "-m", "gonio.cli.main", "settings", "show"], capture_output=True,
                       text=True, env=dict(os.environ), timeout=120)
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0 and "GONIO_THREADS = '0'" in r.stderr, r.stderr
    monkeypatch.delenv("GONIO_THREADS")
    monkeypatch.setenv("GONIO_LLVM_TARGET", "avx1024")
    assert env_problem().startswith("GONIO_LLVM_TARGET: unknown LLVM target 'avx1024'")


def test_a_recording_is_kept_per_size_of_drjits_pool():
    """A frozen kernel recorded on one thread and replayed on two segfaulted (the per-thread
    copies of its in-kernel sums are those of the pool it was recorded with): the recordings
    are kept per pool size, and a fit after a change of the pool is the one-thread fit."""
    import drjit as dr
    import numpy as np

    import gonio.models as gm
    from gonio.models.engine import fast as _fast

    model = gm.get("roughconductor", distribution="ggx")
    before = dr.thread_count()
    try:
        dr.set_thread_count(1)
        one = _fast._frozen_for(_fast._normal_sums, model)
        dr.set_thread_count(2)
        two = _fast._frozen_for(_fast._normal_sums, model)
        assert one is not two
        dr.set_thread_count(1)
        assert _fast._frozen_for(_fast._normal_sums, model) is one
    finally:
        dr.set_thread_count(before)
