"""``tabulated``'s sheen lobe (option ``sheen="ggx"``): a wide second lobe whose colour follows theta_d.

    S_c(wi, wo) = A_c(theta_d) D(theta_h; a) G1(wi; a) G1(wo; a) / (4 cos_i cos_o)

D the GGX (Trowbridge-Reitz) distribution and G1 its Smith masking (Walter et al. 2007, eqs. 33
and 34), a = ``sheen_alpha``; A_c piecewise linear in 1 - cos theta_d on tabulated's Fresnel
knots, ``sheen_0`` ... ``sheen_3`` per channel at theta_d = 0, 41.4, 60, 75.5 deg and 0 at
90 deg (no measured pair reaches it). A function of theta_h and theta_d, symmetric in the two
directions: reciprocal; non-negative; its directional albedo is at most max A_c (a normalised D
with its own Smith masking). The numpy value and its derivatives live here; the compiled kernel
and the Mitsuba plugin evaluate the same expression.
"""

# Why (issue 35, docs/performance.md "leaf_maple: a grazing sheen lobe"): a leaf's and a felt's
# blue channel is near 0 at small theta_d and rises toward grazing, while its red and green
# bodies hide the main lobe's tail; one lobe whose width follows theta_d cannot take that
# shape, a second wide lobe held near 0 at small theta_d can. The stable form: with
# q(w) = sqrt(cos^2 + a^2 sin^2), G1(w) / cos(w) = 2 / (cos + q), so
# S = A D / ((cos_i + q_i)(cos_o + q_o)), finite at grazing, and
# d ln S / d a = 2 / a - 4 a cos_h^2 / u - a sin_i^2 / (q_i (cos_i + q_i)) - (the same at o),
# u = a^2 cos_h^2 + sin_h^2 (D = a^2 / (pi u^2)).
#
# Reference: Walter, B., Marschner, S. R., Li, H., Torrance, K. E. (2007). Microfacet models for
# refraction through rough surfaces. EGSR.

from __future__ import annotations

import math

import numpy as np

from gonio.models.base import CHANNELS, Parameter

__all__ = ["ALPHA_BOUNDS", "N_SHEEN", "parameters", "amplitudes", "shape", "value", "columns"]

#: the amplitude knots that are parameters (the Fresnel knots but the last, held at 0)
N_SHEEN = 4
#: the sheen roughness's bounds (a lobe at least as wide as the main lobe's tail)
ALPHA_BOUNDS = (0.05, 1.0)
#: the default roughness and amplitude (no sheen)
DEFAULT_ALPHA = 0.4


def parameters(default, n_fresnel):
    """The sheen's parameters; ``default(name, value)`` gives each its start (the model's)."""
    out = [Parameter("sheen_alpha", default("sheen_alpha", DEFAULT_ALPHA), *ALPHA_BOUNDS, "1",
                     "the sheen lobe's GGX roughness")]
    for j in range(N_SHEEN):
        deg = math.degrees(math.acos(1.0 - j / (n_fresnel - 1)))
        out.append(Parameter(f"sheen_{j}", default(f"sheen_{j}", 0.0), 0.0, 1.0, "1",
                             f"sheen amplitude at theta_d = {deg:.1f} deg (0 at 90 deg)", per_channel=True))
    return tuple(out)


def amplitudes(p) -> np.ndarray:
    """The amplitude table (C, N_SHEEN + 1): the knots and 0 at theta_d = 90 deg."""
    a = np.zeros((CHANNELS, N_SHEEN + 1))
    for j in range(N_SHEEN):
        a[:, j] = p[f"sheen_{j}"]
    return a


def shape(alpha, ci, co, cos_h, ok):
    """(D / ((ci + q_i)(co + q_o)), d ln of it / d alpha), 0 where not ``ok``: the lobe per
    unit amplitude and its log-derivative."""
    a2 = alpha * alpha
    with np.errstate(all="ignore"):
        ci_, co_ = np.where(ok, ci, 1.0), np.where(ok, co, 1.0)
        ch2 = np.clip(np.where(ok, cos_h, 1.0), 0.0, 1.0) ** 2
        u = a2 * ch2 + (1.0 - ch2)
        si2, so2 = 1.0 - ci_ * ci_, 1.0 - co_ * co_
        qi, qo = np.sqrt(ci_ * ci_ + a2 * si2), np.sqrt(co_ * co_ + a2 * so2)
        unit = a2 / (math.pi * u * u) / ((ci_ + qi) * (co_ + qo))
        dln = 2.0 / alpha - 4.0 * alpha * ch2 / u - alpha * si2 / (qi * (ci_ + qi)) - alpha * so2 / (qo * (co_ + qo))
    return np.where(ok, unit, 0.0), np.where(ok, dln, 0.0)


def value(p, ci, co, cos_h, s_f, ok, interp):
    """S (N, C) at the pairs (``s_f`` the Fresnel knots' fractional index, ``interp``
    tabulated's linear interpolation of a (C, n) table)."""
    unit, _ = shape(float(p["sheen_alpha"]), ci, co, cos_h, ok)
    return interp(amplitudes(p), s_f) * unit[:, None]


def columns(p, ci, co, cos_h, ok, hats, interp, s_f):
    """(S (N, C), {parameter: d S / d parameter (N, C)}): ``hats`` the Fresnel knots' hat
    weights (N, 1) each; a per-channel amplitude's column c is d S_c / d A_{c, j}."""
    unit, dln = shape(float(p["sheen_alpha"]), ci, co, cos_h, ok)
    S = interp(amplitudes(p), s_f) * unit[:, None]
    J = {"sheen_alpha": S * dln[:, None]}
    for j in range(N_SHEEN):
        J[f"sheen_{j}"] = np.broadcast_to(hats[j] * unit[:, None], S.shape)
    return S, J
