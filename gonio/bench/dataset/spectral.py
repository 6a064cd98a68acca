"""A spectral session's dataset.nc variables: dimensions ``point`` (a geometry) and
``wavelength`` (nm, CF standard name ``radiation_wavelength``).

A spectral plan's journal holds one row per (geometry, wavelength), each with the monochrome
sensor's three Bayer channels of f_r at that wavelength (equal in expectation: the sensor
sites see the same light). `spectral_variables` combines them by inverse variance into one
f_r per row (its 1-sigma from the channels' own), then lays the rows out as ``brdf(point,
wavelength)``; a (geometry, wavelength) never measured is NaN and flagged in ``saturated``
(the reader leaves it out). Per point: the angles, the stage pose and the reciprocal partner
of its geometry; per (point, wavelength): the plan index, the monitor's reading, the
instrument time and the wavelength the monochromator read back.
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

from gonio.bench.plan.plans import find_partners
from gonio.bench.plan.spectral import geometry_groups

__all__ = ["spectral_variables", "combine", "WAVELENGTH_ATTRS", "COLOUR_SPACE"]

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
    for r in rows:
        i, j = where[int(geo[r["idx"]])], int(np.searchsorted(wl, plan_wl[r["idx"]]))
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
    point_s = np.array([np.nansum(time_s[i]) if np.any(np.isfinite(time_s[i])) else np.nan for i in range(n)])
    return coords, data, monitor[np.isfinite(monitor)], point_s
