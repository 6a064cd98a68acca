"""Model base class and the :class:`Parameter` declaration (the registry: :mod:`gonio.models.registry`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from gonio.core.channels import CHANNELS, current, of_values
from gonio.core.sides import sides_mask
from gonio.models.engine import albedo as _compiled_albedo
from gonio.models.engine import fast as _engine
from gonio.models.inputs import eval_dtype, eval_inputs
from gonio.models.physics.albedo import albedo
from gonio.models.registry import _REGISTRY, get, names, register  # noqa: F401  (re-exported)
from gonio.models.structure import Structure

__all__ = ["Parameter", "Model", "register", "get", "names", "CHANNELS", "eval_inputs", "eval_dtype",
           "weighted_sample"]

#: Points per block in :meth:`Model.eval` (bounds temporaries: ~10 MB per array).
_BLOCK = 1 << 16


@dataclass(frozen=True)
class Parameter:
    """Declaration of one fit parameter of a model.

    Attributes
    ----------
    name : str
        Key in the ``params`` dict.
    default : float
        Default value (per channel parameters: the same value in every channel).
    lower, upper : float
        Closed bounds; :meth:`Model.validate` rejects values outside them.
    unit : str
        Unit ("1" for dimensionless).
    description : str
        Meaning, one line.
    per_channel : bool
        True if the parameter has one value per colour channel (shape (3,)).
    """

    name: str
    default: float
    lower: float
    upper: float
    unit: str
    description: str
    per_channel: bool = False


#: A spectral per-channel value has at least this many wavelengths (fewer is no spectrum).
MIN_SPECTRAL = 4


def _channel_count(name, parameters, params) -> int:
    """The channel count of ``params``: the common length of its per-channel arrays (three
    colours, or one per wavelength of a spectrum: :data:`MIN_SPECTRAL` or more),
    :data:`CHANNELS` where every value is a scalar; other lengths are refused by the caller."""
    lengths = set()
    for p in parameters:
        if p.per_channel and p.name in params:
            shape = np.shape(params[p.name])
            if len(shape) == 1:
                lengths.add(shape[0])
    if len(lengths) > 1:
        raise ValueError(f"{name}: per-channel parameters of different lengths {sorted(lengths)}; give one value "
                         "per channel to each")
    n = lengths.pop() if lengths else CHANNELS
    return n if n >= MIN_SPECTRAL else CHANNELS


class Model:
    """Base class of a BRDF model (see :mod:`gonio.models` for the conventions).

    Subclasses set ``name``, ``OPTIONS`` (option name -> tuple of allowed values, the
    first one the default), ``energy_conserving``, implement ``_parameters()``,
    ``_eval(wi, wo, p)`` on float64 arrays of unit directions and validated parameters
    ``p`` and ``to_mitsuba``. A microfacet model may also implement ``_eval_parts``
    returning (smooth part, lobe part) and ``_lobe_distribution(p)`` so that
    :meth:`albedo` integrates the lobe in half-vector space.
    """

    name = ""
    OPTIONS: dict = {}
    energy_conserving = True

    @property
    def structure(self) -> Structure:
        """What fitting and the compiled path may rely on (:class:`Structure`): a compiled
        kernel, an affine per-channel parameter. Subclasses declare theirs."""
        return Structure()

    def __init__(self, **options):
        opts = {}
        for key, allowed in self.OPTIONS.items():
            value = options.pop(key, allowed[0])
            if isinstance(value, str):
                value = value.lower()
            if value not in allowed:
                raise ValueError(f"{self.name}: option {key}={value!r} not one of {allowed}")
            opts[key] = value
        if options:
            raise ValueError(
                f"{self.name}: unknown option(s) {sorted(options)}; known: {sorted(self.OPTIONS)}"
            )
        self.options = opts
        self.parameters = tuple(self._parameters())
        self._by_name = {p.name: p for p in self.parameters}

    def __repr__(self):
        opts = ", ".join(f"{k}={v!r}" for k, v in self.options.items())
        return f"gonio.models.get({self.name!r}{', ' if opts else ''}{opts})"

    def _parameters(self):
        raise NotImplementedError

    # -- parameters ------------------------------------------------------------------
    def defaults(self):
        """Dict of default parameter values (validated form)."""
        return self.validate({})

    def validate(self, params):
        """Check and normalise a parameter dict.

        Missing parameters take their default. Per-channel parameters become float64
        arrays of shape (3,) (a scalar broadcasts); the others become Python floats.

        Raises
        ------
        ValueError
            Unknown name, wrong shape, NaN or infinite value, or a value outside the
            parameter's bounds [lower, upper].
        """
        if params is None:
            params = {}
        unknown = set(params) - set(self._by_name)
        if unknown:
            raise ValueError(
                f"{self.name}: unknown parameter(s) {sorted(unknown)}; "
                f"expected {[p.name for p in self.parameters]}"
            )
        out = {}
        n = _channel_count(self.name, self.parameters, params)
        for p in self.parameters:
            v = params.get(p.name, p.default)
            try:
                a = np.asarray(v, dtype=np.float64)
            except (TypeError, ValueError):
                raise ValueError(f"{self.name}: parameter {p.name}={v!r} is not a number") from None
            if p.per_channel:
                if a.ndim == 0:
                    a = np.full(n, float(a))
                elif a.shape != (n,):
                    raise ValueError(
                        f"{self.name}: parameter {p.name} must be a float or shape ({n},), got {a.shape}"
                    )
                else:
                    a = a.copy()
            elif a.ndim != 0:
                if a.size == 1:
                    a = a.reshape(())
                else:
                    raise ValueError(f"{self.name}: parameter {p.name} must be a scalar, got shape {a.shape}")
            # checked on Python floats: for 1-3 values this is ~10x faster than numpy's
            # ufuncs, and validation runs on every evaluation
            vals = a.tolist() if p.per_channel else [float(a)]
            if not all(math.isfinite(x) for x in vals):
                raise ValueError(f"{self.name}: parameter {p.name}={v!r} is not finite")
            if min(vals) < p.lower or max(vals) > p.upper:
                raise ValueError(
                    f"{self.name}: parameter {p.name}={v!r} outside its bounds [{p.lower}, {p.upper}] ({p.unit})"
                )
            out[p.name] = a if p.per_channel else float(a)
        self._check(out)
        return out

    def _check(self, p):
        """Hook for cross-parameter checks (raise ValueError)."""

    # -- evaluation ----------------------------------------------------------------------
    #: Pairs from which :meth:`eval` runs the compiled kernel (``backend="auto"``). Measured
    #: on this project's 2-core machine (``python -m gonio.perf.models --crossover``): the
    #: compiled call costs ~60 us whatever N up to ~1e4 pairs (validation, the replayed
    #: kernel, the numpy round trip); numpy's microfacet models cost that at ~10 pairs, the
    #: diffuse ones at ~500-1000. Models set their own.
    compiled_min_pairs = 32

    def eval(self, wi, wo, params, backend="auto"):
        """BRDF f_r(wi, wo) in sr^-1, shape (N, 3), in the precision of the directions.

        Parameters
        ----------
        wi : array_like, shape (N, 3)
            Unit directions toward the light (local frame, +z normal).
        wo : array_like, shape (N, 3)
            Unit directions toward the detector.
        params : dict
            Parameter values (see :attr:`parameters`); validated on every call.
        backend : {"auto", "numpy", "drjit"}
            ``"auto"`` (default): the compiled kernel (:func:`gonio.models.fast.eval`, the
            same formulas) from :attr:`compiled_min_pairs` pairs where Dr.Jit's LLVM backend
            works, otherwise the numpy reference; ``"numpy"``: the reference
            (:meth:`eval_reference`, in float64; rounded to float32 for float32 directions);
            ``"drjit"``: the compiled kernel at any size
            (ValueError where there is none). The environment variable
            ``GONIO_EVAL_BACKEND=numpy`` makes ``"auto"`` numpy.

        Returns
        -------
        ndarray, shape (N, 3), float64 or float32
            f_r without the cosine factor; 0 where either direction is at or below the
            horizon (and for non-finite directions). The type follows the directions, as
            numpy's arithmetic does (:func:`eval_dtype`):

            * float64 (and anything else: lists, integers, float32 mixed with float64):
              float64, the compiled float64 kernel equal to the reference to ~1e-14
              relative (roughplastic Beckmann ~1e-8, through Dr.Jit's erfinv in its tables);
            * ``wi`` and ``wo`` both float32: float32, the compiled float32 kernel (Mitsuba's
              precision; the fast path, half the bytes and twice the SIMD lanes): equal to
              the float64 reference on the same float32 directions to 2e-5 relative
              wherever f_r cos(theta_i) > 1e-6 (measured <= 7.5e-6). The numpy reference
              (``backend="numpy"``, below :attr:`compiled_min_pairs`, or without Dr.Jit)
              computes in float64 and returns it rounded to float32.
        """
        dtype = eval_dtype(wi, wo)
        if backend == "numpy":
            return self.eval_reference(wi, wo, params).astype(dtype, copy=False)
        if backend not in ("auto", "drjit"):
            raise ValueError(f"backend={backend!r}: give 'auto', 'numpy' or 'drjit'")
        wi, wo, p = eval_inputs(self, wi, wo, params, dtype)
        if self.n_channels(p) != CHANNELS:       # the compiled kernels hold three channels
            if backend == "drjit":
                raise ValueError(f"{self.name}: the compiled kernel evaluates {CHANNELS} channels, not "
                                 f"{self.n_channels(p)}")
            return self.eval_reference(wi, wo, p).astype(dtype, copy=False)
        if backend == "drjit" or (wi.shape[0] >= self.compiled_min_pairs and _engine.compiled_for(self)):
            if backend == "drjit" and not _engine.compiled_for(self):
                raise ValueError(f"{self.name}: no compiled kernel here (Dr.Jit's LLVM backend or the model's kernel missing)")
            return _engine.eval_checked(self, wi, wo, p)
        return self.eval_reference(wi, wo, p).astype(dtype, copy=False)

    def eval_reference(self, wi, wo, params):
        """f_r from the numpy reference implementation: float64 whatever the directions'
        type (float32 ones are promoted), in blocks of 65536 pairs; otherwise the contract of
        :meth:`eval`, which equals it to rounding (tests compare them)."""
        wi, wo, p = eval_inputs(self, wi, wo, params)
        n = wi.shape[0]
        out = np.empty((n, self.n_channels(p)))
        with np.errstate(all="ignore"):
            for s in range(0, n, _BLOCK):
                e = min(s + _BLOCK, n)
                a, b = wi[s:e], wo[s:e]
                finite = np.isfinite(a).all(axis=1) & np.isfinite(b).all(axis=1)
                if not finite.all():    # a NaN would index roughplastic's tables: evaluate the normal, give 0
                    a, b = (np.where(finite[:, None], v, [0.0, 0.0, 1.0]) for v in (a, b))
                f = self._eval(a, b, p)
                ok = finite & sides_mask(self.structure.sides, a[:, 2], b[:, 2])
                out[s:e] = np.where(ok[:, None], f, 0.0)
        return out

    def n_channels(self, p) -> int:
        """The channels of validated parameters ``p``: their per-channel arrays' length (one per
        wavelength in a spectral fit; :data:`CHANNELS` for a model without one)."""
        for q in self.parameters:
            if q.per_channel:
                return int(np.shape(p[q.name])[0])
        return CHANNELS

    def _eval(self, wi, wo, p):
        smooth, lobe = self._eval_parts(wi, wo, p)
        if lobe is None:
            return smooth
        return smooth + lobe

    def _eval_parts(self, wi, wo, p):
        raise NotImplementedError

    def _lobe_distribution(self, p):
        return None

    #: f_r is the lobe of :meth:`_eval_parts` alone (its smooth part is zero everywhere):
    #: :meth:`albedo` then integrates the lobe only, evaluated by the compiled kernel
    #: (:mod:`gonio.models.physics.albedo`).
    lobe_only = False

    #: The parameter whose Lambertian term rho / pi is the whole smooth part of
    #: :meth:`_eval_parts` (cooktorrance: ``diffuse_reflectance``), or None: :meth:`albedo`
    #: then takes the smooth part's integral as rho and the lobe as f_r - rho / pi from the
    #: compiled kernel (:mod:`gonio.models.physics.albedo`).
    lambert_smooth = None

    #: Parameter values that switch the smooth part of :meth:`_eval_parts` off, so that f_r is
    #: the lobe alone (roughplastic: ``{"diffuse_reflectance": 0}``), or None: :meth:`albedo`
    #: then integrates f_r - f_r(off) at the smooth part's nodes and f_r(off) at the lobe's,
    #: both on the compiled kernel (:mod:`gonio.models.physics.albedo`).
    smooth_off = None

    #: True where the compiled kernel gives the lobe of :meth:`_eval_parts` alone when its
    #: parameter map holds ``_structure.LOBE_ONLY`` (principled, whose base colour is in its
    #: lobe too, so no parameter value switches the smooth part off): :meth:`albedo` then
    #: splits f_r as with ``smooth_off``.
    lobe_switch = False

    # -- directional albedo --------------------------------------------------------------
    def albedo(self, wo, params, **quadrature):
        """Directional albedo a(wo) = integral of f_r(wi, wo) cos(theta_i) d(wi), (N, 3).

        Deterministic adaptive quadrature; see :func:`gonio.models.physics.albedo.albedo` for
        the options (``n_theta``, ``n_phi``, ``tol``, ``max_level``, ``return_error``)
        and the stated error (<= 1e-3 absolute, typically < 1e-5).
        """
        return albedo(self, wo, params, compiled=_compiled_albedo.quadratures(self), **quadrature)

    # -- Mitsuba ---------------------------------------------------------------------
    def to_mitsuba(self, params):
        """Dict for ``mitsuba.load_dict`` rendering exactly this model."""
        raise NotImplementedError


def weighted_sample(meas, n=3000):
    """For a model's ``data_start``: ``(wi, wo, y, w, use)`` of at most ``n`` of ``meas``'s
    samples, evenly picked; ``w`` = 1 / sigma where a value is used (finite, sigma > 0), else 0,
    and ``y`` = f w (0 where unused): a least-squares fit of ``g`` is ``sum((g w - y)^2)``."""
    pick = np.unique(np.linspace(0, meas.n_points - 1, min(meas.n_points, int(n))).astype(int))
    wi, wo = np.asarray(meas.wi, float)[pick], np.asarray(meas.wo, float)[pick]
    f, sd, use = (np.asarray(x)[pick] for x in (meas.brdf, meas.brdf_std, meas.use))
    use = use & np.isfinite(f) & np.isfinite(sd) & (sd > 0.0)
    w = np.where(use, 1.0 / np.where(use, sd, 1.0), 0.0)
    return wi, wo, np.where(use, f, 0.0) * w, w, use


def rgb(value):
    """Mitsuba texture dict of a per-channel value (:meth:`gonio.core.channels.Channels.mitsuba`:
    an ``rgb`` for the RGB channels)."""
    v = np.atleast_1d(np.asarray(value, dtype=np.float64))
    channels = of_values(v) if v.size > 1 else current()
    return channels.mitsuba(np.broadcast_to(v, (channels.n,)))


INV_PI = 1.0 / math.pi
