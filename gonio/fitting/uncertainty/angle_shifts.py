"""The dataset's angle uncertainty as the fit reads it: the change of each point's (theta_i,
phi_i, theta_o, phi_o) for +1 sigma of each shared input (zero offsets, holder tilt, wedge,
lost motion) and of each axis's per-move error (docs/interfaces.md 5.1), per point or, where a
spectral session revisited its geometries, per (point, wavelength); and the fitted model's
local slope d f_r / d angle that turns them into budget lines
(:func:`gonio.fitting.uncertainty.budget.angle_components`)."""

from __future__ import annotations

import numpy as np

from gonio.core.geometry import (angle_tangents, angles as _angles_of, directions as _directions, tangent_basis,
                                 unit_vectors)

__all__ = ["AXES", "ANGLE_SHIFTS", "IRRADIANCE_SHIFT", "per_point", "slope", "shared_moves", "moved"]

#: the stage axes of ``angle_shift_independent``'s inputs when it has one group label per axis
AXES = ("yaw", "tilt", "azimuth", "lamp")
#: the dataset variables of the angles' uncertainty (docs/interfaces.md 5.1), degrees
ANGLE_SHIFTS = {"shared": "angle_shift_shared", "independent": "angle_shift_independent"}
#: with ``angle_shift_shared``: the relative change of the sample's irradiance alone (the wedge's
#: foreshortening, which the reference square does not share) for +1 sigma of each input
IRRADIANCE_SHIFT = "irradiance_shift_shared"


def _angle_shifts(ds, path, n_points, n_channels):
    """``{shared, independent}``: (K, N, 4) arrays from ``angle_shift_*`` (input, point, angle),
    (K, N, C, 4) where a spectral dataset gives them per (point, wavelength) (the stage revisited
    its geometries); None without."""
    out = {}
    for key, name in ANGLE_SHIFTS.items():
        if name not in ds.variables:
            continue
        v = ds[name]
        cells = (n_points, n_channels) if "wavelength" in v.dims else (n_points,)
        try:
            arr = np.asarray(v.transpose(v.dims[0], "point", *(("wavelength",) * (len(cells) - 1)), "angle").values,
                             float)
        except (ValueError, KeyError):
            raise ValueError(f"{path}: {name} must have dimensions (input, point, angle)") from None
        if arr.shape[1:] != cells + (4,) or not np.all(np.isfinite(arr)):
            raise ValueError(f"{path}: {name} must be finite, (inputs, {' x '.join(map(str, cells))} cells, 4 "
                             "angles) in degrees")
        out[key] = arr
    if "shared" in out and IRRADIANCE_SHIFT in ds.variables:
        v = ds[IRRADIANCE_SHIFT]
        try:
            r = np.asarray(v.transpose(v.dims[0], "point", *(d for d in v.dims if d == "wavelength")).values, float)
        except (ValueError, KeyError):
            raise ValueError(f"{path}: {IRRADIANCE_SHIFT} must have dimensions (input, point)") from None
        if r.shape != out["shared"].shape[:-1] or not np.all(np.isfinite(r)):
            raise ValueError(f"{path}: {IRRADIANCE_SHIFT} must be finite, ({out['shared'].shape[0]} inputs, "
                             f"{n_points} points) as {ANGLE_SHIFTS['shared']}")
        out["shared_irradiance"] = r
    group = ANGLE_SHIFTS["independent"] + "_group"
    if "independent" in out and group in ds.variables:
        gv = ds[group]
        g = np.asarray(gv.transpose(gv.dims[0], "point", *(d for d in gv.dims if d == "wavelength")).values)
        if g.shape != out["independent"].shape[:-1] or not np.issubdtype(g.dtype, np.integer):
            raise ValueError(f"{path}: {group} must be integer labels on the cells of {ANGLE_SHIFTS['independent']}")
        out["independent_groups"] = g.astype(np.int64)
    return out or None


def slope(model, params, wi, wo, h_deg: float = 1e-3) -> np.ndarray:
    """d f_r / d (theta_i, phi_i, theta_o, phi_o) (N, C, 4), sr^-1 per degree, by central
    differences of the model at ``params``. At a pole (theta 0 or 180 deg, where phi is
    undefined) the pair is the derivative along the fixed tangents of
    :func:`gonio.core.geometry.tangent_basis`, per degree of arc, as the dataset's angle shifts
    are there: a tilt then moves a normal-incidence or straight-through point's value by what it
    moves its direction (its phi slope was 0, and a lobe's change across the pole was lost)."""
    ti, pi_ = _angles_of(wi)
    to, po = _angles_of(wo)
    base = np.stack([ti, pi_, to, po], axis=-1)
    h = np.radians(h_deg)
    out = []
    for a in range(4):
        plus, minus = base.copy(), base.copy()
        plus[:, a] += h
        minus[:, a] -= h
        fp = model.eval(_directions(plus[:, 0], plus[:, 1]), _directions(plus[:, 2], plus[:, 3]), params)
        fm = model.eval(_directions(minus[:, 0], minus[:, 1]), _directions(minus[:, 2], minus[:, 3]), params)
        out.append((fp - fm) / (2 * h_deg))
    for k, w in ((0, wi), (2, wo)):
        e_t, e_p, pole = tangent_basis(w)
        if not np.any(pole):
            continue
        a, b = np.asarray(wi, float)[pole], np.asarray(wo, float)[pole]
        for j, e in ((k, e_t[pole]), (k + 1, e_p[pole])):
            moved = [unit_vectors(np.asarray(w, float)[pole] * np.cos(h) + sign * np.sin(h) * e) for sign in (1, -1)]
            pair = [(m, b) if k == 0 else (a, m) for m in moved]
            out[j][pole] = (model.eval(*pair[0], params) - model.eval(*pair[1], params)) / (2 * h_deg)
    return np.stack(out, axis=-1)


def per_point(angles):
    """``angles`` with per-(point, wavelength) shared shifts averaged over each geometry's measured
    wavelengths (its visits): the second-order term and the adequacy refit displace each point's
    directions once (the first-order lines keep every visit's own)."""
    if not angles or np.ndim(angles.get("shared")) != 4:
        return angles
    shared = np.asarray(angles["shared"], float)
    seen = np.any(shared != 0.0, axis=(0, 3)).astype(float)        # (N, C): cells measured (not 0)
    w = seen / np.maximum(seen.sum(axis=1, keepdims=True), 1.0)
    out = {**angles, "shared": np.einsum("knca,nc->kna", shared, w)}
    if angles.get("shared_irradiance") is not None:
        out["shared_irradiance"] = np.einsum("knc,nc->kn", np.asarray(angles["shared_irradiance"], float), w)
    return out


def shared_moves(wi, wo, angles):
    """(t_i, t_o, irr): each point's direction change (K, N, 3) per +1 sigma of each of the K
    shared inputs of ``angles`` (:func:`per_point` applied), and the sample's relative irradiance
    change (K, N), or None where the dataset states none."""
    one = per_point(angles)
    t_i, t_o = angle_tangents(wi, wo, np.asarray(one["shared"], float))
    irr = one.get("shared_irradiance")
    return t_i, t_o, None if irr is None else np.asarray(irr, float)


def moved(wi, wo, moves, e):
    """(wi, wo, g): the directions where the shared inputs ``e`` (K, sigma units) put each point,
    stepped along :func:`shared_moves`' ``moves`` and renormalised (f_r itself is evaluated
    there, not linearised), and the irradiance factor g = 1 + e . irr (N,; ones without)."""
    t_i, t_o, irr = moves
    g = np.ones(len(wi)) if irr is None else 1.0 + np.einsum("k,kn->n", e, irr)
    return (unit_vectors(wi + np.einsum("k,knj->nj", e, t_i)), unit_vectors(wo + np.einsum("k,knj->nj", e, t_o)), g)
