"""One uncertainty statement: its coverage factor, a fit's statement without its data, and
the one xarray layout of any statement.

A fit document (:func:`gonio.fitting.fit_document`) states each parameter's value, u_stat,
u_c, U = k u_c, the 90 % interval and its flags; :func:`result_document` is the same shape for
a FitResult alone (u_c its statistical std, said so), and :func:`fit_to_xarray` lays out either
as an :class:`xarray.Dataset`. This module sits below the optimiser, the uncertainty budget and
the formats, which all read it (it imports none of them).
"""

from __future__ import annotations

import json

import numpy as np

from gonio.fitting.display import FLAGS, parameter_flags, uncertainty_values

__all__ = ["K_EXPANDED", "jsonable", "result_document", "fit_to_xarray"]

#: coverage factor of the expanded uncertainty U = k u_c (about 95 % for a normal distribution, GUM 6.2.2)
K_EXPANDED = 2.0


def jsonable(value, where: str = "", non_finite: list | None = None):
    """``value`` as plain JSON types; NaN and +-inf become None (JSON null).

    Where ``non_finite`` is a list, the dotted path of every value replaced is appended to it
    (``goodness.chi2_dof``, ``covariance.matrix[0][1]``), so the writer can say so.
    """
    if isinstance(value, dict):
        return {str(k): jsonable(v, f"{where}.{k}" if where else str(k), non_finite) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v, f"{where}[{i}]", non_finite) for i, v in enumerate(value)]
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist(), where, non_finite)
    if isinstance(value, np.generic):
        return jsonable(value.item(), where, non_finite)
    if isinstance(value, float) and not np.isfinite(value):
        if non_finite is not None:
            non_finite.append(where or "(top level)")
        return None
    return value


def result_document(result) -> dict:
    """The fit-document shape of ``result`` without its data: no budget, so u_c is the fit's
    statistical std (``uncertainty.components``: ``statistical``), U = 2 u_c, the 90 % interval
    value +- 1.645 u_c within the declared bounds, the flags against them; for views of a
    FitResult alone (``FitResult.to_xarray()``); a fit file is :func:`fit_document`'s."""
    z90 = 1.6448536269514722
    space = result.space
    by_name = {p.name: p for p in result.model.parameters}
    params, per = {}, {}
    for i, name in enumerate(space.names):
        entry = space.entries[i]
        p = by_name[entry.param]
        value, std = float(result.x[i]), float(result.std[i])
        item = {"value": value, "std": std, "u_combined": std, "U": K_EXPANDED * std, "k": K_EXPANDED,
                "unit": p.unit, "parameter": entry.param,
                "channel": space.channels[entry.channel] if entry.channel >= 0 else None,
                "ci90": [max(value - z90 * std, p.lower), min(value + z90 * std, p.upper)], "method": "laplace",
                "at_bound": name in result.at_bound, "undetermined": name in result.undetermined}
        item["flags"] = parameter_flags(item, p.lower, p.upper)
        params[name] = item
        per[name] = {"u_stat": std, "u_combined": std, "U": K_EXPANDED * std, "k": K_EXPANDED,
                     "budget": {"statistical": 1.0}}
    return jsonable({
        "model": {"name": result.model.name, "options": dict(result.model.options)}, "parameters": params,
        "covariance": {"names": list(space.names), "matrix": result.cov},
        "goodness": {"loss": result.loss, "chi2": result.chi2, "dof": result.dof, "chi2_dof": result.chi2_dof,
                     "n_used": result.n_used, "bic": result.bic, "rmse_fr": result.rmse_fr},
        "colour": None,
        "uncertainty": {"k": K_EXPANDED, "parameters": per,
                        "components": {"statistical": "the fit's own 1-sigma (no dataset budget given)"}}})


def fit_to_xarray(doc: dict, model=None):
    """A fit document as an :class:`xarray.Dataset` over ``parameter``: ``value``, ``std``
    (statistical), ``u_stat``, ``u_combined``, ``U`` (as the document states them,
    :func:`gonio.fitting.display.uncertainty_values`), ``ci90_low``, ``ci90_high``, ``lower``,
    ``upper`` (the model's declared bounds, NaN without ``model``), ``at_bound``,
    ``undetermined``, ``flags`` (text) and ``correlation`` (``parameter`` x ``parameter_b``);
    ``unit`` a coordinate; in the attributes the goodness, the model and options, the colour
    space of the per-channel values, ``k`` and the budget's components (JSON). The one layout of
    :meth:`FitFile.to_xarray` and :meth:`FitResult.to_xarray`."""
    import xarray as xr

    values = uncertainty_values(doc)
    names = list(values)
    table = doc.get("parameters") if isinstance(doc.get("parameters"), dict) else {}
    unc = doc.get("uncertainty") if isinstance(doc.get("uncertainty"), dict) else {}
    declared = {p.name: p for p in getattr(model, "parameters", ())}

    def item(n):
        return table[n] if isinstance(table.get(n), dict) else {}

    def ci(n, k):
        v = item(n).get("ci90")
        ok = isinstance(v, list) and len(v) == 2 and isinstance(v[k], (int, float))
        return float(v[k]) if ok else np.nan

    def bound(n, side):
        p = declared.get(item(n).get("parameter"))
        return float(getattr(p, side)) if p is not None else np.nan

    def column(key):
        return "parameter", np.array([values[n][key] for n in names], float)

    corr = np.full((len(names), len(names)), np.nan)
    cov = doc.get("covariance") if isinstance(doc.get("covariance"), dict) else {}
    try:
        c = np.asarray(cov.get("matrix"), float)
        order = [list(cov.get("names") or []).index(n) for n in names]
        c = c[np.ix_(order, order)]
        d = np.sqrt(np.clip(np.diag(c), 0.0, None))
        with np.errstate(invalid="ignore", divide="ignore"):
            corr = np.where(np.outer(d, d) > 0, c / np.outer(d, d), np.nan)
        np.fill_diagonal(corr, 1.0)
    except (TypeError, ValueError, IndexError):
        pass
    spec = doc.get("model") if isinstance(doc.get("model"), dict) else {}
    goodness = doc.get("goodness") if isinstance(doc.get("goodness"), dict) else {}
    attrs = {k: v for k, v in goodness.items() if isinstance(v, (int, float, str)) and not isinstance(v, bool)}
    colour = doc.get("colour") if isinstance(doc.get("colour"), dict) else {}
    attrs.update(model=str(spec.get("name", getattr(model, "name", ""))),
                 options=json.dumps(dict(spec.get("options") or {}), sort_keys=True),
                 colour_space=str(colour.get("space", "camera")), k=float(unc.get("k", K_EXPANDED)),
                 budget=json.dumps(unc.get("components") or {}, sort_keys=True))
    return xr.Dataset(
        {"value": column("value"), "std": column("std"), "u_stat": column("u_stat"), "u_combined": column("u_c"),
         "U": column("U"), "ci90_low": ("parameter", np.array([ci(n, 0) for n in names])),
         "ci90_high": ("parameter", np.array([ci(n, 1) for n in names])),
         "lower": ("parameter", np.array([bound(n, "lower") for n in names])),
         "upper": ("parameter", np.array([bound(n, "upper") for n in names])),
         "at_bound": ("parameter", np.array([bool(item(n).get("at_bound")) for n in names], bool)),
         "undetermined": ("parameter", np.array([bool(item(n).get("undetermined")) for n in names], bool)),
         "flags": ("parameter", [", ".join(FLAGS.get(f, f) for f in values[n]["flags"]) for n in names]),
         "correlation": (("parameter", "parameter_b"), corr)},
        coords={"parameter": names, "parameter_b": names, "unit": ("parameter", [values[n]["unit"] for n in names])},
        attrs=attrs)
