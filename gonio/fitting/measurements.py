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

from gonio.core.channels import COLOUR_SPACE_CHANNELS, spectral
from gonio.core.sides import Side, parse_sides
from gonio.core.geometry import angles_deg
from gonio.core.geometry import directions as direction

from gonio.fitting.display import measurements_summary, table_html, text

__all__ = ["COLOUR_SPACES", "Measurements", "colour_transform", "direction", "load_dataset"]


class DataError(ValueError):
    """Raised when measurement data cannot be fitted as given (NaN, negative sigma, ...)."""


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
    weight : ndarray, shape (N,), optional
        Each sample's solid-angle weight (sr^2 of direction-pair space it stands for; e.g.
        1 / pdf of the directions' sampling), so that a sum over samples approximates an
        integral over the hemispheres. None: every sample counts the same. Used by the
        ``discrepancy`` likelihood and the Ngan / log error metrics.
    """

    wi: np.ndarray
    wo: np.ndarray
    brdf: np.ndarray
    brdf_std: np.ndarray
    use: np.ndarray
    attrs: dict = dataclasses.field(default_factory=dict)
    channels: tuple = ("R", "G", "B")
    weight: np.ndarray | None = None
    #: the independent unit of the measurement geometry each point belongs to (integers):
    #: points of one cluster come from one draw of the layout (an RGL file's outgoing sample
    #: point, shared by every incident elevation), so the cluster-robust sandwich sums their
    #: scores before squaring; None: every point is its own unit
    cluster: np.ndarray | None = None

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
        if self.weight is not None:
            self.weight = np.asarray(self.weight, dtype=np.float64).reshape(-1)
            if self.weight.shape != (n,) or not np.all(np.isfinite(self.weight)) or np.any(self.weight <= 0):
                raise DataError(f"weight must hold {n} finite values > 0 (one solid-angle weight per point)")
        if self.cluster is not None:
            self.cluster = np.asarray(self.cluster).reshape(-1)
            if self.cluster.shape != (n,) or not np.issubdtype(self.cluster.dtype, np.integer):
                raise DataError(f"cluster must hold {n} integers (one geometry unit per point)")

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
                            self.use[index], dict(self.attrs), self.channels,
                            None if self.weight is None else self.weight[index],
                            None if self.cluster is None else self.cluster[index])

    def relative_weight(self) -> np.ndarray:
        """Solid-angle weights scaled to mean 1 (ones when there are none), shape (N,)."""
        if self.weight is None:
            return np.ones(self.n_points)
        return self.weight / self.weight.mean()

    # ---- how a dataset shows itself (terminal, notebook) and leaves as xarray (gonio.fitting.display) ----
    def __repr__(self) -> str:
        """Sizes, the f_r range and median relative 1-sigma per channel; no raw arrays."""
        caption, rows, notes = measurements_summary(self)
        return "Measurements: " + text(caption, _MEAS_HEADER, rows, notes)

    def _repr_html_(self) -> str:
        caption, rows, notes = measurements_summary(self)
        return table_html("Measurements: " + caption, _MEAS_HEADER, rows, notes)

    def to_xarray(self):
        """An :class:`xarray.Dataset` over ``point`` and ``channel``: ``brdf``, ``brdf_std``
        (sr^-1), ``use``, ``weight`` where given; the angles ``theta_i``, ``phi_i``, ``theta_o``,
        ``phi_o`` (degrees, gonio.core.geometry's convention) as coordinates."""
        import xarray as xr

        (ti, pi_), (to, po) = angles_deg(self.wi), angles_deg(self.wo)
        deg = {"units": "degree"}
        data = {"brdf": (("point", "channel"), self.brdf, {"units": "sr^-1"}),
                "brdf_std": (("point", "channel"), self.brdf_std, {"units": "sr^-1"}),
                "use": (("point", "channel"), self.use)}
        if self.weight is not None:
            data["weight"] = ("point", self.weight, {"units": "sr^2"})
        if self.cluster is not None:
            data["cluster"] = ("point", self.cluster)
        coords = {"channel": list(self.channels)[: self.n_channels],
                  **{k: ("point", v, deg) for k, v in (("theta_i", ti), ("phi_i", pi_), ("theta_o", to), ("phi_o", po))}}
        # the space of these values (load_dataset's choice), not the dataset file's camera RGB
        space = str((self.attrs.get("colour") or {}).get("space", "camera"))
        for key in ("brdf", "brdf_std"):
            data[key][2]["colour_space"] = space
        attrs = {k: v for k, v in self.attrs.items() if isinstance(v, (str, int, float))}
        return xr.Dataset(data, coords=coords, attrs={**attrs, "colour_space": space})


_MEAS_HEADER = ("channel", "values used", "f_r range (1/sr)", "median rel. 1-sigma")


#: Angle units a dataset may declare, and the factor to radians.
ANGLE_UNITS = {**dict.fromkeys(("deg", "degree", "degrees"), np.pi / 180.0),
               **dict.fromkeys(("rad", "radian", "radians"), 1.0)}

#: A 1-sigma below this fraction of the value it belongs to (or of the dataset's typical value)
#: is no measurement's uncertainty: it would weight one point ~1e18 times another.
MIN_REL_SIGMA = 1e-9
#: ... nor is one below this, whatever the values (sr^-1): its inverse square overflows.
MIN_SIGMA = 1e-100
#: No measured |f_r| or 1-sigma exceeds this (sr^-1): a mirror seen through a 0.01-degree aperture
#: is ~3e7; beyond it a value is damage, and its square (the fit's chi^2) overflows near 1e154.
MAX_BRDF = 1e10


def _check_sigmas(path, brdf, std, use) -> None:
    """brdf_std must be positive, finite, normal and not absurdly small, and f_r and brdf_std at
    most :data:`MAX_BRDF`, at every usable value."""
    if not np.any(use):
        return
    bad = use & ~(std > 0)
    if np.any(bad):
        i, c = (int(v) for v in np.argwhere(bad)[0])
        raise DataError(f"{path}: brdf_std = {std[i, c]:g} at point {i} (channel {c}) is not positive; "
                        "every used value needs a 1-sigma > 0 (flag the point saturated or drop it)")
    bad = use & ((np.abs(brdf) > MAX_BRDF) | (std > MAX_BRDF))
    if np.any(bad):
        i, c = (int(v) for v in np.argwhere(bad)[0])
        raise DataError(f"{path}: f_r = {brdf[i, c]:g} +- {std[i, c]:g} at point {i} (channel {c}) is beyond any "
                        f"measured BRDF (at most {MAX_BRDF:g} sr^-1); fix the dataset or drop the point")
    typical = float(np.median(np.abs(brdf[use])))
    floor = np.maximum(MIN_REL_SIGMA * np.maximum(np.abs(brdf), typical), MIN_SIGMA)
    bad = use & ((std < floor) | (std < np.finfo(np.float64).tiny))
    if np.any(bad):
        i, c = (int(v) for v in np.argwhere(bad)[0])
        raise DataError(f"{path}: brdf_std = {std[i, c]:g} at point {i} (channel {c}) is absurdly small for "
                        f"brdf = {brdf[i, c]:g} (below {MIN_REL_SIGMA:g} of the value); fix the uncertainties")


#: The colour spaces f_r can be fitted in, and the dataset variables that hold each.
COLOUR_SPACES = {"srgb": "brdf_srgb", "xyz": "brdf_xyz", "camera": "brdf"}
_CHANNELS = COLOUR_SPACE_CHANNELS     # the one declaration (gonio.core.channels)


def _radians(ds, path, name) -> np.ndarray:
    """One angle variable in radians, checked (units, numeric, 1-D, finite)."""
    var = ds[name]
    unit = " ".join(str(var.attrs.get("units", "degree")).split()).lower()
    if unit not in ANGLE_UNITS:
        raise DataError(f"{path}: {name} has units {var.attrs.get('units')!r}; angles must be in "
                        "degree(s)/deg or radian(s)/rad: fix the units attribute")
    try:
        values = np.asarray(var.values, dtype=np.float64)
    except (TypeError, ValueError):
        raise DataError(f"{path}: {name} is not numeric; fix the dataset") from None
    if values.ndim != 1:
        raise DataError(f"{path}: {name} must be one value per point, not shape {values.shape}")
    if not np.all(np.isfinite(values)):
        raise DataError(f"{path}: {name} is NaN or inf at point {int(np.argmax(~np.isfinite(values)))}; "
                        "fix or drop that point")
    return values * ANGLE_UNITS[unit]


def _wavelengths(ds, path) -> list[float] | None:
    """The ``wavelength`` coordinate (nm) of a spectral dataset's ``brdf``, None for a colour one;
    DataError for a wavelength in other units or out of `gonio.core.channels`' range."""
    if "wavelength" not in ds.coords or "wavelength" not in ds["brdf"].dims:
        return None
    units = str(ds["wavelength"].attrs.get("units", "nm"))
    w = [float(v) for v in np.asarray(ds["wavelength"].values, float)]
    try:
        if units != "nm":
            raise ValueError(f"units {units!r}, not nm")
        spectral(w)
    except ValueError as exc:
        raise DataError(f"{path}: its wavelength coordinate is not usable ({exc}); give wavelengths in nm") from None
    return w


def _colour_variables(ds, path, colour_space) -> tuple[str, dict]:
    """The variable holding f_r in ``colour_space`` and what the fit must record about it."""
    if colour_space not in COLOUR_SPACES:
        raise DataError(f"unknown colour space {colour_space!r}: use one of {', '.join(COLOUR_SPACES)}")
    name = COLOUR_SPACES[colour_space]
    declared = ds["brdf"].attrs.get("colour_space")
    info = {"space": colour_space, "variable": name, "matrix": None,
            "mitsuba": "rgb values in linear sRGB: the sample's colour" if colour_space == "srgb" else
            f"rgb values in {colour_space}, which Mitsuba reads as linear sRGB: fit with --colour-space srgb "
            "for a material of the sample's colour"}
    if name not in ds.variables or f"{name}_std" not in ds.variables:
        if declared is not None and str(declared) != colour_space:
            raise DataError(f"{path} holds f_r in {declared} only (no {name}: the session had no colour "
                            f"matrix); fit with --colour-space {declared}")
        name, info["variable"] = "brdf", "brdf"
        if declared is None:
            info["note"] = f"the dataset declares no colour space: brdf taken as {colour_space}"
    if isinstance(ds.attrs.get("colour_matrix"), str) and colour_space != "camera":
        try:
            info["matrix"] = json.loads(ds.attrs["colour_matrix"])
        except json.JSONDecodeError:
            raise DataError(f"{path}: its colour_matrix attribute is not JSON; re-export the session") from None
    if name != "brdf" and f"{name}_corr" in ds.variables:
        corr = np.abs(np.asarray(ds[f"{name}_corr"].values, float))
        info["channel_correlation_max"] = float(np.nanmax(corr)) if np.any(np.isfinite(corr)) else 0.0
        info["left_out"] = ("the fit weights each channel by its own 1-sigma; the noise correlation between "
                            f"channels from the colour matrix (|r| up to {info['channel_correlation_max']:.3f}, "
                            f"{name}_corr in the dataset) is not in its weights, and not in its covariance (each "
                            "parameter's std); the uncertainty section's u_stat and u_c carry it where the dataset "
                            "has its u_ components per camera channel (gonio/fitting/uncertainty/budget.py), and the colour matrix's "
                            "own uncertainty where the dataset states it (a chart's)")
    return name, info


#: Linear sRGB -> CIE XYZ (D65) as IEC 61966-2-1 publishes it (gonio/bench/measure/colour_matrix.SRGB_TO_XYZ's figures).
_SRGB_TO_XYZ = np.array([[0.4124, 0.3576, 0.1805], [0.2126, 0.7152, 0.0722], [0.0193, 0.1192, 0.9505]])


def colour_transform(meas: "Measurements") -> np.ndarray | None:
    """The 3x3 that took the dataset's camera-RGB ``brdf`` into ``meas``' colour space (the
    identity for a camera-RGB fit; None where the dataset declares no matrix): what a quantity
    stated per camera channel (an uncertainty component) must go through to match ``meas``."""
    colour = meas.attrs.get("colour") or {}
    if colour.get("space", "camera") == "camera" or colour.get("variable") == "brdf":
        return np.eye(meas.n_channels)
    matrix = (colour.get("matrix") or {}).get("srgb_from_cam")
    if matrix is None:
        return None
    m = np.asarray(matrix, float)
    return _SRGB_TO_XYZ @ m if colour["space"] == "xyz" else m


def _values(ds, path, name, n_points):
    """f_r and 1-sigma (N, C) of one variable, shape-checked."""
    try:
        brdf = np.asarray(ds[name].transpose("point", ...).values, dtype=np.float64)
        std = np.asarray(ds[f"{name}_std"].transpose("point", ...).values, dtype=np.float64)
    except (TypeError, ValueError):
        raise DataError(f"{path}: {name} and {name}_std must be numeric arrays over point (and channel)") from None
    brdf, std = (a[:, None] if a.ndim == 1 else a for a in (brdf, std))
    if brdf.ndim != 2 or std.shape != brdf.shape or brdf.shape[0] != n_points:
        raise DataError(f"{path}: {name} {brdf.shape} and {name}_std {std.shape} must match the {n_points} points")
    return brdf, std


def _attrs(ds) -> dict:
    """The dataset's attributes as plain Python values (``sample_truth`` parsed from JSON)."""
    attrs = {k: v.item() if isinstance(v, np.generic) else v.tolist() if isinstance(v, np.ndarray) else v
             for k, v in ds.attrs.items()}
    if isinstance(attrs.get("sample_truth"), str):
        try:
            attrs["sample_truth"] = json.loads(attrs["sample_truth"])
        except json.JSONDecodeError:
            pass
    return attrs


def load_dataset(path, colour_space: str = "srgb") -> Measurements:
    """Read a gonio ``dataset.nc`` into :class:`Measurements`.

    Parameters
    ----------
    colour_space : {"srgb", "xyz", "camera"}
        Which f_r to fit: linear sRGB (D65, Mitsuba's rendering space; the default), CIE XYZ or
        white-balanced camera RGB. A dataset without ``brdf_srgb``/``brdf_xyz`` (no colour
        matrix) is fitted in the space its ``brdf`` declares; one that declares none is taken as
        asked (``attrs["colour"]["note"]`` says so). ``attrs["colour"]`` records the space, the
        variable, the matrix and what the fit leaves out.

    Raises
    ------
    DataError
        When the file lacks the variables of docs/interfaces.md section 5, declares angle
        units other than degrees or radians, has a direction below the horizon (theta outside
        [0, 90] deg), holds NaN where values are used, a 1-sigma that is not positive,
        finite and of a plausible size (see `MIN_REL_SIGMA`), or has no f_r in ``colour_space``.
    """
    import xarray as xr

    path = Path(path)
    with xr.open_dataset(path, engine="h5netcdf") as ds:
        ds.load()
    missing = [v for v in ("brdf", "brdf_std", "theta_i", "phi_i", "theta_o", "phi_o") if v not in ds.variables]
    if missing:
        raise DataError(f"{path} is not a gonio dataset: missing {', '.join(missing)}")
    angles = {k: _radians(ds, path, k) for k in ("theta_i", "phi_i", "theta_o", "phi_o")}
    try:
        sides = parse_sides(ds.attrs.get("sides", "reflect"), str(path))
    except ValueError as exc:
        raise DataError(f"{exc}; fix the file's 'sides' attribute") from None
    for k in ("theta_i", "theta_o"):
        bad = (angles[k] < 0) | (angles[k] > np.pi / 2 + 1e-9)
        if k == "theta_o" and Side.TRANSMIT in sides:
            bad &= ~((angles[k] >= np.pi / 2 - 1e-9) & (angles[k] <= np.pi))
        if np.any(bad):
            i = int(np.argmax(bad))
            raise DataError(f"{path}: {k} = {np.degrees(angles[k][i]):.6g} deg at point {i} is below the horizon "
                            "(theta must be in [0, 90] deg); fix the units or drop the point")
    wi, wo = direction(angles["theta_i"], angles["phi_i"]), direction(angles["theta_o"], angles["phi_o"])
    spectrum = _wavelengths(ds, path)           # a spectral session's dataset: brdf(point, wavelength)
    name, colour = ("brdf", {"space": "spectral", "variable": "brdf", "matrix": None}) if spectrum \
        else _colour_variables(ds, path, colour_space)
    brdf, std = _values(ds, path, name, wi.shape[0])
    use = np.ones(brdf.shape, dtype=bool)
    if "saturated" in ds.variables:
        sat = np.asarray(ds["saturated"].values, dtype=bool)
        sat = sat[:, None] if sat.ndim == 1 else sat if name == "brdf" else sat.any(1, keepdims=True)
        use &= ~sat             # a matrix mixes the channels: one saturated camera channel taints all
    nan_rows = ~np.isfinite(brdf) | ~np.isfinite(std)
    if np.any(nan_rows & use):
        bad = int(np.argwhere(nan_rows & use)[0, 0])
        raise DataError(f"{path}: {name} or {name}_std is NaN at point {bad} and it is not flagged saturated;"
                        " re-export the session or drop the point")
    _check_sigmas(path, brdf, std, use)
    attrs = {**_attrs(ds), "colour": colour, **({"wavelengths_nm": spectrum} if spectrum else {})}
    if spectrum:
        channels = spectral(spectrum).names
    elif name == "brdf" and "channel" in ds.coords:
        channels = tuple(str(c) for c in ds["channel"].values)
    else:
        channels = _CHANNELS[colour_space][: brdf.shape[1]]
    return Measurements(wi, wo, brdf, std, use, attrs, channels)
