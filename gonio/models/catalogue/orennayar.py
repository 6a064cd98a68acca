"""Model ``orennayar``: rough diffuse reflection (Oren & Nayar 1994, qualitative model)."""

from __future__ import annotations

import math


from gonio.models.base import CHANNELS, Model, Parameter, register
from gonio.models.engine.jit import _oren_nayar_geometry, _oren_nayar_over_rho, channels
from gonio.models.structure import Affine, Structure
from gonio.models.physics.diffuse import oren_nayar

__all__ = ["OrenNayar"]


@register
class OrenNayar(Model):
    """Oren-Nayar rough diffuse BRDF (see :func:`gonio.models.oren_nayar`).

    Parameters (``params`` keys)
    ----------------------------
    reflectance : (3,)
        Facet albedo rho in [0, 1].
    sigma : float
        Standard deviation of facet slope angles, radians, in [0, pi/2] (0 is Lambert).

    Notes
    -----
    Energy-conserving for rho <= 1 (the qualitative model's albedo stays below rho;
    checked by the albedo tests). Mitsuba 3 has no native plugin: ``to_mitsuba`` uses a
    registered Python BSDF (``gonio_orennayar``) with the same formula.
    """

    name = "orennayar"

    @property
    def structure(self):
        return Structure(kernel=_jit_kernel, freeze=False, affine=Affine("reflectance", ("sigma",), kernel=_jit_affine_parts),
                         geometry=_jit_geometry, body=_jit_body)
    OPTIONS = {}
    energy_conserving = True
    #: not tried by ``--model auto`` (fit it by name): the rough-diffuse term is rarely worth its
    #: second parameter on gonioreflectometer data, and ``diffuse`` is the smooth candidate
    auto_candidate = False
    compiled_min_pairs = 512  # numpy's few operations beat the compiled call's ~50 us below this (measured)

    def _parameters(self):
        return (
            Parameter("reflectance", 0.5, 0.0, 1.0, "1", "facet albedo rho", per_channel=True),
            Parameter("sigma", 0.3, 0.0, math.pi / 2, "rad", "standard deviation of facet slope angle"),
        )

    def _eval_parts(self, wi, wo, p):
        return oren_nayar(wi, wo, p["reflectance"], p["sigma"]), None

    def to_mitsuba(self, params):
        from gonio.models.mitsuba.plugins import ensure_registered, rgb_channels

        p = self.validate(params)
        d = {"type": ensure_registered("orennayar"), "sigma": p["sigma"]}
        for c, v in rgb_channels(self.name, p["reflectance"]):
            d[f"reflectance_{c}"] = float(v)
        return d


def _jit_geometry(model, dr, wi, wo):
    """The kernel's parameter-independent part: :func:`gonio.models.engine.jit._oren_nayar_geometry`'s
    (u, v), shape(sigma) = A(sigma) u + B(sigma) v."""
    return _oren_nayar_geometry(dr, wi, wo)


def _jit_body(model, k, g, P, grad):
    """f_r = rho * shape(sigma) on :func:`_jit_geometry`'s quantities, derivatives by hand."""
    shape = _oren_nayar_over_rho(k.dr, P["sigma"], None, None, grad, g)
    basis, dbasis = shape if grad else (shape, None)
    f = [r * basis for r in channels(P, "reflectance")]
    J = {}
    if grad:
        J["reflectance"] = [basis] * CHANNELS
        J["sigma"] = [r * dbasis for r in channels(P, "reflectance")]
    return f, J


def _jit_kernel(model, k, wi, wo, P, grad):
    """The compiled kernel: :func:`_jit_body` after :func:`_jit_geometry`, in one kernel."""
    return _jit_body(model, k, _jit_geometry(model, k.dr, wi, wo), P, grad)


def _jit_affine_parts(model, k, cols, lanes, K, vi, vo, tables):
    """base = 0, basis = shape(sigma) (``fast.affine_parts``)."""
    dr, F = k.dr, k.F
    return F(0.0) * vi.z, _oren_nayar_over_rho(dr, dr.gather(F, cols[0], lanes), vi, vo)
