"""Losses between a model and measured f_r, each written as a residual vector.

Writing every loss as residuals r (objective = sum rho(r^2)) lets one optimiser, one Jacobian
and one Laplace approximation serve all of them. Every residual is multiplied by sqrt(w), w the
sample's solid-angle weight relative to the mean (``Measurements.weight``; 1 without one), so
that sum r^2 is a solid-angle integral over the hemispheres.

| name | residual | use |
|---|---|---|
| ``chi2`` | (f_model - f_meas) / sigma | Gaussian maximum likelihood; the default, the only loss whose covariance is calibrated |
| ``robust`` | as chi2, objective sum 2 (sqrt(1 + r^2) - 1) | outliers (soft-L1 / pseudo-Huber) |
| ``cosine`` | (f_model - f_meas) cos(theta_i) | the cosine-weighted L2 of Ngan, Durand & Matusik (2005) |
| ``log`` | ln(1 + f_model cos theta_i) - ln(1 + f_meas cos theta_i) | the E2 metric of Loew et al. (2012); the default without a measured sigma (RGL, MERL) |
| ``discrepancy`` | (f_model - f_meas) / s, s^2 = sigma^2 + (rel f_model)^2 + abs^2 | real materials (:mod:`gonio.fitting.likelihood.discrepancy`) |
"""

# The weights make sum r^2 an integral over the hemispheres rather than a sum over however the
# directions were sampled. chi2 is maximum likelihood under the data's Gaussian noise model.
# log, for files without a measured sigma (RGL, MERL): a Gaussian likelihood of the log
# residuals with its scale profiled (BIC), intervals from the sandwich covariance
# (gonio.fitting.optimise.result.sandwich). discrepancy: (rel, abs) are fitted with the model;
# the residuals here are chi2's on data whose sigma is already s.
# References:
# Ngan, A., Durand, F., Matusik, W. (2005). Experimental analysis of BRDF models. EGSR, sec. 4.
# Loew, J., Kronander, J., Ynnerman, A., Unger, J. (2012). BRDF models for accurate and
# efficient rendering of glossy surfaces. ACM TOG 31(1), eq. 11.

from __future__ import annotations

import numpy as np

__all__ = ["LOSSES", "REAL_DEFAULT_LOSS", "residuals", "residual_function", "objective", "objective_weights",
           "value_weight"]

LOSSES = ("chi2", "robust", "cosine", "log", "discrepancy")
#: the loss ``gonio fit`` uses by default on files without a measured uncertainty (RGL
#: ``.bsdf``, MERL ``.binary``: ``attrs["nominal_sigma"]``); datasets keep ``chi2``
REAL_DEFAULT_LOSS = "log"


def default_loss(meas) -> str:
    """``chi2`` for data with a measured sigma; :data:`REAL_DEFAULT_LOSS` for files without."""
    return REAL_DEFAULT_LOSS if meas.attrs.get("nominal_sigma") else "chi2"


def value_weight(meas) -> np.ndarray:
    """sqrt of each sample's relative solid-angle weight, shape (N, 1): every residual is
    multiplied by it, so that sum r^2 is the solid-angle-weighted sum (ones without weights)."""
    if meas.weight is None:
        return np.ones((meas.n_points, 1))
    return np.sqrt(meas.relative_weight())[:, None]


def validate_loss(name: str) -> str:
    if name not in LOSSES:
        raise ValueError(f"unknown loss {name!r}: choose one of {', '.join(LOSSES)}")
    return name


def residuals(loss: str, model_fr, meas) -> np.ndarray:
    """Residuals of the used values, flattened (length ``meas.n_used``), each multiplied by
    the square root of its sample's solid-angle weight (:func:`value_weight`)."""
    cos_i = np.clip(meas.wi[:, 2:3], 0.0, 1.0)
    if loss in ("chi2", "robust", "discrepancy"):
        r = (model_fr - meas.brdf) / meas.brdf_std
    elif loss == "cosine":
        r = (model_fr - meas.brdf) * cos_i
    elif loss == "log":
        r = np.log1p(np.maximum(model_fr * cos_i, -0.999)) - np.log1p(np.maximum(meas.brdf * cos_i, -0.999))
    else:
        raise ValueError(f"unknown loss {loss!r}")
    if meas.weight is not None:
        r = r * value_weight(meas)
    return r[meas.use]


def residual_function(loss: str, meas):
    """``lambda f: residuals(loss, f, meas)`` with the data's parts computed once (cos
    theta_i, the measured log values, the solid-angle weights): the same operations in the
    same order, so equal to :func:`residuals` bit for bit. For a fit that evaluates the
    residuals many times on one dataset (differenced Jacobians: P + 1 a step); ``meas.use``
    is read at every call."""
    validate_loss(loss)
    cos_i = np.clip(meas.wi[:, 2:3], 0.0, 1.0)
    y = meas.brdf
    sw = value_weight(meas) if meas.weight is not None else None
    if loss in ("chi2", "robust", "discrepancy"):
        s = meas.brdf_std

        def raw(f):
            return (f - y) / s
    elif loss == "cosine":
        def raw(f):
            return (f - y) * cos_i
    else:
        ld = np.log1p(np.maximum(y * cos_i, -0.999))

        def raw(f):
            return np.log1p(np.maximum(f * cos_i, -0.999)) - ld

    def fn(model_fr):
        r = raw(model_fr)
        if sw is not None:
            r = r * sw
        return r[meas.use]

    return fn


def residual_derivative(loss: str, model_fr, meas) -> np.ndarray:
    """d residual / d f_r per value, shape of ``model_fr`` (all values; :func:`residuals`
    keeps the used ones), the solid-angle weight included."""
    sw = value_weight(meas)
    if loss in ("chi2", "robust", "discrepancy"):
        return sw / meas.brdf_std
    cos_i = np.broadcast_to(np.clip(meas.wi[:, 2:3], 0.0, 1.0), model_fr.shape)
    if loss == "cosine":
        return np.array(cos_i * sw)
    if loss == "log":
        x = model_fr * cos_i
        return np.where(x > -0.999, sw * cos_i / (1.0 + np.maximum(x, -0.999)), 0.0)
    raise ValueError(f"unknown loss {loss!r}")


def objective(loss: str, r: np.ndarray) -> float:
    """Scalar objective from residuals."""
    if loss == "robust":
        return float(np.sum(2.0 * (np.sqrt(1.0 + r * r) - 1.0)))
    return float(np.dot(r, r))


def objective_weights(loss: str, r: np.ndarray) -> np.ndarray:
    """d objective / d r, so that grad = J^T @ weights."""
    if loss == "robust":
        return 2.0 * r / np.sqrt(1.0 + r * r)
    return 2.0 * r
