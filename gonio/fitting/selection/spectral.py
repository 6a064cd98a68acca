"""``--model auto`` on spectral data: every candidate screened without its covariance, one finished.

A spectral file (one channel per wavelength, ``attrs["wavelengths_nm"]``) is ranked like any
other (:func:`gonio.fitting.selection.by_data.select`: BIC; the candidates of
:func:`~gonio.fitting.selection.by_data.candidates_for`, which add the ``spectral_candidate``
models), but each candidate is fitted without the sandwich covariance of the ``log`` and
``cosine`` losses (2 P + 1 Jacobians and a Hessian: half or more of a candidate's time at
P = 40-160 parameters); the optimum is the same. Only the fit that is kept gets it
(:func:`with_covariance`), once the rendered check has chosen.
"""

from __future__ import annotations

__all__ = ["SCREEN", "with_covariance"]

#: what each candidate's fit skips on spectral data (``select(..., **SCREEN)``)
SCREEN = {"covariance": False}


def with_covariance(meas, result):
    """``result`` (a fit of ``meas`` made with ``covariance=False``) with the sandwich
    covariance its loss reports (:func:`gonio.fitting.optimise.result.robust_covariance`), as
    :func:`gonio.fitting.optimise.mle.fit` gives it by default; unchanged for the losses whose
    covariance is the Laplace one (chi2, robust, discrepancy)."""
    from gonio.fitting.likelihood.problem import Problem
    from gonio.fitting.optimise.mle import ROBUST_COV
    from gonio.fitting.optimise.result import robust_covariance

    if result.loss not in ROBUST_COV or "sandwich" in result.method:
        return result
    return robust_covariance(result, meas, Problem(meas, result.model, result.space, result.loss, linear=[]))
