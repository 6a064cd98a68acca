"""One fit of one dataset, the same wherever it is asked for.

``gonio fit``, ``gonio fit --batch`` (each worker), the demo and a notebook all call
:func:`fit_measurements` (the fit) or :func:`fit_dataset` (the fit, its posterior and its
fit document), so a single fit and a batch fit of the same data, model, options and seed
give the same model, options and parameters.

``model`` is a registered name or ``"auto"``; ``options`` are the user's. A named model
whose options leave its microfacet distribution open is fitted once per declared
distribution and the better one by BIC is kept (said in the ranking); ``tabulated`` starts
from the data; every fit is refined with the instrument's angular response where the
dataset declares its apertures. The starts draw from ``numpy.random.default_rng(seed)``.
A dataset reaches every path as one :class:`FitInput` (its Measurements and its budget), and
:func:`fit_document_of` writes the fit file from it wherever the fit ran.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from gonio.core.errors import GonioError
from gonio.fitting.formats.fitfile import load_fit_file  # noqa: F401  (re-exported: the use cases read fit files)

__all__ = ["FitInput", "as_fit_input", "data_as_fitted", "fit_dataset", "fit_document_of", "fit_measurements",
           "load_fit_file", "renders_measured", "check_estimate_angles",
           "parse_options", "resolve_candidates", "model_error"]


@dataclasses.dataclass
class FitInput:
    """What a fit of one dataset needs: its Measurements and its uncertainty budget.

    ``budget`` None: the budget of ``meas.attrs`` (:func:`gonio.fitting.uncertainty.budget.budget_from_attrs`:
    type A and the certificate). A dataset.nc's budget holds more (its ``u_`` lines, the shared
    angle inputs of an uncalibrated capture), so a file is opened once, as a FitInput
    (:func:`gonio.bench.dataset.reader.open_fit_input`), and the single fit, each batch worker
    and the fit document all take that.
    """

    meas: object
    budget: object = None


def as_fit_input(data) -> FitInput:
    """``data`` (a FitInput or Measurements) as a FitInput."""
    return data if isinstance(data, FitInput) else FitInput(data, None)


def parse_options(pairs) -> dict:
    """``["distribution=ggx", "anisotropic=true"]`` -> ``{"distribution": "ggx", "anisotropic": True}``."""
    out = {}
    for pair in pairs or []:
        key, sep, value = pair.partition("=")
        if not sep or not key:
            raise GonioError(f"model option {pair!r} is not KEY=VALUE (e.g. distribution=beckmann)")
        low = value.lower()
        out[key] = True if low == "true" else False if low == "false" else value
    return out


def model_error(exc, model, auto: bool) -> GonioError:
    """One line for a model the registry refused: the known models only when the model is the
    unknown thing (a bad option value names the option's own choices), and once."""
    import gonio.models as gm

    if model not in gm.names():
        return GonioError(f"unknown model {str(model)[:40]!r}: choose one of {', '.join(gm.names())}"
                          + (", or auto" if auto else ""))
    return GonioError(" ".join(str(exc.args[0] if exc.args else exc).split())[:300])


def resolve_candidates(model, options):
    """``model`` and ``options`` as select's candidates: None for auto (every candidate),
    else the named model's (one per declared distribution when none is given); one line each
    for what cannot be."""
    from gonio.fitting.selection.by_data import option_candidates

    if model == "auto":
        if options:
            raise GonioError("--option needs a named --model (auto tries every candidate with its own options)")
        return None
    try:
        return option_candidates(model, options)
    except (KeyError, ValueError, TypeError) as exc:
        raise model_error(exc, model, auto=True) from None


def renders_measured(dataset_path) -> bool:
    """A measured file Mitsuba renders (an RGL tensor .bsdf, a MERL .binary; not a Zemax
    table, which shares the .bsdf suffix: told by content) and a vectorised Mitsuba variant
    to take its scene's pixels with."""
    from gonio.fitting.formats.zemax import is_zemax_bsdf
    from gonio.models.mitsuba import mitsuba_variant

    if dataset_path is None or Path(dataset_path).suffix.lower() not in (".bsdf", ".binary"):
        return False
    return not is_zemax_bsdf(dataset_path) and mitsuba_variant().startswith("llvm")


def _rendered_choice(ranking, dataset_path, seed, meas=None, loss=None, progress=None):
    """BIC's ranking with the default scene's rendered check (selection.by_scene.rendered_choice;
    where no candidate renders within its threshold of a measured file, the data-driven
    ``tabulated`` model fitted from ``meas`` is tried too: selection.by_scene.data_driven);
    skipped, and said, where Mitsuba has only its scalar variant (a render would take minutes)."""
    from gonio.fitting.formats.zemax import is_zemax_bsdf
    from gonio.fitting.selection.by_scene import data_driven, rendered_choice
    from gonio.models.mitsuba import mitsuba_variant

    by_bic = next(r for r in ranking if r.chosen)
    if not mitsuba_variant().startswith("llvm"):
        return by_bic.result, ranking, "BIC's choice: no vectorised Mitsuba variant for the default scene's renders"
    path = Path(dataset_path) if dataset_path is not None else None
    measured = str(path) if path is not None and path.suffix.lower() in (".bsdf", ".binary") else None
    if measured is not None and is_zemax_bsdf(path):
        measured = None         # a Zemax table: the best-supported fit is the reference, as for a dataset
    fallback = data_driven(meas, seed=seed, loss=loss) if meas is not None and measured is not None else None
    return rendered_choice(ranking, measured, seed=seed, fallback=fallback, progress=progress)


def check_estimate_angles(budget, loss, name=None) -> bool:
    """Whether ``budget`` states shared angle inputs; GonioError (one line) where the estimate
    is asked for with a loss other than chi2, or (``name``: the dataset, for an explicit
    request) where the budget states none. Called before any fit."""
    shared = (getattr(budget, "angles", None) or {}).get("shared")
    stated = shared is not None and bool(np.size(shared))
    if stated and loss != "chi2":
        raise GonioError(f"estimating the shared angle errors needs the chi2 loss (the data's own sigma), not {loss}")
    if name is not None and not stated:
        raise GonioError(f"--estimate-angles: {name} states no shared angle errors (a dataset.nc whose budget "
                         "carries the stages' zero offsets, the holder's tilt or the wedge); leave it out")
    return stated


def fit_measurements(meas, *, model="auto", options=None, seed=0, loss=None, budget=None, dataset_path=None,
                     rng=None, progress=None, estimate_angles=None):
    """Fit (or select) a model on ``meas``.

    Returns ``(result, meas, budget, ranking, note)``: the FitResult; the Measurements and
    budget as the instrument's angular response left them; the BIC ranking where candidates
    were compared (else None); the selection rule where the rendered check decided (else None).
    ``loss`` None: chi2 for a dataset with measured sigma, the real-data default otherwise.
    ``rng``: the Generator of the starts (default ``numpy.random.default_rng(seed)``); the
    refit with the angular response always starts from ``default_rng(seed)``. ``progress``:
    ``progress(done, total, label)`` from the model selection's fits and renders (None: silent).
    ``estimate_angles``: the budget's shared angle inputs (stage zero offsets, holder tilt,
    wedge) estimated with the fit and the data refitted at the geometry they give
    (gonio/fitting/uncertainty/shared_angles.py). None (default): wherever the budget states
    them and the loss is chi2; True: the same, another loss refused; False: never.
    """
    import gonio.models as gm
    from gonio.fitting.likelihood.aperture import with_instrument_response

    if isinstance(meas, FitInput):
        if budget is not None:
            raise TypeError("give the budget in the FitInput or as budget=, not both")
        meas, budget = meas.meas, meas.budget
    from gonio.fitting.likelihood.loss import LOSSES, default_loss
    from gonio.fitting.optimise.mle import fit
    from gonio.fitting.selection.by_data import select

    from gonio.models.base import MIN_SPECTRAL

    if meas.n_channels != 3 and meas.n_channels < MIN_SPECTRAL:
        raise GonioError(f"the data hold {meas.n_channels} wavelength(s): a fit takes three colour channels or at "
                         f"least {MIN_SPECTRAL} wavelengths; capture with a smaller [spectral] step_nm")
    if loss is None:
        loss = default_loss(meas)
    if loss not in LOSSES:
        raise GonioError(f"unknown loss {str(loss)[:40]!r}: choose one of {', '.join(LOSSES)}")
    if estimate_angles:                                     # before the fit
        check_estimate_angles(budget, loss)
    elif estimate_angles is None:
        estimate_angles = check_estimate_angles(budget, "chi2") and loss == "chi2"
    rng = np.random.default_rng(seed) if rng is None else rng
    ranking, note = None, None
    candidates = resolve_candidates(model, options)
    if candidates is None and renders_measured(dataset_path):
        from gonio.fitting.selection.auto import auto_fit

        try:     # a measured file: screened on a subsample, chosen by the default scene's pixels, refitted
            result, ranking, note = auto_fit(meas, str(dataset_path), seed=seed, loss=loss, rng=rng,
                                             progress=progress)
        except ValueError as exc:
            raise GonioError(str(exc)) from None
    elif candidates is None:
        from gonio.fitting.selection.spectral import SCREEN, with_covariance

        spectral = bool(meas.attrs.get("wavelengths_nm"))      # screened without covariance, the kept one finished
        result, ranking = select(meas, rng=rng, loss=loss, progress=progress, **(SCREEN if spectral else {}))
        result, ranking, note = _rendered_choice(ranking, dataset_path, seed, meas=meas, loss=loss, progress=progress)
        if spectral:
            result = with_covariance(meas, result)
            next(r for r in ranking if r.chosen).result = result
    else:
        try:
            if len(candidates) > 1:     # no distribution given: each declared one, chosen by BIC (said)
                result, ranking = select(meas, rng=rng, loss=loss, candidates=candidates, delta=0.0, progress=progress)
            elif model == "tabulated":      # data-driven NDF: started from the data, not from defaults
                from gonio.fitting.optimise.tabulated_start import fit_tabulated

                result = fit_tabulated(meas, rng=rng, loss=loss, **candidates[0][1])     # its options: body, sheen
            else:
                result = fit(meas, gm.get(model, **candidates[0][1]), rng=rng, loss=loss)
        except ValueError as exc:
            raise GonioError(str(exc)) from None
    # the instrument's angular response, where the dataset declares its apertures (likelihood/aperture.py)
    chosen = result.model
    raw = (meas, budget)                # as opened: the shared-angle estimate corrects the response where it moves them
    refits = []                         # the fit's time is all of it: the refits below count too

    def refit(m, near=None):           # with the loss the fit was made with (auto's refinement: its own)
        r = fit(m, chosen, rng=np.random.default_rng(seed), loss=first.loss,
                **({} if near is None else {"start": near.params, "n_starts": 0}))
        refits.append(r)
        return r

    first = result
    try:
        result, meas, budget = with_instrument_response(meas, budget, result, refit)
        if estimate_angles:             # a no-op where the budget states no shared angle inputs
            from gonio.fitting.uncertainty.shared_angles import with_shared_angles

            # each refit local, from the fit so far
            result, meas, budget = with_shared_angles(meas, budget, result, refit, raw=raw)
    except ValueError as exc:
        raise GonioError(str(exc)) from None
    return _with_time_of(result, [first, *refits]), meas, budget, ranking, note


def _with_time_of(result, fits):
    """``result`` with the time, evaluations and CPU seconds of all ``fits`` (the fit and the
    refits the angular response and the shared-angle estimate made: the fit file's optimiser
    time is what the fit took, not its last refit's), its method saying so."""
    if len(fits) < 2:
        return result
    cpu = [f.cpu_s for f in fits]
    return dataclasses.replace(result, time_s=float(sum(f.time_s for f in fits)),
                               n_evals=int(sum(f.n_evals for f in fits)),
                               cpu_s=None if any(c is None for c in cpu) else float(sum(cpu)),
                               method=f"{result.method}; evaluations and time over the fit and its {len(fits) - 1} "
                                      "refits (angular response, shared angle errors)")


def fit_dataset(meas, *, model="auto", options=None, seed=0, loss=None, posterior=False,
                posterior_budget_s=None, dataset_path=None, budget=None, progress=None, estimate_angles=None):
    """Fit (or select) a model; return (FitResult, fit document, Posterior or None).

    ``budget``: the dataset's uncertainty budget (:func:`gonio.fitting.load_budget`; None:
    from ``meas.attrs``), carried into every parameter's combined uncertainty.

    ``loss`` None: chi2 for a dataset with measured sigma, the real-data default
    (:data:`gonio.fitting.REAL_DEFAULT_LOSS`) for an RGL or MERL file. ``progress``: as
    :func:`fit_measurements`'s, and so is ``estimate_angles``."""
    from gonio.fitting.likelihood.loss import default_loss
    from gonio.fitting.uncertainty.posterior import sample_posterior

    if isinstance(meas, FitInput):
        if budget is not None:
            raise TypeError("give the budget in the FitInput or as budget=, not both")
        meas, budget = meas.meas, meas.budget
    if loss is None:
        loss = default_loss(meas)
    if posterior and loss != "chi2":
        raise GonioError("--posterior needs the chi2 loss (the likelihood of the data's noise model)")
    rng = np.random.default_rng(seed)       # the starts, then the posterior's walkers: one stream
    result, meas, budget, ranking, note = fit_measurements(meas, model=model, options=options, seed=seed, loss=loss,
                                                           budget=budget, dataset_path=dataset_path, rng=rng,
                                                           progress=progress, estimate_angles=estimate_angles)
    post = None
    if posterior:
        # With a time budget: chunks of 250 steps, so the budget is checked every second or
        # two (the sampler integrates the linear parameters out and evaluates the walkers in
        # one batch: 32 walkers on 100 points take ~2 ms a step).
        post = sample_posterior(meas, result, rng=rng, time_budget_s=posterior_budget_s,
                                **({"chunk": 250} if posterior_budget_s else {}))
    doc = fit_document_of(result, FitInput(meas, budget), seed=seed, posterior=post, ranking=ranking,
                          dataset_path=dataset_path, fitted=True)
    if note:
        doc["selection_rule"] = note
    return result, doc, post


def fit_document_of(result, data, *, seed=None, posterior=None, ranking=None, dataset_path=None,
                    fitted: bool = False) -> dict:
    """The fit file of ``result``, a fit of ``data`` (FitInput or Measurements, as the dataset
    was opened): the data and budget as the instrument's angular response left them (the
    result's own correction applied again where ``fitted`` is False), then
    :func:`gonio.fitting.formats.fitfile.fit_document`. ``fitted`` True: ``data`` is already
    what :func:`fit_measurements` returned."""
    from gonio.fitting.formats.fitfile import fit_document

    inp = as_fit_input(data)
    meas, budget = (inp.meas, inp.budget) if fitted else data_as_fitted(inp.meas, inp.budget, result)
    return fit_document(result, meas, seed=seed, posterior=posterior, ranking=ranking, dataset_path=dataset_path,
                        budget=budget)


def data_as_fitted(meas, budget, result):
    """``(meas, budget)`` of the dataset as opened, as ``result``'s fit saw them: divided by its
    angular response's c (``response_factor``), at the geometry and irradiance its shared-angle
    estimate gave them (:func:`gonio.fitting.uncertainty.shared_angles.applied`)."""
    from gonio.fitting.likelihood.aperture import corrected
    from gonio.fitting.uncertainty.shared_angles import applied

    factor = getattr(result, "response_factor", None)
    if factor is not None:
        meas, budget = corrected(meas, budget, factor)
    return applied(meas, budget, result)
