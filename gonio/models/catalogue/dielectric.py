"""Model ``dielectric``: a smooth interface between two dielectrics (Mitsuba 3 ``dielectric``).

Its BSDF is a sum of two Dirac deltas, at the mirror direction and the refracted one, so
:meth:`eval` is 0 at every pair of directions (a finite set of pairs never lands on a delta).
What the model has to say is in :meth:`Dielectric.specular`: the two directions, the
reflectance R(theta_i) and the transmitted factor t = eta^2 (1 - R) of radiance transport
(L_o = t L_i; the power transmittance 1 - R alongside). A gonioreflectometer sees a delta
through its aperture as R / Omega; a fit of measured data belongs to ``roughdielectric``
(alpha -> 0 is this model). Convention as in :mod:`gonio.models.catalogue.roughdielectric`.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from gonio.core.channels import CHANNELS
from gonio.core.geometry import as_directions
from gonio.models.base import Model, Parameter, register
from gonio.models.catalogue.roughdielectric import BOTH_SIDES
from gonio.models.physics.fresnel import fresnel_dielectric
from gonio.models.structure import Structure

__all__ = ["Dielectric", "SpecularLobes"]


class SpecularLobes(NamedTuple):
    """The deltas of a smooth interface lit from ``wi`` (all (N, 3) or (N,)).

    Attributes
    ----------
    wr : ndarray, shape (N, 3)
        Mirror direction.
    r : ndarray, shape (N,)
        Reflectance R (power and radiance alike).
    wt : ndarray, shape (N, 3)
        Transmitted direction; the zero vector under total internal reflection.
    t : ndarray, shape (N,)
        Radiance factor of the transmitted delta: L(wt) = t L(wi) (n_t^2 / n_i^2 (1 - R)).
    t_power : ndarray, shape (N,)
        Power transmittance 1 - R (0 under total internal reflection); R + t_power = 1.
    """

    wr: np.ndarray
    r: np.ndarray
    wt: np.ndarray
    t: np.ndarray
    t_power: np.ndarray


def smooth_lobes(wi, eta):
    """:class:`SpecularLobes` of a smooth interface of relative index ``eta`` (n(-z) / n(+z))
    lit from ``wi`` on either side (Snell's law and the Fresnel equations, Born & Wolf 1.5)."""
    wi = as_directions(wi, "wi")
    c = np.clip(wi[:, 2], -1.0, 1.0)
    F, cos_t, eta_it, eta_ti = fresnel_dielectric(c, eta)
    wr = wi * [-1.0, -1.0, 1.0]
    tir = cos_t == 0.0
    wt = np.concatenate([-wi[:, :2] * eta_ti[:, None], cos_t[:, None]], axis=1)
    wt = np.where(tir[:, None], 0.0, wt)
    t_power = np.where(tir, 0.0, 1.0 - F)
    return SpecularLobes(wr, F, wt, t_power * eta_it * eta_it, t_power)


@register
class Dielectric(Model):
    """Smooth dielectric BSDF (Mitsuba 3 ``dielectric``, radiance mode): two deltas.

    Parameters (``params`` keys)
    ----------------------------
    int_ior : float
        Relative index eta = n_interior / n_exterior, in [0.25, 4].

    Notes
    -----
    R = F(cos theta_i; eta), the transmitted ray obeys sin theta_t = sin theta_i / eta;
    beyond the critical angle asin(eta) (eta < 1) R = 1 and nothing is transmitted.
    """

    name = "dielectric"
    auto_candidate = False   # a delta: no finite data fixes it (see the module docstring)
    OPTIONS: dict = {}
    energy_conserving = True
    delta = True

    @property
    def structure(self):
        return Structure(sides=BOTH_SIDES)

    def _parameters(self):
        return (Parameter("int_ior", 1.5, 0.25, 4.0, "1", "relative index of refraction n_interior / n_exterior"),)

    def _eval_parts(self, wi, wo, p):
        return np.zeros((wi.shape[0], CHANNELS)), None

    def specular(self, wi, params) -> SpecularLobes:
        """The two deltas for light from ``wi`` (:class:`SpecularLobes`)."""
        return smooth_lobes(wi, self.validate(params)["int_ior"])

    def to_mitsuba(self, params):
        p = self.validate(params)
        return {"type": "dielectric", "int_ior": p["int_ior"], "ext_ior": 1.0}
