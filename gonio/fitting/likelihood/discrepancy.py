"""A likelihood for real data: the model's own discrepancy, fitted with the model.

Measured materials are never exactly a gonio model, and files such as RGL's ``.bsdf`` or
MERL's ``.binary`` carry no uncertainty at all. Here every value's variance is

    s^2 = sigma^2 + (rel * f_model)^2 + abs^2

(the data's own sigma, or 0 where it has none; a relative model-discrepancy term; an absolute
floor in sr^-1), and ``-2 ln L = sum_k w_k [(f_model,k - f_k)^2 / s_k^2 + ln s_k^2]`` (w the
sample's solid-angle weight, ``Measurements.weight``, mean 1) is maximised jointly over the
model's parameters and (rel, abs) by coordinate ascent, until (rel, abs) move by less than
1 %. The Laplace covariance is then the Fisher information with s.

References: Kennedy, M. C., O'Hagan, A. (2001). Bayesian calibration of computer models. JRSS
B 63(3). Carroll, R. J., Ruppert, D. (1988). Transformation and Weighting in Regression.
"""

# Why: a chi^2 with a fixed relative sigma hands the fit to whatever values have the smallest
# sigma (near-zero and negative ones), and its Laplace intervals describe the noise of a model
# that does not hold.
# Coordinate ascent: Kennedy & O'Hagan (2001) treat discrepancy as an additive error term; the
# alternating scheme is iteratively reweighted least squares (e.g. Carroll & Ruppert 1988,
# ch. 2, Chapman & Hall): the model by gonio's chi^2 fit with s fixed, then (rel, abs) in
# closed form over a 2-D minimisation with the model fixed. s follows the *model's* f_r, not
# the measured value, so a negative or zero measurement neither gets a vanishing sigma nor
# dominates the fit (the floor abs absorbs them).
# Intervals: on a material the model misses, the Laplace covariance is wider by about the
# Birge ratio of the plain chi^2 fit, and it describes how the parameters move between
# different geometries of the same material (the discrepancy at randomly chosen directions
# acts as independent error). The geometry-resampling test
# (tests/fitting/test_real_resampling.py) checks the real-data default, the log loss's
# sandwich intervals; this loss's intervals are not checked that way.

from __future__ import annotations

import dataclasses
import time

import numpy as np
from scipy.optimize import minimize

__all__ = ["fit_discrepancy", "noise_ml"]

#: (rel, abs) converged when both move by less than this fraction
TOL = 0.01
MAX_ITER = 6
#: lower bounds of the discrepancy: 0.5 % relative (below any measurement's calibration),
#: and an absolute floor of 1 % of the RMS model value
REL_FLOOR, ABS_FLOOR = 0.005, 0.01


def _variance(sigma0, f_model, rel, absf):
    return sigma0 ** 2 + (rel * f_model) ** 2 + absf ** 2


def noise_ml(r, sigma0, f_model, w, start=(0.1, 1e-3)):
    """(rel, abs, -2 ln L) maximising the weighted Gaussian likelihood of residuals ``r``
    (flattened used values) with s^2 = sigma0^2 + (rel f_model)^2 + abs^2."""
    scale = max(float(np.sqrt(np.mean(r * r))), 1e-12)
    # floors keep the likelihood bounded: without them s -> 0 where the model is ~0 and
    # -2 ln L -> -inf (the degenerate direction of any variance proportional to the mean)
    lo_rel, lo_abs = REL_FLOOR, ABS_FLOOR * max(float(np.sqrt(np.mean(f_model * f_model))), 1e-12)

    def nll(z):
        rel, absf = max(np.exp(z[0]), lo_rel), max(np.exp(z[1]) * scale, lo_abs)
        s2 = _variance(sigma0, f_model, rel, absf)
        return float(np.sum(w * (r * r / s2 + np.log(s2))))

    z0 = np.log([max(start[0], 1e-6), max(start[1] / scale, 1e-6)])
    best = None
    for z in (z0, np.log([0.1, 0.1]), np.log([1e-3, 1.0])):
        res = minimize(nll, z, method="Nelder-Mead", options={"xatol": 1e-6, "fatol": 1e-9, "maxiter": 800})
        if best is None or res.fun < best.fun:
            best = res
    rel, absf = max(float(np.exp(best.x[0])), lo_rel), max(float(np.exp(best.x[1]) * scale), lo_abs)
    return rel, absf, float(best.fun)


def fit_discrepancy(meas, model, fit, *, rng, nominal_sigma: bool | None = None, **fit_kwargs):
    """Fit ``model`` and its discrepancy (rel, abs) jointly; a :class:`FitResult` with
    ``loss = "discrepancy"``, its ``std`` and ``cov`` from the Fisher information with the
    fitted variance, ``chi2`` against that variance and ``discrepancy = {"rel", "abs",
    "neg2_loglik", "iterations", "converged"}``.

    ``fit`` is :func:`gonio.fitting.fit` (handed in: this module sits below it).
    ``nominal_sigma``: the data's sigma is a nominal placeholder, not a measured uncertainty
    (RGL and MERL files: ``meas.attrs["nominal_sigma"]``); it is then left out of s.
    """
    t0, c0 = time.perf_counter(), time.process_time()
    if nominal_sigma is None:
        nominal_sigma = bool(meas.attrs.get("nominal_sigma", False))
    use = meas.use
    sigma0_full = np.zeros_like(meas.brdf_std) if nominal_sigma else meas.brdf_std
    w_full = np.broadcast_to(meas.relative_weight()[:, None], meas.brdf.shape)
    w, sigma0 = w_full[use], sigma0_full[use]
    kwargs = dict(fit_kwargs)
    result = fit(meas, model, rng=rng, loss="chi2", **kwargs)
    rel, absf, n2ll = 0.1, 1e-3, np.inf
    converged, it, evals = False, 0, result.n_evals
    eff = meas
    for it in range(1, MAX_ITER + 1):
        f = np.asarray(model.eval(meas.wi, meas.wo, result.params), dtype=np.float64)
        r = (f - meas.brdf)[use]
        new_rel, new_abs, _ = noise_ml(r, sigma0, np.abs(f[use]), w, (rel, absf))
        moved = max(abs(new_rel - rel) / max(rel, 1e-12), abs(new_abs - absf) / max(absf, 1e-300))
        rel, absf = new_rel, new_abs
        s = np.sqrt(_variance(sigma0_full, np.abs(f), rel, absf))
        # the weighted likelihood: chi2 multiplies every residual by sqrt(w) itself
        eff = dataclasses.replace(meas, brdf_std=s, attrs=dict(meas.attrs))
        kwargs["n_local"] = min(kwargs.get("n_local", 3), 2)
        result = fit(eff, model, rng=rng, loss="chi2", **kwargs)
        evals += result.n_evals
        if moved < TOL:
            converged = True
            break
    # -2 ln L at the final model with the final (rel, abs)
    f = np.asarray(model.eval(meas.wi, meas.wo, result.params), dtype=np.float64)
    r = (f - meas.brdf)[use]
    s2 = _variance(sigma0, np.abs(f[use]), rel, absf)
    n2ll = float(np.sum(w * (r * r / s2 + np.log(s2))))
    chi2 = float(np.sum(w * r * r / s2))
    return dataclasses.replace(
        result, loss="discrepancy", objective=n2ll, chi2=chi2, n_evals=int(evals), time_s=time.perf_counter() - t0,
        cpu_s=time.process_time() - c0,
        converged=bool(result.converged and converged),
        method=f"{result.method} + model discrepancy (rel, abs) by coordinate ascent, {it} rounds",
        discrepancy={"rel": rel, "abs": absf, "neg2_loglik": n2ll, "iterations": it, "converged": converged,
                     "nominal_sigma": bool(nominal_sigma), "weighted": meas.weight is not None,
                     "_measurements": eff})
