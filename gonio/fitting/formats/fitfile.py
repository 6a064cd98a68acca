"""The fit file (JSON): what was fitted, how well, how sure, and how to render it.

Layout (docs/interfaces.md, architecture.md "A fit file"):
``model`` {name, options}; ``parameters`` {name: {value, std (statistical), u_combined, U, k,
ci90, coverage_intervals where not normal, unit, at_bound, undetermined, flags, method}}; ``covariance``; ``constraints``;
``goodness`` {chi2, dof, chi2_dof, rmse_fr, rmse_cos_fr, n_used, model_adequate and the
``adequacy`` test behind it: test, statistic, dof, p_value, alpha, verdict}; ``optimiser``;
``posterior`` (or null); ``selection`` (for ``--model auto``); ``mitsuba`` (the BSDF dict);
``provenance`` (versions, seed, dataset path and checksum); ``uncertainty`` (per parameter
u_stat, u_combined, U = k u_combined with k = 2, and its budget: docs/interfaces.md 5.1);
``non_finite`` (only when a
figure was NaN or infinite: the dotted paths written as null, since JSON has no NaN).
"""

from __future__ import annotations

import json
import math
import platform
import warnings
from datetime import datetime, timezone
from importlib import metadata
from pathlib import Path

import numpy as np

import gonio.models as gm
from gonio.core.channels import from_attrs, spectral, use
from gonio.core.errors import GonioError
from gonio.core.atomic import atomic_open
from gonio.core.files import sha256_file

from gonio.fitting.likelihood import loss as _loss
from gonio.fitting.uncertainty.adequacy import TEST_BUDGET, nominal_test
from gonio.fitting.uncertainty.budget import budget_from_attrs, propagate
from gonio.fitting.statement import K_EXPANDED, fit_to_xarray, jsonable as _jsonable, result_document  # noqa: F401
from gonio.fitting.display import UNCERTAINTY_HEADER, parameter_flags, table_html, text, uncertainty_rows
from gonio.fitting.formats.mitsuba_xml import mitsuba_document


__all__ = ["model_adequacy", "fit_document", "write_json_atomic", "load_fit", "parse_fit", "versions", "NonFiniteWarning",
           "FitFile"]

FIT_FORMAT = "gonio-fit/1"


class NonFiniteWarning(UserWarning):
    """A document held NaN or inf, which strict JSON cannot; they were written as null."""


def versions() -> dict:
    """Versions of gonio and the libraries whose numbers it reports."""
    out = {"python": platform.python_version()}
    for dist in ("gonio", "numpy", "scipy", "mitsuba", "drjit", "nlopt", "emcee", "xarray", "rawpy", "pyserial"):
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            pass
    return out


def _with_channels(wavelengths, fn, *args):
    """``fn(*args)`` with per-channel values exported as a spectral fit's ``wavelengths`` say."""
    with use(from_attrs(wavelengths)):
        return fn(*args)


def _mitsuba_or_none(wavelengths, model, params):
    """The fit's Mitsuba dict; None for a spectral fit of a model whose gonio plugin holds
    three channels only (its fit file is still written; ``gonio convert`` says why)."""
    try:
        return _with_channels(wavelengths, model.to_mitsuba, params)
    except ValueError:
        if not wavelengths:
            raise
        return None


def fit_wavelengths(doc, path="fit file"):
    """A fit document's ``wavelengths`` (nm, checked: gonio.core.channels.spectral), or None."""
    wl = doc.get("wavelengths")
    if wl is None:
        return None
    try:
        return spectral(wl).wavelengths_nm
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{path}: wavelengths: {' '.join(str(exc).split())[:120]}") from None


def fit_document(result, meas, *, seed=None, posterior=None, ranking=None, dataset_path=None, budget=None) -> dict:
    """Build the fit file's content from a FitResult (and optional posterior and ranking).

    ``budget``: the dataset's uncertainty budget (:func:`gonio.fitting.uncertainty.budget.load_budget`);
    None reads it from ``meas.attrs`` (type A and ``scale_rel_std``). It fills ``uncertainty``.
    """
    space = result.space
    z90 = 1.6448536269514722  # two-sided 90 % of a standard normal
    budget = budget if budget is not None else budget_from_attrs(meas)
    # the adequacy test (goodness.adequacy): a chi2 fit against its budget's covariance
    # (gonio.fitting.uncertainty.adequacy.adequacy_test, computed with the propagation), any
    # other loss against its nominal chi2 distribution
    test = None if result.loss == "chi2" else nominal_test(result)
    uncertainty = _uncertainty(result, meas, budget, result.std, result.cov, test)
    test = uncertainty.pop("adequacy")
    if uncertainty["statistical"] is not None and result.loss == "chi2":
        # the budget split type A into u_ lines: the statistical covariance is the type-A lines
        # propagated, scaled by sqrt(chi2 / E) where the test rejects the model
        adequate, inflation, warning = budget_adequacy(uncertainty["statistical"], test, result.chi2_dof)
    else:
        adequate, inflation, warning = model_adequacy(result, test)
        if inflation != 1.0:
            uncertainty = _uncertainty(result, meas, budget, result.std * inflation, result.cov * inflation ** 2, test)
            uncertainty.pop("adequacy")
    params = {}
    by_name = {p.name: p for p in result.model.parameters}
    for i, name in enumerate(space.names):
        entry = space.entries[i]
        p = by_name[entry.param]
        std = result.std[i] * inflation
        # a dataset with shared angle errors: the value corrected for their second-order term's
        # mean (gonio/fitting/uncertainty/budget.propagate; the optimiser's own point is ``value_fitted``, and the
        # ``params``/``mitsuba`` tables stay the optimiser's)
        shift = float(uncertainty["parameters"][name].get("angle_second_order_mean", 0.0))
        # and for the lines of known mean (a systematic of known sign left in the data: budget.propagate)
        known = float(uncertainty["parameters"][name].get("systematic_mean", 0.0))
        value = float(result.x[i]) - shift - known
        # one uncertainty statement: u_c, U and k beside the value (the uncertainty section's), the
        # 90 % interval from u_c (the statistical std alone left the truth out where type B dominates)
        unc = uncertainty["parameters"].get(name, {})
        u_c = float(unc.get("u_combined", std))
        item = {"value": value, "std": std, "u_combined": u_c, "U": float(unc.get("U", K_EXPANDED * u_c)),
                "k": float(unc.get("k", K_EXPANDED)), "unit": p.unit, "parameter": entry.param,
                "channel": space.channels[entry.channel] if entry.channel >= 0 else None,
                "ci90": [max(value - z90 * u_c, p.lower), min(value + z90 * u_c, p.upper)],
                "method": "laplace", "at_bound": name in result.at_bound, "undetermined": name in result.undetermined}
        q = unc.get("error_quantiles")
        if q:
            # a distribution that is not normal (the shared angle errors' quadratic term): its
            # coverage intervals from the distribution (JCGM 101 7.7), truth in [value - upper,
            # value - lower]; the 90 % interval is its own
            item["coverage_intervals"] = {lev: [value - hi, value - lo] for lev, (lo, hi) in q.items()}
            if "0.9" in q:
                lo, hi = q["0.9"]
                item["ci90"] = [max(value - hi, p.lower), min(value - lo, p.upper)]
            item["gaussian"] = bool(unc.get("gaussian", True))
        if shift != 0.0 or known != 0.0:
            item["value_fitted"] = result.x[i]
        if shift != 0.0:
            item["angle_second_order_correction"] = -shift
        if known != 0.0:
            item["systematic_correction"] = -known
        if inflation != 1.0:
            item["std_statistical"] = result.std[i]
        if posterior is not None and posterior.converged:
            # the posterior samples the data's noise only: its interval is widened by the budget's
            # part beyond it (u_B^2 = u_c^2 - u_stat^2, each side in quadrature), then corrected as
            # the value is, so the 90 % interval states the same u_c as the value (issue 34)
            q5, q50, q95 = (float(posterior.quantiles[q][i]) - shift - known for q in (5, 50, 95))
            wide = z90 * math.sqrt(max(u_c * u_c - std * std, 0.0))
            item.update(median=posterior.quantiles[50][i],
                        std_posterior=0.5 * (posterior.quantiles[84][i] - posterior.quantiles[16][i]),
                        ci90_posterior=[posterior.quantiles[5][i], posterior.quantiles[95][i]],
                        ci90=[max(q50 - math.hypot(q50 - q5, wide), p.lower), min(q50 + math.hypot(q95 - q50, wide), p.upper)],
                        method="emcee")
        item["flags"] = parameter_flags(item, p.lower, p.upper)
        params[name] = item
    doc = {
        "format": FIT_FORMAT,
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "model": {"name": result.model.name, "options": dict(result.model.options)},
        "params": _jsonable(result.params),
        "parameters": params,
        "covariance": {"names": space.names, "matrix": result.cov * inflation ** 2, "inflation": inflation},
        "constraints": {"energy": result.energy,
                        "reciprocity": {"by_construction": True,
                                        "note": "every gonio model is reciprocal (tests/models); data pairs are checked at capture"}},
        "goodness": {"loss": result.loss, "chi2": result.chi2, "dof": result.dof, "chi2_dof": result.chi2_dof,
                     "rmse_fr": result.rmse_fr, "rmse_cos_fr": result.rmse_cos_fr, "n_used": result.n_used,
                     "bic": result.bic,
                     # sqrt(chi2/dof) (Birge 1932): well above 1 means the model misses the data
                     # by more than its noise, and the 1-sigma values are statistical only
                     "birge_ratio": float(np.sqrt(result.chi2_dof)),
                     "model_adequate": adequate, "std_inflation": inflation, "warning": warning,
                     "adequacy": _adequacy_entry(test),
                     "criterion": {"loss": result.loss, "neg2_loglik": result.neg2_loglik, "k": result.k_criterion,
                                   "bic": result.bic},
                     "discrepancy": ({k: v for k, v in result.discrepancy.items() if not k.startswith("_")}
                                     if result.discrepancy else None)},
        "optimiser": {"method": result.method, "evaluations": result.n_evals, "time_s": result.time_s,
                      "converged": result.converged, "message": result.message,
                      "solved_linearly": list(result.linear)},
        "correlated": [list(pair) for pair in result.correlated],
        "posterior": None,
        "selection": [r.row() for r in ranking] if ranking else None,
        "mitsuba": _mitsuba_or_none(meas.attrs.get("wavelengths_nm"), result.model, result.params),
        # a spectral fit's channels: one wavelength (nm) per per-channel value, else null
        "wavelengths": list(meas.attrs["wavelengths_nm"]) if meas.attrs.get("wavelengths_nm") else None,
        # the colour space of every per-channel value here (gonio/fitting/measurements.load_dataset), the matrix
        # and what the fit leaves out; Mitsuba reads rgb as linear sRGB: only an srgb fit renders true colour
        "colour": meas.attrs.get("colour"),
        "scale_rel_std": _jsonable(meas.attrs.get("scale_rel_std")),
        "uncertainty": uncertainty,
        # the instrument's angular response in the forward model (gonio/fitting/likelihood/aperture.py), or null
        "instrument_response": getattr(result, "response", None),
        # the shared angle errors estimated with the fit (gonio/fitting/uncertainty/shared_angles.py), or null
        "shared_angles": getattr(result, "shared_angles", None),
        "provenance": {"versions": versions(), "seed": seed, "dataset": str(dataset_path) if dataset_path else None,
                       "dataset_sha256": sha256_file(dataset_path) if dataset_path and Path(dataset_path).exists() else None,
                       "dataset_seed": meas.attrs.get("seed")},
    }
    if posterior is not None:
        # at most 2000 thinned draws: enough for a corner plot, small enough for JSON
        samples = posterior.samples[:: max(1, len(posterior.samples) // 2000)][:2000]
        doc["posterior"] = {"converged": posterior.converged, "walkers": posterior.n_walkers,
                            "names": list(posterior.names), "samples": samples,
                            "steps": posterior.n_steps, "tau": posterior.tau, "independent_samples": posterior.n_independent,
                            "acceptance": posterior.acceptance, "time_s": posterior.time_s, "advice": posterior.advice,
                            "table_surrogate_error": posterior.surrogate_error}
    bad: list = []
    doc = _jsonable(doc, non_finite=bad)
    if bad:
        # said in the file: these figures were NaN or infinite and are written as null
        doc["non_finite"] = bad
    return doc


def _uncertainty(result, meas, budget, u_stat, cov_stat, adequacy=None) -> dict:
    """The ``uncertainty`` section: combined and expanded uncertainty and budget per parameter
    (docs/interfaces.md 5.1), and (key ``adequacy``, for the caller to take out) the adequacy
    test: ``adequacy`` where given, else the one the propagation computed."""
    budget = budget if budget is not None else budget_from_attrs(meas)
    out = propagate(result, meas, budget, u_stat, cov_stat, adequacy)
    return {"k": K_EXPANDED, "method": "first-order propagation of every budget component through the fit "
                                      "(correlated ones as shared nuisance errors; GUM 5.1, JCGM 102 6.2), and "
                                      "the shared angle errors' second-order term (its mean corrected in the values, GUM 3.2.4 "
                                      "and 4.1.4 note; its variance carried, GUM 5.1.2 note)",
            "budget_source": budget.source, "components": budget.describe(), "parameters": out["parameters"],
            "statistical": ({"method": "type-A components propagated through the fit (their channel correlation "
                                           "included); Birge factor against the point-wise budget", **out["birge"]}
                            if out["birge"] else None),
            "covariance_combined": {"names": list(result.space.names),
                                    "matrix": out["cov_statistical"] + out["cov_systematic"]},
            "adequacy": out["adequacy"] if out["adequacy"] is not None else nominal_test(result)}


#: what each adequacy test compares (goodness.adequacy.description)
_TESTS = {
    TEST_BUDGET: "chi-square test of the residuals against the dataset's uncertainty budget: the generalised "
                 "least-squares chi^2 r^T V^-1 r with V the budget's covariance (point-wise components, and one "
                 "nuisance input per shared error, each profiled out), chi^2 distributed with dof degrees of "
                 "freedom when the data scatter as the budget says",
    "chi2": "chi-square test of the residuals against the fit's sigma (brdf_std, the budget's type A): chi^2 "
            "against the chi^2 distribution with dof degrees of freedom",
}


def _adequacy_entry(test: dict) -> dict:
    """``goodness.adequacy``: which test, its statistic, dof, p-value and level alpha (its
    false-alarm rate), the points it left out (their rows: a cutoff of f_r within their angle
    law, where a linear budget says nothing), and the verdict."""
    desc = _TESTS.get(test["test"], test["test"])
    return {"test": test["test"], "description": desc, "statistic": test["statistic"], "dof": test["dof"],
            "p_value": test["p_value"], "alpha": test["alpha"], "false_alarm_rate": test["alpha"],
            "nuisance_inputs": test.get("nuisance_inputs", 0), "refined_steps": test.get("refined_steps", 0),
            "left_out": [int(i) for i in test.get("left_out", [])],
            "verdict": "adequate" if test["adequate"] else "inadequate"}


def _said(test: dict, chi2_dof: float) -> str:
    """The warning's head: chi2/dof, then the test that rejected the model, its p and level."""
    return (f"chi2/dof = {chi2_dof:.3g}; adequacy test {test['test']} = {test['statistic']:.4g} on {test['dof']} dof, "
            f"p = {test['p_value']:.2g} < alpha = {test['alpha']:g}")


def budget_adequacy(statistical, test: dict, chi2_dof: float | None = None) -> tuple[bool, float, str | None]:
    """(adequate, std inflation, warning or None) of a chi2 fit judged against its dataset's
    uncertainty budget: the verdict is ``test``'s
    (:func:`gonio.fitting.uncertainty.adequacy.adequacy_test`, at its level alpha); the inflation
    of a rejected model is ``statistical``'s factor sqrt(chi^2 / E)
    (gonio.fitting.uncertainty.budget.birge_against_budget: E what the budget makes chi^2 by
    itself; the plain Birge ratio would count the type-B lines' scatter again)."""
    if test["adequate"]:
        return True, 1.0, None
    factor = float(statistical["factor"])
    chi2_dof = float(statistical["chi2"]) / max(int(test["dof"]), 1) if chi2_dof is None else float(chi2_dof)
    return False, factor, (f"{_said(test, chi2_dof)}: the model misses the data by more than the uncertainty budget allows "
                           f"(chi2 = {float(statistical['chi2']):.4g} against the {float(statistical['chi2_expected']):.4g} "
                           f"the budget predicts); the statistical uncertainties are inflated by {factor:.3g}; "
                           "fit with --loss discrepancy for a fitted model-discrepancy term")


def model_adequacy(result, test: dict | None = None):
    """(adequate, std inflation, warning or None) of a fit.

    The verdict is ``test``'s (default :func:`gonio.fitting.uncertainty.adequacy.nominal_test`:
    chi^2 against the chi^2 distribution with the fit's dof, at level alpha =
    ``gonio.fitting.uncertainty.adequacy.ADEQUACY_ALPHA``). When it rejects, the model misses the data by more than the noise
    and the Laplace sigma describe only the noise: they are multiplied by the Birge ratio
    sqrt(chi^2/dof) (Birge 1932), the scale that makes chi^2/dof = 1, and the fit file says
    so. The ``log`` and ``cosine`` losses report the sandwich covariance of their own
    residuals (:func:`gonio.fitting.optimise.result.sandwich`), which already holds the discrepancy,
    so it is not inflated. The ``discrepancy`` likelihood fits that excess variance itself (its chi^2 is
    against it), so its sigma are reported as they are.
    """
    test = test if test is not None else nominal_test(result)
    if test["adequate"]:
        return True, 1.0, None
    chi2_dof = float(result.chi2_dof)
    if result.loss == "discrepancy":
        return False, 1.0, (f"{_said(test, chi2_dof)} against the fitted discrepancy variance: "
                            "the intervals include the model discrepancy but the fit is still poor")
    if result.loss in _loss.PROFILED:
        return False, 1.0, (f"{_said(test, chi2_dof)} against the nominal sigma: the model misses "
                            f"the data; the intervals are the sandwich covariance of the {result.loss} residuals, "
                            "which includes the model's discrepancy (not inflated again)")
    birge = float(np.sqrt(chi2_dof))
    return False, birge, (f"{_said(test, chi2_dof)}: the model misses the data by more than its "
                          f"noise; 1-sigma and 90 % intervals are inflated by the Birge ratio {birge:.3g} "
                          "(std_statistical keeps the noise-only values); fit with --loss discrepancy for a fitted "
                          "model-discrepancy term")


def write_json_atomic(path, doc) -> Path:
    """Write strict JSON (RFC 8259) to a temporary file beside ``path``, fsync, rename.

    NaN and +-inf, which JSON cannot hold, are written as null. A gonio fit document lists
    the places under ``non_finite``; for any other document a :class:`NonFiniteWarning` names them.
    Nothing is written when ``doc`` cannot be serialised.
    """
    bad: list = []
    clean = _jsonable(doc, non_finite=bad)
    if bad:
        if isinstance(clean, dict) and clean.get("format") == FIT_FORMAT:
            clean["non_finite"] = sorted(set(clean.get("non_finite") or []) | set(bad))
        else:
            warnings.warn(f"{path}: NaN or infinite values written as null at {', '.join(bad[:5])}"
                          + (f" and {len(bad) - 5} more" if len(bad) > 5 else ""), NonFiniteWarning, stacklevel=2)
    text = json.dumps(clean, indent=2, allow_nan=False) + "\n"
    with atomic_open(path, "w", encoding="utf-8") as fh:
        fh.write(text)
    return Path(path)


def _refuse_constant(name):
    raise ValueError(f"{name} is not JSON (a fit file is strict JSON; non-finite values are written as null)")


def parse_fit(doc, path="fit file"):
    """Check a fit document read from ``path``; return (model, params, document).

    Raises ValueError (a one-line reason) when it is not a gonio fit file or its model,
    options or parameter values are not what a fit file holds.
    """
    if not isinstance(doc, dict) or doc.get("format") != FIT_FORMAT:
        fmt = doc.get("format") if isinstance(doc, dict) else None
        raise ValueError(f"{path} is not a gonio fit file (format {fmt!r:.60})")
    spec = doc.get("model")
    if not isinstance(spec, dict) or not isinstance(spec.get("name"), str) or not isinstance(spec.get("options", {}), dict):
        raise ValueError(f"{path}: 'model' must hold a name and an options table")
    if not isinstance(doc.get("params"), dict):
        raise ValueError(f"{path}: 'params' must be a table of parameter values")
    try:
        model = gm.get(spec["name"], **spec.get("options", {}))
    except (KeyError, ValueError, TypeError) as exc:
        raise ValueError(f"{path}: model {spec['name']!r:.60} with options {spec.get('options')!r:.80}: "
                         f"{' '.join(str(exc).split())}") from None
    params = {}
    for k, v in doc["params"].items():
        ok = (isinstance(v, (int, float)) and not isinstance(v, bool)) or (
            isinstance(v, list) and v and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v))
        if not ok:
            raise ValueError(f"{path}: params.{k:.60} must be a number or a list of numbers, not {v!r:.60}")
        arr = np.asarray(v, dtype=np.float64)
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{path}: params.{k:.60} is not finite")
        params[k] = arr if isinstance(v, list) else float(v)
    wavelengths = fit_wavelengths(doc, path)
    counts = {np.size(v) for v in params.values() if isinstance(v, np.ndarray)}
    if wavelengths is not None and counts - {len(wavelengths)}:
        raise ValueError(f"{path}: {len(wavelengths)} wavelengths but per-channel values of {sorted(counts)}")
    try:                                # every value within its parameter's bounds (the model's own check)
        model.validate(params)
    except (ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{path}: {' '.join(str(exc).split())[:200]}") from None
    return model, params, doc


class FitFile:
    """A fit file read back (:func:`load_fit`): the model, its parameter values, the document.

    Attributes
    ----------
    model : gonio.models.Model
        The fitted model with its options.
    params : dict
        Parameter values (``model.eval(wi, wo, params)``), floats or per-channel arrays.
    document : dict
        The whole fit file (layout in this module's docstring).
    path : pathlib.Path or None
        Where it was read from.

    Unpacking it as ``model, params, doc = load_fit(path)`` still works (the tuple that
    ``load_fit`` returned before) but is deprecated.
    """

    def __init__(self, model, params: dict, document: dict, path=None):
        self.model, self.params, self.document = model, params, document
        self.path = Path(path) if path is not None else None

    def __iter__(self):
        warnings.warn("unpacking load_fit() as (model, params, document) is deprecated; use its .model, "
                      ".params and .document", DeprecationWarning, stacklevel=2)
        return iter((self.model, self.params, self.document))

    @property
    def parameters(self) -> dict:
        """``{name: {value, std, unit, ci90, ...}}`` per fitted parameter (one per channel)."""
        table = self.document.get("parameters")
        return table if isinstance(table, dict) else {}

    @property
    def goodness(self) -> dict:
        """chi2, dof, chi2_dof, rmse_fr, the adequacy verdict and its warning."""
        table = self.document.get("goodness")
        return table if isinstance(table, dict) else {}

    def eval(self, wi, wo):
        """f_r (N, C) in sr^-1 of the fit at unit directions ``wi`` (to the light), ``wo`` (to the detector)."""
        return self.model.eval(wi, wo, self.params)

    def to_mitsuba(self) -> dict:
        """The Mitsuba 3 BSDF dict (``mitsuba.load_dict`` accepts it; a ``spectrum`` per
        per-channel value for a spectral fit: render it in a ``*_spectral`` variant)."""
        return _with_channels(self.wavelengths, self.model.to_mitsuba, self.params)

    @property
    def wavelengths(self):
        """A spectral fit's wavelengths (nm), or None."""
        return fit_wavelengths(self.document)

    def to_mitsuba_xml(self) -> str:
        """A Mitsuba 3 XML file's text (``mitsuba.load_file`` and ``<include>`` load it)."""
        return _with_channels(self.wavelengths, mitsuba_document, self.model.name, dict(self.model.options),
                              self.params)

    def _summary(self):
        g = self.goodness
        options = ", ".join(f"{k}={v}" for k, v in dict(self.model.options).items())
        caption = f"{self.model.name}({options}) fit" + (f" from {self.path.name}" if self.path else "")
        notes = []
        if isinstance(g.get("chi2_dof"), (int, float)):
            notes.append(f"chi2/dof = {g['chi2_dof']:.4g} (dof {g.get('dof')}), loss {g.get('loss')}")
        unc = self.document.get("uncertainty")
        if isinstance(unc, dict) and isinstance(unc.get("components"), dict):
            notes.append("u_c: combined standard uncertainty of the budget (" + ", ".join(map(str, unc["components"]))
                         + f"); U = k u_c, k = {unc.get('k', 2)}")
        if g.get("warning"):
            notes.append(str(g["warning"]))
        return caption, uncertainty_rows(self.document), notes

    def __repr__(self) -> str:
        caption, rows, notes = self._summary()
        return text(caption, UNCERTAINTY_HEADER, rows, notes)

    def _repr_html_(self) -> str:
        caption, rows, notes = self._summary()
        return table_html(caption, UNCERTAINTY_HEADER, rows, notes)

    def to_xarray(self):
        """The fit as an :class:`xarray.Dataset`: :func:`fit_to_xarray` of its document (the
        one layout, also ``FitResult.to_xarray``'s)."""
        return fit_to_xarray(self.document, self.model)


def load_fit(path) -> FitFile:
    """Read a fit file into a :class:`FitFile` (``.model``, ``.params``, ``.document``).

    Raises
    ------
    ValueError
        A one-line reason when it is not a gonio fit file.
    """
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"), parse_constant=_refuse_constant)
    except UnicodeDecodeError:
        raise ValueError(f"{path} is not a gonio fit file (not UTF-8 text)") from None
    except RecursionError:
        raise ValueError(f"{path} is not a gonio fit file (nested too deeply)") from None
    model, params, doc = parse_fit(doc, path)
    return FitFile(model, params, doc, path)


def load_fit_file(path):
    """A fit file as (model, params), or one line saying it is not one."""
    try:
        loaded = load_fit(path)
        return loaded.model, loaded.params
    except (ValueError, KeyError, json.JSONDecodeError) as exc:
        raise GonioError(f"{path} is not a readable gonio fit file ({exc})") from None
