"""Compiled evaluation path: the same models written in Dr.Jit (LLVM backend).

The numpy implementations are the reference; this module evaluates the same formulas (tested
to 1e-10 relative in float64, 2e-5 in float32) as fused, multithreaded LLVM kernels, with their
derivatives, where Dr.Jit's LLVM backend works (:func:`available`). numpy in, numpy out:
:func:`eval` (f_r, (N, 3), like ``Model.eval``; float32 directions give float32) and
:func:`value_and_grad` (f_r and the gradient of ``sum(cotangent * f_r)``, reverse-mode AD).
On a resident batch (:class:`Directions`, float32 or float64, loaded once): :meth:`Bound.eval`
/ :func:`eval_resident` (f_r), :func:`jacobian` (f_r and d f_r / d every parameter, derivatives
written by hand in :func:`_kernel`), :func:`chi2_grad` (sum w (f_r - y)^2 and its gradient,
reduced in the kernel), :func:`weighted_sse`, :func:`normal_equations`; for models that declare
``structure.geometry`` these read its parameter-independent part prepared once per batch
(:meth:`Directions.geometry`). Parameters enter as opaque variables: new values do not
recompile. Pieces: :mod:`.jit`, :mod:`.kernels`, :mod:`.sums`, :mod:`.roundtrip`, and
:mod:`.affine` (re-exported: ``affine_parts``, ``affine_tables``, ``affine_q``, ...).
"""

# Prepared geometry: the resident paths (chi2_grad, jacobian, weighted_sse, normal_equations)
# read, for a model that declares it (structure.geometry and structure.body: cooktorrance,
# diffuse, orennayar, roughconductor with an isotropic roughness), the parameter-independent
# part of its kernel prepared once per batch (Directions.geometry: the directions never change
# in a fit) instead of the directions: the same formulas, to rounding, with that part done once.
# Bound.eval reads the directions unless asked (prepared=True). ``gonio bench models`` times
# Bound.eval against Mitsuba's bsdf.eval.
#
# roughplastic: the transmittance table and internal reflectance follow the model's
# exact_tables setting: with exact_tables=False the interpolated grid of
# gonio.models.physics.rough_tables.rough_tables_interp (gradients through the spline's
# derivative); with exact_tables=True (the default, and in grid cells that fall back to the
# exact tables) computed here as well (the quadrature of gonio.models.physics.rough_tables), so
# that gradients with respect to alpha and int_ior include their dependence through the table.
#
# Module layout: building blocks (Fresnel, lobes, tables, Directions) in .jit, the models'
# kernels as these paths call them in .kernels, the fit's in-kernel sums (chi2_grad,
# weighted_sse, normal_equations) in .sums, the public eval's numpy round trip in .roundtrip,
# the batched affine parts of the models that declare an affine parameter in .affine
# (re-exported here: affine_parts, affine_tables, affine_q, affine_spec, prepare).

from __future__ import annotations

import functools
import os
import subprocess
import sys
import threading
from collections import OrderedDict
from functools import lru_cache

import numpy as np

from gonio.models.engine import roundtrip as _roundtrip
from gonio.core.channels import CHANNELS
from gonio.models.inputs import eval_dtype, eval_inputs
from gonio.models.engine.freeze import _FREEZE_LOCK, FREEZE_LIMIT, _frozen_for  # noqa: F401  (the tests reach FREEZE_LIMIT as fast.*)
from gonio.models.engine.affine import affine_parts, affine_q, affine_spec, affine_tables, prepare
from gonio.models.engine.jit import Directions, _dr
from gonio.models.engine.jit import _fresnel_conductor  # noqa: F401  (tests check its derivatives as fast._fresnel_conductor)
from gonio.models.engine.target import env_problem
from gonio.models.engine.kernels import (_body, _fJ, _kernel, _needs_derivatives, _param_vars, _source, jacobian_column)
from gonio.models.engine.reduce import SLOTS, _collect, _reduced  # noqa: F401  (the tests reach them as fast._reduced, ...)
from gonio.models.engine.sums import _normal_sums  # noqa: F401  (the tests record it as fast._normal_sums)
from gonio.models.engine.sums import chi2_grad, normal_equations, weighted_sse

__all__ = ["available", "env_problem", "eval", "value_and_grad", "Directions", "Bound", "eval_resident", "jacobian",
           "jacobian_column", "chi2_grad", "normal_equations", "weighted_sse", "clear_parameter_caches",
           "affine_parts", "affine_q", "affine_spec", "affine_tables", "prepare"]

_PROBE = (
    "import drjit as dr\n"
    "from drjit.llvm.ad import Float64\n"
    "x = dr.sqrt(dr.arange(Float64, 16))\n"
    "dr.eval(x)\n"
    "print(x)\n"
)


def compiled_for(model) -> bool:
    """True when ``model.eval`` may run its compiled kernel: the model has one, Dr.Jit's LLVM
    backend works (probed once per process) and ``GONIO_EVAL_BACKEND`` is not ``numpy``."""
    if model.structure.kernel is None:
        return False
    if os.environ.get("GONIO_EVAL_BACKEND", "").lower() == "numpy":
        return False
    return available()


@lru_cache(maxsize=1)
def available():
    """True when Dr.Jit's LLVM backend works in this environment (probed once, in a
    child process, because a broken libLLVM aborts instead of raising)."""
    try:
        import drjit  # noqa: F401
    except ImportError:
        return False
    try:
        r = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, timeout=120)
    except Exception:
        return False
    if r.returncode != 0:
        return False
    from gonio.models.engine.target import apply_env

    apply_env()  # GONIO_THREADS, GONIO_LLVM_TARGET: before this process compiles its first kernel
    return True


# -- model kernels ---------------------------------------------------------------------------


def _inputs(model, wi, wo, params, grad):
    """Dr.Jit inputs (float64) from numpy. Directions are loaded as flat (3N) arrays without
    copies and de-interleaved by gathers inside the fused kernel; non-finite directions are
    degenerate geometry (f_r = 0), as in the reference."""
    dr, F, V3, U = _dr()
    wi, wo, p = eval_inputs(model, wi, wo, params)
    n = wi.shape[0]
    idx = dr.arange(U, n) * 3
    flat_i, flat_o = F(wi.reshape(-1)), F(wo.reshape(-1))
    vi = V3(*(dr.gather(F, flat_i, idx + k) for k in range(3)))
    vo = V3(*(dr.gather(F, flat_o, idx + k) for k in range(3)))
    finite = dr.isfinite(vi.x) & dr.isfinite(vi.y) & dr.isfinite(vi.z)
    finite &= dr.isfinite(vo.x) & dr.isfinite(vo.y) & dr.isfinite(vo.z)
    down = V3(0.0, 0.0, -1.0)
    vi = dr.select(finite, vi, down)
    vo = dr.select(finite, vo, down)
    P, leaves = _param_vars(model, p, F, grad)
    return vi, vo, P, leaves, n


def _interleave(chans, n):
    """(N, 3) numpy array from three Dr.Jit arrays, evaluated in one fused kernel."""
    dr, F, V3, U = _dr()
    chans = [dr.detach(c) for c in chans]
    dr.eval(*chans)
    out = np.empty((n, CHANNELS))
    for c, ch in enumerate(chans):
        out[:, c] = np.asarray(ch)
    return out


def _empty(model, wi, wo, params):
    """Validate the arguments; True for an empty batch."""
    return eval_inputs(model, wi, wo, params)[0].shape[0] == 0


#: Pairs per launch of :func:`eval` below :data:`gonio.models.engine.roundtrip.SOA_MIN_PAIRS` (the gathering
#: path, :func:`gonio.models.engine.roundtrip.eval_gathered`): up to this many the output is handed to numpy
#: without a copy, a larger batch is evaluated in blocks of this size.
EVAL_BLOCK = 1 << 20


def clear_parameter_caches():
    """Forget every table cached per parameter value: roughplastic's exact and interpolated
    transmittance tables and internal reflectance, in numpy (:mod:`gonio.models.physics.rough_tables`) and in
    Dr.Jit (:func:`gonio.models.engine.jit_tables._cached_tables`, their derivatives). What a benchmark calls before
    each timed run: a fit of a new capture finds none of the tables an earlier, identical run
    computed (the caches keep the values, not the parameter-independent quadrature grids);
    the public eval's parameter scalars (:func:`_eval_params`) as well."""
    from gonio.models.engine import jit_tables as _jit_tables
    from gonio.models.physics import rough_tables as _rough_tables

    with _EVAL_PARAMS_LOCK:
        _EVAL_PARAMS.clear()
    _rough_tables.clear_cache()
    _jit_tables.clear_cache()


def eval(model, wi, wo, params):
    """Compiled f_r(wi, wo), shape (N, 3); same contract as ``model.eval`` (which calls it
    from ``compiled_min_pairs`` pairs), the precision included: float32 directions (both)
    run the float32 kernel and give float32, anything else the float64 kernel and float64
    (:func:`gonio.models.base.eval_dtype`).

    numpy's memory is mapped into Dr.Jit without a copy and the kernel gathers the
    components (:func:`gonio.models.engine.roundtrip.eval_gathered`), except on CPUs whose vector gathers
    cost more than numpy's copies (a race decides, once per process and precision:
    :func:`round_trip_race`): there, from :data:`gonio.models.engine.roundtrip.SOA_MIN_PAIRS` pairs, numpy
    copies the direction components into Dr.Jit's memory, the model's kernel reads them as
    contiguous arrays and numpy interleaves its channels into an output in Dr.Jit's memory
    (:func:`gonio.models.engine.roundtrip.eval_blocks`; :func:`takes_copies`). Either way the kernel is
    replayed from its recording (:func:`_frozen`); per pair 48 bytes read and 24 written at
    least in float64 (24 and 12 in float32), the memory-bandwidth limit ``gonio bench
    models`` prints."""
    dtype = eval_dtype(wi, wo)
    wi, wo, p = eval_inputs(model, wi, wo, params, dtype)
    return eval_checked(model, wi, wo, p)


def eval_checked(model, wi, wo, p):
    """:func:`eval` on what :func:`gonio.models.base.eval_inputs` returned (C-contiguous
    (N, 3) directions of one type, validated parameters): ``Model.eval``'s compiled path,
    which has checked them already (a second check cost ~3-6 us a call)."""
    dtype = wi.dtype
    n = wi.shape[0]
    if n == 0:
        return np.zeros((0, CHANNELS), dtype)
    P = _eval_params(model, p, dtype)
    return _eval_path(model, wi, wo, P, takes_copies(n, dtype))


def _eval_path(model, wi, wo, P, copies: bool):
    """f_r through numpy's copies (:func:`gonio.models.engine.roundtrip.eval_blocks`) or the kernel's gathers
    (:func:`gonio.models.engine.roundtrip.eval_gathered`): the same values, bit for bit."""
    if copies:
        kern = _soa_kernel if wi.dtype == np.float64 else _packed_kernel
        return _roundtrip.eval_blocks(_frozen_for(kern, model), wi, wo, P, _FREEZE_LOCK)
    # replayed even for the diffuse models (unlike Bound.eval): with the gathers and the
    # interleave the trace is long enough (measured 28 us frozen, 57 us traced, 300 pairs)
    f32 = wi.dtype == np.float32
    runs = (_frozen_for(_round_trip, model), _frozen_for(_round_trip_words, model) if f32 else None,
            functools.partial(_roundtrip.gather_into_kernel, _kernel, model),
            functools.partial(_roundtrip.word_gather_into_kernel, _kernel, model) if f32 else None)
    return _roundtrip.eval_gathered(runs, wi, wo, P, _FREEZE_LOCK, EVAL_BLOCK)


def takes_copies(n: int, dtype=np.float32) -> bool:
    """Whether the public eval of ``n`` pairs of ``dtype`` directions takes numpy's copies
    (:func:`gonio.models.engine.roundtrip.eval_blocks`) rather than the kernel's gathers
    (:func:`gonio.models.engine.roundtrip.eval_gathered`): never below :data:`gonio.models.engine.roundtrip.SOA_MIN_PAIRS`,
    else as :data:`gonio.models.engine.roundtrip.COPIES` says (``"auto"``: the winner of
    :func:`round_trip_race`, run once per process and precision)."""
    mode = _roundtrip.COPIES
    if n < _roundtrip.SOA_MIN_PAIRS or mode == "gathers":
        return False
    return mode == "copies" or _copies_faster(np.dtype(dtype).char)


@lru_cache(maxsize=None)
def _copies_faster(char: str) -> bool:
    """Whether numpy's copies beat the kernel's gathers for ``char`` (numpy's type code)
    directions in this process (:func:`round_trip_race`, run once). A code generation
    changed later (``GONIO_LLVM_TARGET`` is read at import) changes only which path is
    faster, never a value."""
    gathers, copies = round_trip_race(np.dtype(char))
    return copies < gathers


#: Pairs each round trip evaluates in :func:`round_trip_race`: large enough that the round
#: trip, not the launch, is what is timed (where the copies win, at 65536 pairs they do by
#: 1.4x: the Zen 5's diffuse in :mod:`gonio.models.engine.roundtrip`'s notes; where the gathers win, by 1.9x
#: on the Zen 3 and 4.4x on the Intel Xeon).
RACE_PAIRS = 1 << 16


def round_trip_race(dtype, repeat: int = 7):
    """``(gathers s, copies s)``: the public eval's two numpy round trips
    (:func:`gonio.models.engine.roundtrip.eval_gathered`, :func:`gonio.models.engine.roundtrip.eval_blocks`) timed on this
    machine for ``dtype`` directions, the best of ``repeat`` calls each, taken in turn after
    one untimed call (which records the kernels): the diffuse model, whose kernel is the
    cheapest, so the round trip is most of what is timed, on :data:`RACE_PAIRS` fixed
    directions. :func:`takes_copies` runs it once per process and precision (measured on
    the Intel Xeon, 2026-12-03: ~20 ms, ~70 ms with the kernels' recordings on a first
    call)."""
    import time

    from gonio.models.registry import get

    dtype = np.dtype(dtype)
    model = get("diffuse")
    rng = np.random.default_rng(20261203)
    wi, wo = (np.abs(rng.standard_normal((RACE_PAIRS, CHANNELS))) + 0.1 for _ in range(2))
    wi, wo = ((w / np.linalg.norm(w, axis=1, keepdims=True)).astype(dtype) for w in (wi, wo))
    P = _eval_params(model, model.defaults(), dtype)
    best = [np.inf, np.inf]
    for r in range(repeat + 1):
        for k in (0, 1) if r % 2 else (1, 0):
            t0 = time.perf_counter()
            _eval_path(model, wi, wo, P, copies=bool(k))
            if r:
                best[k] = min(best[k], time.perf_counter() - t0)
    return best[0], best[1]


#: The parameters of the last few public evaluations as Dr.Jit scalars, by model
#: configuration, precision and the values' bits (:func:`_eval_params`).
_EVAL_PARAMS: OrderedDict = OrderedDict()
_EVAL_PARAMS_SIZE = 8
_EVAL_PARAMS_LOCK = threading.Lock()


def _eval_params(model, p, dtype):
    """:func:`_param_vars` (no derivatives) of validated parameters ``p`` for the public
    eval, kept for the last :data:`_EVAL_PARAMS_SIZE` sets of values: a material evaluated
    again on new directions (a render, a plot, a loop over batches) reuses its scalars.
    Each new opaque scalar is an allocation and a launch that the replayed kernel waits for:
    measured (AVX2 Zen 3, 1000 pairs, best of 2000) diffuse 47 -> 34 us a call through
    :func:`gonio.models.engine.roundtrip.eval_gathered`. Keyed by the model's name and options and the values'
    bytes (0.0 and -0.0 apart); Dr.Jit's scalars are never written to, so sharing them
    between calls and threads is safe. Only for models whose kernel reads nothing but its
    parameters (no ``structure.kernel_inputs``: roughplastic's tables follow an instance's
    ``exact_tables``, tabulated's its data; both are cached where they are built).
    :func:`clear_parameter_caches` empties it."""
    if model.structure.kernel_inputs is not None:
        return _param_vars(model, p, _roundtrip.types(dtype)[1], grad=False)[0]
    key = (model.name, tuple(sorted(model.options.items())), np.dtype(dtype).char,
           b"".join(np.asarray(v, np.float64).tobytes() for v in p.values()), tuple(p))
    with _EVAL_PARAMS_LOCK:
        P = _EVAL_PARAMS.get(key)
        if P is not None:
            _EVAL_PARAMS.move_to_end(key)
            return P
    P, _ = _param_vars(model, p, _roundtrip.types(dtype)[1], grad=False)
    with _EVAL_PARAMS_LOCK:
        _EVAL_PARAMS[key] = P
        while len(_EVAL_PARAMS) > _EVAL_PARAMS_SIZE:
            _EVAL_PARAMS.popitem(last=False)
    return P


def _soa_kernel(model, *inputs):
    """The model's kernel on contiguous components (:func:`gonio.models.engine.roundtrip.soa_kernel`)."""
    return _roundtrip.soa_kernel(_kernel, model, *inputs)


def _packed_kernel(model, *inputs):
    """The model's float32 kernel on rows packed in pairs (:func:`gonio.models.engine.roundtrip.packed_kernel`)."""
    return _roundtrip.packed_kernel(_kernel, model, *inputs)


def _round_trip(model, *inputs):
    """The model's kernel between gathers (:func:`gonio.models.engine.roundtrip.gather_kernel`)."""
    return _roundtrip.gather_kernel(_kernel, model, *inputs)


def _round_trip_words(model, *inputs):
    """The model's float32 kernel between gathers of words of two rows
    (:func:`gonio.models.engine.roundtrip.word_gather_kernel`)."""
    return _roundtrip.word_gather_kernel(_kernel, model, *inputs)


def value_and_grad(model, wi, wo, params, cotangent):
    """f_r and the gradient of ``sum(cotangent * f_r)`` with respect to the parameters.

    Parameters
    ----------
    cotangent : array_like, shape (N, 3)
        Weights of each value (e.g. ``2 w (f_r - y)`` for a weighted least squares).

    Returns
    -------
    f : ndarray, shape (N, 3)
    grad : dict
        Parameter name -> float, or (3,) array for per-channel parameters.

    Notes
    -----
    Roughness below Mitsuba's floor (1e-4) is clamped, so its gradient is 0 there.
    """
    dr, F, V3, U = _dr()
    _needs_derivatives(model)  # AD would not see through tables built in numpy either
    if _empty(model, wi, wo, params):
        p = model.validate(params)
        return np.zeros((0, CHANNELS)), {k: (np.zeros(CHANNELS) if np.ndim(v) else 0.0) for k, v in p.items()}
    vi, vo, P, leaves, n = _inputs(model, wi, wo, params, grad=True)
    cot = np.asarray(cotangent, dtype=np.float64)
    if cot.shape != (n, CHANNELS):
        raise ValueError(f"cotangent must have shape ({n}, {CHANNELS}), got {cot.shape}")
    chans = _kernel(model, vi, vo, P)
    flat_c = F(np.ascontiguousarray(cot).reshape(-1))
    idx = dr.arange(U, n) * 3
    loss = 0.0
    for c, ch in enumerate(chans):
        loss = loss + dr.sum(ch * dr.gather(F, flat_c, idx + c))
    dr.backward(loss)
    f = _interleave(chans, n)
    grad = {}
    for par, vals in leaves:
        g = np.array([float(np.asarray(dr.grad(x)).ravel()[0]) for x in vals])
        grad[par.name] = g if par.per_channel else float(g[0])
    return f, grad


def _to_numpy(chans, n):
    out = np.empty((n, CHANNELS), dtype=np.asarray(chans[0]).dtype if n else np.float64)
    for c, ch in enumerate(chans):
        out[:, c] = np.asarray(ch)
    return out


class Bound:
    """A model with its parameters loaded into Dr.Jit once (validated now, tables and Dr.Jit
    scalars built at the first :meth:`eval`), the
    counterpart of a Mitsuba BSDF instance (``mitsuba.load_dict``): each :meth:`eval` on a
    resident batch is then one kernel launch, as ``bsdf.eval`` is.

    Parameters
    ----------
    model, params
        As for ``model.eval``.
    dtype : float32 (default) or float64
        Must match the batches it evaluates.
    """

    def __init__(self, model, params, dtype=np.float32):
        self.model = model
        self.params = model.validate(params)
        self.dtype = np.dtype(dtype)
        self._P = None

    def eval(self, dirs, numpy=True, prepared=False):
        """f_r on ``dirs`` (a :class:`Directions` of the same dtype): an (N, 3) numpy array,
        or (``numpy=False``) the three channels as evaluated Dr.Jit arrays. With
        ``prepared``, from the batch's prepared geometry where the model declares one
        (:meth:`Directions.geometry`, what :func:`chi2_grad` and the fitter's kernels read;
        prepared at the first such call), else from the directions."""
        import drjit as dr

        if dirs.dtype != self.dtype:
            raise ValueError(f"batch is {dirs.dtype}, the bound parameters are {self.dtype}")
        if dirs.n == 0:
            return np.zeros((0, CHANNELS), dtype=dirs.dtype) if numpy else [dirs.F() for _ in range(CHANNELS)]
        if self._P is None:
            self._P = _param_vars(self.model, self.params, dirs.F, grad=False)[0]
        g = dirs.geometry(self.model) if prepared else None
        with dr.suspend_grad():
            if g is not None:
                chans = _frozen_for(_body_f, self.model)(g, self._P)
            else:
                chans = _frozen_kernel(self.model)(dirs.wi, dirs.wo, self._P)
            dr.eval(*chans)
        return _to_numpy(chans, dirs.n) if numpy else chans


def _body_f(model, g, P):
    """f_r from prepared geometry (:func:`_body`), for :func:`_frozen`."""
    return _body(model, g, P)


def eval_resident(model, dirs, params, numpy=True):
    """f_r on a resident batch: one fused kernel in the batch's precision
    (``Bound(model, params, dirs.dtype).eval(dirs, numpy)``).

    Returns an (N, 3) numpy array, or (``numpy=False``) the three channels as evaluated
    Dr.Jit arrays (for timing, or to keep working in Dr.Jit)."""
    return Bound(model, params, dirs.dtype).eval(dirs, numpy)


def _frozen_kernel(model):
    # _kernel reads only the model's name and options (tables arrive in P). A model whose
    # trace is so short that replaying a recording costs more (the diffuse ones: ~19 us
    # against ~13 us for 1000 pairs) says so (structure.freeze = False).
    if not model.structure.freeze:
        return lambda wi, wo, P: _kernel(model, wi, wo, P)
    return _frozen_for(_kernel, model)


def jacobian(model, dirs, params, numpy=True):
    """f_r and its derivative with respect to every parameter, in one fused kernel.

    Forward-mode derivatives written out next to the value in :func:`_kernel` (every
    intermediate shared; tested against Dr.Jit's reverse-mode AD and against finite
    differences of the numpy reference). For a per-channel parameter p, ``J[p][:, c]`` is
    d f_r[c] / d p[c]; channels are independent (d f_r[c] / d p[c'] = 0 for c' != c) except
    for a parameter the model declares coupled (``structure.coupled``: principled's base
    colour), whose cross-channel part comes through the extra entry ``J[aux]``
    (:func:`jacobian_column` assembles any column); for a shared one it is d f_r[c] / d p.

    Returns
    -------
    f : ndarray (N, 3), or list of 3 Dr.Jit arrays when ``numpy=False``
    J : dict
        Parameter name -> ndarray (N, 3) (or list of 3 Dr.Jit arrays).

    Notes
    -----
    Roughness below Mitsuba's floor (1e-4) is clamped, so its derivative is 0 there. For
    ``roughplastic`` the derivatives include the tables' dependence on alpha and int_ior.
    """
    import drjit as dr

    _needs_derivatives(model)
    p = model.validate(params)
    n = dirs.n
    if n == 0:
        z = np.zeros((0, CHANNELS), dtype=dirs.dtype)
        return z, {par.name: z.copy() for par in model.parameters}
    P, _ = _param_vars(model, p, dirs.F, grad=False, dtables=True)
    run = _frozen_for(_jacobian_kernel, model)  # replayed, as Bound.eval (traced: ~1 ms a call)
    with _FREEZE_LOCK, dr.suspend_grad():
        f, J = run(*_source(model, dirs), P)
        dr.eval(*f, *(t for ts in J.values() for t in ts))
    if not numpy:
        return f, J
    return _to_numpy(f, n), {k: _to_numpy(v, n) for k, v in J.items()}


def _jacobian_kernel(model, *args):
    """(f, J) of :func:`_kernel` with derivatives, for :func:`_frozen`; ``args``: the
    :func:`_source` and P."""
    return _fJ(model, args[:-1], args[-1], grad=True)
