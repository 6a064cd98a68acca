"""Losses between a model and measured f_r, each written as a residual vector.

Writing every loss as residuals r (objective = sum rho(r^2)) lets one optimiser, one Jacobian
and one Laplace approximation serve all of them.

| name | residual | use |
|---|---|---|
| ``chi2`` | (f_model - f_meas) / sigma | maximum likelihood under the data's Gaussian noise model; the default, and the only loss whose covariance is calibrated |
| ``robust`` | as chi2, objective sum 2 (sqrt(1 + r^2) - 1) | outliers (soft-L1 / pseudo-Huber) |
| ``cosine`` | (f_model - f_meas) cos(theta_i) | the cosine-weighted L2 of Ngan, Durand & Matusik (2005) |
| ``log`` | ln(1 + f_model cos theta_i) - ln(1 + f_meas cos theta_i) | the E2 metric of Loew et al. (2012) |
| ``discrepancy`` | (f_model - f_meas) / s, s^2 = sigma^2 + (rel f_model)^2 + abs^2, (rel, abs) fitted with the model | real materials (:mod:`gonio.fitting._discrepancy`); the residuals here are chi2's on data whose sigma is already s |

References
----------
Ngan, A., Durand, F., Matusik, W. (2005). Experimental analysis of BRDF models. EGSR, sec. 4.
Loew, J., Kronander, J., Ynnerman, A., Unger, J. (2012). BRDF models for accurate and efficient
rendering of glossy surfaces. ACM TOG 31(1), eq. 11.
"""

from __future__ import annotations

import numpy as np

__all__ = ["LOSSES", "residuals", "objective", "objective_weights"]

LOSSES = ("chi2", "robust", "cosine", "log", "discrepancy")


def validate_loss(name: str) -> str:
    if name not in LOSSES:
        raise ValueError(f"unknown loss {name!r}: choose one of {', '.join(LOSSES)}")
    return name


def residuals(loss: str, model_fr, meas) -> np.ndarray:
    """Residuals of the used values, flattened (length ``meas.n_used``)."""
    cos_i = np.clip(meas.wi[:, 2:3], 0.0, 1.0)
    if loss in ("chi2", "robust", "discrepancy"):
        r = (model_fr - meas.brdf) / meas.brdf_std
    elif loss == "cosine":
        r = (model_fr - meas.brdf) * cos_i
    elif loss == "log":
        r = np.log1p(np.maximum(model_fr * cos_i, -0.999)) - np.log1p(np.maximum(meas.brdf * cos_i, -0.999))
    else:
        raise ValueError(f"unknown loss {loss!r}")
    return r[meas.use]


def residual_derivative(loss: str, model_fr, meas) -> np.ndarray:
    """d residual / d f_r per value, shape of ``model_fr`` (all values; :func:`residuals`
    keeps the used ones)."""
    if loss in ("chi2", "robust", "discrepancy"):
        return 1.0 / meas.brdf_std
    cos_i = np.broadcast_to(np.clip(meas.wi[:, 2:3], 0.0, 1.0), model_fr.shape)
    if loss == "cosine":
        return np.array(cos_i)
    if loss == "log":
        x = model_fr * cos_i
        return np.where(x > -0.999, cos_i / (1.0 + np.maximum(x, -0.999)), 0.0)
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
