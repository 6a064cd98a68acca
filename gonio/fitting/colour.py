"""Colour from spectral BRDF values: CIE XYZ, CIELAB and CIEDE2000 through colour-science.

A spectral f_r (one value per wavelength, sr^-1) at each geometry is taken as the
reflectance factor pi f_r (a white Lambertian surface: 1) and integrated with the CIE 1931
2-degree observer under an illuminant (D65 by default) by colour-science's ASTM E308 tables
(``colour.msds_to_XYZ``); no colour-matching table is written here. Lab is relative to the
illuminant's white (Y = 1), so a specular highlight may exceed L* = 100. :func:`fit_colour_error`
compares a fit's colour with the measured spectra point by point (CIEDE2000), over the bright
points (the brighter half of the measured geometries by their Y, by default).
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["spectral_xyz", "spectral_lab", "delta_e00", "fit_colour_error", "reflectance_to_linear_srgb",
           "linear_srgb_lab", "OBSERVER"]

#: The colour-matching functions used throughout (colour-science's name).
OBSERVER = "CIE 1931 2 Degree Standard Observer"
#: ASTM E308's weighting tables exist for these wavelength intervals (nm).
_INTERVALS = (1.0, 5.0, 10.0, 20.0)


def _regular(wavelengths, values):
    """``values`` (N, W) on a regular grid ASTM E308 tabulates: as given where the wavelengths
    are one already, else linearly interpolated onto 5 nm steps within their range."""
    w = np.asarray(wavelengths, float)
    step = np.diff(w)
    if w.size >= 3 and np.allclose(step, step[0]) and any(math.isclose(step[0], s) for s in _INTERVALS):
        return w, values
    grid = np.arange(math.ceil(w[0] / 5.0) * 5.0, w[-1] + 1e-9, 5.0)
    if grid.size < 3:
        raise ValueError(f"wavelengths {w[0]:g}-{w[-1]:g} nm span too little of the visible for a colour")
    return grid, np.stack([np.interp(grid, w, row) for row in values])


def spectral_xyz(values, wavelengths, illuminant: str = "D65") -> np.ndarray:
    """CIE XYZ (N, 3), Y = 1 for the perfect white, of spectral f_r ``values`` (N, W) in sr^-1
    at ``wavelengths`` (nm) under ``illuminant`` (a colour-science name: D65, A, D50, F2...)."""
    import colour

    values = np.atleast_2d(np.asarray(values, float))
    if values.shape[1] != len(wavelengths):
        raise ValueError(f"{values.shape[1]} values per point for {len(wavelengths)} wavelengths")
    if not np.all(np.isfinite(values)):
        raise ValueError("spectral values hold NaN or inf: no colour for them")
    if illuminant not in colour.SDS_ILLUMINANTS:
        raise ValueError(f"unknown illuminant {str(illuminant)[:40]!r}; give one of D65, D50, A, F2, ...")
    w, r = _regular(wavelengths, math.pi * values)
    shape = colour.SpectralShape(float(w[0]), float(w[-1]), float(w[1] - w[0]))
    cmfs = colour.MSDS_CMFS[OBSERVER].copy().align(shape)      # aligned here: colour-science warns otherwise
    sd = colour.SDS_ILLUMINANTS[illuminant].copy().align(shape)
    xyz = colour.msds_to_XYZ(np.vstack([r, np.ones(w.size)]), cmfs, sd, method="Integration", shape=shape)
    xyz = np.asarray(xyz, float).reshape(-1, 3)
    return xyz[:-1] / xyz[-1, 1]     # the last row: the perfect white on the same wavelengths, Y = 1


def spectral_lab(values, wavelengths, illuminant: str = "D65") -> np.ndarray:
    """CIELAB (N, 3) of spectral f_r values, relative to ``illuminant``'s white."""
    import colour

    values = np.atleast_2d(np.asarray(values, float))
    xyz = spectral_xyz(np.vstack([values, np.full(values.shape[1], 1.0 / math.pi)]), wavelengths, illuminant)
    xy = colour.XYZ_to_xy(xyz[-1])      # the white of these wavelengths under the illuminant
    return np.asarray(colour.XYZ_to_Lab(xyz[:-1], xy), float)


def delta_e00(lab_a, lab_b) -> np.ndarray:
    """CIEDE2000 colour difference of two Lab arrays (colour-science's implementation)."""
    import colour

    return np.asarray(colour.delta_E(lab_a, lab_b, method="CIE 2000"), float)


def fit_colour_error(meas, model, params, *, illuminant: str = "D65", bright: float = 0.5) -> dict:
    """The fit's colour against the measured spectra at every measured geometry.

    ``meas`` needs ``attrs["wavelengths_nm"]`` (a spectral dataset). Bright points: every value
    used and measured Y at least the ``bright`` quantile of the file's (0.5: the brighter half).
    Returns ``{"de00": per bright point, "mean", "max", "n_bright", "illuminant"}``."""
    wl = meas.attrs.get("wavelengths_nm")
    if not wl:
        raise ValueError("colour from spectra needs a spectral dataset (attrs['wavelengths_nm'])")
    measured = spectral_xyz(meas.brdf, wl, illuminant)
    used = np.all(meas.use, axis=1)
    if not np.any(used):
        raise ValueError("no point with every wavelength used: no colour to compare")
    keep = used & (measured[:, 1] >= np.quantile(measured[used, 1], bright))
    fitted = np.asarray(model.eval(meas.wi[keep], meas.wo[keep], params), float)
    de = delta_e00(spectral_lab(meas.brdf[keep], wl, illuminant), spectral_lab(fitted, wl, illuminant))
    return {"de00": de, "mean": float(de.mean()), "max": float(de.max()), "n_bright": int(keep.sum()),
            "illuminant": illuminant}


def reflectance_to_linear_srgb(wavelengths, values, illuminant: str = "D65") -> np.ndarray:
    """The linear sRGB (3,) of a reflectance spectrum (``values`` at ``wavelengths`` nm, a
    perfect white = 1) under ``illuminant`` (D65: sRGB's own white, no adaptation), through
    colour-science's XYZ -> sRGB matrix (IEC 61966-2-1), without the transfer function."""
    import colour

    r = np.asarray(values, float).reshape(1, -1) / math.pi      # as f_r of a Lambertian surface
    xyz = spectral_xyz(r, wavelengths, illuminant)[0]
    return np.asarray(colour.XYZ_to_RGB(xyz, colour.RGB_COLOURSPACES["sRGB"], apply_cctf_encoding=False), float)


def linear_srgb_lab(rgb) -> np.ndarray:
    """CIELAB (..., 3) of linear sRGB reflectances ``rgb`` (..., 3; a perfect white = 1) under D65,
    sRGB's own white (IEC 61966-2-1's matrix, colour-science's; no transfer function)."""
    import colour

    space = colour.RGB_COLOURSPACES["sRGB"]
    xyz = colour.RGB_to_XYZ(np.asarray(rgb, float), space, apply_cctf_decoding=False)
    return np.asarray(colour.XYZ_to_Lab(xyz, space.whitepoint), float)
