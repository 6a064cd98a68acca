"""Session-wide setup of the suite.

``GONIO_LLVM_TARGET`` (``native``, ``avx2``, ``sse4``) pins the machine code Dr.Jit's LLVM
backend generates for the whole run, before any kernel is compiled, so that one machine
can run the numerical tests under another machine's code generation (issue 12;
``make test-avx2``). The header of the run says which target was in effect.
"""

from __future__ import annotations


def pytest_configure(config):
    import os

    if os.environ.get("GONIO_LLVM_TARGET"):
        from gonio.models._jit_target import apply_env

        config._gonio_llvm_target = apply_env()


def pytest_report_header(config):
    import os

    target = getattr(config, "_gonio_llvm_target", None)
    if target is None:
        return "gonio: Dr.Jit LLVM target native (GONIO_LLVM_TARGET unset)"
    return f"gonio: Dr.Jit LLVM target {os.environ['GONIO_LLVM_TARGET']} = {target[0]}, {target[1]} float32 lanes"
