"""dataset.nc, and a fit as NetCDF, in CF-1.8 (the NetCDF Climate and Forecast conventions,
https://cfconventions.org/Data/cf-conventions/cf-conventions-1.8/cf-conventions.html).

:func:`cf_encode` adds the global attributes of CF 2.6.2 and gonio's angle and colour
conventions; ``long_name`` and ``units`` on every variable (3.2); string coordinates as label
variables such as ``channel_label(channel, string1)`` (6.1, 2.2; named apart from their
dimension, chapter 5); 32-bit integers; ``saturated`` as a flag (3.5); and
``ancillary_variables`` linking every value to its uncertainties and flag (3.4), each of which
says in its ``long_name`` that it is a standard uncertainty (no CF standard name fits a
laboratory f_r, so no ``standard_error`` modifier can). The caller's global attributes
(:data:`GLOBAL_ATTRIBUTES`: CF's and ACDD 1.3's) replace gonio's defaults; a ``history`` given
keeps gonio's export line first. :func:`fit_netcdf` writes a fit file's table the same way
(``gonio convert FIT --to netcdf``).
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

__all__ = ["CF_CONVENTIONS", "GLOBAL_ATTRIBUTES", "cf_encode", "check_global_attributes", "fit_dataset_cf",
           "fit_netcdf", "parse_attributes"]

CF_CONVENTIONS = "CF-1.8"
ACDD_CONVENTIONS = "ACDD-1.3"

#: The global attributes a caller may set: CF-1.8 section 2.6.2, then the Attribute Convention
#: for Data Discovery 1.3's (highly) recommended ones (https://wiki.esipfed.org/ACDD_1.3).
CF_GLOBALS = ("title", "institution", "source", "history", "references", "comment")
ACDD_GLOBALS = ("summary", "keywords", "keywords_vocabulary", "id", "naming_authority", "license",
                "acknowledgement", "project", "program", "processing_level", "product_version", "date_created",
                "date_modified", "date_issued", "creator_name", "creator_email", "creator_url", "creator_type",
                "creator_institution", "contributor_name", "contributor_role", "publisher_name", "publisher_email",
                "publisher_url", "publisher_institution", "instrument", "instrument_vocabulary", "platform",
                "metadata_link")
GLOBAL_ATTRIBUTES = CF_GLOBALS + ACDD_GLOBALS
#: the longest value of a caller's attribute (a file header, not a document)
MAX_ATTRIBUTE_CHARS = 4000

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


#: a string coordinate ``channel`` (on its own dimension) is stored as ``channel_label``
LABEL_SUFFIX = "_label"


def _rename_labels(ds):
    """Each string coordinate on its own dimension (``channel``: R, G, B) as a label variable
    beside the dimension (``channel_label``): CF-1.8 chapter 5 recommends that a
    multidimensional coordinate (a char array) not be named like its dimension, and both CF
    checkers warn where it is. xarray reads it back as a coordinate on ``channel``; readers of
    the older layout are unaffected (`gonio.fitting.load_dataset` knows each colour space's
    channels)."""
    names = {n: f"{n}{LABEL_SUFFIX}" for n, v in ds.coords.items()
             if v.dims == (n,) and v.dtype.kind in ("U", "O", "S") and f"{n}{LABEL_SUFFIX}" not in ds.variables}
    return ds.rename_vars(names) if names else ds


def _labels(ds):
    """Text as fixed-length char arrays (CF-1.8 section 2.2)."""
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
    if "channel_label" in ds.variables:
        ds["channel_label"].attrs.update(long_name="colour channel (R, G, B: the camera's in brdf, linear sRGB's "
                                                   "in brdf_srgb)")
    if "xyz_label" in ds.variables:
        ds["xyz_label"].attrs.update(long_name="CIE 1931 tristimulus component (X, Y, Z)")
    for name, what in _ANGLES.items():
        if name in ds.variables:
            ds[name].attrs.update(long_name=what, units="degree")
            if name.startswith("phi"):
                ds[name].attrs["comment"] = PHI_CONVENTION
    for name, var in ds.variables.items():
        var.attrs.setdefault("long_name", name.replace("_", " "))
        if var.dtype.kind in ("i", "u") and "flag_values" not in var.attrs:
            var.attrs.setdefault("units", "1")          # indices and labels: counts, dimensionless


def check_global_attributes(attrs) -> dict:
    """The caller's global attributes, checked: known names (:data:`GLOBAL_ATTRIBUTES`; a
    misspelling is refused with the closest name), printable text of at most
    :data:`MAX_ATTRIBUTE_CHARS` characters (``history`` may hold line breaks). ValueError, one
    line, otherwise."""
    import difflib

    out = {}
    for key, value in dict(attrs or {}).items():
        if key not in GLOBAL_ATTRIBUTES:
            near = difflib.get_close_matches(str(key), GLOBAL_ATTRIBUTES, n=1)
            hint = f"did you mean {near[0]}? " if near else ""
            raise ValueError(f"unknown global attribute {str(key)[:40]!r}: {hint}give one of "
                             f"{', '.join(CF_GLOBALS)} (CF) or an ACDD-1.3 attribute such as summary, "
                             "creator_name, license")
        if not isinstance(value, str):
            raise ValueError(f"global attribute {key}: give text, not {type(value).__name__}")
        allowed = "\n" if key == "history" else ""
        if any((not ch.isprintable() and ch not in allowed) for ch in value):
            raise ValueError(f"global attribute {key}: the text holds a control character")
        if len(value) > MAX_ATTRIBUTE_CHARS or not value.strip():
            raise ValueError(f"global attribute {key}: give 1 to {MAX_ATTRIBUTE_CHARS} characters")
        out[key] = value
    return out


def parse_attributes(pairs) -> dict:
    """``["institution=NPL", "title=Gloss tile 7"]`` (the command line's ``--attr``) as a checked
    dict (:func:`check_global_attributes`)."""
    out = {}
    for pair in pairs or []:
        key, sep, value = str(pair).partition("=")
        if not sep or not key.strip():
            raise ValueError(f"--attr {str(pair)[:40]!r} is not KEY=VALUE (e.g. institution=\"NPL, Teddington\")")
        out[key.strip()] = value
    return check_global_attributes(out)


#: the variables that state a value's uncertainty or quality, by the value's name: suffixes
_UNCERTAINTY_SUFFIXES = ("_std", "_u", "_corr")


def _ancillary(ds, values, extra=None):
    """``ancillary_variables`` of each of ``values``: its ``<name>_std``, ``<name>_u``,
    ``<name>_u_*`` and ``<name>_corr`` and the names ``extra`` gives it (CF-1.8 section 3.4);
    each uncertainty among them says so in its ``long_name``."""
    for name in values:
        if name not in ds.variables:
            continue
        linked = [f"{name}{s}" for s in _UNCERTAINTY_SUFFIXES if f"{name}{s}" in ds.variables]
        linked += sorted(n for n in ds.variables if n.startswith(f"{name}_u_"))
        linked += [n for n in (extra or {}).get(name, ()) if n in ds.variables and n not in linked]
        if not linked:
            continue
        ds[name].attrs["ancillary_variables"] = " ".join(linked)
        for other in linked:
            if other.endswith("_corr") or "flag_values" in ds[other].attrs:
                continue
            text = str(ds[other].attrs.get("long_name", other.replace("_", " ")))
            if "uncertainty" not in text:
                ds[other].attrs["long_name"] = f"standard uncertainty of {name}: {text}"


def _globals(ds, defaults: dict, attrs) -> None:
    """CF's global attributes: gonio's ``defaults`` under the caller's ``attrs``; a caller's
    ``history`` follows gonio's line; ACDD-1.3 named in ``Conventions`` where one of its
    attributes is given."""
    given = check_global_attributes(attrs)
    merged = {**defaults, **given}
    if "history" in given:
        merged["history"] = f"{defaults['history']}\n{given['history']}"
    if any(k in ACDD_GLOBALS for k in given):
        merged["Conventions"] = f"{CF_CONVENTIONS} {ACDD_CONVENTIONS}"
    ds.attrs.update(merged)


def cf_encode(ds, doc: dict, session_name: str, attrs=None):
    """``ds`` (from :func:`gonio.bench.dataset.export.to_dataset`) with CF-1.8 attributes and encodings.

    Parameters
    ----------
    ds : xarray.Dataset
        The dataset; changed in place and returned (use the returned object: its labels are
        renamed).
    doc : dict
        The session document (session.toml): versions, settings, plan.
    session_name : str
        The session folder's name, for ``history``.
    attrs : dict, optional
        Global attributes of the caller (:data:`GLOBAL_ATTRIBUTES`, e.g. ``institution``),
        over gonio's defaults; ValueError, one line, for an unknown name or bad text.
    """
    ds = _rename_labels(ds)
    _integers(ds)
    _saturated(ds)
    _long_names(ds)
    _labels(ds)
    budget = str(ds["u_combined"].attrs.get("components", "")).split() if "u_combined" in ds.variables else []
    _ancillary(ds, ["brdf", "brdf_srgb", "brdf_xyz", "theta_i", "phi_i", "theta_o", "phi_o"],
               {"brdf": ["u_combined"] + [f"u_{c}" for c in budget] + ["saturated"],
                "brdf_srgb": ["saturated"], "brdf_xyz": ["saturated"]})
    sess = doc.get("session", {})
    version = str(sess.get("gonio", "unknown"))
    who = doc.get("settings", {}).get("session", {})
    simulated = "sample_truth" in doc
    now = datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
    _globals(ds, {
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
    }, attrs)
    return ds


# --------------------------------------------------------------------------- a fit as NetCDF
_FIT_NAMES = {
    "value": "fitted value of the parameter (the fit file's value: the estimate, corrected for a known "
             "systematic effect where the budget states one)",
    "std": "standard uncertainty (1-sigma) of value: the fit's statistical one (Laplace or sandwich covariance)",
    "u_stat": "standard uncertainty of value from the data's type-A (statistical) budget lines",
    "u_combined": "combined standard uncertainty u_c of value (the uncertainty budget, JCGM 100:2008)",
    "U": "expanded uncertainty U = k u_c of value (k: the global attribute k)",
    "ci90_low": "lower end of the 90 % interval of value",
    "ci90_high": "upper end of the 90 % interval of value",
    "lower": "lower bound of the parameter the model declares",
    "upper": "upper bound of the parameter the model declares",
    "flags": "what limits the parameter's statement (empty: nothing)",
    "correlation": "correlation coefficient of the combined uncertainties of two parameters",
    "unit": "unit of the parameter (of value and its uncertainties)",
    "parameter_label": "name of the fitted parameter ([R], [G], [B]: its colour channel)",
    "parameter_b_label": "name of the fitted parameter (the correlation's second axis)",
}
_FIT_FLAGS = {"at_bound": ("the value lies at a bound of the parameter", "within_bounds at_bound"),
              "undetermined": ("the data do not determine the parameter", "determined undetermined")}


def fit_dataset_cf(doc: dict, model=None, *, source_name: str = "fit.json", attrs=None):
    """A fit document's table (`gonio.fitting.statement.fit_to_xarray`: value, std, u_stat,
    u_combined, U, the 90 % interval, the bounds, the flags and the correlation over
    ``parameter``) as a CF-1.8 dataset: labels as ``parameter_label``, the booleans as CF flags,
    a ``long_name`` on every variable, each value linked to its uncertainties by
    ``ancillary_variables``, the global attributes (``attrs`` over gonio's defaults)."""
    from gonio.fitting.statement import fit_to_xarray

    ds = _rename_labels(fit_to_xarray(doc, model))
    for name, (what, meanings) in _FIT_FLAGS.items():
        ds[name] = ds[name].astype(np.int8)
        ds[name].attrs.update(long_name=what, flag_values=np.array([0, 1], np.int8), flag_meanings=meanings)
    units = {str(u) for u in np.ravel(ds["unit"].values)} if "unit" in ds.variables else set()
    for name, var in ds.variables.items():
        if name in _FIT_NAMES:
            var.attrs["long_name"] = _FIT_NAMES[name]
        var.attrs.setdefault("long_name", name.replace("_", " "))
        if name in ("value", "std", "u_stat", "u_combined", "U", "ci90_low", "ci90_high", "lower", "upper"):
            if len(units) == 1:
                var.attrs["units"] = next(iter(units))
            else:
                var.attrs["comment"] = "each parameter in its own unit: the variable unit"
    ds["correlation"].attrs["units"] = "1"
    _labels(ds)
    _ancillary(ds, ["value"], {"value": ["std", "u_stat", "u_combined", "U", "ci90_low", "ci90_high", "at_bound",
                                         "undetermined", "flags"]})
    prov = doc.get("provenance") if isinstance(doc.get("provenance"), dict) else {}
    version = str((prov.get("versions") or {}).get("gonio", "unknown"))
    spec = doc.get("model") if isinstance(doc.get("model"), dict) else {}
    options = spec.get("options") or {}
    opts = " ".join(f"{k}={v}" for k, v in sorted(options.items())) if isinstance(options, dict) else ""
    now = datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
    dataset = prov.get("dataset")
    _globals(ds, {
        "Conventions": CF_CONVENTIONS,
        "title": f"gonio fit: {spec.get('name', ds.attrs.get('model', '?'))} {opts}".strip(),
        "institution": "not recorded in the fit file",
        "source": f"gonio {version} fit" + (f" of {dataset}" if dataset else ""),
        "history": f"{now} gonio {version}: written from the fit file {source_name}",
        "references": "uncertainty: JCGM 100:2008 (GUM), JCGM 101:2008; fit file layout: gonio docs/interfaces.md "
                      "section 5.1; conventions: CF-1.8",
        "comment": "value +- u_combined is the parameter's statement; U = k u_combined; the fit file (JSON) holds "
                   "the rest (the optimiser, the constraints, the Mitsuba BSDF)",
    }, attrs)
    return ds


def fit_netcdf(fit_path, out, attrs=None):
    """Write the fit file ``fit_path``'s table as CF-1.8 NetCDF ``out`` (atomically: the old
    file, or the whole new one); returns the path. ValueError, one line, for a file that is not a
    gonio fit file or a bad global attribute."""
    from pathlib import Path

    from gonio.core.atomic import atomic_open
    from gonio.fitting.formats.fitfile import load_fit

    attrs = check_global_attributes(attrs)
    fit = load_fit(fit_path)
    ds = fit_dataset_cf(fit.document, fit.model, source_name=Path(fit_path).name, attrs=attrs)
    data = ds.to_netcdf(engine="h5netcdf")
    with atomic_open(out, "wb") as fh:
        fh.write(bytes(data))
    return Path(out)
