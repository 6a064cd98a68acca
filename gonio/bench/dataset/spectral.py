"""A spectral session's dataset.nc variables: dimensions ``point`` (a geometry) and
``wavelength`` (nm, CF standard name ``radiation_wavelength``).

A spectral plan's journal holds one row per (geometry, wavelength), each with the monochrome
sensor's three Bayer channels of f_r at that wavelength (equal in expectation: the sensor
sites see the same light). `spectral_variables` combines them by inverse variance into one
f_r per row (its 1-sigma from the channels' own), then lays the rows out as ``brdf(point,
wavelength)``; a (geometry, wavelength) never measured is NaN and flagged in ``saturated``
(the reader leaves it out). Per point: the angles, the stage pose and the reciprocal partner
of its geometry; per (point, wavelength): the plan index, the monitor's reading, the
instrument time and the wavelength the monochromator read back; and the uncertainty budget
(`spectral_budget`: docs/interfaces.md 5.1's lines on (point, wavelength), the angle shifts per
geometry).
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

from gonio.bench.plan.plans import find_partners
from gonio.bench.plan.spectral import geometry_groups

__all__ = ["spectral_variables", "spectral_budget", "combine", "WAVELENGTH_ATTRS", "COLOUR_SPACE"]

#: the wavelength coordinate's attributes (CF standard name table: radiation_wavelength)
WAVELENGTH_ATTRS = {"standard_name": "radiation_wavelength", "units": "nm",
                    "long_name": "wavelength the monochromator was set to (nm, in air)"}
COLOUR_SPACE = ("spectral: brdf, brdf_std per wavelength (coordinate wavelength, nm) of the monochromator's "
                "beam, from a monochrome sensor (the Bayer sites' channels combined by inverse variance)")


def combine(brdf, std) -> tuple[float, float]:
    """One f_r and its 1-sigma from a row's channels: the inverse-variance mean over the finite,
    positive-sigma ones; (NaN, NaN) where there is none."""
    f, s = np.asarray(brdf, float), np.asarray(std, float)
    ok = np.isfinite(f) & np.isfinite(s) & (s > 0)
    if not ok.any():
        return np.nan, np.nan
    w = 1.0 / s[ok] ** 2
    return float(np.sum(w * f[ok]) / np.sum(w)), float(1.0 / np.sqrt(np.sum(w)))


def _seconds(v) -> float:
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) and v >= 0 else np.nan


def spectral_variables(doc: Mapping, rows: list) -> tuple[dict, dict, np.ndarray, np.ndarray]:
    """(coords, data, the monitor's readings, each point's instrument time) of a spectral
    session's journalled ``rows`` (module docstring), for `gonio.bench.dataset.export`."""
    plan_angles = np.asarray(doc["plan"]["points"], float)
    plan_wl = np.asarray(doc["plan"]["wavelength_nm"], float)
    geo, _ = geometry_groups(plan_angles)
    wl = np.unique(plan_wl)
    kept = sorted({int(geo[r["idx"]]) for r in rows})          # geometries with a row, in plan order
    where = {g: i for i, g in enumerate(kept)}
    n, m = len(kept), len(wl)
    brdf, std = np.full((n, m), np.nan), np.full((n, m), np.nan)
    sat = np.ones((n, m), bool)                                # not measured: left out by the reader
    plan_index = np.full((n, m), -1, int)
    monitor, time_s, read = np.full((n, m), np.nan), np.full((n, m), np.nan), np.full((n, m), np.nan)
    first: dict[int, Mapping] = {}
    cell = np.zeros((len(rows), 2), int)
    for k, r in enumerate(rows):
        i, j = where[int(geo[r["idx"]])], int(np.searchsorted(wl, plan_wl[r["idx"]]))
        cell[k] = i, j
        first.setdefault(i, r)
        brdf[i, j], std[i, j] = combine(r["brdf"], r["brdf_std"])
        sat[i, j] = bool(r["saturated"]) or not np.isfinite(brdf[i, j])
        plan_index[i, j] = r["idx"]
        d = r["detail"]
        monitor[i, j] = float(d.get("p_start", np.nan))
        time_s[i, j] = _seconds(d.get("instrument_s"))
        read[i, j] = float(d.get("wavelength_nm", np.nan))
    reps = [first[i] for i in range(n)]
    angles = np.array([[r[k] for k in ("theta_i", "phi_i", "theta_o", "phi_o")] for r in reps], float)
    partner = find_partners(angles)
    deg = {"units": "degree"}
    coords = {"point": np.arange(n), "wavelength": ("wavelength", wl, dict(WAVELENGTH_ATTRS)),
              **{k: ("point", angles[:, c], deg) for c, k in enumerate(("theta_i", "phi_i", "theta_o", "phi_o"))}}
    sr, pw = {"units": "sr^-1", "colour_space": "spectral"}, ("point", "wavelength")
    data = {
        "brdf": (pw, brdf, {**sr, "long_name": "bidirectional reflectance distribution function f_r (no cosine "
                            "factor) at each wavelength"}),
        "brdf_std": (pw, std, {**sr, "long_name": "standard uncertainty (1-sigma) of brdf from shot and read noise "
                               "(the scale's: scale_rel_std)"}),
        "saturated": (pw, sat, {"long_name": "some region pixel was saturated in every exposure, or the point was "
                                "not measured at this wavelength (value left out)"}),
        "reciprocal_partner": ("point", partner, {"long_name": "index of the point with wi and wo swapped, -1 if none"}),
        "plan_index": (pw, plan_index, {"long_name": "index of the measurement in the session's plan, -1 if none"}),
        **{k: ("point", np.array([r[k] for r in reps], float), {**deg, "long_name": f"stage angle {k}"})
           for k in ("yaw", "tilt", "azimuth", "lamp")},
        "monitor_power": (pw, monitor, {"units": "W", "long_name": "power-meter reading of the monitor at the "
                                        "wavelength, at the start of the measurement"}),
        "instrument_time": (pw, time_s, {"units": "s", "long_name": "instrument time of the measurement (NaN: not "
                                         "measured or not recorded)"}),
        "wavelength_read": (pw, read, {"units": "nm", "long_name": "wavelength the monochromator read back (WAVE?)"}),
    }
    data.update(spectral_budget(rows, doc["settings"], cell, brdf))
    point_s = np.array([np.nansum(time_s[i]) if np.any(np.isfinite(time_s[i])) else np.nan for i in range(n)])
    return coords, data, monitor[np.isfinite(monitor)], point_s


# The budget on (point, wavelength). Each row (a geometry at one wavelength) is first given the
# RGB export's budget over its three Bayer channels (`gonio.bench.dataset.budget.budget_variables`,
# the rows in the journal's order: the dark frames' overlaps, linearity levels and move history
# are the rows'); the inverse-variance combination f = sum_c a_c f_c (a_c = w_c / sum w, `combine`)
# is linear, so a shared (signed) line maps as sum_c a_c u_c and an independent one as
# sqrt(sum_c a_c^2 u_c^2) (JCGM 100 5.1.2, 5.2.2): the type-A lines still add up to brdf_std.

#: the angle variables of `budget.angle_variables`: per geometry, the per-move ones per (point,
#: wavelength) where the stage revisited geometries (`_angles_per_geometry`)
_ANGLE_VARS = ("angle_shift_shared", "irradiance_shift_shared", "angle_shift_independent",
               "angle_shift_independent_group")


def _weights(brdf, std) -> np.ndarray:
    """(R, 3) the channels' weights a_c of `combine` (0 where a channel is not used)."""
    f, s = np.asarray(brdf, float), np.asarray(std, float)
    ok = np.isfinite(f) & np.isfinite(s) & (s > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.where(ok, 1.0 / np.where(ok, s, 1.0) ** 2, 0.0)
    total = w.sum(axis=1, keepdims=True)
    return np.where(total > 0, w / np.where(total > 0, total, 1.0), 0.0)


def _certificate(settings: Mapping, brdf: np.ndarray) -> tuple | None:
    """``u_reference_certificate`` (point, wavelength): brdf x [reference] rel_std (one number, the
    same at every wavelength, or one per wavelength); correlation ``full`` (one certificate error
    shared by every wavelength: the simulator draws one) or ``channel`` ([reference]
    rel_std_correlation = "channel": one independent error per wavelength)."""
    ref = settings.get("reference", {})
    try:
        rel = np.broadcast_to(np.asarray(ref.get("rel_std", 0.0), float), (brdf.shape[1],))
    except ValueError:
        raise ValueError(f"[reference] rel_std must be one number or one per wavelength ({brdf.shape[1]})") from None
    if not np.any(rel > 0):
        return None
    corr = str(ref.get("rel_std_correlation", "full"))
    what = ("one independent error per wavelength" if corr == "channel" else
            "one error shared by every wavelength and point")
    return (("point", "wavelength"), brdf * rel[None, :], {
        "units": "sr^-1", "gum_type": "B", "correlation": corr,
        "source": f"reference certificate: relative 1-sigma [reference] rel_std of its reflectance at each "
                  f"wavelength ({what})",
        "long_name": "standard uncertainty of brdf from reference certificate (signed: the change for +1 sigma "
                     "of the shared input)"})


def spectral_budget(rows: list, settings: Mapping, cell: np.ndarray, brdf: np.ndarray) -> dict:
    """The budget variables of a spectral dataset (docs/interfaces.md 5.1) on (point, wavelength):
    ``u_<component>`` and ``u_combined`` from the rows' Bayer-channel budget (module comment),
    the certificate per wavelength (:func:`_certificate`) and the angle shifts per geometry (the
    stage does not move between a geometry's wavelengths when wavelength is the fastest axis) or
    per visit (:func:`_angles_per_geometry`). ``cell`` (R, 2): each row's (point, wavelength) index;
    ``brdf`` (n, m) the combined values. ValueError for a line this layout cannot carry."""
    from gonio.bench.dataset.budget import BUDGET_FORMAT, budget_variables

    f3 = np.array([r["brdf"] for r in rows], float).reshape(len(rows), -1)
    s3 = np.array([r["brdf_std"] for r in rows], float).reshape(len(rows), -1)
    f3 = np.where(np.isfinite(s3), f3, np.nan)
    a = _weights(f3, s3)
    # the certificate apart (per wavelength, :func:`_certificate`), not per Bayer site
    rgb = budget_variables(rows, {**settings, "reference": {**settings.get("reference", {}), "rel_std": 0.0}}, f3, s3)
    n, m = brdf.shape
    i, j = cell[:, 0], cell[:, 1]
    out, total, names = {}, np.zeros((n, m)), []

    def place(values):                              # (R, ...) per row -> (n, m, ...) per cell
        grid = np.full((n, m) + values.shape[1:], np.nan)
        grid[i, j] = values
        grid[~np.isfinite(brdf)] = np.nan           # no value (no usable site, or not measured): no u
        return grid

    for name, (dims, value, attrs) in rgb.items():
        if not name.startswith("u_") or name in ("u_combined", "u_reference_certificate"):
            continue
        corr, attrs = str(attrs.get("correlation", "")), dict(attrs)
        aa = a if np.ndim(value) == 2 else a[..., None]
        u = np.where(aa > 0, value, 0.0)            # a channel left out of the row's f_r: none of its u
        if corr == "none" and u.ndim == 2:
            v, dims2 = np.sqrt(((aa * u) ** 2).sum(axis=1)), ("point", "wavelength")
        elif corr in ("full", "point"):
            v = (aa * u).sum(axis=1)
            dims2 = ("point", "wavelength") + tuple(dims[2:])
            if corr == "point":                     # one error per row: each (point, wavelength) its own
                v, attrs["correlation"] = np.abs(v), "none"
        elif corr == "channel" and u.ndim == 2:     # one error per Bayer site, shared by every row
            v, dims2 = aa * u, ("point", "wavelength", f"{name[2:]}_input")
            attrs["correlation"] = "full"
        else:
            raise ValueError(f"budget line {name} ({corr}) has no (point, wavelength) form")
        grid = place(v)
        out[name] = (dims2, grid, attrs)
        total += (grid ** 2).sum(axis=2) if grid.ndim == 3 else grid ** 2
        names.append(name[2:])
    cert = _certificate(settings, brdf)
    if cert is not None:
        out["u_reference_certificate"] = cert
        total += cert[1] ** 2
        names.append("reference_certificate")
    out["u_combined"] = (("point", "wavelength"), np.where(np.isfinite(brdf), np.sqrt(total), np.nan), {
        "units": "sr^-1", "budget_format": BUDGET_FORMAT, "components": " ".join(sorted(names)),
        "long_name": "combined standard uncertainty of brdf (root sum of squares of the u_ components)"})
    out.update(_angles_per_geometry(rows, rgb, i, n, j, m))
    return out


def _angles_per_geometry(rows, rgb: dict, point: np.ndarray, n: int, wavelength: np.ndarray, m: int) -> dict:
    """The angle variables on the n geometries, each geometry's first-measured row's. Where the
    stage revisited geometries (wavelength the slowest axis) each visit has its own move errors
    and lost-motion signs: every angle variable then gains a ``wavelength`` dimension, each
    (point, wavelength) cell its own row's, 0 and label -1 where a cell was not measured (it has
    no value to move). The shared inputs stay one error each across all cells
    (gonio.fitting.uncertainty.budget.angle_components keeps them ``full``)."""
    if "angle_shift_shared" not in rgb:
        return {}
    t = np.array([float(r.get("finished", k)) for k, r in enumerate(rows)], float)
    order = np.argsort(t, kind="stable")
    pick = np.full(n, -1, int)
    for k in order[::-1]:
        pick[point[k]] = k
    per_move = ("angle_shift_independent", "angle_shift_independent_group")
    moved = False                    # a geometry's rows differ in their per-move errors: revisited
    for name in per_move:
        if name in rgb:
            v = np.asarray(rgb[name][1])
            moved |= not bool(np.allclose(v, v[:, pick[point]], rtol=0.0, atol=1e-12))
    out = {}
    for name in _ANGLE_VARS:
        if name not in rgb:
            continue
        dims, v, attrs = rgb[name]
        attrs, v = dict(attrs), np.asarray(v)
        if "source" in attrs:
            attrs["source"] += ("; per (point, wavelength): the stage revisited geometries between wavelengths, "
                                "each visit with its own move errors" if moved else
                                "; per geometry (the angles do not depend on the wavelength)")
        if moved:
            grid = np.full((v.shape[0], n, m) + v.shape[2:], -1 if v.dtype.kind in "iu" else 0.0, dtype=v.dtype)
            grid[:, point, wavelength] = v
            out[name] = ((dims[0], dims[1], "wavelength") + tuple(dims[2:]), grid, attrs)
        else:
            out[name] = (dims, v[:, pick], attrs)
    return out
