"""The measurement report's front matter: who, what, when and where; the status box; the results.

A calibration laboratory's report (ISO/IEC 17025 7.8.2: the item's identification, the date,
the method, the equipment, the results with their uncertainty) opens with the identification
and a plain statement of what is wrong, then the results. Here:

- :func:`identification`: the dataset's attributes (sample, operator, date, plan), the devices
  session.toml's ``[devices]`` table records and what a resume on other hardware found
  different (``hardware`` events), all as hostile text, cut and escaped by the template;
- :func:`status`: what is incomplete (points measured of the plan), inadequate (chi2/dof
  beyond its 99.9 % point) or violated (energy, reciprocity beyond the noise);
- :func:`results`: each parameter with its combined standard uncertainty u_c and the expanded
  uncertainty U = k u_c, rounded by the GUM rule (JCGM 100:2008 7.2.6; :func:`gum`).
"""

# identification reads settings with its [session] table (sample id, description, operator),
# versions (with the date) and plan; the [devices] table holds each device's *IDN?, Zaber
# device id, serial and firmware, read from the session journal's copy of session.toml, or
# from its identification event for a session from before the table.
# gum: the uncertainty to two significant digits, the value to the same decimal place.

from __future__ import annotations

import json
import math
import sqlite3

import numpy as np

from gonio.bench.report.inputs import Doc, Folder, cut

__all__ = ["gum", "identification", "status", "results"]

NOT_RECORDED = "not recorded"


def gum(value, u) -> tuple[str, str]:
    """``value`` and its uncertainty ``u`` as text, rounded by JCGM 100:2008 7.2.6.

    ``u`` to two significant digits, ``value`` to the same decimal place: ``gum(0.5500496,
    7.696e-05) == ("0.550050", "0.000077")``. Beyond 10 decimal places or at 1e6 and above both
    share one power of ten (``"1.2346e-12"``-style values become ``"(1.2346 ± ...)e-12"``
    mantissas). A missing or non-finite ``u`` leaves the value with 4 significant digits.
    """
    if value is None or not math.isfinite(value):
        return ("–" if value is None else str(value)), ("–" if u is None else f"{u:.2g}")
    if u is None or not math.isfinite(u) or u <= 0:
        return f"{value:.4g}", ("–" if u is None else f"{u:.2g}")
    u2 = float(f"{u:.2g}")                        # two significant digits (9.96e-5 -> 1.0e-4)
    place = math.floor(math.log10(u2)) - 1        # the decimal place of the second digit
    if -10 <= place <= 0 and abs(value) < 1e6:
        d = -place
        return f"{round(value, d):.{d}f}", f"{u2:.{d}f}"
    if 0 < place and abs(value) < 1e15:           # u >= 100: whole numbers rounded to that place
        q = 10 ** place
        return f"{round(value / q) * q:.0f}", f"{round(u2 / q) * q:.0f}"
    # the power of ten of the larger of the two: a value far inside its uncertainty (a parameter at
    # a bound of 0, 3e-65 +- 1.5e-62) is 0.0 at the uncertainty's place, not 3 +- 1511 of its own
    e = math.floor(math.log10(max(abs(value), u2)))
    d = max(0, e - place)
    mant = f"{value / 10 ** e:.{d}f}"
    mant = mant.lstrip("-") if float(mant) == 0 else mant
    return f"{mant}e{e:+03d}", f"{u2 / 10 ** e:.{d}f}e{e:+03d}"


def _json_attr(attrs, key) -> dict:
    """A JSON-object attribute of the dataset ({} when absent or not an object)."""
    v = attrs.get(key)
    if isinstance(v, dict):
        return v
    try:
        doc = json.loads(v) if isinstance(v, str) else None
    except (ValueError, RecursionError):
        return {}
    return doc if isinstance(doc, dict) else {}


def _text(v, limit=200) -> str | None:
    return cut(str(v), limit) if isinstance(v, (str, int, float)) and not isinstance(v, bool) and str(v).strip() else None


def _loads(text):
    """A JSON object of the journal (hostile text: bounded, checked); None otherwise."""
    try:
        doc = json.loads(text) if isinstance(text, str) and len(text) < 1 << 22 else None
    except (ValueError, RecursionError):
        return None
    return doc if isinstance(doc, dict) else None


def _read_journal(real) -> tuple[dict | None, dict | None, list[str]]:
    """From the journal: session.toml's ``[devices]`` as recorded when the session started (the
    ``session`` table's parsed doc; None for a session from before the table, or a journal
    without it), the last ``identification`` event, and the ``hardware`` events (a resume on
    other hardware, oldest first)."""
    db = sqlite3.connect(f"{real.as_uri()}?mode=ro", uri=True)
    try:
        row = db.execute("SELECT text FROM events WHERE kind = 'identification' ORDER BY id DESC LIMIT 1").fetchone()
        hardware = [r[0] for r in db.execute("SELECT text FROM events WHERE kind = 'hardware' ORDER BY id LIMIT 100")]
        try:
            doc = db.execute("SELECT value FROM session WHERE key = 'doc'").fetchone()
        except sqlite3.OperationalError:             # no session table: no session.toml recorded
            doc = None
    finally:
        db.close()
    devices = (_loads(doc[0]) or {}).get("devices") if doc else None
    return (devices if isinstance(devices, dict) else None, _loads(row[0]) if row else None,
            [h for h in hardware if isinstance(h, str)])


def _devices(root: Folder, journal) -> list[dict]:
    """session.toml's ``[devices]`` (as the journal recorded it; the last ``identification``
    event for a session from before the table), checked field by field; then what each resume
    on other hardware said differs."""
    if journal is None:
        return []
    real = root.check(journal, "session journal")
    try:
        recorded, event, hardware = _read_journal(real)
    except sqlite3.Error:
        return [{"role": "devices", "text": "the session journal cannot be read (damaged database)"}]
    ident = event
    if recorded is not None:                     # the table is keyed by address; the event lists them
        zaber = recorded.get("zaber") if isinstance(recorded.get("zaber"), dict) else {}
        ident = {**recorded, "zaber": list(zaber.values())}
    if not isinstance(ident, dict):
        return []
    out = []
    zaber = ident.get("zaber") if isinstance(ident.get("zaber"), list) else []
    for d in zaber[:99]:
        if not isinstance(d, dict):
            continue
        parts = [f"{label} {_text(d.get(key), 64)}" for key, label in
                 (("device_id", "device id"), ("serial", "serial"), ("firmware", "firmware"), ("build", "build"))
                 if _text(d.get(key), 64)]
        out.append({"role": f"Zaber device {_text(d.get('address'), 8) or '?'}", "text": ", ".join(parts) or "?"})
    for key, role in (("meter", "power meter (*IDN?)"), ("camera", "camera"),
                      ("monochromator", "monochromator (INFO?)")):
        if _text(ident.get(key)):
            out.append({"role": role, "text": _text(ident.get(key))})
    port = _text(ident.get("zaber_port")) or ""
    if port.startswith("sim://"):
        out.append({"role": "instrument", "text": "the simulated instrument (gonio.sim) over its serial protocols"})
    seen = []
    for h in hardware:
        if h not in seen:
            seen.append(h)
    for h in seen[-5:]:
        out.append({"role": "Hardware on resume", "text": cut(h, 900)})
    return out


_SPACES = {"srgb": "linear sRGB (D65; IEC 61966-2-1 primaries, no transfer curve)", "xyz": "CIE 1931 XYZ (D65)",
           "camera": "the camera's own RGB (its colour filters, white-balanced)"}


_MATRIX_SOURCES = {"dng": "the RAW files' own ColorMatrix1 (DNG)", "libraw": "LibRaw's colour matrix of the RAW files",
                   "chart": "a matrix fitted to a ColorChecker capture"}


def _band(meas) -> str:
    """The channels the report's values are in: the colour space the dataset was read in, and
    from what (the DNG's matrix or a ColorChecker's), as `load_dataset` recorded it."""
    colour = meas.attrs.get("colour") if isinstance(meas.attrs.get("colour"), dict) else {}
    space = colour.get("space") if colour.get("space") in _SPACES else None
    channels = ", ".join(map(str, meas.channels))
    if space is None:
        return f"channels {channels} (colour space not recorded)"
    text = f"channels {channels} in {_SPACES[space]}"
    source = colour.get("matrix", {}).get("source") if isinstance(colour.get("matrix"), dict) else None
    if space != "camera" and _text(source):
        how = _MATRIX_SOURCES.get(str(source), f"the {_text(source, 40)} colour matrix")
        text += f", converted from camera RGB by {how}"
    return text


def _num(table, key) -> float | None:
    v = table.get(key) if isinstance(table, dict) else None
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) else None


def _pm(table, key, fmt=".4f", unit=" deg") -> str:
    v, u = _num(table, key), _num(table, f"u_{key}")
    if v is None:
        return "?"
    return f"{v:{fmt}}{unit}" if u is None else f"{v:{fmt}} ± {u:{fmt}}{unit}"


def _calibration(settings: dict) -> str:
    """The calibration the session applied (``gonio capture --calibration``), from the settings it
    merged into: what was estimated and what it corrects; or that none was applied."""
    cal = settings.get("calibration") if isinstance(settings.get("calibration"), dict) else {}
    a = settings.get("alignment") if isinstance(settings.get("alignment"), dict) else None
    if a is None:
        return ("none applied: the nominal stage angles, no alignment, linearity or reference-factor correction "
                "(`gonio calibrate`, then `gonio capture --calibration CAL.toml`)")
    lin = settings.get("linearity") if isinstance(settings.get("linearity"), dict) else {}
    ref = settings.get("reference") if isinstance(settings.get("reference"), dict) else {}
    errors = cal.get("errors") if isinstance(cal.get("errors"), dict) else {}
    made = "the simulated instrument" if cal.get("sim") else "this instrument"
    if cal.get("sim") and _text(errors.get("preset"), 20):
        made += f" ({_text(errors.get('preset'), 20)} errors)"
    head = f"gonio calibrate on {made}, seed {_text(cal.get('seed'), 20) or '?'}"
    parts = [f"yaw zero {_pm(a, 'yaw_zero_deg')}", f"tilt zero {_pm(a, 'tilt_zero_deg')}",
             f"holder tilt x {_pm(a, 'holder_tilt_x_deg')}, y {_pm(a, 'holder_tilt_y_deg')}"]
    if _num(a, "lamp_zero_u_deg") is not None:
        parts.append(f"lamp-arm zero not identifiable, its surveyed u {_num(a, 'lamp_zero_u_deg'):.3g} deg carried")
    if _num(lin, "gamma") is not None:
        parts.append(f"detector non-linearity gamma {_pm(lin, 'gamma', '.5f', '')}")
    applied = "every point's angles (calibrated, with their u)"
    if _num(lin, "gamma") is not None:
        applied += ", the HDR merge's linearisation"
    if isinstance(ref.get("factor"), list):
        applied += ", the reference's non-Lambertian factor table"
    return cut(f"{head}: {'; '.join(parts)}. Applied to {applied}; their uncertainties are components of the "
               "budget.", 900)


def identification(meas, root: Folder, journal) -> dict:
    """Who, what, when, where: rows of (label, text) for the report's first table."""
    attrs = meas.attrs
    settings = _json_attr(attrs, "settings")
    session = settings.get("session") if isinstance(settings.get("session"), dict) else {}
    ref = settings.get("reference") if isinstance(settings.get("reference"), dict) else {}
    meter = settings.get("meter") if isinstance(settings.get("meter"), dict) else {}
    plan = _json_attr(attrs, "plan")
    versions = _json_attr(attrs, "versions")
    truth = attrs.get("sample_truth") if isinstance(attrs.get("sample_truth"), dict) else None
    sample_id = _text(session.get("sample_id"))
    if sample_id is None and truth is not None:
        sample_id = "simulated sample (no sample id recorded)"
    rows = [("Sample id", sample_id or f"{NOT_RECORDED} (give `gonio capture --sample-id`)"),
            ("Sample description", _text(session.get("sample_description"), 400) or (
                cut(f"simulated {truth.get('model', '?')} {json.dumps(truth.get('params', {}))}", 300)
                if truth else NOT_RECORDED)),
            ("Operator", _text(session.get("operator")) or NOT_RECORDED),
            ("Date of measurement (session start, UTC)", _text(versions.get("created")) or NOT_RECORDED)]
    rho, rel = ref.get("reflectance", attrs.get("reference_reflectance")), ref.get("rel_std", attrs.get("scale_rel_std"))
    rows.append(("Reference standard", cut(f"diffuse reflectance {json.dumps(rho) if rho is not None else '?'}, "
                                           f"certificate relative 1-sigma {rel if rel is not None else '?'}; "
                                           f"certificate id {_text(ref.get('certificate')) or NOT_RECORDED}", 400)))
    n_plan = len(plan["points"]) if isinstance(plan.get("points"), list) else None
    rows.append(("Measurement plan", cut(f"{_text(plan.get('name')) or '?'}: {n_plan if n_plan is not None else '?'} "
                                         f"planned points. {_text(plan.get('description'), 300) or ''}".strip(), 500)))
    wl = _text(meter.get("wavelength_nm"))
    rows.append(("Wavelength band", cut(_band(meas) + (f"; source monitor at {wl} nm" if wl else ""), 400)))
    devices = _devices(root, journal)
    for d in devices:
        rows.append((d["role"], d["text"]))
    if not devices:
        rows.append(("Instrument", "no device identification recorded (session journal not in the folder)"))
    rows.append(("Calibration", _calibration(settings)))
    rows.append(("Software", cut(f"gonio {attrs.get('gonio_version', '?')}, seed {attrs.get('seed', '?')}", 200)))
    return {"rows": rows, "sample_id": sample_id, "planned": n_plan}


def _reciprocity_z(meas, partner) -> tuple[float, int] | None:
    """Median over reciprocal pairs of |f_a - f_b| / sqrt(u_a^2 + u_b^2), and the pair count."""
    if partner is None:
        return None
    i = np.where((partner > np.arange(partner.size)) & (partner < partner.size))[0]
    if i.size == 0:
        return None
    j = partner[i]
    z = np.abs(meas.brdf[i] - meas.brdf[j]) / np.maximum(np.hypot(meas.brdf_std[i], meas.brdf_std[j]), 1e-300)
    return float(np.median(z)), int(i.size)


def status(meas, planned, fit: Doc | None, partner) -> list[dict]:
    """What is complete, adequate and respected, in plain words; ``level`` ok / warn / bad."""
    out = []
    complete = meas.attrs.get("complete")
    if planned is not None and meas.n_points < planned or complete == 0:
        out.append({"level": "bad", "text": f"Incomplete: {meas.n_points} of {planned if planned else '?'} planned "
                    "points measured; finish the session with `gonio capture --resume SESSION`, then export again."})
    else:
        out.append({"level": "ok", "text": f"Complete: {meas.n_points} of {planned or meas.n_points} planned points."})
    if fit is None:
        out.append({"level": "warn", "text": "Not fitted: no fit.json in the folder; the measured BRDF is shown "
                    "without a model (`gonio fit DATASET --out FIT.json`)."})
    else:
        g = fit.need("goodness")
        chi, dof = g.num("chi2_dof"), g.count("dof")
        test = _adequacy_named(g.sub("adequacy"))
        if g.raw("model_adequate") is False:
            tail = ("the statistical part of u_c below is Birge-inflated; chi2 weighs the points by their "
                    "noise alone, so terms of the budget that differ from point to point (angles, stray light) "
                    "also raise it" if fit.sub("uncertainty") is not None else
                    "the uncertainties below are Birge-inflated statistical ones and understate the error")
            said = f"{test} rejects it" if test else "beyond its 99.9 % point"
            out.append({"level": "bad", "text": f"Inadequate model: chi2/dof = {chi:.3g} over {dof} degrees of "
                        f"freedom; {said}: the model misses the data by more than their budget allows; {tail}."})
        elif chi is not None:
            if test:
                out.append({"level": "ok", "text": f"Model adequate: {test} accepts it (chi2/dof = {chi:.3g} over "
                            f"{dof} dof against the type-A noise alone)."})
            else:
                out.append({"level": "ok", "text": f"Model adequate: chi2/dof = {chi:.3g} ({dof} dof)."})
        energy = fit.need("constraints").need("energy")
        if energy.raw("holds") is False:
            alb = energy.num("max_albedo")
            out.append({"level": "bad", "text": f"Energy violated: the fit's directional albedo reaches "
                        f"{alb:.3g} > 1." if alb is not None else "Energy violated: the fit reflects more than it receives."})
        flagged = [n for n, p in fit.items("parameters") if p.flag("undetermined") or p.flag("at_bound")]
        if flagged:
            out.append({"level": "warn", "text": cut("At a bound or not determined by the data: "
                                                     + ", ".join(flagged), 400)})
    rz = _reciprocity_z(meas, partner)
    if rz is not None:
        z, n = rz
        level = "bad" if z > 3 else "ok"
        word = "Reciprocity violated" if z > 3 else "Reciprocity holds"
        out.append({"level": level, "text": f"{word}: median |f(wi, wo) - f(wo, wi)| = {z:.2g} sigma over {n} "
                    "reciprocal pairs (Helmholtz; beyond 3 sigma means the data or the geometry are wrong)."})
    return out


def _adequacy_named(a) -> str | None:
    """What the fit's adequacy verdict tested and at what level, as words (None without a
    ``goodness.adequacy`` section: an older fit file)."""
    if a is None:
        return None
    names = {"budget_chi2": "the budget chi-square test (the residuals against the budget's covariance, its "
                            "shared inputs profiled)",
             "chi2": "the chi-square test against the fit's sigma"}
    what = names.get(str(a.raw("test")), f"the {cut(str(a.raw('test')), 30)} test")
    alpha, stat, p, dof = a.num("alpha"), a.num("statistic"), a.num("p_value"), a.count("dof")
    parts = [f"{what} at alpha = {alpha:.2g} (its false-alarm rate)" if alpha is not None else what]
    if stat is not None and dof is not None:
        parts.append(f"statistic {stat:.4g} over {dof} dof" + (f", p = {p:.2g}" if p is not None else ""))
    return ", ".join(parts)


def results(fit: Doc, truth_of: dict, rel_std) -> dict:
    """Rows of value, u_c, U and k, GUM-rounded; and the statement of what u_c includes."""
    unc = fit.sub("uncertainty")
    per = dict(unc.items("parameters")) if unc is not None else {}
    rows = []
    for name, p in fit.items("parameters"):
        value, u_stat = p.num("value"), p.num("std")
        q = per.get(name)
        u_c = q.num("u_combined") if q is not None else u_stat
        k = (q.num("k") if q is not None and q.num("k") is not None else 2.0)
        big_u = q.num("U") if q is not None and q.num("U") is not None else (k * u_c if u_c is not None else None)
        v_text, uc_text = gum(value, u_c)
        _, U_text = gum(value, big_u)
        t = truth_of.get(name)
        z = (value - t) / u_c if (t is not None and value is not None and u_c) else None
        budget = []
        if q is not None and q.sub("budget") is not None:
            shares = q.need("budget").data
            shares = sorted(((c, float(s)) for c, s in shares.items() if isinstance(s, (int, float))
                             and not isinstance(s, bool) and math.isfinite(s)), key=lambda cs: -cs[1])
            budget = [f"{cut(str(c), 40)} {100 * s:.0f} %" for c, s in shares[:12]]
        rows.append({"name": cut(name, 80), "value": v_text, "u": uc_text, "U": U_text, "k": f"{k:g}",
                     "unit": p.text("unit") or "", "truth": "–" if t is None else f"{t:.6g}",
                     "z": "–" if z is None else f"{z:+.2f}", "budget": ", ".join(budget)})
    if unc is not None:
        comps = ", ".join(cut(c, 40) for c, _ in unc.items("components")) or "none declared"
        statement = (f"u_c is the combined standard uncertainty: the fit's statistical uncertainty and the "
                     f"propagated components of the data's uncertainty budget ({comps}); U = k u_c with the "
                     "coverage factor k given (k = 2: about 95 % for a normal distribution, JCGM 100 6.2).")
    else:
        rel = f"{100 * rel_std:.2g} %" if isinstance(rel_std, (int, float)) and math.isfinite(rel_std) else "its"
        statement = ("u is the fit's statistical standard uncertainty only (from the measured noise of each value). "
                     f"It leaves out the reference certificate's fully correlated scale uncertainty ({rel} relative, "
                     "1-sigma), and the angle, stray-light and linearity terms of a full budget: this fit file "
                     "carries no uncertainty budget. U = 2u is therefore a lower bound of the expanded uncertainty.")
    return {"rows": rows, "statement": statement, "combined": unc is not None,
            "truth": any(r["truth"] != "–" for r in rows)}

