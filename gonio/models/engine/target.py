"""Which machine code Dr.Jit's LLVM backend generates: the host's, or a named x86-64 level.

Dr.Jit compiles every kernel for the host CPU by default, so the last bits of a float32 result
depend on the machine. Pinning a target makes them the same on every machine that supports it,
and lets one machine run the test suite under another machine's code generation. It applies to
kernels compiled after the call, so set it before the first evaluation: the environment
variable ``GONIO_LLVM_TARGET`` (read by :func:`apply_env`) does that for a whole process.

Targets
-------
``native``   the host's CPU, features and width (Dr.Jit's default; nothing is changed)
``avx2``     x86-64-v3: Haswell's features (AVX2, FMA, F16C, BMI1/2), 8 float32 lanes
``avx2-4``   the same features, 4 float32 lanes: the second code generation of an AVX2 host

There is no SSE4 (x86-64-v2) target and no width beyond the hardware's (see below).
"""

# Dr.Jit's host default on AVX-512 machines: 16 float32 lanes, FMA contraction, the host's
# rcp/rsqrt refinements. Its Python package does not expose the setting, but its C library does:
# jit_llvm_set_target(const char *cpu, const char *features, uint32_t vector_width) in
# libdrjit-core.so (C++ linkage; see drjit-core's include/drjit-core/jit.h). Kernels already
# compiled stay as they are.
#
# No SSE4 (x86-64-v2) target: gonio's kernels and Mitsuba's use fused multiply-adds, which LLVM
# lowers to a call of libm's fma on a CPU without FMA, a symbol Dr.Jit's JIT does not resolve,
# and the process aborts ("LLVM ERROR") at the first kernel. Nor is a wider width than the
# hardware's possible (16 lanes with AVX2 features: "Do not know how to split the result").

from __future__ import annotations

import ctypes
import os

__all__ = ["TARGETS", "llvm_target", "set_llvm_target", "apply_threads", "apply_env", "env_problem", "other_target"]

TARGETS: dict[str, tuple[str, str, int] | None] = {
    "native": None,
    "avx2": ("haswell", "+sse2,+sse3,+ssse3,+sse4.1,+sse4.2,+popcnt,+cx16,+avx,+avx2,+fma,+f16c,+bmi,+bmi2,"
             "+lzcnt,+movbe", 8),
}
TARGETS["avx2-4"] = ("haswell", TARGETS["avx2"][1], 4)

# the host features each target needs (names as /proc/cpuinfo spells them)
_NEEDS = {"avx2": {"avx", "avx2", "fma", "f16c", "bmi1", "bmi2"}}
_NEEDS["avx2-4"] = _NEEDS["avx2"]

_lib = None


def _core():
    global _lib
    if _lib is None:
        import drjit as dr

        _lib = ctypes.CDLL(os.path.join(os.path.dirname(dr.__file__), "libdrjit-core.so"))
        _lib._Z19jit_llvm_target_cpuv.restype = ctypes.c_char_p
        _lib._Z24jit_llvm_target_featuresv.restype = ctypes.c_char_p
        _lib._Z21jit_llvm_vector_widthv.restype = ctypes.c_uint32
        _lib._Z19jit_llvm_set_targetPKcS0_j.argtypes = [ctypes.c_char_p, ctypes.c_char_p, ctypes.c_uint32]
        _lib._Z19jit_llvm_set_targetPKcS0_j.restype = None
    return _lib


def _init_llvm() -> None:
    # the target strings exist once the backend has started: one tiny evaluation starts it
    import drjit as dr
    from drjit.llvm import Float

    dr.eval(Float(0.0) + 1.0)


def llvm_target() -> tuple[str, int]:
    """(cpu name, float32 vector width) that Dr.Jit's LLVM backend compiles for now."""
    _init_llvm()
    lib = _core()
    return lib._Z19jit_llvm_target_cpuv().decode(), int(lib._Z21jit_llvm_vector_widthv())


def _host_flags() -> set[str]:
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as f:
            for line in f:
                if line.startswith("flags"):
                    return set(line.split(":", 1)[1].split())
    except OSError:
        pass
    return set()


def _checked_target(name: str) -> str:
    """The key of target ``name``; ValueError for an unknown one or one the host's CPU
    cannot execute (reads /proc/cpuinfo only: Dr.Jit is not started)."""
    key = name.strip().lower()
    if key not in TARGETS:
        raise ValueError(f"unknown LLVM target {name!r}: choose one of {', '.join(TARGETS)}")
    flags = _host_flags()
    missing = sorted(_NEEDS.get(key, set()) - flags) if flags else []
    if missing:
        raise ValueError(f"this CPU cannot run the {key} target (it lacks {', '.join(missing)})")
    return key


def set_llvm_target(name: str) -> tuple[str, int]:
    """Make Dr.Jit compile every later LLVM kernel for target ``name`` (see the module
    docstring); return the (cpu, width) now in effect.

    Raises
    ------
    ValueError
        For an unknown name, or a target the host cannot execute (its CPU lacks a feature
        the target needs: the kernels would stop with an illegal instruction).
    """
    spec = TARGETS[_checked_target(name)]
    if spec is None:
        return llvm_target()
    _init_llvm()
    cpu, features, width = spec
    _core()._Z19jit_llvm_set_targetPKcS0_j(cpu.encode(), features.encode(), width)
    return llvm_target()


def _env_threads() -> int | None:
    text = os.environ.get("GONIO_THREADS", "").strip()
    if not text:
        return None
    try:
        n = int(text)
    except ValueError:
        n = 0
    if not 1 <= n <= 1024:
        raise ValueError(f"GONIO_THREADS = {text!r}: give a whole number of threads from 1 to 1024; or unset it")
    return n


def env_problem() -> str | None:
    """What is wrong with ``GONIO_THREADS`` or ``GONIO_LLVM_TARGET``, in one line, or None;
    checked without starting Dr.Jit (the CLI refuses a bad value before any work)."""
    try:
        _env_threads()
        name = os.environ.get("GONIO_LLVM_TARGET", "").strip()
        if name:
            try:
                _checked_target(name)
            except ValueError as exc:
                raise ValueError(f"GONIO_LLVM_TARGET: {exc}; or unset it") from None
    except ValueError as exc:
        return str(exc)
    return None


def apply_threads() -> int | None:
    """Apply ``GONIO_THREADS`` when set: the number of threads of Dr.Jit's pool, which runs
    gonio's compiled kernels and Mitsuba's llvm variants (Dr.Jit's default is one a core
    this process may run on). Return the number applied, or None when the variable is unset.

    Two processes that each start a thread a core share the cores badly: under pytest-xdist
    with two workers on two cores, the emcee coverage captures took 1.63-1.73 s each with
    Dr.Jit's default and 0.83 s with one thread a worker (measured 2026-12-02)."""
    n = _env_threads()
    if n is None:
        return None
    import drjit as dr

    dr.set_thread_count(n)
    return n


def apply_env() -> tuple[str, int] | None:
    """Apply ``GONIO_THREADS`` (:func:`apply_threads`) and ``GONIO_LLVM_TARGET`` when set
    (``native``, ``avx2``, ``avx2-4``); return the target in effect, or None when
    ``GONIO_LLVM_TARGET`` is unset."""
    apply_threads()
    name = os.environ.get("GONIO_LLVM_TARGET", "").strip()
    if not name:
        return None
    try:
        return set_llvm_target(name)
    except ValueError as exc:
        raise ValueError(f"GONIO_LLVM_TARGET: {exc}; or unset it") from None


def other_target() -> str:
    """A target other than the host's own code generation that this host can run: ``avx2``
    on an AVX-512 host, ``avx2-4`` on an AVX2 host, '' otherwise (no LLVM, or not x86-64)."""
    flags = _host_flags()
    if _NEEDS["avx2"] <= flags:
        return "avx2" if "avx512f" in flags else "avx2-4"
    return ""


if __name__ == "__main__":  # python -m gonio.models.engine.target [--other] (the Makefile imports other_target)
    import sys

    if sys.argv[1:] == ["--other"]:
        print(other_target())
    else:
        print(*llvm_target())
