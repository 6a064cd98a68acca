"""Coverage intervals of the fitted parameters where their distribution is not normal.

A narrow lobe's parameters answer the shared angle errors (stage zeros, holder tilt, wedge)
through a quadratic term, so the error of a corrected estimate is a e + (1/2) e^T H e - b plus
the normal rest: skewed and peaked, its ±u_c covering 85-90 % instead of 68 %. The standard
uncertainty u_c stays the distribution's standard deviation; the coverage intervals come from
the distribution itself (JCGM 101:2008 7.7, probabilistically symmetric), with the check of
JCGM 101 8 whether ±k u_c would have done.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["LEVELS", "MC_DRAWS", "MC_SEED", "error_quantiles", "gaussian_adequate"]

#: the coverage probabilities stated: 1 and 2 standard deviations of a normal, and 90 %
LEVELS = (0.6827, 0.90, 0.9545)
#: Monte Carlo draws of the error distribution (JCGM 101 7.2: the quantiles' standard error is
#: then about 0.3 % of u_c at the 95.45 % ends)
MC_DRAWS = 100_000
#: the draws' fixed seed: the same fit gives the same intervals
MC_SEED = 0x6A10


def error_quantiles(L: np.ndarray, H: np.ndarray, b: np.ndarray, var_rest: np.ndarray,
                    levels=LEVELS, draws: int = MC_DRAWS, rng: np.random.Generator | None = None) -> dict:
    """The error of each reported parameter, ``estimate - truth``, at the ends of each level's
    probabilistically symmetric interval: ``{level: (P, 2)}`` (lower, upper quantile).

    err_p = L_p e + (1/2) e^T H_p e - b_p + sqrt(var_rest_p) z, with e ~ N(0, I_K) the shared
    inputs (``L`` (P, K): the parameters' first-order shift per +1 sigma of each; ``H`` (P, K, K):
    their second derivatives; ``b`` = tr(H) / 2 the mean the estimate was corrected by) and z ~
    N(0, 1) the rest of the budget (``var_rest`` (P,), independent of e). The truth lies in
    [estimate - upper, estimate - lower] with the level's probability."""
    L, H = np.asarray(L, float), np.asarray(H, float)
    b, var_rest = np.asarray(b, float), np.clip(np.asarray(var_rest, float), 0.0, None)
    P, K = L.shape
    rng = np.random.default_rng(MC_SEED) if rng is None else rng
    e = rng.standard_normal((draws, K))
    z = rng.standard_normal((draws, P))
    err = e @ L.T - b[None, :] + z * np.sqrt(var_rest)[None, :]
    for p in range(P):                 # one parameter at a time: (draws, K) at most in memory
        err[:, p] += 0.5 * np.einsum("mk,mk->m", e @ H[p], e)
    if not np.all(np.isfinite(err)):
        raise ValueError("the error distribution has non-finite draws: the budget's terms are not finite")
    out = {}
    for p in levels:
        lo, hi = np.quantile(err, [(1.0 - p) / 2.0, (1.0 + p) / 2.0], axis=0)
        out[float(p)] = np.stack([lo, hi], axis=-1)
    return out


def gaussian_adequate(quantiles: np.ndarray, u_c: float, level: float = 0.9545) -> bool:
    """JCGM 101:2008 8.2: whether ``±k u_c`` (k the normal's for ``level``) matches the interval
    ``quantiles`` (lower, upper error quantiles) to within the numerical tolerance of u_c stated to
    two significant digits (delta = half a unit of its second digit)."""
    if not (u_c > 0.0 and math.isfinite(u_c)):
        return True
    from scipy import stats

    k = float(stats.norm.isf((1.0 - level) / 2.0))
    delta = 0.5 * 10.0 ** (math.floor(math.log10(u_c)) - 1)
    lo, hi = float(quantiles[0]), float(quantiles[1])
    return abs(lo + k * u_c) <= delta and abs(hi - k * u_c) <= delta
