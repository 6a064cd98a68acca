"""Export a session's journal to ``dataset.nc`` (docs/interfaces.md section 5).

Dimensions ``point`` and ``channel`` (R, G, B); coordinates ``theta_i``, ``phi_i``, ``theta_o``,
``phi_o`` (degrees); variables ``brdf`` and ``brdf_std`` (sr^-1, 1-sigma), ``saturated``,
``reciprocal_partner`` (dataset index, -1 if none), ``plan_index``, the stage angles and a sequential
plan's ``design_weight`` (sr^2, gonio.bench.plan.design_weights); attributes ``gonio_version``,
``seed``, ``plan``, ``settings``, ``versions``, ``sample_truth`` (simulated sessions), ``scale_rel_std``
(the certificate's relative 1-sigma: a fully correlated scale uncertainty, not in ``brdf_std``),
``complete``, ``instrument_time_s`` (per point: ``instrument_time``). Transmitted points (theta_o > 90)
hold f_t by the open beam, whose record and ``sides`` are attributes. A calibrated session also has
``<angle>_nominal``, ``<angle>_u``, ``angle_calibration`` and ``aperture_*``. Where the RAW files carry
colour matrices, also ``brdf_srgb`` (linear sRGB, D65) and ``brdf_xyz`` (CIE XYZ) with their 1-sigma
and ``brdf_srgb_corr``, each saying its space (``colour_space``); a spectral session's are on ``point``
and ``wavelength`` (nm; `gonio.bench.dataset.spectral`). Written atomically and read back first
(every variable, its point count and values, or nothing); a damaged point row is refused.
"""

# A full disk is one line and leaves no partial file.

# Calibration: a session captured with a calibration ([alignment] in its settings,
# gonio.bench.measure.calpoint.dataset_angles) has the calibrated angles as coordinates and
# the nominal ones beside them; the aperture_* attributes are also written from an [aperture]
# table alone.
# Colour: the camera-RGB f_r is white-balanced by construction (the reference is spectrally
# flat and shares the illumination), so the camera -> sRGB matrix
# (gonio/bench/measure/colour_matrix.py: from a RAW file's ColorMatrix1, else LibRaw's
# journalled one) applies to it directly, and XYZ = M_sRGB->XYZ sRGB (IEC 61966-2-1). Camera
# channel noise is independent, so the sRGB channels' covariance is S diag(sigma^2) S^T. The
# attribute colour_matrix records the matrix and its source.
# Writing: serialised with xarray's h5netcdf engine in memory (h5py never writes to the disk:
# on a full disk it crashed the process), after a check that the disk has room for it; then
# written to a temporary name in the session folder, fsynced and renamed.

from __future__ import annotations

import errno
import json
import os
from pathlib import Path

import numpy as np

from gonio.bench.session import integrity as _integrity
from gonio.bench.dataset.budget import budget_variables, move_history, rear_rows
from gonio.bench.measure.transmission import journalled_open_beam
from gonio.bench.dataset.cf import cf_encode, check_global_attributes
from gonio.bench.dataset.spectral import COLOUR_SPACE as SPECTRAL_SPACE, spectral_variables
from gonio.bench.calibrate import dataset_angles, instrument_response
from gonio.core.files import commit_file, tmp_name
from gonio.bench.session.journal import RAW_DIR, preparation_times
from gonio.core.preflight import check_free_space, check_output_file, oserror_line
from gonio.bench.measure.colour_matrix import (ColourMatrix, colour_matrix_components, convert, matrix_from_chart_dng, matrix_from_dng, matrix_from_libraw)
from gonio.core.errors import GonioError, SessionError
from gonio.bench.plan.plans import find_partners
from gonio.bench.plan.design_weights import VARIABLE, dataset_variable, wanted

__all__ = ["export", "to_dataset", "DATASET_FILE"]

DATASET_FILE = "dataset.nc"



def to_dataset(session_dir, chart=None, attrs=None):
    """The session's journalled points as an `xarray.Dataset` (see the module docstring);
    ``chart``: a RAW capture of the ColorChecker whose fit gives the colour matrix instead of
    the RAW files' own (gonio/bench/measure/colour_matrix.matrix_from_chart_dng); ``attrs``:
    CF/ACDD global attributes (``institution``, ``title``, ...; `gonio.bench.dataset.cf`) over
    gonio's defaults."""
    import xarray as xr

    global_attrs = attrs
    folder = Path(session_dir)
    data, doc, why = _integrity.load_session(folder)
    if doc is None:
        raise SessionError(f"{folder / 'session.toml'} is not valid TOML ({why}); the session cannot be exported")
    # the same checks as a resume: session.toml as journalled, the journal whole, no unknown RAW file
    with _integrity.open_journal(folder, data, doc, why, write=False) as j:
        rows = j.points()
        open_beam, ob_info = journalled_open_beam(j.events(), j.frames("open_beam"), doc["settings"])
        rgb_cam = j.first_event("rgb_cam")
        charts = j.frames("chart")
        events = j.events()
        preparations = preparation_times(events)
    stopped = strategy_stop(events)
    if not rows:
        raise SessionError(f"{folder} has no measured point yet; resume the capture first")
    n_plan = len(doc["plan"]["points"])
    if doc["plan"].get("wavelength_nm") is not None:     # a spectral plan: brdf(point, wavelength)
        coords, data, monitor, point_s = spectral_variables(doc, rows)
        attrs = {**_attributes(doc, rows, n_plan, monitor, None, None, stopped),
                 **_instrument_time(point_s, preparations)}
        if isinstance(doc["settings"].get("aperture"), dict):      # the apertures a fit averages over
            attrs.update(instrument_response(doc["settings"]))
        ds = cf_encode(xr.Dataset(data, coords=coords, attrs=attrs), doc, folder.name, attrs=global_attrs)
        ds.attrs["colour_space"] = SPECTRAL_SPACE
        ds["wavelength"].encoding["_FillValue"] = None     # CF 2.5.1: a coordinate variable has none
        return ds
    idx = np.array([r["idx"] for r in rows], int)
    where = np.full(n_plan, -1, int)
    where[idx] = np.arange(len(idx))
    partner_plan = find_partners(np.asarray(doc["plan"]["points"], float))
    partner = np.array([where[p] if p >= 0 else -1 for p in partner_plan[idx]], int)
    deg = {"units": "degree"}
    coords = {
        "point": np.arange(len(rows)),
        "channel": ["R", "G", "B"],
        **{k: ("point", np.array([r[k] for r in rows], float), deg) for k in ("theta_i", "phi_i", "theta_o", "phi_o")},
    }
    sr = {"units": "sr^-1"}
    brdf = np.array([r["brdf"] for r in rows], float)
    std = np.array([r["brdf_std"] for r in rows], float)
    # a value journalled without a finite uncertainty (before the run dropped them: a region left
    # with one unsaturated pixel) is no measurement: NaN, as the run now records it
    brdf = np.where(np.isfinite(std), brdf, np.nan)
    data = {
        "brdf": (("point", "channel"), brdf,
                 {**sr, "long_name": "bidirectional reflectance distribution function f_r (no cosine factor)"}),
        "brdf_std": (("point", "channel"), std,
                     {**sr, "long_name": "standard uncertainty (1-sigma) of brdf from shot and read noise (the scale's: "
                           "scale_rel_std)"}),
        "saturated": ("point", np.array([bool(r["saturated"]) for r in rows]),
                      {"long_name": "some region pixel was saturated in every exposure (value less reliable)"}),
        "reciprocal_partner": ("point", partner, {"long_name": "index of the point with wi and wo swapped, -1 if none"}),
        "plan_index": ("point", idx, {"long_name": "index of the point in the session's plan"}),
        **{k: ("point", np.array([r[k] for r in rows], float), {**deg, "long_name": f"stage angle {k}"})
           for k in ("yaw", "tilt", "azimuth", "lamp")},
    }
    if wanted(doc.get("strategy")):         # a sequential plan's points: their share of the measure
        data[VARIABLE] = dataset_variable(*(coords[k][1] for k in ("theta_i", "phi_i", "theta_o", "phi_o")))
    monitor = np.array([float(r["detail"].get("p_start", np.nan)) for r in rows])
    data["monitor_power"] = ("point", monitor, {"units": "W", "long_name": "power-meter reading of the lamp "
                                                "monitor at the start of the point"})
    point_s = np.array([_seconds(r["detail"].get("instrument_s")) for r in rows])
    data["instrument_time"] = ("point", point_s, {
        "units": "s", "long_name": "instrument time of the point: the move to it, settling, its exposures and "
        "monitor readings, and any pause, from the end of the previous point's bracket (NaN: not recorded)"})
    # the per-point uncertainty budget, u_<component> and u_combined (gonio/bench/dataset/budget.py)
    rear = rear_rows(rows)
    used = {r["detail"].get("open_beam_sha256") for r, t in zip(rows, rear) if t} - {None}
    if rear.any() and (open_beam is None or used - {ob_info.get("sha256")}):
        raise SessionError(f"{folder}: {int(rear.sum())} transmitted point(s) but not the intact open-beam frame they "
                           f"were normalised by; see `gonio verify {folder}` and resume it, which measures them again")
    ob_attrs = open_beam.to_attrs() if rear.any() else {}
    if rear.any():
        data["brdf"][2]["long_name"] = ("bidirectional scattering distribution function: f_r (theta_o < 90) or f_t "
                                        "(theta_o > 90, normalised by the open beam), no cosine factor")
    data.update(budget_variables(rows, doc["settings"], data["brdf"][1], data["brdf_std"][1], open_beam=ob_attrs))
    data["brdf"][2]["colour_space"] = data["brdf_std"][2]["colour_space"] = "camera"
    if chart is None and charts:            # the session's own chart frame ([capture] colour_chart)
        chart = folder / next(iter(charts.values()))[1]
    matrix = matrix_from_chart_dng(chart) if chart is not None else _colour_matrix(folder, rgb_cam)
    if matrix is not None:
        data.update(_colour(matrix, data["brdf"][1], data["brdf_std"][1]))
        coords["xyz"] = ["X", "Y", "Z"]
    # a calibrated session (gonio capture --calibration): the true angles, their u, the apertures
    stage = np.stack([data[k][1] for k in ("yaw", "tilt", "azimuth", "lamp")], -1)
    cal_coords, cal_data, cal_attrs = dataset_angles(doc["settings"], stage, last_dir=move_history(rows)[1], rear=rear)
    coords.update(cal_coords)
    data.update(cal_data)
    if not cal_attrs and isinstance(doc["settings"].get("aperture"), dict):
        cal_attrs = instrument_response(doc["settings"])
    attrs = _attributes(doc, rows, n_plan, monitor, matrix, chart, stopped)
    attrs.update(_instrument_time(point_s, preparations))
    attrs.update(cal_attrs)
    if rear.any():                          # the transmitted points' normalisation (ASTM E2387)
        attrs.update(ob_attrs, sides=[s for s, on in (("reflect", not rear.all()), ("transmit", True)) if on])
    return cf_encode(xr.Dataset(data, coords=coords, attrs=attrs), doc, folder.name, attrs=global_attrs)


def strategy_stop(events) -> str | None:
    """Why the session's plan strategy stopped asking for points (its last ``strategy`` event's
    ``stopped_by``: budget, time, target, candidates), or None (a fixed plan, or not yet)."""
    last = None
    for _, kind, text in events:
        if kind == "strategy":
            try:
                last = json.loads(text).get("stopped_by")
            except (ValueError, AttributeError):
                last = None
    return None if last is None else str(last)


def scale_rel_std(value):
    """The ``scale_rel_std`` attribute: ``[reference] rel_std``, one number, or one per channel
    or wavelength (a 1-D float attribute) where the certificate gives several."""
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim > 1 or arr.size == 0 or not np.all(np.isfinite(arr)) or np.any(arr < 0):
        raise ValueError("[reference] rel_std must be one number >= 0 or a list of them (one per channel)")
    return float(arr) if arr.ndim == 0 else arr


def _attributes(doc, rows, n_plan, monitor, matrix, chart, stopped=None) -> dict:
    """The dataset's global attributes: versions, seed, plan and settings, the reference,
    completeness (every planned point, or a plan strategy that stopped: ``stopped``), the
    lamp's drift, the colour matrix and the simulated truth."""
    sess = doc.get("session", {})
    attrs = {
        "gonio_version": str(sess.get("gonio", "unknown")),
        "seed": int(sess.get("seed", -1)),
        "plan": json.dumps(doc["plan"], sort_keys=True),
        "settings": json.dumps(doc["settings"], sort_keys=True),
        "versions": json.dumps(sess, sort_keys=True),
        "scale_rel_std": scale_rel_std(doc["settings"]["reference"].get("rel_std", 0.0)),
        "reference_reflectance": json.dumps(doc["settings"]["reference"]["reflectance"]),
        "complete": int(len(rows) == n_plan or stopped is not None),
        # relative span of the monitor over the session: what normalisation had to correct
        "lamp_drift": float((np.nanmax(monitor) - np.nanmin(monitor)) / np.nanmedian(monitor))
        if np.any(np.isfinite(monitor)) and np.nanmedian(monitor) > 0 else 0.0,
        "capture_wall_s": float(max(r["finished"] for r in rows) - min(r["finished"] for r in rows)),
        "title": "gonio BRDF measurement",
    }
    if matrix is not None:
        attrs["colour_matrix"] = json.dumps({**matrix.describe(), "chart_file": None if chart is None else str(chart)},
                                            sort_keys=True)
    if "sample_truth" in doc:
        attrs["sample_truth"] = str(doc["sample_truth"]["json"])
    if stopped is not None:
        attrs["strategy_stopped_by"] = stopped
    return attrs


def _seconds(v) -> float:
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) and v >= 0 else np.nan


def _instrument_time(point_s: np.ndarray, preparations) -> dict:
    """``instrument_time_s`` (the session's instrument time: every run's preparation and every
    kept point's time, as the simulator's clock or the rig measured it), its preparation part
    and a comment saying what it counts; NaN, said so, where a point's time is not recorded."""
    prep = float(sum(s for _, s in preparations))
    missing = int(np.sum(~np.isfinite(point_s)))
    total = prep + float(np.sum(point_s)) if not missing else np.nan
    what = ("instrument_time_s: seconds of instrument time (motion, settling, exposures, monitor readings and "
            "pauses, by the simulator's clock or the rig's) of every run's preparation (homing, dark and flat "
            f"frames, lamp on: instrument_time_preparation_s, {len(preparations)} run(s)) and of each point in the "
            "dataset (variable instrument_time); a point cut short by a stop and superseded rows are not counted")
    if missing:
        what += f"; NaN: {missing} point(s) were journalled by a gonio that did not record their time"
    return {"instrument_time_s": total, "instrument_time_preparation_s": prep, "instrument_time_comment": what}


def _colour_matrix(folder: Path, rgb_cam):
    """The camera -> sRGB matrix: a RAW file's own ColorMatrix1, else LibRaw's journalled
    ``rgb_cam``, else None (gonio/bench/measure/colour_matrix.py)."""
    for raw in sorted((folder / RAW_DIR).glob("*.dng")) if (folder / RAW_DIR).is_dir() else ():
        if not raw.name.startswith("."):
            found = matrix_from_dng(raw)
            if found is not None:
                return found
            break
    return None if rgb_cam is None else matrix_from_libraw(np.asarray(json.loads(rgb_cam), float))


def _colour(matrix: ColourMatrix, f: np.ndarray, sd: np.ndarray) -> dict:
    """``brdf_srgb``, ``brdf_xyz``, their 1-sigma and the sRGB channel correlation from
    white-balanced camera-RGB f_r (N, 3)."""
    out = {}
    sr = {"units": "sr^-1"}
    for name, dim, what in (("srgb", "channel", "linear sRGB (D65)"), ("xyz", "xyz", "CIE XYZ (D65)")):
        value, std, cov = convert(f, sd, matrix, name)
        space = {"colour_space": name, "colour_matrix_source": matrix.source}
        out[f"brdf_{name}"] = (("point", dim), value, {**sr, **space, "long_name": f"f_r in {what}"})
        out[f"brdf_{name}_std"] = (("point", dim), std, {**sr, **space, "long_name": f"standard uncertainty (1-sigma) of "
                                                         f"brdf_{name} from the camera noise (colour matrix "
                                                         "uncertainty not included)"})
        if name == "srgb":
            pairs = ((1, 2), (0, 2), (0, 1))
            corr = np.stack([cov[:, a, b] / np.maximum(std[:, a] * std[:, b], 1e-300) for a, b in pairs], 1)
            out["brdf_srgb_corr"] = (("point", "channel"), corr, {
                "units": "1", "long_name": "correlation of brdf_srgb's other two channels' noise (R: G-B, "
                "G: R-B, B: R-G), from the colour matrix mixing independent camera channels"})
    parts = colour_matrix_components(f, matrix, "srgb")
    if parts:                   # a chart fit's uncertainty: its budget lines (gonio/fitting/uncertainty/budget.py reads them)
        out["brdf_srgb_u_colour_matrix"] = (("point", "channel", "colour_input"), np.stack(parts, -1), {
            **sr, "gum_type": "B", "correlation": "full", "colour_space": "srgb",
            "source": f"colour matrix from a {matrix.source} fit: row covariance and prediction error",
            "long_name": "standard uncertainty of brdf_srgb from the colour matrix (signed: the change for +1 "
                         "sigma of each of its independent inputs)"})
    return out


def export(session_dir, chart=None, attrs=None) -> Path:
    """Write ``session_dir/dataset.nc`` from the journal; return its path. ``attrs``: CF/ACDD
    global attributes (``institution``, ``title``, ``comment``, ...) over gonio's defaults.

    Raises
    ------
    SessionError
        Not a session folder, or no point measured yet.
    GonioError
        An unknown global attribute or one that is not plain text (before anything is read).
    """
    folder = Path(session_dir)
    try:
        attrs = check_global_attributes(attrs)
    except ValueError as exc:
        raise GonioError(str(exc)) from None
    ds = to_dataset(folder, chart, attrs)
    path = folder / DATASET_FILE
    check_output_file(path, "dataset")
    check_free_space(folder, estimated_bytes(ds), f"{path} (its estimated size)")
    data = _serialise(ds)                           # in memory: bytes (a memoryview)
    _check_read_back(data, ds, path)
    check_free_space(folder, len(data), f"{path} ({len(data) / 2 ** 20:.1f} MiB)")
    tmp = tmp_name(path)
    try:
        with open(tmp, "wb") as fh:
            fh.write(data)
        commit_file(tmp, path)
    except OSError as exc:
        raise GonioError(oserror_line(OSError(exc.errno or errno.EIO, exc.strerror or str(exc), str(path)))) from None
    finally:
        if os.path.lexists(tmp):
            os.unlink(tmp)
    return path


def _serialise(ds):
    """The NetCDF-4 bytes of ``ds``, every array stored with HDF5's Fletcher-32 checksum filter,
    so a damaged block of dataset.nc is an error when it is read, never a value."""
    for v in ds.variables.values():
        if v.ndim:
            v.encoding["fletcher32"] = True
    return ds.to_netcdf(engine="h5netcdf")


def _check_read_back(data, ds, path: Path) -> None:
    """Read the serialised file back from memory: every variable of ``ds``, with as many points
    and the same values (NaN where NaN); `GonioError` naming the first difference otherwise."""
    import io

    import xarray as xr

    want = int(ds.sizes.get("point", 0))
    try:
        with xr.open_dataset(io.BytesIO(bytes(data)), engine="h5netcdf") as back:
            got = int(back.sizes.get("point", 0))
            problem = f"{got} point(s) of the {want} written" if got != want else ""
            for name in ds.variables if not problem else ():
                a = np.asarray(ds[name].values)
                if name not in back.variables:
                    problem = f"no variable {name}"
                    break
                b = np.asarray(back[name].values)
                nan = a.dtype.kind in "fc" and b.dtype.kind in "fc"
                if a.shape != b.shape or not np.array_equal(a, b, equal_nan=nan):
                    problem = f"other values of {name} than were written"
                    break
    except (OSError, ValueError, TypeError, KeyError, RuntimeError) as exc:
        problem = f"an unreadable file ({' '.join(str(exc).split())[:200]})"
    if problem:
        raise GonioError(f"{path} was not written: the NetCDF serialisation reads back {problem}; nothing was "
                         "changed (a fault in the NetCDF writer: report it with the versions of xarray, h5netcdf "
                         "and h5py)")


def estimated_bytes(ds) -> int:
    """An upper estimate of the netCDF-4 file of ``ds``: its arrays, its attributes and about
    4 KiB of HDF5 structure per variable (a quick plan's file is 37 KB for 10 KB of values)."""
    attrs = sum(len(str(v)) for v in ds.attrs.values())
    names = list(ds.variables)
    attrs += sum(len(str(v)) for n in names for v in ds[n].attrs.values())
    return int(ds.nbytes) + attrs + 4096 * len(names) + (64 << 10)
