"""The process-global Mitsuba variant, chosen once (public face: :mod:`gonio.models.mitsuba`)."""

from __future__ import annotations

import os
import subprocess
import sys

__all__ = ["mitsuba_variant", "PREFERRED", "FALLBACK", "SCENE_VARIANT"]

PREFERRED = "llvm_ad_rgb"
FALLBACK = "scalar_rgb"
#: The variant of the one-scene-per-pose renders: one pose is one ray, which Mitsuba's scalar
#: variant renders in about 0.4 ms here and the LLVM variant in about 2 ms (a kernel launch).
SCENE_VARIANT = "scalar_rgb"

_chosen: str | None = None

# A broken system libLLVM can abort the process (not raise) at the first kernel
# compilation, so the llvm variant is first probed in a child process.
_PROBE = (
    "import mitsuba as mi, drjit as dr\n"
    f"mi.set_variant('{PREFERRED}')\n"
    "y = dr.sqrt(dr.arange(mi.Float, 16))\n"
    "dr.eval(y)\n"
    "print(y)\n"
)


def _llvm_works():
    try:
        r = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True, timeout=120)
    except Exception as exc:  # pragma: no cover - environment dependent
        return False, f"{type(exc).__name__}: {exc}"
    if r.returncode != 0:
        tail = (r.stderr or r.stdout).strip().splitlines()
        return False, tail[-1] if tail else f"exit status {r.returncode}"
    return True, ""


def mitsuba_variant():
    """Select the Mitsuba variant for this process and return its name.

    ``llvm_ad_rgb`` when LLVM works, else ``scalar_rgb`` (one line on stderr says so).
    The environment variable ``GONIO_MITSUBA_VARIANT`` forces a variant. Idempotent:
    the choice is made once per process; later calls re-select it if something else
    changed the global variant in between.

    Raises
    ------
    ImportError
        If Mitsuba is not installed.
    """
    global _chosen
    import mitsuba as mi

    if _chosen is None:
        forced = os.environ.get("GONIO_MITSUBA_VARIANT")
        if forced:
            mi.set_variant(forced)
            _chosen = forced
        else:
            ok, why = _llvm_works()
            if ok:
                try:
                    mi.set_variant(PREFERRED)
                    _chosen = PREFERRED
                except Exception as exc:  # pragma: no cover
                    ok, why = False, f"{type(exc).__name__}: {exc}"
            if not ok:
                print(
                    f"gonio: Mitsuba variant {PREFERRED} unavailable ({why}); using {FALLBACK}",
                    file=sys.stderr,
                )
                mi.set_variant(FALLBACK)
                _chosen = FALLBACK
        if _chosen.startswith("llvm"):
            from gonio.models.engine.target import apply_env

            apply_env()  # GONIO_THREADS, GONIO_LLVM_TARGET: before Mitsuba compiles its first kernel
    elif mi.variant() != _chosen:
        mi.set_variant(_chosen)
    return _chosen
