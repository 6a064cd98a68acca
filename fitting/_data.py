"""Measurements as the fitter sees them: directions, f_r, 1-sigma, and a mask.

A dataset on disk (``dataset.nc``, see docs/interfaces.md section 5) stores angles in degrees;
the fitter works on unit vectors in the sample's local frame (+z the normal, ``wi`` toward
the light, ``wo`` toward the detector).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

__all__ = ["Measurements", "direction", "load_dataset"]


class DataError(ValueError):
    """Raised when measurement data cannot be fitted as given (NaN, negative sigma, ...)."""


def direction(theta, phi):
    """Unit vectors from polar angle ``theta`` and azimuth ``phi`` (radians), shape (N, 3)."""
    theta = np.asarray(theta, dtype=np.float64)
    phi = np.asarray(phi, dtype=np.float64)
    sin_theta = np.sin(theta)
    return np.stack([sin_theta * np.cos(phi), sin_theta * np.sin(phi), np.cos(theta)], axis=-1)


@dataclasses.dataclass
class Measurements:
    """BRDF samples ready to fit.

    Attributes
    ----------
    wi, wo : ndarray, shape (N, 3)
        Unit directions toward the light and toward the detector, local frame.
    brdf : ndarray, shape (N, C)
        Measured f_r in sr^-1.
    brdf_std : ndarray, shape (N, C)
        1-sigma uncertainty of ``brdf`` (sr^-1), strictly positive where used.
    use : ndarray of bool, shape (N, C)
        Which values enter the fit (saturated or flagged values are left out).
    attrs : dict
        Provenance carried over from the dataset (seed, version, sample truth...).
    """

    wi: np.ndarray
    wo: np.ndarray
    brdf: np.ndarray
    brdf_std: np.ndarray
    use: np.ndarray
    attrs: dict = dataclasses.field(default_factory=dict)
    channels: tuple = ("R", "G", "B")

    def __post_init__(self):
        self.wi = np.atleast_2d(np.asarray(self.wi, dtype=np.float64))
        self.wo = np.atleast_2d(np.asarray(self.wo, dtype=np.float64))
        self.brdf = np.asarray(self.brdf, dtype=np.float64)
        if self.brdf.ndim == 1:
            self.brdf = self.brdf[:, None]
        self.brdf_std = np.broadcast_to(np.asarray(self.brdf_std, dtype=np.float64), self.brdf.shape).copy()
        self.use = np.broadcast_to(np.asarray(self.use, dtype=bool), self.brdf.shape).copy()
        n = self.brdf.shape[0]
        if self.wi.shape != (n, 3) or self.wo.shape != (n, 3):
            raise DataError(f"directions must have shape ({n}, 3) to match {n} BRDF values")
        for name, arr in (("wi", self.wi), ("wo", self.wo)):
            if not np.all(np.isfinite(arr)):
                raise DataError(f"{name} contains NaN or inf: fix or drop those points before fitting")
        used = self.use
        if not np.all(np.isfinite(self.brdf[used])):
            raise DataError("brdf contains NaN or inf at points marked usable: flag them or drop them")
        if not np.all(np.isfinite(self.brdf_std[used])) or np.any(self.brdf_std[used] <= 0):
            raise DataError("brdf_std must be finite and > 0 at every usable point (it weights the fit)")
        if used.sum() == 0:
            raise DataError("no usable BRDF values (all flagged): nothing to fit")

    @property
    def n_points(self) -> int:
        return self.brdf.shape[0]

    @property
    def n_channels(self) -> int:
        return self.brdf.shape[1]

    @property
    def n_used(self) -> int:
        return int(self.use.sum())

    def subset(self, index) -> "Measurements":
        return Measurements(self.wi[index], self.wo[index], self.brdf[index], self.brdf_std[index],
                            self.use[index], dict(self.attrs), self.channels)


def load_dataset(path) -> Measurements:
    """Read a gonio ``dataset.nc`` into :class:`Measurements`.

    Raises
    ------
    DataError
        When the file lacks the variables of docs/interfaces.md section 5, or holds NaN where
        values are used.
    """
    import xarray as xr

    path = Path(path)
    with xr.open_dataset(path, engine="h5netcdf") as ds:
        ds.load()
    missing = [v for v in ("brdf", "brdf_std", "theta_i", "phi_i", "theta_o", "phi_o") if v not in ds.variables]
    if missing:
        raise DataError(f"{path} is not a gonio dataset: missing {', '.join(missing)}")

    def radians(name):
        var = ds[name]
        unit = str(var.attrs.get("units", "degree")).lower()
        values = np.asarray(var.values, dtype=np.float64)
        return np.deg2rad(values) if unit.startswith("deg") else values

    wi = direction(radians("theta_i"), radians("phi_i"))
    wo = direction(radians("theta_o"), radians("phi_o"))
    brdf = np.asarray(ds["brdf"].transpose("point", ...).values, dtype=np.float64)
    std = np.asarray(ds["brdf_std"].transpose("point", ...).values, dtype=np.float64)
    if brdf.ndim == 1:
        brdf, std = brdf[:, None], std[:, None]
    use = np.ones(brdf.shape, dtype=bool)
    if "saturated" in ds.variables:
        sat = np.asarray(ds["saturated"].values, dtype=bool)
        use &= ~(sat if sat.ndim == 2 else sat[:, None])
    nan_rows = ~np.isfinite(brdf) | ~np.isfinite(std)
    if np.any(nan_rows & use):
        bad = int(np.argwhere(nan_rows & use)[0, 0])
        raise DataError(f"{path}: brdf or brdf_std is NaN at point {bad} and it is not flagged saturated;"
                        " re-export the session or drop the point")
    attrs = {}
    for key, value in ds.attrs.items():
        if isinstance(value, np.generic):
            value = value.item()
        elif isinstance(value, np.ndarray):
            value = value.tolist()
        attrs[key] = value
    if isinstance(attrs.get("sample_truth"), str):
        try:
            attrs["sample_truth"] = json.loads(attrs["sample_truth"])
        except json.JSONDecodeError:
            pass
    channels = tuple(str(c) for c in ds["channel"].values) if "channel" in ds.coords else ("R", "G", "B")[: brdf.shape[1]]
    return Measurements(wi, wo, brdf, std, use, attrs, channels)
