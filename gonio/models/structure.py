"""What a model declares about its own structure, for fitting and the compiled path.

A model's :attr:`~gonio.models.Model.structure` says, without anyone testing its name:

* ``kernel``: its compiled Dr.Jit kernel (values and exact derivatives), or None, with
  ``kernel_inputs`` (what it needs beyond the parameters), ``freeze`` (whether replaying a
  recorded kernel launch pays off) and ``derivatives`` (False: values only, the fit differences);
* ``geometry(model, dr, wi, wo)``: the parameter-independent per-pair quantities its kernel
  reads, and ``body(model, ctx, g, P, grad)``: the rest of the kernel on them (see below);
* ``compile_always``: the compiled path pays off at any number of points;
* ``affine``: f_r[c] = base(theta) + coef[c] * basis(theta) with base and basis the same in
  every channel (an :class:`Affine` declaration), or None;
* ``sides``: the sides it scatters into (:mod:`gonio.core.sides`; reflection by default);
* ``coupled``: per-channel parameters reaching the other channels through one weighted sum of
  their channels (:class:`Coupling`).
"""

# Notes on the declarations:
# * kernel: written beside the model; gonio.models.engine.fast runs it. kernel_inputs:
#   roughplastic's tables. freeze does not pay off for the two diffuse models' short traces.
#   derivatives=False: tabulated, whose 42 parameters act through tables built in numpy.
# * geometry returns a tuple of arrays, or None for an option it does not cover; ctx.active is
#   None in body (the geometry carries the horizon). kernel computes the same, to rounding: body
#   after geometry in one kernel, or, for roughconductor, its own formulas on the directions. On
#   a resident batch the chi^2, its gradient, the normal equations and the Jacobian read the
#   geometry prepared once (gonio.models.engine.fast.Directions.geometry) instead of the
#   directions.
# * sides: every horizon mask (the numpy reference, the kernels, the Mitsuba twin) reads it.
# * coupled: every other per-channel parameter acts on its own channel only.
# * compile_always: its parameter-dependent precomputation is much cheaper compiled (roughplastic's
#   quadrature tables).
# * coupled: principled's base colour, through its luminance.
#
# The idea is astropy.modeling's linear / fit_deriv declarations and Mitsuba's traverse: the
# model says what it is, the fitter reads it.

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from gonio.core.sides import REFLECTION_ONLY

__all__ = ["Affine", "Coupling", "Structure"]


@dataclass(frozen=True)
class Affine:
    """A per-channel parameter entering f_r affinely.

    Attributes
    ----------
    coefficient : str
        The model's parameter (per channel) that is ``coef * q(theta)``.
    theta : tuple of str
        The nonlinear parameters, in the column order of ``fast.affine_parts``' thetas.
    tables : bool
        base and basis depend on parameter-dependent tables (``fast.affine_tables``, (K, 64))
        and q differs from 1 (``fast.affine_q`` gives it exactly).
    q_approx : callable, optional
        ``q_approx(thetas (K, T)) -> (K,)``: a cheap q for the iterations (None: exact q).
    q_gradient : callable, optional
        ``q_gradient(theta (T,)) -> (T,)``: d q / d theta (None: q is 1, derivative 0).
    kernel : callable, optional
        ``kernel(model, ctx, cols, lanes, K, vi, vo, tables) -> (base, basis)``: the batched
        Dr.Jit kernel of ``fast.affine_parts`` (K parameter sets times N directions).
    """

    coefficient: str
    theta: tuple = ()
    tables: bool = False
    q_approx: Callable | None = None
    q_gradient: Callable | None = None
    kernel: Callable | None = None

    def approx_q(self, thetas) -> np.ndarray:
        """q at thetas (K, T) for the iterations: 1 without tables."""
        thetas = np.atleast_2d(thetas)
        if not self.tables or self.q_approx is None:
            return np.ones(thetas.shape[0])
        return self.q_approx(thetas)

    def q_grad(self, theta) -> np.ndarray:
        """d q / d theta at theta (T,): 0 without tables."""
        theta = np.asarray(theta, dtype=np.float64)
        if not self.tables or self.q_gradient is None:
            return np.zeros(theta.size)
        return self.q_gradient(theta)


@dataclass(frozen=True)
class Coupling:
    """A per-channel parameter p that enters channel c directly and through
    aux = sum_k weights[k] p[k]: d f[c] / d p[k] = delta_ck J[param][c] + weights[k] J[aux][c],
    with ``J[param][c]`` the derivative at a fixed aux and ``J[aux][c]`` = d f[c] / d aux, both
    from the model's kernel (:func:`gonio.models.fast.jacobian_column` assembles them).

    Attributes
    ----------
    param : str
        The per-channel parameter.
    aux : str
        The kernel's name for d f / d aux (not a parameter; starts with an underscore).
    weights : tuple of float
        The sum's weight of each channel.
    """

    param: str
    aux: str
    weights: tuple


@dataclass(frozen=True)
class Structure:
    """A model's structure (see the module notes)."""

    kernel: Callable | None = None
    kernel_inputs: Callable | None = None
    geometry: Callable | None = None
    body: Callable | None = None
    freeze: bool = True
    derivatives: bool = True
    compile_always: bool = False
    affine: Affine | None = None
    coupled: tuple = ()
    sides: tuple = REFLECTION_ONLY

    def coupling(self, param):
        """The :class:`Coupling` of ``param``, or None (it acts on its own channel only)."""
        return next((c for c in self.coupled if c.param == param), None)


#: Key of a compiled kernel's parameter map that asks a kernel which honours it
#: (``Model.lobe_switch``) for the lobe of ``_eval_parts`` alone, values only.
LOBE_ONLY = "_lobe_only"
