"""Model ``roughconductor``: Mitsuba 3's rough conductor (microfacet metal).

The anisotropic option adds ``tangent_deg``, the angle of the sample's tangent (the axis
``alpha_u`` acts along) from the holder's x axis, counter-clockwise seen from above, in
[0, 180] (0 and 180 are one frame: D and G are even in the local x and y, so the model has
period 180 deg). f_r(wi, wo) is the tangent-frame model at wi, wo rotated about the normal by
-tangent_deg. The Mitsuba BSDF dict is written in the tangent frame; the scene puts the frame
in the shape: its ``to_world`` rotated by ``tangent_deg`` about the normal
(:meth:`RoughConductor.tangent_deg`, :func:`gonio.models.mitsuba.tangent_rotation`).
"""

from __future__ import annotations

import numpy as np

from gonio.core.channels import CHANNELS
from gonio.models.base import Model, Parameter, eval_dtype, register, rgb
from gonio.models.engine.jit import (_fresnel_conductor, _lobe_iso_geometry, channels, microfacet_lobe, microfacet_lobe_iso,
                                    rotate_about_normal)
from gonio.models.structure import Structure
from gonio.models.physics.fresnel import fresnel_conductor
from gonio.core.geometry import half_vector
from gonio.models.physics.microfacet import MicrofacetDistribution, smith_g1_xyz

__all__ = ["RoughConductor"]


@register
class RoughConductor(Model):
    """Rough conductor BRDF (Mitsuba 3 ``roughconductor``).

    Options
    -------
    distribution : {"beckmann", "ggx"}
        Microfacet distribution (default "beckmann", Mitsuba's default).
    anisotropic : bool
        False: one roughness ``alpha``; True: ``alpha_u`` (local x) and ``alpha_v`` (y).

    Parameters (``params`` keys)
    ----------------------------
    eta : (3,)
        Real part of the relative complex index per channel, in [0.01, 10].
    k : (3,)
        Imaginary part (extinction coefficient) per channel, in [0, 10].
    alpha, or alpha_u and alpha_v : float
        Roughness (GGX alpha / Beckmann RMS slope), in [1e-4, 1].
    tangent_deg : float (anisotropic only)
        Angle of the tangent (``alpha_u``'s axis) from the holder's x axis, deg, in [0, 180];
        (alpha_u, alpha_v, t) and (alpha_v, alpha_u, t + 90) are the same BRDF (a fit reports
        the form with alpha_u <= alpha_v: :meth:`canonical`).

    Notes
    -----
    .. math:: f_r = \\frac{F(w_i\\cdot w_m; \\eta + i k)\\,D(w_m)\\,G_1(w_i,w_m)\\,G_1(w_o,w_m)}
                         {4\\cos\\theta_i\\cos\\theta_o}

    with the exact conductor Fresnel term, the separable Smith G of Mitsuba (rational
    Beckmann G1) and ``wm`` the half vector (Walter et al. 2007, eq. 20).
    Energy-conserving (single scattering loses energy at large alpha).
    """

    name = "roughconductor"
    lobe_only = True   # f_r is the microfacet lobe alone: its albedo's lobe nodes run the compiled kernel

    @property
    def structure(self):
        return Structure(kernel=_jit_kernel, geometry=_jit_geometry, body=_jit_body)
    OPTIONS = {"distribution": ("beckmann", "ggx"), "anisotropic": (False, True)}
    energy_conserving = True

    def _parameters(self):
        common = (
            Parameter("eta", 0.2, 0.01, 10.0, "1", "real part of the complex index of refraction", per_channel=True),
            Parameter("k", 3.0, 0.0, 10.0, "1", "extinction coefficient (imaginary part of the index)", per_channel=True),
        )
        if self.options["anisotropic"]:
            return common + (
                Parameter("alpha_u", 0.1, 1e-4, 1.0, "1", "roughness along the local x (tangent) axis"),
                Parameter("alpha_v", 0.1, 1e-4, 1.0, "1", "roughness along the local y (bitangent) axis"),
                Parameter("tangent_deg", 0.0, 0.0, 180.0, "deg", "angle of the tangent from the holder's x axis"),
            )
        return common + (Parameter("alpha", 0.1, 1e-4, 1.0, "1", "roughness (GGX alpha or Beckmann RMS slope)"),)

    def _alphas(self, p):
        if self.options["anisotropic"]:
            return p["alpha_u"], p["alpha_v"]
        return p["alpha"], p["alpha"]

    def _lobe_distribution(self, p):
        return MicrofacetDistribution(self.options["distribution"], *self._alphas(p))

    def eval(self, wi, wo, params, backend="auto"):
        """:meth:`Model.eval`; float32 directions with a turned tangent (not a multiple of 90
        deg) are evaluated in float64 and rounded once. The turn rounded in float32 moves f_r
        by |d ln f / d phi| times float32's roundoff, which a narrow anisotropic lobe makes
        larger than the float32 contract's 2e-5 (measured 3.9e-5 at alpha_u 0.0057, alpha_v
        0.0116, tangent 179.9 deg, and still 3.9e-5 with the turn's cosine and sine, or the
        whole turn, computed in float64 and rounded once); an isotropic lobe does not change
        under a turn."""
        if (self.options["anisotropic"] and backend != "numpy" and eval_dtype(wi, wo) == np.float32
                and self.tangent_deg(params) % 90.0 != 0.0):
            f = super().eval(np.asarray(wi, np.float64), np.asarray(wo, np.float64), params, backend)
            return np.ascontiguousarray(f, dtype=np.float32)
        return super().eval(wi, wo, params, backend)

    def tangent_deg(self, params) -> float:
        """The rotation about the normal, deg, of the frame :meth:`to_mitsuba` is written in:
        a scene rotates the shape's ``to_world`` by it (0 for an isotropic roughness)."""
        return float(self.validate(params)["tangent_deg"]) if self.options["anisotropic"] else 0.0

    def canonical(self, params):
        """The same BRDF with alpha_u <= alpha_v and the tangent wrapped into [0, 180)
        (alpha_u and alpha_v swap when the tangent turns by 90 deg); validated params."""
        p = self.validate(params)
        if not self.options["anisotropic"]:
            return p
        t = p["tangent_deg"]
        if p["alpha_u"] > p["alpha_v"]:
            p["alpha_u"], p["alpha_v"], t = p["alpha_v"], p["alpha_u"], t + 90.0
        p["tangent_deg"] = float(t % 180.0)
        return p

    def albedo(self, wo, params, **quadrature):
        """Directional albedo (:meth:`Model.albedo`): for a turned tangent, that of the
        tangent-frame model at ``wo`` turned by -tangent_deg (the quadrature's nodes follow
        the unrotated distribution)."""
        t = self.tangent_deg(params)
        if t == 0.0:
            return super().albedo(wo, params, **quadrature)
        return super().albedo(to_tangent_frame(np.asarray(wo, dtype=np.float64), t),
                              {**params, "tangent_deg": 0.0}, **quadrature)

    def _eval_parts(self, wi, wo, p):
        if self.options["anisotropic"] and p["tangent_deg"] != 0.0:
            wi, wo = to_tangent_frame(wi, p["tangent_deg"]), to_tangent_frame(wo, p["tangent_deg"])
        kind = self.options["distribution"]
        dist = self._lobe_distribution(p)
        au, av = dist.alpha_u, dist.alpha_v
        ci, co = wi[:, 2], wo[:, 2]
        wm, valid = half_vector(wi, wo)
        di = np.einsum("ij,ij->i", wi, wm)
        do = np.einsum("ij,ij->i", wo, wm)
        D = dist.D(wm)
        G = smith_g1_xyz(kind, au, av, wi[:, 0], wi[:, 1], ci, di) * smith_g1_xyz(kind, au, av, wo[:, 0], wo[:, 1], co, do)
        den = 4.0 * ci * co
        ok = valid & (den > 0.0)
        s = np.where(ok, D * G / np.where(ok, den, 1.0), 0.0)
        F = fresnel_conductor(0.5 * (di + do)[:, None], p["eta"], p["k"])
        return np.zeros((wi.shape[0], CHANNELS)), F * s[:, None]

    def _eval(self, wi, wo, p):
        return self._eval_parts(wi, wo, p)[1]

    def to_mitsuba(self, params):
        """Mitsuba's ``roughconductor`` in the tangent frame: with a nonzero
        :meth:`tangent_deg` the scene turns the shape's ``to_world`` by it about the normal
        (a dict cannot hold the frame: the BSDF reads it from the shape's dp/du)."""
        p = self.validate(params)
        d = {
            "type": "roughconductor",
            "distribution": self.options["distribution"],
            "eta": rgb(p["eta"]),
            "k": rgb(p["k"]),
        }
        au, av = self._alphas(p)
        if self.options["anisotropic"]:
            d["alpha_u"], d["alpha_v"] = au, av
        else:
            d["alpha"] = au
        return d


def to_tangent_frame(w, tangent_deg):
    """Directions (N, 3) in the holder frame -> the tangent frame: turned by -tangent_deg
    about the normal (the tangent (cos t, sin t, 0) -> (1, 0, 0))."""
    t = np.radians(tangent_deg)
    c, s = np.cos(t), np.sin(t)
    return np.stack([c * w[..., 0] + s * w[..., 1], c * w[..., 1] - s * w[..., 0], w[..., 2]], axis=-1)


def _jit_geometry(model, dr, wi, wo):
    """The kernel's parameter-independent part for an isotropic roughness
    (:func:`gonio.models.engine.jit._lobe_iso_geometry`: 7 values a pair); None for an anisotropic one."""
    return None if model.options["anisotropic"] else _lobe_iso_geometry(dr, wi, wo)


def _jit_body(model, k, g, P, grad):
    """The kernel on :func:`_jit_geometry`'s quantities (isotropic): the same formulas as
    :func:`_jit_kernel`'s, to rounding."""
    s, c, ds = microfacet_lobe_iso(k.dr, model.options["distribution"], P["alpha"], g, grad)
    return _conductor(model, k, s, c, ds, P, grad)


def _jit_kernel(model, k, wi, wo, P, grad):
    """The compiled kernel: conductor Fresnel times the microfacet term, derivatives by hand."""
    dr = k.dr
    aniso = model.options["anisotropic"]
    alphas = (P["alpha_u"], P["alpha_v"]) if aniso else (P["alpha"], P["alpha"])
    if aniso:   # the tangent frame; d f / d tangent_deg from the lobe's d ln / d turn
        wi, wo = rotate_about_normal(dr, wi, P["tangent_deg"]), rotate_about_normal(dr, wo, P["tangent_deg"])
    s, c, ds = microfacet_lobe(dr, model.options["distribution"], alphas, wi, wo, grad, aniso)
    return _conductor(model, k, s, c, ds, P, grad)


def _conductor(model, k, s, c, ds, P, grad):
    """Conductor Fresnel at c times the microfacet term s (and ds per roughness parameter)."""
    dr = k.dr
    fres = [_fresnel_conductor(dr, c, e, kk, grad) for e, kk in zip(channels(P, "eta"), channels(P, "k"))]
    if not grad:
        return [Fc * s for Fc in fres], {}
    J = {"eta": [Fc[1] * s for Fc in fres], "k": [Fc[2] * s for Fc in fres]}
    for key, d in ds.items():
        J[key] = [Fc[0] * d for Fc in fres]
    return [Fc[0] * s for Fc in fres], J
