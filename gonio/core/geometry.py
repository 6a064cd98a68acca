"""gonio's one geometry module: directions from angles and back, local-frame helpers.

Every conversion between angles and unit vectors in gonio goes through here:
:func:`directions` / :func:`angles` (radians) and :func:`directions_deg` / :func:`angles_deg`
(degrees, as in files and on the command line); phi = atan2(y, x), theta from +z.

Conventions (used everywhere in :mod:`gonio.models`): the local shading frame has
+z along the surface normal; ``wi`` points from the surface toward the light,
``wo`` from the surface toward the detector; both are unit vectors stored as arrays
of shape (N, 3). ``wm`` is a microfacet normal (for reflection the half vector).

All helpers are branch-free numpy: degenerate geometry is masked, never NaN.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "directions",
    "directions_deg",
    "equal_solid_angle_pairs",
    "angles",
    "angles_deg",
    "finite_directions",
    "as_directions",
    "cos_theta",
    "safe_sqrt",
    "half_vector",
    "reflect",
    "sincos_phi",
    "angle_tangents",
    "tangent_basis",
    "POLE_SIN",
    "unit_vectors",
]


def safe_sqrt(x):
    """``sqrt(max(0, x))`` (pbrt-v4 ``util/math.h`` ``SafeSqrt``)."""
    return np.sqrt(np.maximum(x, 0.0))


def cos_theta(w):
    """z component of the (N, 3) direction array ``w``."""
    return w[..., 2]


def as_directions(w, name="w", dtype=np.float64):
    """Return ``w`` as a C-contiguous array of shape (N, 3) and type ``dtype``.

    Parameters
    ----------
    w : array_like, shape (N, 3) or (3,)
        Unit directions in the local frame (converted to ``dtype``: float32 input is
        promoted to the default float64).
    name : str
        Used in the error message.
    dtype : float64 (default) or float32

    Raises
    ------
    ValueError
        If the last axis is not of length 3.
    """
    a = np.asarray(w, dtype=dtype)
    if a.ndim == 1 and a.shape[0] == 3:
        a = a[None, :]
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {np.shape(w)}")
    return np.ascontiguousarray(a)


def directions(theta, phi):
    """Unit vectors (..., 3) from polar angle ``theta`` and azimuth ``phi`` (radians)."""
    theta = np.asarray(theta, dtype=np.float64)
    phi = np.asarray(phi, dtype=np.float64)
    sin_theta = np.sin(theta)
    return np.stack([sin_theta * np.cos(phi), sin_theta * np.sin(phi), np.cos(theta)], axis=-1)


def directions_deg(theta_deg, phi_deg):
    """Unit vectors (..., 3) from ``theta`` and ``phi`` in degrees."""
    return directions(np.radians(np.asarray(theta_deg, float)), np.radians(np.asarray(phi_deg, float)))


def equal_solid_angle_pairs(theta_max_deg=80.0, n_theta_i=12, n_theta_o=24, n_phi_o=48):
    """(wi, wo) on equal-solid-angle cells of both hemispheres below ``theta_max_deg``:
    cell centres uniform in cos(theta) and in phi (for isotropic materials: phi_i = 0), so
    every pair has the same solid-angle weight (2 pi (1 - cos theta_max))^2 / n."""
    cmax = np.cos(np.radians(theta_max_deg))
    ci = 1.0 - (1.0 - cmax) * (np.arange(n_theta_i) + 0.5) / n_theta_i
    co = 1.0 - (1.0 - cmax) * (np.arange(n_theta_o) + 0.5) / n_theta_o
    po = -np.pi + 2.0 * np.pi * (np.arange(n_phi_o) + 0.5) / n_phi_o
    TI, TO, PO = np.meshgrid(np.arccos(ci), np.arccos(co), po, indexing="ij")
    return directions(TI.reshape(-1), np.zeros(TI.size)), directions(TO.reshape(-1), PO.reshape(-1))


def angles(w):
    """(theta, phi) in radians of unit vectors (..., 3); phi = atan2(y, x) in (-pi, pi]."""
    w = np.asarray(w, dtype=np.float64)
    return np.arccos(np.clip(w[..., 2], -1.0, 1.0)), np.arctan2(w[..., 1], w[..., 0])


def angles_deg(w):
    """(theta, phi) in degrees of unit vectors (..., 3); phi in (-180, 180]."""
    theta, phi = angles(w)
    return np.degrees(theta), np.degrees(phi)


def finite_directions(w, name="w"):
    """``w`` as float64 (N, 3) (reshaped if need be); ValueError if it holds NaN or inf."""
    w = np.asarray(w, dtype=np.float64)
    if w.ndim != 2 or w.shape[1] != 3:
        w = w.reshape(-1, 3)
    if not np.all(np.isfinite(w)):
        raise ValueError(f"{name} contains NaN or inf")
    return w


def half_vector(wi, wo):
    """Normalised half vector ``wm = (wi + wo) / |wi + wo|`` and a validity mask.

    Returns
    -------
    wm : ndarray, shape (N, 3)
        The half vector; (0, 0, 1) where ``wi + wo`` vanishes (wi == -wo).
    valid : ndarray of bool, shape (N,)
        False where the half vector is undefined.
    """
    h = wi + wo
    n2 = np.einsum("ij,ij->i", h, h)
    valid = n2 > 1e-300
    inv = 1.0 / np.sqrt(np.where(valid, n2, 1.0))
    wm = h * inv[:, None]
    if not valid.all():
        wm[~valid] = (0.0, 0.0, 1.0)
    return wm, valid


def reflect(w, wm):
    """Mirror ``w`` about ``wm``: ``2 (w . wm) wm - w`` (both (N, 3))."""
    d = np.einsum("ij,ij->i", w, wm)
    return 2.0 * d[:, None] * wm - w


def sincos_phi(w, eps=4.0 * np.finfo(np.float32).eps):
    """Sine and cosine of the azimuth of ``w``; (0, 1) at the pole.

    Mirrors Mitsuba's ``Frame3f::sincos_phi`` (``core/frame.h``), including its
    pole threshold ``sin^2 theta <= 4 eps`` (float32 epsilon).
    """
    s2 = w[..., 0] ** 2 + w[..., 1] ** 2
    pole = s2 <= eps
    inv = 1.0 / np.sqrt(np.where(pole, 1.0, s2))
    c = np.where(pole, 1.0, np.clip(w[..., 0] * inv, -1.0, 1.0))
    s = np.where(pole, 0.0, np.clip(w[..., 1] * inv, -1.0, 1.0))
    return s, c


#: |sin theta| below this: a direction at a pole (theta 0 or 180 deg), where phi is undefined and
#: an angle shift's phi part is an arc along a fixed tangent instead (:func:`tangent_basis`)
POLE_SIN = 1e-6


def tangent_basis(w):
    """``(e_theta, e_phi, pole)`` of unit vectors ``w`` (N, 3): the unit tangents along increasing
    theta and phi (N, 3) and where ``w`` lies at a pole (N,). At a pole phi is undefined, so the
    pair is fixed: the tangents of phi = 0, e_theta = (cos theta, 0, 0), e_phi = (0, 1, 0). An
    angle shift (d theta, d phi) in degrees moves ``w`` by d theta e_theta + d phi sin(theta)
    e_phi (radians) away from a pole and by d theta e_theta + d phi e_phi at one: there the
    stored d phi is the arc along e_phi (the dataset's angle shifts, the budget's slopes)."""
    w = np.asarray(w, dtype=np.float64)
    theta, phi = angles(w)
    pole = np.abs(np.sin(theta)) < POLE_SIN
    phi = np.where(pole, 0.0, phi)
    c, s = np.cos(theta), np.sin(theta)
    e_theta = np.stack([c * np.cos(phi), c * np.sin(phi), np.where(pole, 0.0, -s)], axis=-1)
    e_phi = np.stack([-np.sin(phi), np.cos(phi), np.zeros_like(phi)], axis=-1)
    return e_theta, e_phi, pole


def angle_tangents(wi, wo, shifts, h: float = 1e-4):
    """The directions' first-order displacement (K, N, 3) each for ``wi`` and ``wo`` (N, 3) per
    unit of each of K angle shifts ``shifts`` (K, N, 4: theta_i, phi_i, theta_o, phi_o in
    degrees): a central difference of the directions along the shift; at a pole, where a
    shift's phi part is an arc (:func:`tangent_basis`), that arc along the fixed tangent."""
    ti, pi_ = angles(wi)
    to, po = angles(wo)
    base = np.stack([ti, pi_, to, po], axis=-1)                              # radians (N, 4)
    d = np.radians(np.asarray(shifts, float))
    plus, minus = base[None] + h * d, base[None] - h * d
    t_i = (directions(plus[..., 0], plus[..., 1]) - directions(minus[..., 0], minus[..., 1])) / (2 * h)
    t_o = (directions(plus[..., 2], plus[..., 3]) - directions(minus[..., 2], minus[..., 3])) / (2 * h)
    for t, w, k in ((t_i, wi, 0), (t_o, wo, 2)):
        e_t, e_p, pole = tangent_basis(w)
        if np.any(pole):
            t[:, pole] = d[:, pole, k, None] * e_t[pole] + d[:, pole, k + 1, None] * e_p[pole]
    return t_i, t_o


def unit_vectors(v):
    """``v`` (..., 3) scaled to unit length along its last axis."""
    return v / np.linalg.norm(v, axis=-1, keepdims=True)
