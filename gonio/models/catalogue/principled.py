"""Model ``principled``: Mitsuba 3's ``principled`` BSDF (the Disney principled BRDF of
Burley 2012 as Mitsuba implements it), its opaque reflection part, term by term.

Reproduced from Mitsuba 3's ``src/bsdfs/principled.cpp`` and ``principledhelpers.h``
(read, not copied; the formulas are Burley's), with the conventions of gonio.models
(``wi`` toward the light = Mitsuba's ``wo``; ``wo`` toward the detector = Mitsuba's
``si.wi``). ``spec_trans`` (transmission) and ``anisotropic`` are not modelled: a
gonioreflectometer measures an opaque, isotropic sample in reflection; both are 0 in
:meth:`Principled.to_mitsuba`, which makes Mitsuba skip those lobes.

References
----------
Burley, B. (2012). Physically-based shading at Disney. SIGGRAPH course notes.
Mitsuba 3, ``principled`` plugin documentation and source (mitsuba-renderer/mitsuba3).
"""

from __future__ import annotations

import math

import numpy as np

from gonio.core.channels import CHANNELS
from gonio.models.base import INV_PI, Model, Parameter, register, rgb
from gonio.models.physics.fresnel import fresnel_dielectric
from gonio.models.engine.jit import _floor, _fresnel_outside, channels, microfacet_lobe
from gonio.models.physics.microfacet import MicrofacetDistribution, smith_g1_xyz
from gonio.models.structure import LOBE_ONLY, Coupling, Structure
from gonio.core.geometry import half_vector

__all__ = ["Principled", "LUMINANCE", "luminance_weights", "specular_to_eta"]

#: Mitsuba's ``luminance`` of a linear sRGB colour (Rec. 709 Y row)
LUMINANCE = np.array([0.212671, 0.715160, 0.072169])


def luminance_weights(n: int) -> np.ndarray:
    """The tint's luminance weights: Rec. 709's Y for three channels; for ``n`` spectral samples
    their mean (the luminance of a spectrum without its illuminant's weighting)."""
    return LUMINANCE if n == LUMINANCE.size else np.full(n, 1.0 / n)


def specular_to_eta(specular):
    """Mitsuba's map from ``specular`` to the index: eta = 2 / (1 - sqrt(0.08 s)) - 1."""
    return 2.0 / (1.0 - np.sqrt(0.08 * specular)) - 1.0


def schlick_weight(c):
    """(1 - c)^5 clipped to [0, 1] (Schlick 1994)."""
    m = np.clip(1.0 - c, 0.0, 1.0)
    return (m * m) * (m * m) * m


def _schlick(r0, cos, eta):
    """Mitsuba's ``calc_schlick`` for a front-side ray and eta >= 1 (where the transmitted
    cosine equals the incident one at eta = 1): r0 + (1 - r0) (1 - cos)^5."""
    w = schlick_weight(np.abs(cos))
    return r0 + (1.0 - r0) * w


def _smith_ggx1(z, dot_vh, alpha):
    """The clearcoat's Smith G1 (GGX form with a fixed alpha), Mitsuba's ``smith_ggx1``."""
    c2 = z * z
    t2 = (1.0 - c2) / np.where(c2 > 0, c2, 1.0)
    g = 2.0 / (1.0 + np.sqrt(1.0 + alpha * alpha * t2))
    g = np.where(z == 1.0, 1.0, g)
    return np.where(dot_vh * z <= 0.0, 0.0, g)


def _gtr1(cos_h, alpha):
    """Burley's GTR1 (Berry) distribution of the clearcoat, normalised as Mitsuba's."""
    a2 = alpha * alpha
    r = (a2 - 1.0) / (math.pi * math.log(a2) * (1.0 + (a2 - 1.0) * cos_h * cos_h))
    return np.where(r * cos_h > 1e-20, r, 0.0)


@register
class Principled(Model):
    """Mitsuba 3's ``principled`` BSDF, opaque and isotropic.

    Options
    -------
    distribution : {"ggx"}
        The main lobe's distribution: Mitsuba's principled BSDF has GGX only (the
        clearcoat is GTR1).

    Parameters (``params`` keys; Mitsuba's names)
    ---------------------------------------------
    base_color : (3,)
        Base colour (diffuse albedo, metallic F0), in [0, 1].
    roughness : float
        alpha = max(0.001, roughness^2) of the main GGX lobe, in [0.0317, 1].
    metallic, spec_tint, sheen, sheen_tint, clearcoat, clearcoat_gloss, flatness : float
        Burley's weights, in [0, 1].
    specular : float
        Specular level, eta = 2 / (1 - sqrt(0.08 specular)) - 1, in [0.001, 1].

    Notes
    -----
    With h the half vector, c_d = h . wi, F_w(c) = (1 - c)^5, lum the luminance of
    base_color and c_tint = base_color / lum, m = metallic:

    * main lobe: F D G / (4 cos_i cos_o), D and G GGX (separable Smith), F =
      (1 - m)(1 - spec_tint) F_dielectric(h . wo, eta) + m Schlick(base_color) +
      (1 - m) spec_tint Schlick(c_tint R0(eta));
    * clearcoat: clearcoat / 4 * Schlick(0.04) * GTR1(lerp(0.1, 0.001, gloss)) * G1(0.25)
      G1(0.25) -- without the 1 / (4 cos_i cos_o) of a microfacet lobe, as Mitsuba writes it;
    * diffuse: (1 - m) base_color / pi * lerp(f_d + f_retro, f_ss, flatness) with Burley's
      f_d = (1 - F_w(cos_i)/2)(1 - F_w(cos_o)/2), Rr = 2 roughness c_d^2,
      f_retro = Rr (F_i + F_o + F_i F_o (Rr - 1)) and the Hanrahan-Krueger-like f_ss;
    * sheen: sheen (1 - m) F_w(c_d) lerp(1, c_tint, sheen_tint) (no 1/pi, as Mitsuba).

    Agreement with Mitsuba: ~1e-7 relative (float32) everywhere but within ~0.3 deg of the
    mirror direction with a glossy clear coat, where Mitsuba's float32 GTR1 denominator
    1 + (alpha^2 - 1) cos^2 theta_h cancels (~6e-8 / alpha^2 relative; 2e-4 at gloss 0.76).

    Compiled kernel (:func:`_jit_kernel`, :mod:`gonio.models.fast`): the same terms with
    hand-written derivatives, equal to this reference to ~1e-14 in float64; its GTR1
    denominator is written sin^2 theta_h + alpha^2 cos^2 theta_h, so the float32 kernel does
    not share Mitsuba's cancellation at the mirror direction (<= 1.2e-6 relative to the
    float64 reference on the tests' hard pairs, where that form gave 4e-4).

    Not energy-conserving for every parameter (the retro-reflection and sheen terms can
    push the albedo above 1): ``energy_conserving = False``, so a fit constrains albedo <= 1.
    """

    name = "principled"
    OPTIONS = {"distribution": ("ggx",)}
    energy_conserving = False
    lobe_switch = True   # albedo: the kernel gives its lobe alone on request (gonio/models/engine/albedo)

    @property
    def structure(self):
        # the compiled kernel (value and hand-written derivatives); base_color is coupled
        # across channels through its luminance (the tints c_tint = base_color / lum), which
        # the kernel's derivative d f / d lum carries (:class:`Coupling`); no affine parameter
        return Structure(kernel=_jit_kernel, coupled=(Coupling("base_color", "_lum", tuple(LUMINANCE)),))

    def _parameters(self):
        w = "weight in [0, 1]"
        return (
            Parameter("base_color", 0.5, 0.0, 1.0, "1", "base colour (diffuse albedo, metallic F0)", per_channel=True),
            Parameter("roughness", 0.5, 0.0317, 1.0, "1", "roughness; GGX alpha = roughness^2"),
            Parameter("metallic", 0.0, 0.0, 1.0, "1", f"metallic {w}"),
            Parameter("specular", 0.5, 0.001, 1.0, "1", "specular level (eta = 2/(1 - sqrt(0.08 s)) - 1)"),
            Parameter("spec_tint", 0.0, 0.0, 1.0, "1", f"tint of the specular lobe toward base_color, {w}"),
            Parameter("sheen", 0.0, 0.0, 1.0, "1", f"sheen {w}"),
            Parameter("sheen_tint", 0.0, 0.0, 1.0, "1", f"tint of the sheen toward base_color, {w}"),
            Parameter("clearcoat", 0.0, 0.0, 1.0, "1", f"clear-coat lobe {w}"),
            Parameter("clearcoat_gloss", 0.0, 0.0, 1.0, "1", "clear-coat gloss (GTR1 alpha 0.1 -> 0.001)"),
            Parameter("flatness", 0.0, 0.0, 1.0, "1", f"fake subsurface {w}"),
        )

    def _lobe_distribution(self, p):
        return MicrofacetDistribution("ggx", max(0.001, p["roughness"] ** 2))

    def _eval_parts(self, wi, wo, p):
        base = p["base_color"]
        m, rough = p["metallic"], p["roughness"]
        eta = specular_to_eta(p["specular"])
        alpha = max(0.001, rough * rough)
        ci, co = wi[:, 2], wo[:, 2]
        h, valid = half_vector(wi, wo)
        dh_o = np.einsum("ij,ij->i", wo, h)      # Mitsuba's dot(si.wi, wh)
        dh_i = np.einsum("ij,ij->i", wi, h)      # Mitsuba's dot(wh, wo): cos_theta_d
        ok = valid & (dh_o > 0.0) & (dh_i > 0.0) & (ci > 0.0) & (co > 0.0)
        lum = float(luminance_weights(base.size) @ base)
        c_tint = base / lum if lum > 0.0 else np.ones(base.size)
        # main GGX lobe
        D = MicrofacetDistribution("ggx", alpha).D(h)
        G = smith_g1_xyz("ggx", alpha, alpha, wi[:, 0], wi[:, 1], ci, dh_i) * \
            smith_g1_xyz("ggx", alpha, alpha, wo[:, 0], wo[:, 1], co, dh_o)
        F_d = fresnel_dielectric(dh_o, eta)[0][:, None]
        r0 = ((eta - 1.0) / (eta + 1.0)) ** 2
        st = p["spec_tint"]
        F = ((1.0 - m) * (1.0 - st) * F_d + m * _schlick(base, dh_o[:, None], eta)
             + (1.0 - m) * st * _schlick(c_tint * r0, dh_o[:, None], eta))
        den = np.where(ok, 4.0 * ci * co, 1.0)
        lobe = np.where(ok, D * G / den, 0.0)[:, None] * F
        # clear coat (GTR1, Schlick 0.04, fixed-alpha G; no 1/(4 cos cos), as Mitsuba)
        cc = p["clearcoat"]
        if cc > 0.0:
            a_cc = 0.1 + p["clearcoat_gloss"] * (0.001 - 0.1)
            Fcc = _schlick(0.04, dh_o, eta)
            Gcc = _smith_ggx1(co, dh_o, 0.25) * _smith_ggx1(ci, dh_i, 0.25)
            lobe = lobe + np.where(ok, 0.25 * cc * Fcc * _gtr1(h[:, 2], a_cc) * Gcc, 0.0)[:, None]
        # diffuse, retro-reflection, fake subsurface
        Fo, Fi = schlick_weight(ci), schlick_weight(co)
        f_diff = (1.0 - 0.5 * Fi) * (1.0 - 0.5 * Fo)
        Rr = 2.0 * rough * dh_i * dh_i
        f_retro = Rr * (Fo + Fi + Fo * Fi * (Rr - 1.0))
        shape = f_diff + f_retro
        if p["flatness"] > 0.0:
            fss = (1.0 + (0.5 * Rr - 1.0) * Fo) * (1.0 + (0.5 * Rr - 1.0) * Fi)
            f_ss = 1.25 * (fss * (1.0 / np.where(ok, ci + co, 1.0) - 0.5) + 0.5)
            shape = shape + p["flatness"] * (f_ss - shape)
        smooth = np.where(ok, shape, 0.0)[:, None] * ((1.0 - m) * INV_PI * base)
        if p["sheen"] > 0.0:
            c_sheen = 1.0 + p["sheen_tint"] * (c_tint - 1.0)
            smooth = smooth + np.where(ok, schlick_weight(np.abs(dh_i)), 0.0)[:, None] * (p["sheen"] * (1.0 - m) * c_sheen)
        return smooth, lobe

    def to_mitsuba(self, params):
        p = self.validate(params)
        d = {"type": "principled", "base_color": rgb(p["base_color"])}
        for key in ("roughness", "metallic", "specular", "spec_tint", "sheen", "sheen_tint", "clearcoat",
                    "clearcoat_gloss", "flatness"):
            # Mitsuba reads each weight's flag back through std::stof of its text, which throws
            # on a subnormal float32 (a fitted weight at its bound, e.g. 1e-300): below 1e-30
            # a weight changes nothing measurable, so it is written as 0
            v = float(p[key])
            d[key] = v if abs(v) >= 1e-30 else 0.0
        return d


def _jit_kernel(model, k, wi, wo, P, grad):
    """The compiled kernel: :meth:`Principled._eval_parts` term by term, value and exact
    derivatives written out beside it (forward mode, every intermediate shared).

    Derivatives. With w = F_w(c) at the microfacet cosine c, S the microfacet term
    D G / (4 cos_i cos_o) (:func:`gonio.models.engine.jit.microfacet_lobe`: d S / d alpha, alpha =
    roughness^2), t_c = base_c / lum the tint and m the metallic weight:

    * F_c = (1 - m)(1 - st) F_d + m (b_c + (1 - b_c) w) + (1 - m) st (w + t_c r0 (1 - w)),
      so dF_c / d m, d st and d t_c are the bracketed factors, and through eta(specular)
      d eta / d specular = 0.08 / (q (1 - q)^2), q = sqrt(0.08 specular), with dF_d / d eta
      from :func:`_fresnel_outside` and d r0 / d eta = 4 (eta - 1) / (eta + 1)^3;
    * the clear coat is linear in ``clearcoat``; d ln GTR1 / d a^2 = 1 / (a^2 - 1)
      - 1 / (a^2 ln a^2) - cos_h^2 / (1 + (a^2 - 1) cos_h^2), d a / d gloss = -0.099;
    * the diffuse shape depends on roughness through Rr = 2 roughness c^2:
      d(f_d + f_retro) / d Rr = F_o + F_i + F_o F_i (2 Rr - 1),
      d f_ss / d Rr = 1.25 (1 / (cos_i + cos_o) - 1/2) d fss / d Rr;
    * base_color: ``J["base_color"][c]`` is d f_c / d b_c at a fixed luminance and
      ``J["_lum"][c]`` is d f_c / d lum = -(d f_c / d t_c) b_c / lum^2, so that
      d f_c / d b_k = delta_ck J["base_color"][c] + LUMINANCE[k] J["_lum"][c]
      (:func:`gonio.models.fast.jacobian_column`). Where lum = 0 the tints are 1 and
      J["_lum"] is 0, as the reference's ``c_tint = 1`` branch.
    """
    dr, active = k.dr, k.active
    ci, co = wi.z, wo.z
    rough, m, spec, st = P["roughness"], P["metallic"], P["specular"], P["spec_tint"]
    sh, sht, cc, gloss, fl = P["sheen"], P["sheen_tint"], P["clearcoat"], P["clearcoat_gloss"], P["flatness"]
    base = channels(P, "base_color")
    # main GGX lobe (alpha = max(0.001, roughness^2): the bound 0.0317 keeps it above 0.001)
    alpha = dr.maximum(rough * rough, 0.001)
    S, _, dS = microfacet_lobe(dr, "ggx", (alpha, alpha), wi, wo, grad, aniso=False)
    h = wi + wo
    h2 = dr.squared_norm(h)
    inv = dr.rsqrt(dr.select(h2 > _floor(h2), h2, 1.0))
    mz = h.z * inv
    # h . wo (Fresnel) and h . wi (retro-reflection, sheen) each on its own, as the reference
    # (they differ in the last bits for directions not exactly of unit length)
    c, c_i = dr.dot(wo, h) * inv, dr.dot(wi, h) * inv
    ok = active & (h2 > _floor(h2)) & (c > 0) & (c_i > 0)
    S = dr.select(ok, S, 0.0)

    def fw(x):
        y = dr.clip(1.0 - x, 0.0, 1.0)
        return (y * y) * (y * y) * y

    w = fw(c)
    q = dr.sqrt(0.08 * spec)
    eta = 2.0 / (1.0 - q) - 1.0
    fres = _fresnel_outside(dr, c, eta, grad)
    Fd = dr.select(ok, fres[0], 0.0)
    r0 = (eta - 1.0) / (eta + 1.0)
    r0 = r0 * r0
    lum = sum(float(L) * b for L, b in zip(LUMINANCE, base))
    pos = lum > 0.0
    rl = 1.0 / dr.select(pos, lum, 1.0)
    tint = [dr.select(pos, b * rl, 1.0) for b in base]
    one_m = 1.0 - m
    Fc = [one_m * (1.0 - st) * Fd + m * (b + (1.0 - b) * w) + one_m * st * (w + t * r0 * (1.0 - w))
          for b, t in zip(base, tint)]
    # clear coat: GTR1 with a = lerp(0.1, 0.001, gloss), Schlick(0.04), G1 of alpha 0.25
    a_cc = 0.1 + gloss * (0.001 - 0.1)
    a2 = a_cc * a_cc
    # 1 + (a^2 - 1) cos_h^2 = sin_h^2 + a^2 cos_h^2: no cancellation at the mirror direction
    # (Mitsuba's float32 form loses ~6e-8 / a^2 there, see the class notes)
    E = (h.x * h.x + h.y * h.y) * (inv * inv) + a2 * mz * mz
    d1 = (a2 - 1.0) / (math.pi * dr.log(a2) * E)
    d1_ok = ok & (d1 * mz > 1e-20)
    d1 = dr.select(d1_ok, d1, 0.0)

    def g1cc(z):  # 2 / (1 + sqrt(1 + 0.0625 tan^2)) = 2 z / (z + sqrt(z^2 + 0.0625 (1 - z^2)))
        zs = dr.select(ok, z, 1.0)
        return 2.0 * zs / (zs + dr.sqrt(zs * zs + 0.0625 * (1.0 - zs * zs)))

    Fcc = 0.04 + 0.96 * w
    coat_unit = 0.25 * Fcc * d1 * g1cc(co) * g1cc(ci)      # d coat / d clearcoat
    coat = cc * coat_unit
    if P.get(LOBE_ONLY) and not grad:     # the lobe of _eval_parts alone (the albedo's quadrature)
        return [S * Fcc_c + coat for Fcc_c in Fc], {}
    # diffuse, retro-reflection, fake subsurface (F_o = F_w(cos_i), F_i = F_w(cos_o), as the reference)
    Fo, Fi = fw(ci), fw(co)
    f_diff = (1.0 - 0.5 * Fi) * (1.0 - 0.5 * Fo)
    c2 = c_i * c_i
    Rr = 2.0 * rough * c2
    shape0 = f_diff + Rr * (Fo + Fi + Fo * Fi * (Rr - 1.0))
    ai, ao = 1.0 + (0.5 * Rr - 1.0) * Fo, 1.0 + (0.5 * Rr - 1.0) * Fi
    rsum = 1.0 / dr.select(ok, ci + co, 1.0)
    f_ss = 1.25 * (ai * ao * (rsum - 0.5) + 0.5)
    shape = dr.select(ok, shape0 + fl * (f_ss - shape0), 0.0)
    wd = dr.select(ok, fw(c_i), 0.0)
    kd = one_m * (1.0 / math.pi)
    f = [shape * kd * b + wd * sh * one_m * (1.0 + sht * (t - 1.0)) + S * Fcc_c + coat
         for b, t, Fcc_c in zip(base, tint, Fc)]
    if not grad:
        return f, {}
    J = {}
    dSda = dS["alpha"]
    dalpha = dr.select(rough * rough > 0.001, 2.0 * rough, 0.0)
    dshape0 = Fo + Fi + Fo * Fi * (2.0 * Rr - 1.0)
    dfss = 0.5 * Fo * ao + 0.5 * Fi * ai
    dshape = dr.select(ok, ((1.0 - fl) * dshape0 + fl * 1.25 * (rsum - 0.5) * dfss) * (2.0 * c2), 0.0)
    J["roughness"] = [dr.select(ok, dSda, 0.0) * dalpha * Fcc_c + dshape * kd * b for b, Fcc_c in zip(base, Fc)]
    J["metallic"] = [S * (-(1.0 - st) * Fd + b + (1.0 - b) * w - st * (w + t * r0 * (1.0 - w)))
                     - shape * (1.0 / math.pi) * b - wd * sh * (1.0 + sht * (t - 1.0)) for b, t in zip(base, tint)]
    dFd = dr.select(ok, fres[2], 0.0)
    dr0 = 4.0 * (eta - 1.0) / ((eta + 1.0) * (eta + 1.0) * (eta + 1.0))
    deta = 0.08 / (q * (1.0 - q) * (1.0 - q))
    J["specular"] = [S * one_m * ((1.0 - st) * dFd + st * t * (1.0 - w) * dr0) * deta for t in tint]
    J["spec_tint"] = [S * one_m * (-Fd + w + t * r0 * (1.0 - w)) for t in tint]
    J["sheen"] = [wd * one_m * (1.0 + sht * (t - 1.0)) for t in tint]
    J["sheen_tint"] = [wd * sh * one_m * (t - 1.0) for t in tint]
    J["clearcoat"] = [coat_unit] * CHANNELS
    dlnd = (1.0 / (a2 - 1.0) - 1.0 / (a2 * dr.log(a2)) - mz * mz / E) * (2.0 * a_cc) * (0.001 - 0.1)
    J["clearcoat_gloss"] = [coat * dlnd] * CHANNELS
    J["flatness"] = [dr.select(ok, f_ss - shape0, 0.0) * kd * b for b in base]
    dt = S * one_m * st * r0 * (1.0 - w) + wd * sh * one_m * sht      # d f_c / d t_c (the same for every c)
    J["base_color"] = [S * m * (1.0 - w) + shape * kd + dr.select(pos, dt * rl, 0.0) for _ in base]
    J["_lum"] = [dr.select(pos, -dt * b * rl * rl, 0.0) for b in base]
    return f, J
