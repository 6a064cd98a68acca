"""One self-contained HTML report of a session: capture, fit, and the Mitsuba loop closure.

The report reads what the other commands wrote (``dataset.nc``, ``fit.json``, ``speed.json``,
``render/render.json``, ``render/preview/preview.json``) and embeds matplotlib PNGs as
base64, so the single file reads offline; the PNGs are also written beside it for reuse.

It treats every one of those files as hostile (gonio/bench/report/inputs.py): it reads only files
that resolve inside the output folder, refuses a file reference that points out of it and a
field of the wrong type with one line (:class:`GonioError`, exit status 2) before it writes
anything, and builds the page from one Jinja2 template with autoescape: each section is a
function below that returns plain values (strings, numbers, lists), never HTML.
"""

from __future__ import annotations

import base64
import hashlib
import json
import os
from pathlib import Path

import numpy as np

from gonio.core.hdf5check import check_hdf5
from gonio.fitting import DataError, load_dataset, parse_fit
from gonio.core.atomic import atomic_open
from gonio.core.files import sha256_file

from gonio.bench.report import certificate as cert
from gonio.bench.report import fitdoc as _fitdoc
from gonio.bench.report import figures as figs
from gonio.bench.report import meta
from gonio.bench.report.fitdoc import as_fitted, truth_for
from gonio.bench.report.inputs import MAX_IMAGE_BYTES, PNG_MAGIC, Doc, Folder, cut, show
from gonio.bench.report.view import view_data
from gonio.core.errors import GonioError

__all__ = ["find_outputs", "write_report"]

TEMPLATES = Path(__file__).with_name("templates")
FIX_FIT = "re-run `gonio fit DATASET --out FIT.json`"
FIX_RENDER = "re-run `gonio render FIT.json --dataset DATASET --out DIR/render`"
FIX_PREVIEW = "re-run `gonio render FIT.json --dataset DATASET --out DIR/render --preview`"
FIX_SPEED = "re-run `gonio demo` or delete speed.json"


def find_outputs(folder) -> dict:
    """Locate the dataset, fit file and render summary under ``folder`` (inside it only)."""
    root = Folder(folder)
    folder = root.path

    def first(*patterns):
        for pattern in patterns:
            hits = sorted(folder.glob(pattern))
            if hits:
                return hits[0]
        return None

    found = {"dataset": first("dataset.nc", "*/dataset.nc"), "fit": first("fit.json", "*/fit.json"),
             "render": first("render/render.json", "render.json", "*/render.json"),
             "preview": first("render/preview/preview.json", "preview/preview.json", "*/preview/preview.json"),
             "speed": first("speed.json", "*/speed.json"),
             "journal": first("journal.sqlite", "session/journal.sqlite", "*/journal.sqlite")}
    if found["dataset"] is None:
        raise GonioError(f"no dataset.nc under {folder}; run `gonio export SESSION` first")
    for key, path in found.items():
        if path is not None:
            root.check(path, "input file")
    return found


def _fmt(v, digits=4) -> str:
    """A value as plain text for the template (which escapes it); never HTML."""
    if v is None:
        return "–"
    if isinstance(v, np.ndarray):
        v = v.tolist()
    if isinstance(v, (list, tuple)):
        return cut("[" + ", ".join(_fmt(x, digits) for x in v[:50]) + (", ..." if len(v) > 50 else "") + "]")
    if isinstance(v, (bool, np.bool_)):
        return str(bool(v))
    if isinstance(v, (float, np.floating)):
        return f"{float(v):.{digits}g}"
    return cut(str(v))


def _plan_text(plan):
    if not plan:
        return None
    try:
        doc = json.loads(plan) if isinstance(plan, str) else plan
    except (ValueError, RecursionError):
        return cut(str(plan), 200)
    if not isinstance(doc, dict):
        return cut(str(plan), 200)
    points = doc.get("points") or doc.get("angles") or []
    n = len(points) if isinstance(points, (list, tuple)) else "?"
    return cut(f"{doc.get('name', '?')}: {n} points. {doc.get('description', '')}".strip())


def _truth_text(truth):
    if not isinstance(truth, dict):
        return None
    try:
        return cut(f"{truth.get('model', truth.get('bsdf_file', '?'))} {json.dumps(truth.get('options', {}))} "
                   f"{json.dumps(truth.get('params', {}))}")
    except (ValueError, TypeError, RecursionError):
        return None


def _reciprocity(dataset_path, meas):
    """Median relative difference between reciprocal partners (wi and wo swapped), or None."""
    partner = _partners(dataset_path, meas.n_points)
    if partner is None:
        return None
    i = np.where((partner > np.arange(partner.size)) & (partner < partner.size))[0]
    if i.size == 0:
        return None
    a, b = meas.brdf[i], meas.brdf[partner[i]]
    rel = np.abs(a - b) / np.maximum(0.5 * np.abs(a + b), 1e-12)
    return f"{float(np.median(rel)):.2e} over {i.size} pairs (max {float(rel.max()):.2e})"


# --------------------------------------------------------------------------- sections
def capture_section(meas, dataset_path) -> dict:
    attrs = meas.attrs
    rows = [("points", meas.n_points), ("usable values", meas.n_used), ("seed", attrs.get("seed")),
            ("plan", _plan_text(attrs.get("plan"))), ("sample (simulated truth)", _truth_text(attrs.get("sample_truth"))),
            ("reciprocity (median |f_a - f_b| / mean over pairs)", _reciprocity(dataset_path, meas)),
            ("capture wall time, first to last point (s)", attrs.get("capture_wall_s")),
            ("instrument time: motion, settling, exposures, preparation (s)", attrs.get("instrument_time_s")),
            ("lamp drift over the session (monitor span / median)", attrs.get("lamp_drift")),
            ("reference scale uncertainty (relative 1-sigma)", attrs.get("scale_rel_std")),
            ("gonio version", attrs.get("gonio_version"))]
    return {"rows": [(k, _fmt(v)) for k, v in rows if v is not None]}


def fit_section(fit: Doc, truth) -> dict:
    spec = fit.need("model")
    name = spec.text("name", required=True)
    params = fit.items("parameters")
    truths = truth_for(truth, name, [k for k, _ in params])
    rows = []
    # the fit file's one statement (gonio.fitting.display.uncertainty_rows): z against u_c, the
    # flags as the file states them
    from gonio.fitting.display import FLAGS

    unc = fit.raw("uncertainty") if isinstance(fit.raw("uncertainty"), dict) else {}
    per = unc.get("parameters") if isinstance(unc.get("parameters"), dict) else {}
    for pname, p in params:
        value, std, t = p.num("value"), p.num("std"), truths.get(pname)
        q = per.get(pname) if isinstance(per.get(pname), dict) else {}
        u_c = p.num("u_combined")
        if u_c is None and isinstance(q.get("u_combined"), (int, float)):
            u_c = float(q["u_combined"])
        u_c = std if u_c is None else u_c
        z = (value - t) / u_c if (t is not None and value is not None and u_c) else None
        listed = p.raw("flags") if isinstance(p.raw("flags"), list) else [
            f for f in ("at_bound", "undetermined") if p.flag(f)]
        flags = ", ".join(FLAGS.get(str(f), cut(str(f), 40)) for f in listed)
        rows.append({"name": cut(pname, 80), "value": _fmt(value), "std": _fmt(std, 2), "u_c": _fmt(u_c, 2),
                     "ci90": _fmt(p.numbers("ci90"), 7),
                     "truth": _fmt(t), "z": _fmt(z, 2), "unit": p.text("unit") or "", "method": p.text("method") or "",
                     "flags": flags})
    g, opt = fit.need("goodness"), fit.need("optimiser")
    nulled = fit.raw("non_finite") if isinstance(fit.raw("non_finite"), list) else []
    energy = fit.need("constraints").need("energy")
    energy_text = _fitdoc.energy_text({"by_construction": energy.flag("by_construction"), "holds": energy.flag("holds"),
                                "max_albedo": energy.num("max_albedo")})
    out = {"model": name, "options": spec.json_text("options"), "rows": rows,
           "chi2_dof": _fmt(g.num("chi2_dof")), "dof": _fmt(g.count("dof")), "rmse_fr": _fmt(g.num("rmse_fr")),
           "rmse_cos_fr": _fmt(g.num("rmse_cos_fr")), "method": opt.text("method") or "–",
           "evaluations": _fmt(opt.count("evaluations")), "time_s": _fmt(opt.num("time_s"), 3), "energy": energy_text,
           "non_finite": cut(", ".join(x for x in nulled if isinstance(x, str))),
           # a poor fit says so beside its intervals (Birge-inflated or discrepancy ones)
           "warning": cut(g.text("warning") or "", 400) or (
               "" if g.raw("model_adequate") is not False else
               f"chi2/dof = {_fmt(g.num('chi2_dof'))}: the model misses the data by more than its noise; "
               "the 1-sigma values are statistical only")}
    out["shared_angles"] = _shared_angles_text(fit.sub("shared_angles"))
    post = fit.sub("posterior")
    out["posterior"] = None if post is None else {
        "walkers": _fmt(post.count("walkers")), "steps": _fmt(post.count("steps")),
        "independent": _fmt(post.num("independent_samples"), 3), "converged": str(post.flag("converged")),
        "advice": post.text("advice") or ""}
    out["selection"] = [{"model": r.text("model", required=True), "options": r.json_text("options"),
                         "k": _fmt(r.count("k")), "chi2": _fmt(r.num("chi2")), "delta_bic": _fmt(r.num("delta_bic"), 3),
                         "chosen": "yes" if r.flag("chosen") else ""} for r in fit.rows("selection")]
    return out


def _shared_angles_text(sa: "Doc | None") -> str:
    """The fit file's ``shared_angles`` as ``gonio fit`` prints it
    (:func:`gonio.fitting.display.shared_angles_line`), its values read through the typed
    :class:`Doc` ("" without it): what the estimate found and how sure it is, or why it was not
    applied."""
    from gonio.fitting.display import shared_angles_line

    if sa is None:
        return ""
    if not sa.flag("applied"):
        record = {"applied": False, "reason": sa.text("reason", limit=400) or "no reason recorded"}
    else:
        est, post = sa.numbers("estimate_sigma"), sa.numbers("posterior_sigma")
        if not est or not post:
            sa.refuse("estimate_sigma" if not est else "posterior_sigma", "a non-empty list of numbers")
        record = {"applied": True, "inputs": sa.count("inputs", required=True), "estimate_sigma": est,
                  "posterior_sigma": post, "max_direction_change_deg": sa.num("max_direction_change_deg")}
    line = shared_angles_line({"shared_angles": record})
    return cut(line[:1].upper() + line[1:] + ".", 600)


def posterior_samples(fit: Doc):
    """(samples (N, k), names, converged) for the corner plot, or None; refuse malformed ones."""
    post = fit.sub("posterior")
    if post is None or not post.raw("samples"):
        return None
    raw, names = post.raw("samples"), post.raw("names")
    try:
        samples = np.asarray(raw, dtype=float) if isinstance(raw, list) and len(raw) <= 100_000 else None
    except (ValueError, TypeError):
        samples = None
    if samples is None or samples.ndim != 2 or samples.shape[1] > 64 or not np.all(np.isfinite(samples)):
        post.refuse("samples", "a table of finite numbers (draws x parameters)", raw)
    if names is not None and (not isinstance(names, list) or len(names) != samples.shape[1]
                              or not all(isinstance(n, str) for n in names)):
        post.refuse("names", f"a list of {samples.shape[1]} names", names)
    return samples, names, post.flag("converged")


def speed_section(sp: Doc) -> dict:
    return {"points": _fmt(sp.count("points")), "model": sp.text("model") or "–",
            "rows": [{"optimiser": r.text("optimiser") or "–", "time_s": _fmt(r.num("time_s"), 3),
                      "evaluations": _fmt(r.count("evaluations")), "chi2": _fmt(r.num("chi2")),
                      "max_pull": _fmt(r.num("max_pull"), 3), "rmse_fr": _fmt(r.num("rmse_fr"), 3)}
                     for r in sp.rows("rows")]}


def render_section(rd: Doc, meas) -> tuple[dict, np.ndarray]:
    sc, s = rd.sub("scene_check") or Doc({}, rd.label, "scene_check", fix=rd.fix), rd.need("summary")
    section = {"variant": rd.text("variant") or "–", "points": _fmt(rd.count("points")), "time_s": _fmt(rd.num("time_s"), 3),
               "poses": _fmt(sc.count("poses") or 0), "scene_variant": sc.text("variant") or "None",
               "max_rel": _fmt(sc.num("max_rel"), 2), "export_max_rel": _fmt(s.num("export_max_rel")),
               "rms": _fmt(s.num("residual_rms_sigma"), 3), "max": _fmt(s.num("residual_max_sigma"), 3),
               "worst": [{"point": _fmt(w.count("point")), **{k: _fmt(w.num(k), 3) for k in
                                                              ("theta_i", "phi_i", "theta_o", "phi_o", "residual_sigma")}}
                         for w in s.rows("worst", limit=1000)]}
    raw = rd.raw("brdf_render")
    try:
        rendered = np.asarray(raw, dtype=float) if isinstance(raw, list) else None
    except (ValueError, TypeError):
        rendered = None
    if rendered is None or rendered.ndim != 2 or rendered.shape[1] < 1:
        rd.refuse("brdf_render", "a table of numbers (points x channels)", raw)
    if rendered.shape[0] != meas.n_points:
        raise GonioError(f"{rd.label} holds {rendered.shape[0]} rendered points, the dataset {meas.n_points}: "
                         f"it was rendered from another capture; {rd.fix}")
    return section, rendered


def preview_section(pv: Doc, root: Folder, path: Path) -> tuple[dict, bytes | None]:
    rows = [{"lighting": cut(k, 80), "mean": _fmt(v.num("mean"), 3), "p95": _fmt(v.num("p95"), 3),
             "noise": _fmt(v.num("noise_mean"), 3)} for k, v in pv.items("delta_e")]
    images = pv.raw("images") if isinstance(pv.raw("images"), dict) else {}
    # `gonio render --preview --measured FILE` renders the measured BSDF beside the fit and the
    # CIEDE2000 difference; without --measured the previews are the fit's alone
    measured = bool(rows) or any(isinstance(v, dict) and v.get("measured_png") for v in images.values())
    section = {"size": _fmt(pv.count("size")), "spp": _fmt(pv.count("spp")), "variant": pv.text("variant") or "None",
               "time_s": _fmt(pv.num("time_s"), 3), "note": None, "measured": measured, "rows": rows}
    section["tiles"] = _preview_tiles(images, root, path, measured)
    side = pv.raw("side_by_side_png")
    if side is None:
        return section, None
    real = root.reference(side, path, "side_by_side_png", fix=FIX_PREVIEW)
    if real is None:
        section["note"] = (f"The side-by-side image that {root.label(path)} names ({cut(str(side), 200)}) is missing "
                           "from the folder; re-run the preview to include it.")
        return section, None
    data = root.read_bytes(real, "side_by_side_png", MAX_IMAGE_BYTES)
    if not data.startswith(PNG_MAGIC):
        raise GonioError(f"{root.label(path)}: side_by_side_png {show(side)} is not a PNG image; {FIX_PREVIEW}")
    return section, data


#: the largest preview tile the report decodes (pixels a side; `gonio render` allows 2048)
MAX_TILE = 2048


def _preview_tiles(images: dict, root: Folder, path: Path, measured: bool) -> list | None:
    """The preview's own images, by lighting ([(lighting, {"model_png": PNG bytes, ...})]), for
    the report to compose them with print-sized titles (figures.preview); None, and the
    side-by-side image stays, when any is missing, names a file outside the folder (nothing is
    opened then), is not a PNG or is larger than :data:`MAX_TILE`."""
    import struct

    keys = ("model_png", "measured_png", "delta_e_png") if measured else ("model_png",)
    tiles = []
    for lighting, entry in list(images.items())[:4]:
        if not isinstance(entry, dict):
            return None
        tile = {}
        for key in keys:
            try:
                real = root.reference(entry.get(key), path, f"images.{key}", fix=FIX_PREVIEW)
                data = root.read_bytes(real, f"images.{key}", MAX_IMAGE_BYTES) if real is not None else b""
            except GonioError:
                return None
            if not data.startswith(PNG_MAGIC) or len(data) < 24 or data[12:16] != b"IHDR" or \
                    not 0 < max(struct.unpack(">II", data[16:24])) <= MAX_TILE:
                return None
            tile[key] = data
        tiles.append((cut(str(lighting), 40), tile))
    return tiles or None


def mitsuba_section(model, params, fit: Doc) -> dict:
    from gonio.fitting.formats import mitsuba_snippet

    xml, _ = mitsuba_snippet(model.name, dict(model.options), params)
    try:
        as_json = json.dumps(fit.raw("mitsuba"), indent=1)
    except (ValueError, TypeError, RecursionError):
        fit.refuse("mitsuba", "a plain JSON object", fit.raw("mitsuba"))
    return {"xml": xml, "dict": cut(as_json, 20_000)}


# --------------------------------------------------------------------------- the report
def _check_out(out: Path) -> Path:
    """The report's figure folder, after checking that both can be written; refuse otherwise."""
    image_dir = out.with_name(out.stem + "_files")
    if out.is_dir():
        raise GonioError(f"--out {out} is a folder; give a file name such as {out / 'report.html'}")
    parent = out.parent if str(out.parent) else Path(".")
    probe = next((p for p in (parent, *parent.parents) if p.exists()), None)
    if probe is None or not probe.is_dir() or not os.access(probe, os.W_OK | os.X_OK):
        raise GonioError(f"cannot write the report in {parent}: not a writable folder; choose another --out")
    if image_dir.is_symlink() or (image_dir.exists() and not image_dir.is_dir()):
        raise GonioError(f"{image_dir} exists and is not a plain folder (a link or a file); remove it and run again")
    return image_dir


def _load_dataset(root: Folder, path: Path):
    root.check(path, "dataset")
    check_hdf5(path, root.label(path))      # a damaged file can loop in HDF5 for ever: walked first, in a child
    try:
        return load_dataset(path)
    except DataError:
        raise
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise GonioError(f"{root.label(path)} is not a readable gonio dataset ({' '.join(str(exc).split())[:160]}); "
                         "re-export the session with `gonio export SESSION`") from None


def _load_fit(root: Folder, path: Path):
    fit = root.read_json(path, "fit file", fix=FIX_FIT, strict=True)
    try:
        model, params, _ = parse_fit(fit.data, root.label(path))
    except (ValueError, KeyError, TypeError) as exc:
        raise GonioError(f"{' '.join(str(exc).split())[:300]}; {FIX_FIT}") from None
    return fit, model, params


CAPTIONS = {
    "inplane.png": "Measured f_r (dots, 1-sigma bars) and the fit (lines) in the plane of incidence at up to four "
                   "incidence angles; theta_o negative on the lamp's side, positive on the mirror side; one colour "
                   "per camera channel. Where the sample transmits, the whole plane: |theta_o| > 90 (shaded) is "
                   "the transmitted side, 180 - theta_i straight through.",
    "polar.png": "At the incidence with the most out-of-plane points. Left: the fitted lobe over the hemisphere "
                 "(background) and the measured values (dots) on the same logarithmic colour scale. Right: measured "
                 "/ fit per point. Radius theta_o (deg), angle phi_o.",
    "polar_transmitted.png": "The transmitted side, at the incidence with the most out-of-plane transmitted points: "
                             "the fitted BTDF (background) and the measured values (dots) on the same logarithmic "
                             "colour scale, and measured / fit per point. Radius 180 - theta_o (deg: 0 is straight "
                             "through a normal beam), angle phi_o.",
    "residuals.png": "Left: histogram of (measured - fit) / sigma over every value used in the fit. Right: the rms "
                     "normalised residual of each point, by incidence and outgoing angle.",
    "albedo.png": "Directional albedo of the fit against theta_o, one curve per channel; above 1 would violate "
                  "energy conservation. For a model that transmits: its reflectance R (dashed), transmittance T "
                  "(dotted) and R + T (solid) against theta_i.",
    "measured.png": "Measured f_r (dots, 1-sigma bars) in the plane of incidence at up to four incidence angles; "
                    "theta_o negative on the lamp's side; one colour per camera channel. No fit in the folder.",
    "coverage.png": "The measured directions: radius theta_o (deg), angle phi_o, colour theta_i.",
    "corner.png": "Posterior samples (emcee) of the parameters, each as its offset from the posterior median in the "
                  "unit its axis names; dashed: the 5, 50 and 95 % quantiles.",
    "mitsuba_vs_measured.png": "Mitsuba 3's render of the fitted BSDF at each measured geometry against the measured "
                               "value (log-log, one colour per channel); dashed: equality.",
    "preview_side_by_side.png": "Sphere previews rendered by Mitsuba 3, one row per lighting: the fitted model "
                                "(left), the measured BSDF given to `gonio render --measured` (the demo gives the "
                                "simulated sample's true BSDF) and their CIEDE2000 difference.",
}
#: the preview's caption when `gonio render --preview` ran without --measured: the fit alone
PREVIEW_FIT_ONLY = ("Sphere previews of the fitted model rendered by Mitsuba 3, one per lighting; no measured BSDF "
                    "was given to `gonio render --preview --measured FILE`, so there is nothing beside them to compare.")
ORDER = ["inplane.png", "polar.png", "polar_transmitted.png", "residuals.png", "albedo.png", "measured.png", "coverage.png", "corner.png",
         "mitsuba_vs_measured.png", "preview_side_by_side.png"]


def _figures(images: dict, captions: dict | None = None) -> dict:
    """Each PNG with its number (in the page's order), caption, alt text and printed width.

    The width (CSS px, 96 a printed inch) is the figure's own size (its pixels at the dpi it was
    drawn at, figures.DPI), so a figure prints at the size its fonts were chosen for
    (figures.legible), never enlarged, and is scaled down only to the page's width."""
    captions = {**CAPTIONS, **(captions or {})}
    names = [n for n in ORDER if n in images] + [n for n in images if n not in ORDER]
    return {name: {"b64": base64.b64encode(images[name]).decode("ascii"), "number": k + 1,
                   "caption": captions.get(name, name), "alt": f"{name}: {captions.get(name, name)[:100]}",
                   "width": figs.css_width(images[name])}
            for k, name in enumerate(names)}


def _partners(dataset_path, n):
    """The dataset's reciprocal_partner index (int64), or None when absent or malformed."""
    import xarray as xr

    try:
        with xr.open_dataset(dataset_path, engine="h5netcdf") as ds:
            if "reciprocal_partner" not in ds.variables:
                return None
            partner = np.asarray(ds["reciprocal_partner"].values, dtype=float)
    except (OSError, ValueError, TypeError, KeyError):
        return None
    if partner.shape != (n,) or not np.all(np.isfinite(partner)):
        return None
    return partner.astype(np.int64)


def _draw_all(meas, model, params, samples, rendered, side, notes, preview=None, progress=None, fitted=None) -> dict:
    """Every figure the inputs allow, one ``figs.draw`` each; the fit against ``fitted`` (the data
    as it was fitted, default ``meas``); ``progress(done, total, label)`` before each (the
    report's slowest part: 7-15 s in all)."""
    images: dict[str, bytes] = {}
    jobs = []
    if model is not None:
        for name, fn in (("inplane.png", figs.inplane), ("polar.png", figs.polar), ("residuals.png", figs.residuals)):
            jobs.append((name, fn, (meas if fitted is None else fitted, model, params)))
        jobs.append(("albedo.png", figs.albedo, (model, params)))
    else:
        jobs.append(("measured.png", figs.inplane, (meas,)))
    jobs.append(("coverage.png", figs.coverage, (meas,)))
    if samples is not None:
        jobs.append(("corner.png", figs.corner_plot, tuple(samples)))
    if rendered is not None:
        jobs.append(("mitsuba_vs_measured.png", figs.mitsuba_vs_measured, (meas if fitted is None else fitted, rendered)))
    if preview is not None and preview.get("tiles"):
        # the preview's images composed with titles that print at 8 pt or more (the side-by-side
        # PNG `gonio render` writes is 9.6 in wide: its titles printed at 6.7 pt on A4)
        jobs.append(("preview_side_by_side.png", figs.preview, (preview["tiles"], preview["rows"])))
    for k, (name, fn, args) in enumerate(jobs):
        if progress is not None:
            progress(k, len(jobs), f"figure {name[:-4]}")
        figs.draw(images, notes, name, fn, *args)
    if progress is not None:
        progress(len(jobs), len(jobs), "the page")
    if side is not None and "preview_side_by_side.png" not in images:
        images["preview_side_by_side.png"] = side
    return images


def certificate_section(meas, root: Folder, found: dict, fit: Doc | None, *, approver=None, role=None,
                        issued=None) -> dict:
    """The certificate's own fields (gonio/bench/report/certificate.py): number, issue date,
    laboratory, customer, method, conditions, data files with their SHA-256, budget table,
    traceability, statements and approval."""
    settings = meta._json_attr(meas.attrs, "settings")
    date = cert.issue_date(issued)
    files = []
    for key, what in (("dataset", "data file"), ("fit", "fit file")):
        if found.get(key) is not None:
            real = root.check(found[key], what)
            files.append({"what": what, "name": root.label(found[key]), "sha256": sha256_file(real),
                          "bytes": real.stat().st_size})
    dataset_sha = files[0]["sha256"]
    fit_sha = files[1]["sha256"] if len(files) > 1 else None
    return {"number": cert.report_number(dataset_sha, fit_sha, date), "issued": date.isoformat(),
            "laboratory": cert.laboratory(meas, settings), "customer": cert.customer(settings),
            "method": cert.method_text(meas, settings, fit), "conditions": cert.conditions(meas, settings),
            "files": files, "dataset_sha256": dataset_sha,
            "budget": cert.budget_table(fit) if fit is not None else [],
            "traceability": cert.traceability(meas, settings), "statements": cert.statements(meas, settings),
            "approval": cert.approval(settings, approver, role), "simulated": cert.simulated(meas, settings)}


def _provenance_status(fit: Doc, dataset_sha: str) -> dict | None:
    """A fit made from another dataset than the one in the folder (its provenance's SHA-256)."""
    prov = fit.sub("provenance")
    stated = prov.text("dataset_sha256", limit=80) if prov is not None else None
    if stated is None or stated == dataset_sha:
        return None
    return {"level": "bad", "text": f"The fit file states another dataset (SHA-256 {cut(stated, 16)}...) than the "
                                    f"folder's dataset.nc ({dataset_sha[:16]}...): fit this dataset again "
                                    "(`gonio fit DATASET --out FIT.json`) before the report is issued."}


def build_page(folder, found: dict, root: Folder, *, approver=None, role=None, issued=None,
               progress=None) -> tuple[str, dict, dict]:
    """Read and check every input, draw the figures and fill the template; write nothing.
    Returns the page, its images and the certificate's record (report_files/certificate.json).
    ``progress(done, total, label)``: before each figure (None: silent)."""
    import jinja2

    meas = _load_dataset(root, found["dataset"])
    ctx = {"notes": [], "fit": None, "speed": None, "render": None, "preview": None, "mitsuba": None,
           "results": None}
    ctx["capture"] = capture_section(meas, found["dataset"])
    ident = meta.identification(meas, root, found.get("journal"))
    ctx["ident"] = ident
    ctx["title"] = cut(f"sample {ident['sample_id']}, " if ident["sample_id"] else "", 200) + \
        cut(f"session folder {Path(folder).resolve().name}", 200)
    fit = model = params = samples = rendered = side = None
    fitted = meas           # the data as the fit saw them: at its shared-angle estimate's directions
    if found["fit"] is not None:
        fit, model, params = _load_fit(root, found["fit"])
        sa, ir = fit.sub("shared_angles"), fit.sub("instrument_response")      # corrected as the fit was
        fitted, note = as_fitted(meas, root.check(found["dataset"], "dataset"), None if sa is None else
                                 {"applied": sa.flag("applied"), "estimate_sigma": sa.numbers("estimate_sigma")},
                                 None if ir is None else (model, params, ir.num("source_half_deg"),
                                                          ir.num("detector_half_deg")))
        ctx["notes"] += [note] if note else []
        truth = meas.attrs.get("sample_truth")
        truth = truth if isinstance(truth, dict) else None
        ctx["fit"] = fit_section(fit, truth)
        ctx["results"] = meta.results(fit, truth_for(truth, model.name, [k for k, _ in fit.items("parameters")]),
                                      meas.attrs.get("scale_rel_std"))
        samples = posterior_samples(fit)
        ctx["mitsuba"] = mitsuba_section(model, params, fit)
    if found["speed"] is not None:
        ctx["speed"] = speed_section(root.read_json(found["speed"], "speed file", fix=FIX_SPEED))
    if found["render"] is not None:
        ctx["render"], rendered = render_section(root.read_json(found["render"], "render summary", fix=FIX_RENDER), meas)
    if found["preview"] is not None:
        ctx["preview"], side = preview_section(root.read_json(found["preview"], "preview summary", fix=FIX_PREVIEW),
                                               root, found["preview"])
    ctx["cert"] = certificate = certificate_section(meas, root, found, fit, approver=approver, role=role,
                                                    issued=issued)
    ctx["status"] = meta.status(meas, ident["planned"], fit, _partners(found["dataset"], meas.n_points))
    if fit is not None and (stale := _provenance_status(fit, certificate["dataset_sha256"])) is not None:
        ctx["status"].append(stale)
    ctx["status_bad"] = any(s["level"] == "bad" for s in ctx["status"])

    # every input is read and checked: now the figures and the view's data
    notes = ctx["notes"]
    images = _draw_all(meas, model, params, samples, rendered, side, notes, ctx["preview"], progress, fitted=fitted)
    if ctx["preview"] is not None and ctx["preview"]["note"]:
        notes.append(ctx["preview"]["note"])
    measured = ctx["preview"] is None or ctx["preview"]["measured"]
    ctx["figures"] = _figures(images, None if measured else {"preview_side_by_side.png": PREVIEW_FIT_ONLY})
    ctx["view"] = view_data(fitted, model, params)

    script = (TEMPLATES / "report.js").read_text(encoding="utf-8").removesuffix("\n")
    ctx["script_hash"] = base64.b64encode(hashlib.sha256(script.encode("utf-8")).digest()).decode("ascii")
    env = jinja2.Environment(loader=jinja2.FileSystemLoader(TEMPLATES), autoescape=True,
                             undefined=jinja2.StrictUndefined, trim_blocks=True, lstrip_blocks=True)
    record = {"format": "gonio-certificate/1", "number": certificate["number"], "issued": certificate["issued"],
              "files": certificate["files"], "approval": certificate["approval"],
              "laboratory": certificate["laboratory"], "customer": certificate["customer"],
              "sample_id": ident["sample_id"], "gonio_version": meas.attrs.get("gonio_version"),
              "standard": "ISO/IEC 17025:2017 7.8.2, 7.8.4"}
    return env.get_template("report.html.j2").render(**ctx), images, record


def write_report(folder, out=None, *, approver=None, approver_role=None, issue_date=None, progress=None) -> Path:
    """Write the HTML report for ``folder``; returns its path.

    Every input is read and checked before anything is written; a bad one is refused with a
    one-line :class:`GonioError`. The report and its ``*_files`` PNGs are written atomically,
    with the mode the user's umask gives. The page embeds every image (it reads alone, moved
    anywhere); ``*_files`` holds the same PNGs and ``certificate.json``, the record of the
    certificate's number, issue date, approval and the SHA-256 of the files it states.

    ``approver``, ``approver_role``: who approves the certificate (default: the settings'
    ``[session] approver`` and ``approver_role``; blank lines to sign by hand when neither gives
    one). ``issue_date``: a date or ``YYYY-MM-DD`` (default: today, UTC). ``progress(done, total,
    label)``: called before each figure is drawn (None: silent).
    """
    import matplotlib

    matplotlib.use("Agg")

    found = find_outputs(folder)
    root = Folder(folder)
    out = Path(out) if out else Path(folder) / "report.html"
    image_dir = _check_out(out)
    page, images, record = build_page(folder, found, root, approver=approver, role=approver_role, issued=issue_date,
                                     progress=progress)
    record["report"] = {"name": out.name, "sha256": hashlib.sha256(page.encode("utf-8")).hexdigest()}
    try:
        image_dir.mkdir(parents=True, exist_ok=True)
        for name, data in images.items():
            with atomic_open(image_dir / name, "wb") as fh:
                fh.write(data)
        with atomic_open(image_dir / "certificate.json", "w", encoding="utf-8") as fh:
            json.dump(record, fh, indent=1)
            fh.write("\n")
        with atomic_open(out, "w", encoding="utf-8") as fh:
            fh.write(page)
    except OSError as exc:
        raise GonioError(f"cannot write the report {out}: {exc.strerror or exc}; free space or choose another --out") from None
    return out
