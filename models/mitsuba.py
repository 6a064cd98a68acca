"""Choice of the process-global Mitsuba variant, made once and reused.

``mitsuba.set_variant`` is process-global; every part of gonio that talks to Mitsuba
calls :func:`mitsuba_variant` instead, so they all agree. Mitsuba is imported here
lazily: ``import gonio.models`` does not import it.
"""

from __future__ import annotations

import os
import subprocess
import sys

__all__ = ["mitsuba_variant", "mitsuba_eval_cos", "PREFERRED", "FALLBACK"]

PREFERRED = "llvm_ad_rgb"
FALLBACK = "scalar_rgb"

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
            from ._jit_target import apply_env

            apply_env()  # GONIO_LLVM_TARGET, before Mitsuba compiles its first kernel
    elif mi.variant() != _chosen:
        mi.set_variant(_chosen)
    return _chosen


def mitsuba_eval_cos(bsdf, wi, wo):
    """Evaluate a Mitsuba BSDF on a batch in gonio's convention.

    Parameters
    ----------
    bsdf : dict or mitsuba.BSDF
        A ``mitsuba.load_dict`` dict (e.g. ``model.to_mitsuba(params)``) or a loaded BSDF.
    wi, wo : array_like, shape (N, 3)
        Toward the light and toward the detector (gonio convention).

    Returns
    -------
    ndarray, shape (N, 3), float64
        Mitsuba's ``bsdf.eval`` = f_r(wi, wo) * cos(theta_i): Mitsuba's ``si.wi`` is
        set to our ``wo`` and its ``wo`` argument to our ``wi``. Mitsuba computes in
        float32: directions are rounded to float32 first.
    """
    import numpy as np

    variant = mitsuba_variant()
    import drjit as dr
    import mitsuba as mi

    if isinstance(bsdf, dict):
        bsdf = mi.load_dict(bsdf)
    wi = np.ascontiguousarray(np.asarray(wi, dtype=np.float32).reshape(-1, 3))
    wo = np.ascontiguousarray(np.asarray(wo, dtype=np.float32).reshape(-1, 3))
    n = wi.shape[0]
    if n == 0:
        return np.zeros((0, 3))
    ctx = mi.BSDFContext()
    if variant.startswith(("llvm", "cuda")):
        si = dr.zeros(mi.SurfaceInteraction3f, n)
        si.wi = mi.Vector3f(np.ascontiguousarray(wo.T))
        si.sh_frame = mi.Frame3f(mi.Normal3f(0.0, 0.0, 1.0))
        v = bsdf.eval(ctx, si, mi.Vector3f(np.ascontiguousarray(wi.T)))
        return np.array(v, dtype=np.float64).reshape(3, n).T.copy()
    out = np.empty((n, 3))
    si = dr.zeros(mi.SurfaceInteraction3f)
    si.sh_frame = mi.Frame3f(mi.Normal3f(0.0, 0.0, 1.0))
    for j in range(n):
        si.wi = mi.Vector3f(*map(float, wo[j]))
        out[j] = np.array(bsdf.eval(ctx, si, mi.Vector3f(*map(float, wi[j]))), dtype=np.float64).reshape(3)
    return out
