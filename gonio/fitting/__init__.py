"""gonio.fitting: turn a dataset into a few physical numbers, and say how sure they are.

- :func:`load_dataset` reads ``dataset.nc`` into :class:`Measurements` (unit directions in
  the local frame, f_r and its 1-sigma, a usable-value mask); NaN in used values raises.
- :func:`fit` is the constrained maximum-likelihood fit (stratified multi-start, parameters in
  which f_r is affine solved exactly, bounded Levenberg-Marquardt on the rest, a Gauss-Newton SQP
  polish under albedo <= 1 for models that can break it) with a Laplace covariance; :func:`sample_posterior` the emcee posterior with an autocorrelation check;
  :func:`select` model selection by BIC ("model only what the data needs").
- :func:`fit_document` / :func:`write_json_atomic` / :func:`load_fit`: the fit file (read back as a
  :class:`FitFile`: ``.model``, ``.params``, ``.document``, ``to_xarray()``, notebook reprs).
- :func:`fit_batch`: many datasets on Dask; :func:`crlb`: the Cramer-Rao bound;
  :func:`tune_allocator`: glibc's allocator set for fitting (the ``gonio`` command does it).
- :mod:`gonio.fitting.render`: Mitsuba re-renders the fit at the measured geometry;
  :mod:`gonio.fitting.formats` (MERL, RGL, Mitsuba snippets, CSV); :mod:`gonio.fitting.render.preview`.
"""

from gonio.fitting.likelihood.aperture import with_instrument_response
from gonio.fitting.batch.dask_batch import (check_dashboard_address, check_scheduler_address, check_workers, fit_batch, fit_serial)
from gonio.fitting.uncertainty.budget import Budget, BudgetComponent, load_budget
from gonio.fitting.uncertainty.crlb import crlb, efficiency
from gonio.fitting.measurements import (COLOUR_SPACES, DataError, Measurements, colour_transform, direction, load_dataset)
from gonio.fitting.formats.fitfile import FitFile, fit_document, load_fit, parse_fit, versions, write_json_atomic
from gonio.fitting.likelihood.loss import LOSSES, REAL_DEFAULT_LOSS, default_loss
from gonio.fitting.batch.malloc import tune as tune_allocator
from gonio.fitting.optimise.mle import FitResult, fit
from gonio.fitting.pipeline import FitInput, fit_dataset, fit_document_of, fit_measurements
from gonio.fitting.uncertainty.posterior import Posterior, sample_posterior
from gonio.fitting.realdata import merl_samples, rgl_samples
from gonio.fitting.selection.by_data import CANDIDATES, Ranked, option_candidates, select
from gonio.fitting.optimise.space import ParameterSpace
from gonio.fitting.optimise.tabulated_start import fit_tabulated

__all__ = [
    "FitInput", "fit_dataset", "fit_document_of", "fit_measurements",
    "Budget", "BudgetComponent", "load_budget", "with_instrument_response", "CANDIDATES", "DataError", "FitFile", "FitResult", "crlb", "efficiency", "fit_batch", "fit_serial", "LOSSES", "REAL_DEFAULT_LOSS", "default_loss", "Measurements", "ParameterSpace", "Posterior", "Ranked", "fit_tabulated",
    "COLOUR_SPACES", "colour_transform", "direction", "fit", "option_candidates", "rgl_samples", "merl_samples", "fit_document", "load_dataset", "load_fit", "sample_posterior", "select", "versions",
    "write_json_atomic", "parse_fit", "check_dashboard_address", "check_scheduler_address", "check_workers", "tune_allocator",
]
