"""Diffuse reflection terms: Lambertian and Oren-Nayar.

References
----------
.. [1] J. H. Lambert, *Photometria* (1760); f_r = rho / pi, e.g. pbrt-v4 sec. 9.2.
.. [2] M. Oren and S. K. Nayar, "Generalization of Lambert's Reflectance Model",
       SIGGRAPH 1994, eq. (30) (the "qualitative" model, as in pbrt-v3 sec. 8.4.2 and
       Mitsuba 0.6 ``roughdiffuse`` fast approximation).
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["lambert", "oren_nayar"]


def lambert(reflectance, n):
    """Lambertian BRDF rho / pi in sr^-1, broadcast to (n, C).

    Parameters
    ----------
    reflectance : array_like, shape (C,) or scalar
        Albedo rho in [0, 1].
    n : int
        Number of direction pairs.
    """
    r = np.asarray(reflectance, dtype=np.float64) / math.pi
    return np.broadcast_to(r, (n,) + r.shape).copy() if r.ndim else np.full(n, float(r))


def oren_nayar(wi, wo, reflectance, sigma):
    """Oren-Nayar BRDF (qualitative model) in sr^-1, shape (N, C).

    Parameters
    ----------
    wi, wo : ndarray, shape (N, 3)
        Unit directions (toward light, toward detector), local frame.
    reflectance : array_like, shape (C,)
        Albedo rho of the facets.
    sigma : float
        Standard deviation of the facet slope angle, radians (0 gives Lambert).

    Notes
    -----
    .. math:: f_r = \\frac{\\rho}{\\pi}\\left(A + B\\max(0, \\cos(\\phi_i-\\phi_o))
              \\sin\\alpha\\tan\\beta\\right),\\quad
              A = 1 - \\frac{\\sigma^2}{2(\\sigma^2+0.33)},\\
              B = \\frac{0.45\\sigma^2}{\\sigma^2+0.09}

    with :math:`\\alpha = \\max(\\theta_i,\\theta_o)`, :math:`\\beta = \\min(\\theta_i,\\theta_o)`
    (Oren & Nayar 1994 [2]_ eq. 30). Symmetric in wi, wo (reciprocal). The product
    :math:`\\sin\\alpha\\tan\\beta` is computed as :math:`\\sin\\theta_i\\sin\\theta_o /
    \\max(\\cos\\theta_i, \\cos\\theta_o)`, finite at the horizon.
    """
    s2 = sigma * sigma
    A = 1.0 - s2 / (2.0 * (s2 + 0.33))
    B = 0.45 * s2 / (s2 + 0.09)
    ci = np.clip(wi[:, 2], 0.0, 1.0)
    co = np.clip(wo[:, 2], 0.0, 1.0)
    # cos(phi_i - phi_o) * sin_i * sin_o = wi_x wo_x + wi_y wo_y (no sines needed)
    cdphi_ss = wi[:, 0] * wo[:, 0] + wi[:, 1] * wo[:, 1]
    cmax = np.maximum(ci, co)
    term = np.maximum(cdphi_ss, 0.0) / np.where(cmax > 0.0, cmax, 1.0)
    term = np.where(cmax > 0.0, term, 0.0)
    rho = np.asarray(reflectance, dtype=np.float64)
    return (rho / math.pi) * (A + B * term)[:, None]
