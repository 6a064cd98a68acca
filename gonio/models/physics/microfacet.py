"""Microfacet normal distributions: Beckmann and GGX (Trowbridge-Reitz), iso/anisotropic.

A :class:`MicrofacetDistribution` gives the normal distribution ``D(wm)``, Smith's
auxiliary function ``lambda_(w)``, the masking function ``G1(w, wm)``, the
shadowing-masking function ``G(wi, wo, wm)`` in its separable and height-correlated
forms, visible-normal sampling ``sample_visible(wi, u)`` and its density ``pdf_visible``.

Roughness ``alpha`` is the GGX alpha or, for Beckmann, the RMS slope, as in Mitsuba 3
(``include/mitsuba/render/microfacet.h``); ``alpha_u`` acts along the local x axis, ``alpha_v``
along y; it is floored at 1e-4 (Mitsuba and pbrt-v4 do the same). Mitsuba 3's
``roughconductor`` and ``roughplastic`` use the **separable** Smith form ``G1(wi) G1(wo)`` and,
for Beckmann, not the exact ``1 / (1 + Lambda)`` but the rational approximation of Walter et al.
2007, eq. (27) (< 0.35 % relative error): ``G1(..., exact=False)`` reproduces it, ``exact=True``
uses the erf form of ``Lambda``; GGX's G1 is exact in both. References [1]-[4]: the comment
below (Walter et al. 2007; Heitz 2014; Heitz & d'Eon 2014; Jakob 2014; Heitz 2018).
"""

# References
# [1] B. Walter, S. R. Marschner, H. Li, K. E. Torrance, "Microfacet Models for Refraction
#     through Rough Surfaces", EGSR 2007: Beckmann D eq. (25), GGX D eq. (33), Beckmann G1
#     rational fit eq. (27), GGX G1 eq. (34).
# [2] E. Heitz, "Understanding the Masking-Shadowing Function in Microfacet-Based BRDFs",
#     JCGT 3(2), 2014: Lambda eqs. (72) (Beckmann) and (86) (GGX); height-correlated G2
#     eq. (99); anisotropic projected roughness eq. (80).
# [3] E. Heitz, E. d'Eon, "Importance Sampling Microfacet-Based BSDFs using the Distribution of
#     Visible Normals", EGSR 2014 (visible-normal density eq. (2)).
# [4] W. Jakob, "An Improved Visible Normal Sampling Routine for the Beckmann Distribution",
#     tech. report, 2014; E. Heitz, "Sampling the GGX Distribution of Visible Normals",
#     JCGT 7(4), 2018 (the routines used by Mitsuba 3).

from __future__ import annotations

import math

import numpy as np

from gonio.core.geometry import safe_sqrt, sincos_phi

__all__ = ["MicrofacetDistribution", "DISTRIBUTIONS", "ALPHA_MIN", "smith_g1_xyz"]

#: Roughness floor (Mitsuba ``MicrofacetDistribution::configure``, pbrt-v4).
ALPHA_MIN = 1e-4

#: Registry of distribution names.
DISTRIBUTIONS = ("beckmann", "ggx")

_INV_SQRT_PI = 1.0 / math.sqrt(math.pi)


def _concentric_disk(u1, u2):
    """Shirley-Chiu concentric square-to-disk map (Mitsuba ``warp.h`` form)."""
    x = 2.0 * u1 - 1.0
    y = 2.0 * u2 - 1.0
    q13 = np.abs(x) < np.abs(y)
    r = np.where(q13, y, x)
    rp = np.where(q13, x, y)
    zero = r == 0.0
    phi = 0.25 * np.pi * rp / np.where(zero, 1.0, r)
    phi = np.where(q13, 0.5 * np.pi - phi, phi)
    phi = np.where(zero, 0.0, phi)
    return r * np.cos(phi), r * np.sin(phi)


def smith_g1_xyz(kind, alpha_u, alpha_v, x, y, z, dot_wm):
    """Mitsuba-convention Smith G1 from direction components (hot-loop form).

    ``x, y, z`` are the components of the direction, ``dot_wm`` its dot product with
    the microfacet normal. GGX: exact ``2 / (1 + sqrt(1 + alpha^2 tan^2))``; Beckmann:
    rational fit of Walter et al. 2007 eq. (27). 1 at normal incidence, 0 for a
    back-facing facet or a direction in the horizon plane.
    """
    xy = (alpha_u * x) ** 2 + (alpha_v * y) ** 2
    z2 = z * z
    ok = z2 > 0.0
    t2 = xy / np.where(ok, z2, 1.0)
    if kind == "ggx":
        g = 2.0 / (1.0 + np.sqrt(1.0 + t2))
    else:
        pos = t2 > 0.0
        a = 1.0 / np.sqrt(np.where(pos, t2, 1.0))
        a2 = a * a
        g = np.where(a >= 1.6, 1.0, (3.535 * a + 2.181 * a2) / (1.0 + 2.276 * a + 2.577 * a2))
    g = np.where(ok, g, 0.0)
    g = np.where(xy == 0.0, 1.0, g)
    return np.where(dot_wm * z <= 0.0, 0.0, g)


class MicrofacetDistribution:
    """Beckmann or GGX microfacet distribution.

    Parameters
    ----------
    kind : {"beckmann", "ggx"}
        Distribution name.
    alpha_u : float
        Roughness along the local x axis (dimensionless; GGX alpha or Beckmann RMS slope).
    alpha_v : float, optional
        Roughness along y; defaults to ``alpha_u`` (isotropic).
    """

    def __init__(self, kind, alpha_u, alpha_v=None):
        kind = str(kind).lower()
        if kind not in DISTRIBUTIONS:
            raise ValueError(f"unknown microfacet distribution {kind!r}; choose one of {DISTRIBUTIONS}")
        if alpha_v is None:
            alpha_v = alpha_u
        for nm, a in (("alpha_u", alpha_u), ("alpha_v", alpha_v)):
            if not np.isfinite(a) or a <= 0.0:
                raise ValueError(f"{nm} must be a finite positive number, got {a!r}")
        self.kind = kind
        self.alpha_u = max(float(alpha_u), ALPHA_MIN)
        self.alpha_v = max(float(alpha_v), ALPHA_MIN)

    def __repr__(self):
        return f"MicrofacetDistribution({self.kind!r}, alpha_u={self.alpha_u!r}, alpha_v={self.alpha_v!r})"

    @property
    def is_isotropic(self):
        return self.alpha_u == self.alpha_v

    # -- normal distribution -------------------------------------------------------
    def D(self, wm):
        """Normal distribution function D(wm) in sr^-1 (projected area normalised:
        the integral of D(wm) cos(theta_m) over the hemisphere is 1).

        Walter et al. 2007 [1]_ eqs. (25) and (33), anisotropic forms. Zero for
        ``wm`` below the horizon and where ``D cos(theta_m) < 1e-20`` (Mitsuba's cut).
        """
        x, y, z = wm[..., 0], wm[..., 1], wm[..., 2]
        au, av = self.alpha_u, self.alpha_v
        z2 = z * z
        up = z > 0.0
        z2s = np.where(up, z2, 1.0)
        if self.kind == "beckmann":
            e = ((x / au) ** 2 + (y / av) ** 2) / z2s
            r = np.exp(-e) / (math.pi * au * av * z2s * z2s)
        else:
            t = (x / au) ** 2 + (y / av) ** 2 + z2
            r = 1.0 / (math.pi * au * av * np.where(up, t * t, 1.0))
        return np.where(up & (r * z > 1e-20), r, 0.0)

    # -- Smith masking ---------------------------------------------------------------
    def _tan2_alpha2(self, w):
        """alpha(phi)^2 tan^2(theta) of ``w``, and the mask of directions off the pole."""
        xy = (self.alpha_u * w[..., 0]) ** 2 + (self.alpha_v * w[..., 1]) ** 2
        z2 = w[..., 2] ** 2
        ok = z2 > 0.0
        return xy / np.where(ok, z2, 1.0), xy, ok

    def lambda_(self, w):
        """Smith's Lambda(w) (exact; Heitz 2014 [2]_ eqs. 72, 86). ``inf`` at the horizon."""
        t2, xy, ok = self._tan2_alpha2(w)
        if self.kind == "ggx":
            lam = 0.5 * (np.sqrt(1.0 + t2) - 1.0)
        else:
            from scipy.special import erf

            pos = t2 > 0.0
            a = 1.0 / np.sqrt(np.where(pos, t2, 1.0))
            lam = 0.5 * (erf(a) - 1.0) + np.exp(-a * a) / (2.0 * a * math.sqrt(math.pi))
            lam = np.where(pos, lam, 0.0)
        lam = np.where(xy == 0.0, 0.0, lam)
        return np.where(ok | (xy == 0.0), lam, np.inf)

    def G1(self, w, wm, exact=False):
        """Smith masking function G1(w, wm) in [0, 1].

        Parameters
        ----------
        w, wm : ndarray, shape (N, 3)
            Direction and microfacet normal.
        exact : bool
            Beckmann only: False (default) uses the rational fit of Walter et al. 2007
            eq. (27) exactly as Mitsuba 3 does; True uses ``1 / (1 + Lambda)``.

        Notes
        -----
        Zero where ``(w . wm) cos(theta_w) <= 0`` (a facet seen from its back side).
        """
        d = np.einsum("...i,...i->...", w, wm)
        if exact and self.kind == "beckmann":
            g = 1.0 / (1.0 + self.lambda_(w))
            _, xy, _ = self._tan2_alpha2(w)
            g = np.where(xy == 0.0, 1.0, g)
            return np.where(d * w[..., 2] <= 0.0, 0.0, g)
        return smith_g1_xyz(self.kind, self.alpha_u, self.alpha_v, w[..., 0], w[..., 1], w[..., 2], d)

    def G(self, wi, wo, wm, form="separable", exact=False):
        """Smith shadowing-masking G2(wi, wo, wm).

        Parameters
        ----------
        form : {"separable", "height_correlated"}
            ``separable``: G1(wi) G1(wo) (what Mitsuba 3 uses);
            ``height_correlated``: 1 / (1 + Lambda(wi) + Lambda(wo)) (Heitz 2014 eq. 99,
            always with exact Lambda).
        exact : bool
            Passed to :meth:`G1` for the separable form.
        """
        if form == "separable":
            return self.G1(wi, wm, exact) * self.G1(wo, wm, exact)
        if form != "height_correlated":
            raise ValueError("form must be 'separable' or 'height_correlated'")
        di = np.einsum("ij,ij->i", wi, wm)
        do = np.einsum("ij,ij->i", wo, wm)
        vis = (di * wi[:, 2] > 0.0) & (do * wo[:, 2] > 0.0)
        lam = self.lambda_(wi) + self.lambda_(wo)
        g = 1.0 / (1.0 + np.where(np.isfinite(lam), lam, 0.0))
        return np.where(vis & np.isfinite(lam), g, 0.0)

    # -- visible normal sampling ---------------------------------------------------
    def _sample_visible_11(self, cos_theta_i, u1, u2):
        """Slopes of visible normals for alpha = 1 (Mitsuba ``sample_visible_11``)."""
        c = np.clip(cos_theta_i, 1e-12, 1.0)
        if self.kind == "beckmann":
            from scipy.special import erf, erfinv

            s = safe_sqrt(1.0 - c * c)
            tan_i = s / c
            pos = tan_i > 0.0
            cot_i = np.where(pos, c / np.where(s > 0.0, s, 1.0), np.inf)
            maxval = erf(cot_i)
            u1 = np.clip(u1, 1e-6, 1.0 - 1e-6)
            u2 = np.clip(u2, 1e-6, 1.0 - 1e-6)
            x = maxval - (maxval + 1.0) * erf(np.sqrt(-np.log(u1)))
            ex = np.where(pos, np.exp(-np.where(pos, cot_i, 0.0) ** 2), 0.0)
            u1 = u1 * (1.0 + maxval + _INV_SQRT_PI * tan_i * ex)
            for _ in range(3):
                slope = erfinv(x)
                value = 1.0 + x + _INV_SQRT_PI * tan_i * np.exp(-slope * slope) - u1
                deriv = 1.0 - slope * tan_i
                x = x - value / deriv
            return erfinv(x), erfinv(2.0 * u2 - 1.0)
        px, py = _concentric_disk(u1, u2)
        s = 0.5 * (1.0 + c)
        py = safe_sqrt(1.0 - px * px) * (1.0 - s) + py * s
        z = safe_sqrt(1.0 - px * px - py * py)
        sin_i = safe_sqrt(1.0 - c * c)
        norm = 1.0 / (sin_i * py + c * z)
        return (c * py - sin_i * z) * norm, px * norm

    def sample_visible(self, wi, u):
        """Sample microfacet normals visible from ``wi`` (Heitz & d'Eon 2014 [3]_).

        Parameters
        ----------
        wi : ndarray, shape (N, 3)
            Direction (upper hemisphere) from which the facets are seen.
        u : ndarray, shape (N, 2)
            Uniform random numbers in [0, 1).

        Returns
        -------
        wm : ndarray, shape (N, 3)
            Sampled normals, distributed with :meth:`pdf_visible`.

        Notes
        -----
        Stretch ``wi`` by (alpha_u, alpha_v), sample the alpha = 1 slope distribution
        (Jakob 2014 for Beckmann, Heitz 2018 for GGX [4]_), rotate, unstretch,
        normalise; the same steps as Mitsuba 3 ``MicrofacetDistribution::sample``.
        """
        wi = np.asarray(wi, dtype=np.float64)
        u = np.asarray(u, dtype=np.float64)
        au, av = self.alpha_u, self.alpha_v
        wp = np.stack([au * wi[:, 0], av * wi[:, 1], wi[:, 2]], axis=1)
        wp /= np.linalg.norm(wp, axis=1)[:, None]
        sin_phi, cos_phi = sincos_phi(wp)
        sx, sy = self._sample_visible_11(wp[:, 2], u[:, 0], u[:, 1])
        mx = -(cos_phi * sx - sin_phi * sy) * au
        my = -(sin_phi * sx + cos_phi * sy) * av
        inv = 1.0 / np.sqrt(mx * mx + my * my + 1.0)
        return np.stack([mx * inv, my * inv, inv], axis=1)

    def pdf_visible(self, wi, wm, exact=True):
        """Density of :meth:`sample_visible` per unit solid angle of ``wm``:
        ``D(wm) G1(wi, wm) max(0, wi . wm) / cos(theta_i)`` (Heitz & d'Eon 2014 eq. 2).

        ``exact=True`` (default) uses the exact Smith G1, which is what the sampling
        routines invert; Mitsuba's own ``pdf`` uses the rational Beckmann G1.
        """
        ci = wi[:, 2]
        d = np.einsum("ij,ij->i", wi, wm)
        ok = (ci > 0.0) & (d > 0.0)
        r = self.D(wm) * self.G1(wi, wm, exact=exact) * np.maximum(d, 0.0) / np.where(ok, ci, 1.0)
        return np.where(ok, r, 0.0)
