"""Python BSDF plugins for Mitsuba 3 (``mitsuba.register_bsdf``) for gonio models that
Mitsuba has no native plugin for. They evaluate the same formulas as the numpy models
(written again in Dr.Jit; tests compare the two).

Mitsuba's ``si.wi`` is gonio's ``wo`` (toward the camera/detector) and its ``wo`` is
gonio's ``wi`` (toward the light); ``eval`` returns f_r * cos(theta of gonio's wi).
Sampling is cosine-weighted (correct for any BRDF, efficient enough for these lobes).
"""

from __future__ import annotations

import math

import numpy as np

from gonio.models.mitsuba.variant import mitsuba_variant

__all__ = ["bsdf_base", "ensure_registered", "add_plugin", "rgb_channels"]

_registered: set = set()


def bsdf_base(mi, dr):
    """The base of gonio's Python BSDFs for the active variant: a front-side glossy reflector
    with cosine-weighted sampling; a subclass only defines ``_f(self, si, wo)`` -> f_r, with
    gonio's wi = Mitsuba's ``wo`` (light) and gonio's wo = ``si.wi`` (detector).

    Shared with :mod:`gonio.fitting.render.preview` (its tabulated MERL BSDF).
    """
    class GonioBSDF(mi.BSDF):
        def __init__(self, props):
            mi.BSDF.__init__(self, props)
            self.m_components = [mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide]
            self.m_flags = self.m_components[0]

        def _f(self, si, wo):  # gonio: wi = wo (light), wo = si.wi (detector)
            raise NotImplementedError

        def eval(self, ctx, si, wo, active=True):
            ci = mi.Frame3f.cos_theta(wo)
            co = mi.Frame3f.cos_theta(si.wi)
            ok = active & (ci > 0) & (co > 0)
            return dr.select(ok, self._f(si, wo) * ci, 0.0)

        def pdf(self, ctx, si, wo, active=True):
            ok = active & (mi.Frame3f.cos_theta(si.wi) > 0)
            return dr.select(ok, mi.warp.square_to_cosine_hemisphere_pdf(wo), 0.0)

        def eval_pdf(self, ctx, si, wo, active=True):
            return self.eval(ctx, si, wo, active), self.pdf(ctx, si, wo, active)

        def sample(self, ctx, si, sample1, sample2, active=True):
            bs = mi.BSDFSample3f()
            bs.wo = mi.warp.square_to_cosine_hemisphere(sample2)
            bs.pdf = mi.warp.square_to_cosine_hemisphere_pdf(bs.wo)
            bs.eta = 1.0
            bs.sampled_type = mi.UInt32(+mi.BSDFFlags.GlossyReflection)
            bs.sampled_component = mi.UInt32(0)
            ok = active & (mi.Frame3f.cos_theta(si.wi) > 0) & (bs.pdf > 0)
            value = self.eval(ctx, si, bs.wo, ok) / dr.select(ok, bs.pdf, 1.0)
            return bs, dr.select(ok, value, 0.0)

        def traverse(self, callback):
            pass

        def parameters_changed(self, keys):
            pass

    return GonioBSDF


def _make_classes(mi, dr):
    def rgb(props, key):
        return mi.Color3f(props[f"{key}_r"], props[f"{key}_g"], props[f"{key}_b"])

    _Base = bsdf_base(mi, dr)

    class CookTorranceBSDF(_Base):
        def __init__(self, props):
            _Base.__init__(self, props)
            self.rho_d = rgb(props, "diffuse_reflectance")
            self.rho_s = rgb(props, "specular_reflectance")
            self.f0 = rgb(props, "f0")
            self.m = mi.Float(props["roughness"])
            # opaque, as Mitsuba's own plugins keep their parameters: a new value reuses the
            # compiled kernel instead of being folded into a new one
            dr.make_opaque(self.rho_d, self.rho_s, self.f0, self.m)

        def _f(self, si, wo):
            wi_g, wo_g = wo, si.wi
            ci = mi.Frame3f.cos_theta(wi_g)
            co = mi.Frame3f.cos_theta(wo_g)
            h = dr.normalize(wi_g + wo_g)
            ch = mi.Frame3f.cos_theta(h)
            vh = dr.dot(wo_g, h)
            ch2 = ch * ch
            up = (ch > 0) & (vh > 0)
            ch2s = dr.select(up, ch2, 1.0)
            m2 = self.m * self.m
            tan2 = (h.x * h.x + h.y * h.y) / ch2s
            D = dr.exp(-tan2 / m2) / (m2 * ch2s * ch2s)
            G = dr.minimum(1.0, 2.0 * ch * dr.minimum(ci, co) / dr.select(up, vh, 1.0))
            x = dr.clip(1.0 - vh, 0.0, 1.0)
            x2 = x * x
            F = self.f0 + (1.0 - self.f0) * (x2 * x2 * x)
            s = dr.select(up, D * G / (math.pi * ci * co), 0.0)
            return self.rho_d / math.pi + self.rho_s * F * s

        def to_string(self):
            return "GonioCookTorrance[]"

    class OrenNayarBSDF(_Base):
        def __init__(self, props):
            _Base.__init__(self, props)
            self.rho = rgb(props, "reflectance")
            s2 = float(props["sigma"]) ** 2
            self.A = mi.Float(1.0 - s2 / (2.0 * (s2 + 0.33)))
            self.B = mi.Float(0.45 * s2 / (s2 + 0.09))
            dr.make_opaque(self.rho, self.A, self.B)  # as above

        def _f(self, si, wo):
            wi_g, wo_g = wo, si.wi
            ci = dr.clip(mi.Frame3f.cos_theta(wi_g), 0.0, 1.0)
            co = dr.clip(mi.Frame3f.cos_theta(wo_g), 0.0, 1.0)
            cd = wi_g.x * wo_g.x + wi_g.y * wo_g.y
            cmax = dr.maximum(ci, co)
            term = dr.select(cmax > 0, dr.maximum(cd, 0.0) / dr.select(cmax > 0, cmax, 1.0), 0.0)
            return self.rho / math.pi * (self.A + self.B * term)

        def to_string(self):
            return "GonioOrenNayar[]"

    classes = {"cooktorrance": CookTorranceBSDF, "orennayar": OrenNayarBSDF}
    classes.update({name: maker(mi, dr, _Base) for name, maker in _MAKERS.items()})
    return classes


#: BSDF classes that models written elsewhere add (:func:`add_plugin`): name -> maker(mi, dr, base)
_MAKERS: dict = {}


def rgb_channels(model_name, value):
    """``zip("rgb", value)`` for a gonio plugin's per-channel properties (``name_r``, ``_g``,
    ``_b``; the plugins are RGB). A spectrum (a spectral fit's value, its wavelengths declared:
    gonio.core.channels.of_values) enters as its linear sRGB under D65 (colour-science:
    CIE 1931 2-degree observer, IEC 61966-2-1), a flat spectrum as its own value."""
    from gonio.core.channels import of_values

    v = np.atleast_1d(np.asarray(value, dtype=np.float64))
    if v.size != 3:
        try:
            channels = of_values(v)
        except ValueError as exc:
            raise ValueError(f"{model_name}: {exc}") from None
        v = _linear_srgb(channels.wavelengths_nm, v)
    return zip("rgb", [float(x) for x in v])


def _linear_srgb(wavelengths, values) -> np.ndarray:
    """Linear sRGB of ``values`` at ``wavelengths`` (nm) taken as a reflectance under D65."""
    import colour

    shape = colour.SpectralShape(5.0 * math.ceil(wavelengths[0] / 5.0), 5.0 * math.floor(wavelengths[-1] / 5.0), 5.0)
    grid = np.arange(shape.start, shape.end + 1e-9, 5.0)
    rows = np.stack([np.interp(grid, wavelengths, values), np.ones(grid.size)])
    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"].copy().align(shape)
    xyz = np.asarray(colour.msds_to_XYZ(rows, cmfs, colour.SDS_ILLUMINANTS["D65"].copy().align(shape),
                                        method="Integration", shape=shape), float)
    xyz = xyz[0] / xyz[1, 1]
    return np.asarray(colour.XYZ_to_RGB(xyz, colour.RGB_COLOURSPACES["sRGB"], apply_cctf_encoding=False), float)


def add_plugin(model_name, maker):
    """Let a model module add its Python BSDF: ``maker(mi, dr, base)`` returns the class
    (derived from ``base``, :func:`bsdf_base`); registered by :func:`ensure_registered`."""
    _MAKERS[model_name] = maker


def ensure_registered(model_name):
    """Register the Python BSDF of ``model_name`` for the active Mitsuba variant (gonio's
    default variant if none is active yet); return its plugin name (``gonio_<model_name>``).

    Registration is per variant, and callers may hold another variant in a
    ``mi.scoped_set_variant`` block (the scalar virtual gonioreflectometer does), so the
    active variant wins over gonio's default.
    """
    import mitsuba as mi

    variant = mi.variant() or mitsuba_variant()
    plugin = f"gonio_{model_name}"
    if (variant, plugin) not in _registered:
        import drjit as dr

        classes = _make_classes(mi, dr)
        cls = classes[model_name]
        mi.register_bsdf(plugin, lambda props: cls(props))
        _registered.add((variant, plugin))
    return plugin
