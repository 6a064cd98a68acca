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
| ``luminance`` | (f_model - f_meas) cos theta_i / (a + Y cos theta_i) | a colour error relative to the pair's measured luminance Y (above a floor a): dark channels and dark pairs weigh as a colour difference does |
| ``discrepancy`` | (f_model - f_meas) / s, s^2 = sigma^2 + (rel f_model)^2 + abs^2 | real materials (:mod:`gonio.fitting.likelihood.discrepancy`) |
"""

# The weights make sum r^2 an integral over the hemispheres rather than a sum over however the
# directions were sampled. chi2 is maximum likelihood under the data's Gaussian noise model.
# log, for files without a measured sigma (RGL, MERL): a Gaussian likelihood of the log
# residuals with its scale profiled (BIC), intervals from the sandwich covariance
# (gonio.fitting.optimise.result.sandwich). discrepancy: (rel, abs) are fitted with the model;
# the residuals here are chi2's on data whose sigma is already s.
# luminance: a fixed weight per value, cos_i / (a + Y cos_i), Y the measured luminance of the
# pair (of its used values: Rec. 709 weights of its RGB, Y of XYZ, the channels' mean otherwise;
# at least 0), a = LUMINANCE_FLOOR times Y cos_i's solid-angle mean. CIELAB's chroma and hue
# scale with the colour's luminance, so a blue channel at 0.005 against a red at 0.05 weighs by
# its share of the colour, where the log loss (ln(1 + x) ~ x for x << 1) weighs it as an
# absolute, nearly nothing (docs/performance.md, leaf_maple). Like cosine, a weighted L2 without
# a noise model: its scale profiled, its covariance the sandwich.
# References:
# Ngan, A., Durand, F., Matusik, W. (2005). Experimental analysis of BRDF models. EGSR, sec. 4.
# Loew, J., Kronander, J., Ynnerman, A., Unger, J. (2012). BRDF models for accurate and
# efficient rendering of glossy surfaces. ACM TOG 31(1), eq. 11.

from __future__ import annotations

import numpy as np

from gonio.core.channels import LUMINANCE, SRGB_Y

__all__ = ["LOSSES", "LUMINANCE_FLOOR", "PROFILED", "REAL_DEFAULT_LOSS", "WEIGHTED_L2", "fixed_weight", "luminance", "residuals",
           "residual_function", "objective", "objective_weights", "value_weight"]

LOSSES = ("chi2", "robust", "cosine", "log", "luminance", "discrepancy")
#: losses that are an L2 of (f_model - f_meas) times a fixed weight, without a noise model
#: (their scale profiled in the likelihood, their covariance the sandwich)
WEIGHTED_L2 = ("cosine", "luminance")
#: losses without a noise model: the likelihood of their residuals has its scale profiled (one
#: parameter more in the BIC) and their covariance is the sandwich of their own residuals
PROFILED = ("log",) + WEIGHTED_L2
#: the luminance loss's floor a, as a fraction of Y cos_i's solid-angle mean: below it a pair's
#: error counts as an absolute one (kappa 0.1-1 rendered leaf_maple within 0.03 of each other)
LUMINANCE_FLOOR = 0.3
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


def luminance(values, use=None, space="srgb") -> np.ndarray:
    """Y of each row of ``values`` (N, C), shape (N, 1), at least 0: for three channels the
    luminance weights of ``space`` (:data:`gonio.core.channels.LUMINANCE`, sRGB's for a space
    it does not name), the channels' mean for other counts; only the values ``use`` marks (and finite ones) count, the weights
    renormalised over them (0 where a row has none)."""
    v = np.asarray(values, dtype=np.float64)
    ok = np.isfinite(v) if use is None else (np.asarray(use, bool) & np.isfinite(v))
    n = v.shape[1]
    w = np.asarray(LUMINANCE.get(str(space), SRGB_Y) if n == 3 else np.full(n, 1.0 / n), dtype=np.float64)
    num = np.where(ok, v, 0.0) @ w
    den = ok.astype(np.float64) @ w
    y = np.where(den > 0.0, num / np.where(den > 0.0, den, 1.0), 0.0)
    return np.maximum(y, 0.0)[:, None]


def fixed_weight(loss: str, meas) -> np.ndarray:
    """d residual / d f_r of a :data:`WEIGHTED_L2` loss, (N, 1), before the solid-angle
    weight: cos theta_i (cosine), cos theta_i / (a + Y cos theta_i) (luminance: Y of the used
    values, a over the pairs with one)."""
    cos_i = np.clip(meas.wi[:, 2:3], 0.0, 1.0)
    if loss == "cosine":
        return cos_i
    if loss != "luminance":
        raise ValueError(f"{loss!r} is not one of {WEIGHTED_L2}")
    space = (meas.attrs.get("colour") or {}).get("space", "srgb") if getattr(meas, "attrs", None) else "srgb"
    yc = luminance(meas.brdf, meas.use, space) * cos_i
    w = np.ones(meas.n_points) if meas.weight is None else np.asarray(meas.weight, dtype=np.float64)
    w = np.where(np.asarray(meas.use, bool).any(axis=1), w, 0.0)
    a = LUMINANCE_FLOOR * float(np.sum(w * yc[:, 0]) / np.sum(w)) if np.sum(w) > 0 else float("nan")
    if not (np.isfinite(a) and a > 0.0):
        raise ValueError("the luminance loss needs data with a positive mean luminance")
    return cos_i / (a + yc)


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
    elif loss in WEIGHTED_L2:
        r = (model_fr - meas.brdf) * fixed_weight(loss, meas)
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
    elif loss in WEIGHTED_L2:
        fw = fixed_weight(loss, meas)

        def raw(f):
            return (f - y) * fw
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
    if loss in WEIGHTED_L2:
        return np.array(np.broadcast_to(fixed_weight(loss, meas), model_fr.shape) * sw)
    cos_i = np.broadcast_to(np.clip(meas.wi[:, 2:3], 0.0, 1.0), model_fr.shape)
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
