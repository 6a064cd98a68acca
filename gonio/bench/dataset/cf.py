"""dataset.nc as CF-1.8 (NetCDF Climate and Forecast Metadata Conventions, version 1.8).

Specification: https://cfconventions.org/Data/cf-conventions/cf-conventions-1.8/cf-conventions.html.
:func:`cf_encode` adds to the dataset :func:`gonio.bench.dataset.export.to_dataset` builds: the
global attributes of CF section 2.6.2 (``Conventions = "CF-1.8"``, ``title``, ``institution``,
``source``, ``history``, ``references``, ``comment``) and gonio's own ``angle_convention``,
``angle_units``, ``phi_convention`` and ``colour_space``; ``long_name`` on every variable that
lacks one (section 3.2) and ``units`` where they apply; the channel labels and any other
string coordinate (e.g. ``xyz``) as fixed-length char arrays with ``_Encoding = "utf-8"``
(section 2.2); integer variables as 32-bit ``int``; ``saturated`` as a CF flag (section 3.5).

No CF standard name fits these variables (gonio's f_r is in sr^-1 of a laboratory sample);
the angles say what they are in ``long_name`` and ``comment`` instead.
"""

# Encoding details:
# - units go on the dimensionless indices' neighbours where they have a unit;
# - string coordinates become channel(channel, string1): CF-1.8 strings are char arrays, and
#   netCDF-4 variable-length strings are not among its types; _Encoding = "utf-8" lets xarray
#   read them back as text;
# - section 2.2 lists char, byte, short, int, float and double;
# - saturated is a byte with flag_values = 0, 1 and flag_meanings = "not_saturated saturated".
# No standard name: surface_bidirectional_reflectance is dimensionless (a reflectance factor
# of the Earth's surface), and the zenith/azimuth names are defined against the local vertical
# of the Earth.

from __future__ import annotations

from datetime import datetime, timezone

import numpy as np

__all__ = ["CF_CONVENTIONS", "cf_encode"]

CF_CONVENTIONS = "CF-1.8"

_ANGLES = {
    "theta_i": "polar angle of the incident direction wi (toward the light) from the sample normal",
    "phi_i": "azimuth of the incident direction wi (toward the light) in the sample frame",
    "theta_o": "polar angle of the outgoing direction wo (toward the camera) from the sample normal",
    "phi_o": "azimuth of the outgoing direction wo (toward the camera) in the sample frame",
}
PHI_CONVENTION = ("local sample frame, +z the surface normal; phi from +x toward +y (counter-clockwise seen "
                  "from above the sample): w = (sin theta cos phi, sin theta sin phi, cos theta); wi points to "
                  "the light, wo to the camera, both away from the surface")
COLOUR_SPACE = ("brdf, brdf_std: linear camera RGB (channel R, G, B), white-balanced by the spectrally flat "
                "reference that shares the illumination; brdf_srgb: linear sRGB (D65, IEC 61966-2-1); "
                "brdf_xyz: CIE 1931 XYZ (D65), where the RAW files carry colour matrices")
REFERENCES = ("f_r: F. E. Nicodemus, J. C. Richmond, J. J. Hsia, I. W. Ginsberg, T. Limperis, Geometrical "
              "Considerations and Nomenclature for Reflectance, NBS Monograph 160 (1977); file layout: gonio "
              "docs/interfaces.md section 5; conventions: CF-1.8")


def _labels(ds):
    """String coordinates as fixed-length char arrays (CF-1.8 section 2.2)."""
    for name, var in ds.variables.items():
        if var.dtype.kind in ("U", "O"):
            width = max((len(str(v).encode("utf-8")) for v in np.ravel(var.values)), default=1) or 1
            var.encoding.update(dtype="S1", char_dim_name=f"string{width}")


def _integers(ds):
    """64-bit integers as CF-1.8's 32-bit int (values checked to fit)."""
    for name in list(ds.variables):
        var = ds[name]
        if var.dtype.kind in ("i", "u") and var.dtype.itemsize > 4:
            values = np.asarray(var.values)
            if values.size and (values.min() < np.iinfo(np.int32).min or values.max() > np.iinfo(np.int32).max):
                raise ValueError(f"{name} does not fit a 32-bit int (CF-1.8 has no 64-bit integer)")
            ds[name] = var.astype(np.int32)
            ds[name].attrs.update(var.attrs)


def _saturated(ds):
    if "saturated" not in ds.variables:
        return
    attrs = dict(ds["saturated"].attrs)
    ds["saturated"] = ds["saturated"].astype(np.int8)
    ds["saturated"].attrs.update(attrs, flag_values=np.array([0, 1], np.int8),
                                 flag_meanings="not_saturated saturated")


def _long_names(ds):
    ds["point"].attrs.update(long_name="index of the measured point in this dataset (in capture order)", units="1")
    if "channel" in ds.variables:
        ds["channel"].attrs.update(long_name="colour channel of the camera (R, G, B)")
    if "xyz" in ds.variables:
        ds["xyz"].attrs.update(long_name="CIE 1931 tristimulus component (X, Y, Z)")
    for name, what in _ANGLES.items():
        if name in ds.variables:
            ds[name].attrs.update(long_name=what, units="degree")
            if name.startswith("phi"):
                ds[name].attrs["comment"] = PHI_CONVENTION
    for name, var in ds.variables.items():
        var.attrs.setdefault("long_name", name.replace("_", " "))


def cf_encode(ds, doc: dict, session_name: str):
    """``ds`` (from :func:`gonio.bench.dataset.export.to_dataset`) with CF-1.8 attributes and encodings.

    Parameters
    ----------
    ds : xarray.Dataset
        The dataset; changed in place and returned.
    doc : dict
        The session document (session.toml): versions, settings, plan.
    session_name : str
        The session folder's name, for ``history``.
    """
    _integers(ds)
    _saturated(ds)
    _long_names(ds)
    _labels(ds)
    sess = doc.get("session", {})
    version = str(sess.get("gonio", "unknown"))
    who = doc.get("settings", {}).get("session", {})
    simulated = "sample_truth" in doc
    now = datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
    ds.attrs.update({
        "Conventions": CF_CONVENTIONS,
        "title": f"BRDF of {who['sample_id']}" if who.get("sample_id") else ds.attrs.get("title", "gonio BRDF measurement"),
        "institution": str(who.get("institution") or ("gonio simulator (no laboratory)" if simulated
                                                        else "not recorded in the session's settings")),
        "source": f"gonio {version} camera-based gonioreflectometer"
                  + (" (simulated instrument)" if simulated else ""),
        "history": f"{now} gonio {version}: exported from the journal of session {session_name}",
        "references": REFERENCES,
        "comment": "f_r in sr^-1 without the cosine factor; brdf_std is the 1-sigma of shot and read noise, "
                   "scale_rel_std the reference certificate's fully correlated relative 1-sigma",
        "angle_units": "degree",
        "angle_convention": PHI_CONVENTION,
        "phi_convention": "phi from +x toward +y about the sample normal, as planned (not wrapped)",
        "colour_space": COLOUR_SPACE,
    })
    return ds
