"""How fits and datasets show themselves in a terminal and a notebook.

Short text reprs (never raw arrays) and HTML tables for Jupyter's ``_repr_html_``; every
string that comes from a file or a user (model names, options, channel labels, dataset
attributes) is escaped with :func:`html.escape` before it reaches HTML. Values are printed
with their 1-sigma rounded to two significant digits and the value to the same decimal place
(the GUM's rounding of a result, JCGM 100:2008 section 7.2.6).
"""

from __future__ import annotations

import html
import math

import numpy as np

__all__ = ["value_pm", "parameter_rows", "table_html", "fit_summary", "measurements_summary", "parameter_flags",
           "uncertainty_rows", "uncertainty_values", "interval_column", "FLAGS", "UNCERTAINTY_HEADER",
           "shared_angles_line"]

#: a fit file's parameter flags (``parameters.<name>.flags``) and what each says
FLAGS = {"at_bound": "at bound", "undetermined": "undetermined",
         "interval_wider_than_range": "U wider than the range",
         "outside_bounds": "non-physical (outside its bounds)",
         "not_normal": "not normal: use its coverage intervals, not value ± U"}
#: the columns of :func:`uncertainty_rows`
UNCERTAINTY_HEADER = ("parameter", "value", "u_stat", "u_c", "U", "k", "unit", "flags")


def value_pm(x, u=None) -> str:
    """``x`` and its 1-sigma ``u`` as text, ``u`` to two significant digits (``0.54992 ± 0.00077``);
    ``x`` alone to 6 digits when ``u`` is missing, zero or not finite."""
    x = float(x)
    if not math.isfinite(x):
        return str(x)
    if u is None or not math.isfinite(float(u)) or float(u) <= 0:
        return f"{x:.6g}"
    u = float(u)
    last = math.floor(math.log10(u)) - 1              # the decimal place of u's second digit
    if 1e-3 <= abs(x) < 1e5 or (x == 0 and 1e-3 <= u < 1e5):
        d = max(-last, 0)
        return f"{round(x, -last):.{d}f} ± {round(u, -last):.{d}f}"
    # the power of ten of the larger: a value far inside its 1-sigma (a parameter at a bound of 0,
    # 3e-65 ± 1.5e-62) is 0.0 at the 1-sigma's place, not (3 ± 1511...)e-65
    ex = math.floor(math.log10(max(abs(x), u)))
    d = max(ex - last, 0)
    mant = f"{x / 10 ** ex:.{d}f}"
    return f"({mant.lstrip('-') if float(mant) == 0 else mant} ± {u / 10 ** ex:.{d}f})e{ex:+03d}"


def parameter_rows(names, values, stds, units, flags=None) -> list[tuple[str, str, str, str]]:
    """(name, value ± 1-sigma, unit, flags) per parameter."""
    flags = flags or {}
    return [(str(n), value_pm(v, s), str(u), ", ".join(flags.get(n, ()))) for n, v, s, u in zip(names, values, stds, units)]


def parameter_flags(item: dict, lower: float, upper: float) -> list:
    """The flags (keys of :data:`FLAGS`) of one fitted parameter ``item`` (value, U, at_bound,
    undetermined) against its bounds: at a bound, undetermined, an expanded interval 2U wider
    than the physical range (upper - lower), a value outside the bounds (a corrected value can
    leave them), a distribution that ±k u_c does not describe (``gaussian`` false: JCGM 101 8.2,
    the document's ``coverage_intervals`` are the statement)."""
    out = [k for k in ("at_bound", "undetermined") if item.get(k)]
    v, big_u = float(item.get("value", np.nan)), float(item.get("U", np.nan))
    if math.isfinite(lower) and math.isfinite(upper) and math.isfinite(big_u) and 2 * big_u > upper - lower:
        out.append("interval_wider_than_range")
    if math.isfinite(v) and not lower <= v <= upper:
        out.append("outside_bounds")
    if item.get("gaussian") is False:
        out.append("not_normal")
    return out


def uncertainty_values(doc: dict) -> dict:
    """Each parameter's ``{"value", "std", "u_stat", "u_c", "U", "k", "unit", "flags"}`` as a fit
    document states them (numbers; NaN where missing; a document without an ``uncertainty``
    section gives u_c = std and u_stat = std): what :func:`uncertainty_rows` prints, and
    what z = (value - truth) / u_c is taken against."""
    params = doc.get("parameters") if isinstance(doc.get("parameters"), dict) else {}
    unc = ((doc.get("uncertainty") or {}).get("parameters") or {}) if isinstance(doc.get("uncertainty"), dict) else {}
    out = {}
    for name, p in params.items():
        p = p if isinstance(p, dict) else {}
        q = unc.get(name) if isinstance(unc.get(name), dict) else {}

        def num(key, *tables):
            for t in tables:
                v = t.get(key)
                if isinstance(v, (int, float)) and not isinstance(v, bool):
                    return float(v)
            return math.nan
        value, std = num("value", p), num("std", p)
        u_stat = num("u_stat", q, p) if q else std
        u_c = num("u_combined", p, q)
        u_c = std if not math.isfinite(u_c) else u_c
        k = num("k", p, q)
        k = 2.0 if not math.isfinite(k) else k
        big_u = num("U", p, q)
        big_u = k * u_c if not math.isfinite(big_u) else big_u
        flags = p.get("flags") if isinstance(p.get("flags"), list) else [
            f for f in ("at_bound", "undetermined") if p.get(f)]
        out[str(name)] = {"value": value, "std": std, "u_stat": u_stat, "u_c": u_c, "U": big_u, "k": k,
                          "unit": str(p.get("unit") or ""), "flags": [str(f) for f in flags]}
    return out


def interval_column(doc: dict) -> tuple[dict, str]:
    """The 90 % interval of each parameter as text (``lo .. hi``) where one of them says more
    than value +- 1.645 u_c (an emcee posterior's, or one clipped at a bound; else ``{}``), and
    the caption that says what the interval is on."""
    params = doc.get("parameters") if isinstance(doc.get("parameters"), dict) else {}
    items = {str(n): p for n, p in params.items() if isinstance(p, dict)}
    emcee = any(p.get("method") == "emcee" for p in items.values())
    if not (emcee or any(p.get("at_bound") for p in items.values())):
        return {}, "90 % interval = value ± 1.645 u_c"
    out = {}
    for name, p in items.items():
        ci = p.get("ci90")
        ok = isinstance(ci, list) and len(ci) == 2 and all(isinstance(v, (int, float)) for v in ci)
        out[name] = f"{ci[0]:.6g} .. {ci[1]:.6g}" if ok else "-"
    return out, ("90 % interval: the posterior's (emcee) widened by the budget beyond the data's noise where "
                 "sampled, else value ± 1.645 u_c; clipped at the bounds"
                 if emcee else "90 % interval = value ± 1.645 u_c, clipped at the bounds")


def uncertainty_rows(doc: dict) -> list:
    """The one uncertainty statement of a fit document, a row per parameter (:data:`UNCERTAINTY_HEADER`):
    value and u_c by the GUM rounding, u_stat, U, k, unit and flags (text). The fit file, its
    repr, ``to_xarray``, the report and the CLI show these; a document without an ``uncertainty``
    section gives u_c = std."""
    return [(name, value_pm(v["value"], v["u_c"]), f"{v['u_stat']:.2g}", f"{v['u_c']:.2g}", f"{v['U']:.2g}",
             f"{v['k']:g}", v["unit"], ", ".join(FLAGS.get(f, f) for f in v["flags"]))
            for name, v in uncertainty_values(doc).items()]


def table_html(caption: str, header, rows, notes=()) -> str:
    """An HTML table (everything escaped) with a caption and notes below it."""
    esc = html.escape
    head = "".join(f"<th style='text-align:left'>{esc(str(h))}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td style='text-align:left'>{esc(str(c))}</td>" for c in row) + "</tr>"
                   for row in rows)
    foot = "".join(f"<p style='margin:0.2em 0'>{esc(str(n))}</p>" for n in notes)
    return (f"<div><table><caption style='text-align:left'><b>{esc(caption)}</b></caption>"
            f"<thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>{foot}</div>")


def fit_summary(result) -> tuple[str, list, list]:
    """(caption, rows, notes) of a :class:`~gonio.fitting.FitResult`."""
    units = [e.unit for e in result.space.entries]
    flags = {n: ["at bound"] for n in result.at_bound}
    for n in result.undetermined:
        flags.setdefault(n, []).append("undetermined")
    rows = parameter_rows(result.space.names, result.x, result.std, units, flags)
    options = ", ".join(f"{k}={v}" for k, v in dict(result.model.options).items())
    caption = f"{result.model.name}({options}) fit, loss {result.loss}"
    notes = [f"chi2/dof = {result.chi2_dof:.4g} (dof {result.dof}), {result.n_used} values used, "
             f"{'converged' if result.converged else 'NOT converged: ' + str(result.message)}",
             f"method: {result.method}; 1-sigma from the {'sandwich' if 'sandwich' in result.method else 'Laplace'} covariance"]
    notes += [f"correlated: {a} and {b} (rho = {rho:+.3f})" for a, b, rho in result.correlated]
    return caption, rows, notes


def measurements_summary(meas) -> tuple[str, list, list]:
    """(caption, rows, notes) of :class:`~gonio.fitting.Measurements`: one row per channel."""
    theta_i = np.degrees(np.arccos(np.clip(meas.wi[:, 2], -1, 1)))
    theta_o = np.degrees(np.arccos(np.clip(meas.wo[:, 2], -1, 1)))
    rows = []
    for c in range(meas.n_channels):
        used = meas.use[:, c]
        f, s = meas.brdf[used, c], meas.brdf_std[used, c]
        rows.append((str(meas.channels[c]) if c < len(meas.channels) else str(c), int(used.sum()),
                     f"{f.min():.4g} .. {f.max():.4g}" if f.size else "-",
                     f"{np.median(s / np.maximum(np.abs(f), 1e-300)):.2g}" if f.size else "-"))
    caption = f"{meas.n_points} direction pairs x {meas.n_channels} channels, {meas.n_used} values used"
    notes = [f"theta_i {theta_i.min():.1f} .. {theta_i.max():.1f} deg, theta_o {theta_o.min():.1f} .. "
             f"{theta_o.max():.1f} deg" + (", solid-angle weights" if meas.weight is not None else "")]
    for key in ("gonio_version", "seed", "title"):
        if key in meas.attrs:
            notes.append(f"{key}: {str(meas.attrs[key])[:120]}")
    return caption, rows, notes


def text(caption, header, rows, notes) -> str:
    """The same table as aligned plain text."""
    widths = [max(len(str(h)), *(len(str(r[i])) for r in rows)) if rows else len(str(h)) for i, h in enumerate(header)]
    lines = [caption, "  " + "  ".join(str(h).ljust(w) for h, w in zip(header, widths)).rstrip()]
    lines += ["  " + "  ".join(str(c).ljust(w) for c, w in zip(r, widths)).rstrip() for r in rows]
    return "\n".join(lines + [f"  {n}" for n in notes])


def inadequate_text(g) -> str:
    """The warning of a fit whose model misses its data by more than the data's noise (a fit
    document's ``goodness``)."""
    return (f"chi2/dof = {g['chi2_dof']:.3g}: the model misses the data by more than its noise "
            f"(Birge ratio {g['birge_ratio']:.3g}); the 1-sigma values are statistical only and "
            "understate the model's error")


def shared_angles_line(doc) -> str:
    """One line on ``--estimate-angles`` (the fit file's ``shared_angles``): what was estimated
    and how far it moved the geometry, or why it was not applied; "" without it."""
    sa = doc.get("shared_angles")
    if not sa:
        return ""
    if not sa.get("applied"):
        return f"shared angle errors not estimated: {sa.get('reason', 'no reason recorded')}"
    est, post = np.abs(sa["estimate_sigma"]), np.asarray(sa["posterior_sigma"])
    moved = sa.get("max_direction_change_deg")         # absent in fit files before 2026-12-05
    return (f"shared angle errors estimated: {sa['inputs']} inputs, the largest {est.max():.2f} sigma of its stated "
            f"error, posterior {post.min():.2f}-{post.max():.2f} sigma"
            + (f"; directions moved up to {moved:.3f} deg" if moved is not None else ""))
