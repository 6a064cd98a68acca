"""The report as a calibration certificate (ISO/IEC 17025:2017 clause 7.8; 7.8.6, conformity,
is not stated).

Each item of 7.8.2 and 7.8.4 and where it comes from: the unique number on every page and the
end (7.8.2.1 d), :func:`report_number` from the SHA-256 of dataset.nc and fit.json and the issue
date; laboratory and customer (b, c, e) from ``[session]`` or the dataset; method (f),
:func:`method_text`; conditions (7.8.4.1 b), :func:`conditions`: apertures and solid angles,
polarisation, temperature, humidity, or "not recorded"; the budget as a table (7.8.4.1 a),
:func:`budget_table`; traceability (7.8.4.1 c), :func:`traceability`; the statements (7.8.2.1
l, n); the approval (o) from ``--approver``/``--approver-role`` or ``[session]``, else blank to
sign. Every text is plain text from hostile files, cut (inputs.cut); the template escapes it.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import math
import re

import numpy as np

from gonio.bench.report.inputs import Doc, cut

__all__ = ["issue_date", "report_number", "NUMBER_PATTERN", "conditions", "traceability",
           "approval", "budget_table", "method_text", "laboratory", "customer", "simulated", "statements"]

NOT_RECORDED = "not recorded"
#: a certificate number: the prefix, the issue date, 10 hex digits of the data's digest
NUMBER_PATTERN = re.compile(r"^GONIO-\d{8}-[0-9A-F]{10}$")


def issue_date(value=None) -> _dt.date:
    """The date of issue: ``value`` (a date, or ISO text ``YYYY-MM-DD``), today in UTC when None."""
    from gonio.core.errors import GonioError

    if value is None:
        return _dt.datetime.now(_dt.timezone.utc).date()
    if isinstance(value, _dt.datetime):
        return value.date()
    if isinstance(value, _dt.date):
        return value
    try:
        return _dt.date.fromisoformat(str(value))
    except ValueError:
        raise GonioError(f"issue date {str(value)[:40]!r} is not a date YYYY-MM-DD") from None


def report_number(dataset_sha256: str, fit_sha256: str | None, date: _dt.date) -> str:
    """``GONIO-YYYYMMDD-XXXXXXXXXX``: the issue date and the first 10 hex digits of the SHA-256 of
    the dataset's and the fit file's digests and the date; the same data issued on the same day
    gives the same number, any other data or day another one."""
    digest = hashlib.sha256(f"{dataset_sha256}\n{fit_sha256 or '-'}\n{date.isoformat()}".encode("ascii")).hexdigest()
    number = f"GONIO-{date:%Y%m%d}-{digest[:10].upper()}"
    assert NUMBER_PATTERN.match(number)          # it goes into the stylesheet's margin boxes
    return number


def _table(settings: dict, key: str) -> dict:
    v = settings.get(key)
    return v if isinstance(v, dict) else {}


def _text(v, limit=300) -> str | None:
    if isinstance(v, bool) or not isinstance(v, (str, int, float)):
        return None
    return cut(str(v), limit) if str(v).strip() else None


def _num(v) -> float | None:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        return None
    return float(v)


def _rel_text(v) -> str | None:
    """The certificate's relative 1-sigma as text: one number (``1.5 %``) or, one per channel or
    wavelength, their range (``0.4-0.7 % (one per channel)``); None when absent or not numbers."""
    arr = np.asarray(v if isinstance(v, (list, tuple, np.ndarray)) else [v], dtype=object).reshape(-1)
    nums = [_num(x.item() if isinstance(x, np.generic) else x) for x in arr]
    if not nums or any(x is None for x in nums):
        return None
    lo, hi = 100 * min(nums), 100 * max(nums)
    return f"{lo:.2g} %" if len(nums) == 1 or lo == hi else f"{lo:.2g}-{hi:.2g} % (one per channel)"


def simulated(meas, settings: dict) -> bool:
    """Whether the session ran on the simulated instrument (gonio.sim)."""
    return (isinstance(meas.attrs.get("sample_truth"), dict) or "simulated" in str(meas.attrs.get("source", ""))
            or bool(_table(settings, "calibration").get("sim")))


def laboratory(meas, settings: dict) -> str:
    """The laboratory's name and address: the settings' ``[session] institution``, else the
    dataset's ``institution`` attribute (gonio export --attr institution=...)."""
    return (_text(_table(settings, "session").get("institution"), 400) or _text(meas.attrs.get("institution"), 400)
            or f"{NOT_RECORDED} (give [session] institution in the settings)")


def customer(settings: dict) -> str:
    return _text(_table(settings, "session").get("customer"), 400) or \
        f"{NOT_RECORDED} (give [session] customer in the settings)"


def solid_angle(half_deg: float) -> float:
    """The solid angle (sr) of a cone of half-angle ``half_deg``: 2 pi (1 - cos a)."""
    return 2.0 * math.pi * (1.0 - math.cos(math.radians(half_deg)))


def _aperture(meas, settings: dict, which: str, what: str) -> str:
    half = _num(meas.attrs.get(f"aperture_{which}_half_deg"))
    profile = _text(meas.attrs.get("aperture_profile"), 60)
    if half is None:
        ap = _table(settings, "aperture")
        half, profile = _num(ap.get(f"{which}_half_deg")), _text(ap.get("profile"), 60)
    if half is None:
        return f"{NOT_RECORDED} (the {what}'s aperture is stated by a calibration, gonio calibrate's [aperture])"
    if half <= 0:
        return f"half-angle 0 deg as stated: a point {what} assumed, solid angle 0 sr"
    return (f"half-angle {half:.3g} deg ({profile or 'uniform disk'}), solid angle {solid_angle(half):.3g} sr")


def conditions(meas, settings: dict) -> list[tuple[str, str]]:
    """The conditions of the measurement (7.8.4.1 b) as (label, text) rows."""
    cond = _table(settings, "conditions")
    sim = simulated(meas, settings)
    pol = _text(cond.get("polarisation"), 200)
    if pol is None:
        pol = NOT_RECORDED + (" (the simulated instrument renders unpolarised light and a polarisation-blind "
                              "detector)" if sim else " (give [conditions] polarisation in the settings)")
    t, rh = _num(cond.get("temperature_c")), _num(cond.get("humidity_pct"))
    hint = " (the simulated instrument has none)" if sim else " (give [conditions] {} in the settings)"
    return [("Source aperture (illumination)", _aperture(meas, settings, "source", "source")),
            ("Detector aperture (viewing)", _aperture(meas, settings, "detector", "detector")),
            ("Polarisation", pol),
            ("Ambient temperature", f"{t:.1f} °C" if t is not None else NOT_RECORDED + hint.format("temperature_c")),
            ("Ambient relative humidity", f"{rh:.0f} %" if rh is not None else NOT_RECORDED + hint.format("humidity_pct"))]


def method_text(meas, settings: dict, fit: Doc | None) -> str:
    """The method (7.8.2.1 f) in one paragraph."""
    plan = meas.attrs.get("plan")
    try:
        plan = json.loads(plan) if isinstance(plan, str) else plan
    except (ValueError, RecursionError):
        plan = None
    name = _text(plan.get("name"), 60) if isinstance(plan, dict) else None
    text = (f"Relative goniometric BRDF measurement with gonio {_text(meas.attrs.get('gonio_version'), 40) or '?'}: "
            f"at each of the {meas.n_points} geometries of the plan {name or '?'} a RAW camera images the sample beside "
            "a diffuse reference standard under the collimated LED source; f_r (sr^-1) is the ratio of their "
            "HDR-merged signals times the reference's f_r (its certified reflectance / pi and its non-Lambertian "
            "factor). ")
    if fit is not None:
        spec = fit.sub("model")
        model = spec.text("name") if spec is not None else None
        opt = fit.sub("optimiser")
        unc = fit.sub("uncertainty")
        how = unc.text("method", limit=400) if unc is not None else None
        text += (f"The BRDF model {model or '?'} is fitted to every value by weighted least squares "
                 f"(optimiser {(opt.text('method') if opt is not None else None) or '?'}); its parameters' "
                 "uncertainty is evaluated by JCGM 100:2008 (GUM) and JCGM 102:2011"
                 + (f": {how}" if how else " from the fit's statistical covariance only")
                 + ". Expanded uncertainty U = k u_c.")
    return cut(text, 1400)


def _rho_text(ref: dict, attrs) -> str:
    rho = ref.get("reflectance", attrs.get("reference_reflectance"))
    if isinstance(rho, str):
        try:
            rho = json.loads(rho)
        except (ValueError, RecursionError):
            pass
    if isinstance(rho, list) and all(_num(r) is not None for r in rho[:3]):
        return ", ".join(f"{r:.4g}" for r in rho[:3])
    return f"{rho:.4g}" if _num(rho) is not None else "?"


def traceability(meas, settings: dict) -> list[str]:
    """Paragraphs: how the results are traceable (7.8.4.1 c): the reference standard and its
    certificate; the calibration applied, or plainly that none was."""
    ref = _table(settings, "reference")
    rel = _rel_text(ref.get("rel_std", meas.attrs.get("scale_rel_std")))
    cert = _text(ref.get("certificate"), 200)
    sim = simulated(meas, settings)
    out = [cut(f"The scale of f_r is traceable through the reference standard measured beside the sample in every "
               f"frame: certified diffuse reflectance {_rho_text(ref, meas.attrs)}"
               + (f", relative standard uncertainty {rel}" if rel is not None else "")
               + f", certificate {cert or NOT_RECORDED}"
               + (" (the simulated reference of gonio.sim: no physical standard)" if sim else "")
               + ". Its uncertainty is a component of the uncertainty budget (reference_certificate).", 800)]
    cal = _table(settings, "calibration")
    if not isinstance(settings.get("alignment"), dict):
        out.append("No calibration applied: the angles are the stages' nominal angles (no alignment, detector "
                   "linearity or reference-factor correction); calibrate with `gonio calibrate` and capture with "
                   "`--calibration CAL.toml`.")
        return out
    made = "the simulated instrument" if cal.get("sim") else "this instrument"
    proc = _text(cal.get("procedure"), 500)
    ap = _table(settings, "aperture")
    parts = [f"Calibration applied: gonio calibrate on {made}, seed {_text(cal.get('seed'), 20) or '?'}"
             + (f" ({proc})" if proc else "")]
    applied = ["the alignment (stage zeros, holder tilt) to every point's angles"]
    if isinstance(settings.get("linearity"), dict):
        applied.append("the detector's linearity to the HDR merge")
    if isinstance(ref.get("factor"), list):
        applied.append("the reference's non-Lambertian factor table")
    if ap:
        applied.append("the source and detector apertures to the fit (instrument response)")
    if (_num(_table(settings, "stray").get("floor")) or 0.0) > 0:
        applied.append("the stray-light floor's removal")
    parts.append("Applied: " + "; ".join(applied))
    parts.append("The calibration's own uncertainties are components of the budget. The calibration record is "
                 "the tables the capture merged into its settings (session.toml and dataset.nc); the calibration "
                 "file's name, date and checksum are not recorded by the capture")
    out.append(cut(". ".join(parts) + ".", 1200))
    return out


def approval(settings: dict, name=None, role=None) -> dict:
    """Who approves the report (7.8.2.1 o): the options, else the settings' ``[session]``
    ``approver`` / ``approver_role``; None where neither gives one (a blank line to fill in)."""
    sess = _table(settings, "session")
    return {"name": _text(name, 200) or _text(sess.get("approver"), 200),
            "role": _text(role, 200) or _text(sess.get("approver_role"), 200)}


def statements(meas, settings: dict) -> list[str]:
    out = ["The results relate only to the item calibrated, as identified above, at the time and under the "
           "conditions of the measurement.",
           "This certificate shall not be reproduced except in full without the written approval of the "
           "issuing laboratory."]
    if simulated(meas, settings):
        out.append("Deviation from the method: the measurement ran on the simulated instrument (gonio.sim); the "
                   "results describe a simulated sample, not a physical item.")
    return out


# --------------------------------------------------------------------------- the budget as a table
def _line(name: str, components: dict) -> tuple[str, str, str]:
    """(GUM type, correlation, source) of a budget line of the fit file."""
    from gonio.fitting.uncertainty.budget import ANGLE_SECOND_ORDER, STATISTICAL

    c = components.get(name)
    if isinstance(c, dict):
        return (_text(c.get("gum_type"), 4) or "?", _text(c.get("correlation"), 40) or "?",
                _text(c.get("source"), 200) or "")
    if name == STATISTICAL:
        return "A", "none", _text(c, 200) or "the fit's own statistical 1-sigma (brdf_std as the weights)"
    if name == ANGLE_SECOND_ORDER:
        return "B", "full", "the shared angle errors' second-order term (GUM 5.1.2 note)"
    if name == "angle_shared":
        return "B", "full", "the shared angle errors (zeros, holder tilt, lamp zero, wedge) x the local slope of f_r"
    if name.startswith("angle_repeatability"):
        axis = name.removeprefix("angle_repeatability").strip("_")
        return ("B", "group" if axis else "point",
                f"the {axis + ' axis' if axis else 'stages'}' per-move repeatability x the local slope of f_r")
    return "?", "?", _text(c, 200) or ""


def _u(v) -> str:
    return "–" if v is None or not math.isfinite(v) else f"{v:.2g}"


#: parameters side by side in one budget table (more make further tables)
BUDGET_COLUMNS = 4


def budget_table(fit: Doc) -> list[dict]:
    """The budget as tables (JCGM 100:2008 8): a row per component of the fit file's budget
    (``uncertainty.parameters[p].budget``, fractions of u_c^2) with its GUM type, correlation and
    source, and for each parameter its contribution u_i = sqrt(fraction) u_c (the component's
    standard uncertainty times its sensitivity, in the parameter's unit) and share; then each
    parameter's u_c, U and k. At most :data:`BUDGET_COLUMNS` parameters a table."""
    unc = fit.sub("uncertainty")
    if unc is None:
        return []
    comps = unc.raw("components") if isinstance(unc.raw("components"), dict) else {}
    units = {n: p.text("unit") or "" for n, p in fit.items("parameters")}
    params, shares = [], {}
    for name, q in unc.items("parameters"):
        u_c, k = q.num("u_combined"), q.num("k")
        k = k if k is not None else unc.num("k")
        big_u = q.num("U")
        if big_u is None and u_c is not None and k is not None:
            big_u = k * u_c
        budget = q.sub("budget")
        mine = {}
        for comp, frac in (budget.data.items() if budget is not None else []):
            if isinstance(frac, bool) or not isinstance(frac, (int, float)) or not math.isfinite(frac):
                continue
            contrib = math.sqrt(frac) * u_c if (u_c is not None and math.isfinite(u_c) and frac >= 0) else None
            mine[str(comp)] = {"u": _u(contrib), "share": f"{100 * frac:.2g} %", "fraction": float(frac)}
        unit = units.get(name, "")
        params.append({"name": cut(name, 80), "unit": "" if unit in ("1", "") else cut(unit, 20), "u_c": _u(u_c),
                       "U": _u(big_u), "k": "–" if k is None else f"{k:g}"})
        shares[params[-1]["name"]] = mine
    tables = []
    for start in range(0, len(params), BUDGET_COLUMNS):
        chunk = params[start:start + BUDGET_COLUMNS]
        names = {c for p in chunk for c in shares[p["name"]]}
        order = sorted(names, key=lambda c: -max(shares[p["name"]].get(c, {}).get("fraction", 0.0) for p in chunk))
        rows = []
        for comp in order[:60]:
            gum_type, corr, source = _line(comp, comps)
            rows.append({"component": cut(comp, 80), "type": gum_type, "correlation": corr, "source": source,
                         "cells": [{"parameter": p["name"], **shares[p["name"]].get(comp, {"u": "–", "share": ""})}
                                   for p in chunk]})
        tables.append({"params": chunk, "rows": rows})
    return tables
