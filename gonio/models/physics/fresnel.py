"""Fresnel reflectance: exact dielectric, exact conductor, Schlick's approximation.

Pure functions on numpy arrays (broadcasting). ``cos_theta_i`` is the cosine between
the incident direction and the interface normal; for the dielectric a negative value
means the ray arrives from the inside (Mitsuba's convention, ``render/fresnel.h``).

References
----------
.. [1] M. Born and E. Wolf, *Principles of Optics*, 7th ed., Cambridge University Press
       (1999), sec. 1.5.2, eqs. (21a), (21b) (Fresnel amplitudes).
.. [2] K. D. Moeller, *Optics*, University Science Books (1988) (conductor form used by
       Mitsuba 3 ``fresnel_conductor``).
.. [3] C. Schlick, "An Inexpensive BRDF Model for Physically-based Rendering",
       Computer Graphics Forum 13(3), 233-246 (1994), eq. (24).
"""

from __future__ import annotations

import numpy as np

__all__ = ["fresnel_dielectric", "fresnel_conductor", "fresnel_schlick"]


def fresnel_dielectric(cos_theta_i, eta):
    """Unpolarised Fresnel reflectance of a dielectric interface.

    Parameters
    ----------
    cos_theta_i : array_like
        Cosine of the angle of incidence, in [-1, 1]. Negative: the ray arrives from
        the interior side.
    eta : array_like
        Relative index of refraction interior / exterior (> 0).

    Returns
    -------
    F : ndarray
        Reflectance in [0, 1]; 1 under total internal reflection and at grazing
        incidence, 0 for index-matched interfaces (eta == 1).
    cos_theta_t : ndarray
        Signed cosine of the transmitted direction (opposite sign to
        ``cos_theta_i``); 0 under total internal reflection.
    eta_it : ndarray
        Relative index in the direction of travel (eta outside-in, 1/eta inside-out).
    eta_ti : ndarray
        ``1 / eta_it``.

    Notes
    -----
    With :math:`\\eta_{it}` and :math:`\\cos\\theta_t^2 = 1 - (1-\\cos^2\\theta_i)/\\eta_{it}^2`,

    .. math:: r_s = \\frac{c_i - \\eta_{it} c_t}{c_i + \\eta_{it} c_t},\\quad
              r_p = \\frac{c_t - \\eta_{it} c_i}{c_t + \\eta_{it} c_i},\\quad
              F = (r_s^2 + r_p^2) / 2

    (Born & Wolf [1]_ eqs. 21a-b); TIR follows from :math:`c_t = 0`.
    """
    cos_theta_i = np.asarray(cos_theta_i, dtype=np.float64)
    eta = np.asarray(eta, dtype=np.float64)
    outside = cos_theta_i >= 0.0
    rcp_eta = 1.0 / eta
    eta_it = np.where(outside, eta, rcp_eta)
    eta_ti = np.where(outside, rcp_eta, eta)
    cos_i = np.minimum(np.abs(cos_theta_i), 1.0)
    cos_t_sqr = 1.0 - (1.0 - cos_i * cos_i) * (eta_ti * eta_ti)
    cos_t = np.sqrt(np.maximum(cos_t_sqr, 0.0))
    special = (eta == 1.0) | (cos_i == 0.0)
    den_s = cos_i + eta_it * cos_t
    den_p = cos_t + eta_it * cos_i
    den_s = np.where(special, 1.0, den_s)
    den_p = np.where(special, 1.0, den_p)
    a_s = (cos_i - eta_it * cos_t) / den_s
    a_p = (cos_t - eta_it * cos_i) / den_p
    F = 0.5 * (a_s * a_s + a_p * a_p)
    F = np.where(special, np.where(eta == 1.0, 0.0, 1.0), F)
    cos_theta_t = np.where(outside, -cos_t, cos_t)
    return F, cos_theta_t, eta_it, eta_ti


def fresnel_conductor(cos_theta_i, eta, k):
    """Unpolarised Fresnel reflectance of a conductor with index ``eta + i k``.

    Parameters
    ----------
    cos_theta_i : array_like
        Cosine of the angle of incidence (clamped to [0, 1]; light arrives from the
        dielectric side).
    eta, k : array_like
        Real and imaginary parts of the relative complex index of refraction
        (broadcast against ``cos_theta_i``, e.g. shape (3,) per colour channel).

    Returns
    -------
    F : ndarray
        Reflectance in [0, 1]; exactly 1 at grazing incidence.

    Notes
    -----
    Exact for unpolarised light (Moeller [2]_; the same algebra as Mitsuba 3
    ``fresnel_conductor``): with :math:`t_1 = \\eta^2 - k^2 - \\sin^2\\theta`,
    :math:`a^2 + b^2 = \\sqrt{t_1^2 + 4\\eta^2k^2}`, :math:`a = \\sqrt{(a^2+b^2+t_1)/2}`,

    .. math:: R_s = \\frac{a^2+b^2+\\cos^2\\theta - 2a\\cos\\theta}
                          {a^2+b^2+\\cos^2\\theta + 2a\\cos\\theta},\\quad
              R_p = R_s\\frac{(a^2+b^2)\\cos^2\\theta + \\sin^4\\theta - 2a\\cos\\theta\\sin^2\\theta}
                              {(a^2+b^2)\\cos^2\\theta + \\sin^4\\theta + 2a\\cos\\theta\\sin^2\\theta}

    and :math:`F = (R_s + R_p)/2`. At normal incidence
    :math:`F = ((\\eta-1)^2 + k^2)/((\\eta+1)^2 + k^2)`.
    """
    c = np.clip(np.asarray(cos_theta_i, dtype=np.float64), 0.0, 1.0)
    eta = np.asarray(eta, dtype=np.float64)
    k = np.asarray(k, dtype=np.float64)
    c2 = c * c
    s2 = 1.0 - c2
    s4 = s2 * s2
    t1 = eta * eta - k * k - s2
    a2pb2 = np.sqrt(np.maximum(t1 * t1 + 4.0 * eta * eta * k * k, 0.0))
    a = np.sqrt(np.maximum(0.5 * (a2pb2 + t1), 0.0))
    term1 = a2pb2 + c2
    term2 = 2.0 * c * a
    den1 = term1 + term2
    r_s = np.where(den1 > 0.0, (term1 - term2) / np.where(den1 > 0.0, den1, 1.0), 1.0)
    term3 = a2pb2 * c2 + s4
    term4 = term2 * s2
    den2 = term3 + term4
    r_p = r_s * np.where(den2 > 0.0, (term3 - term4) / np.where(den2 > 0.0, den2, 1.0), 1.0)
    return np.clip(0.5 * (r_s + r_p), 0.0, 1.0)


def fresnel_schlick(cos_theta_i, f0):
    """Schlick's approximation ``F0 + (1 - F0) (1 - cos)^5`` (Schlick [3]_ eq. 24).

    Parameters
    ----------
    cos_theta_i : array_like
        Cosine of the angle of incidence (clamped to [0, 1]).
    f0 : array_like
        Reflectance at normal incidence (broadcast, e.g. per channel).
    """
    c = np.clip(np.asarray(cos_theta_i, dtype=np.float64), 0.0, 1.0)
    f0 = np.asarray(f0, dtype=np.float64)
    m = 1.0 - c
    m2 = m * m
    return f0 + (1.0 - f0) * (m2 * m2 * m)
