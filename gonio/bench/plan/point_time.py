"""A time-budgeted plan's estimate of a point's instrument time before it is measured (issue 38).

A point's journalled time is the move the run makes to it (the session's own stage solution,
session.toml's ``[order] stage_deg``, at the session's axis speeds) and what the point costs there:
settling, the probe, the bracket, the monitor readings. The bracket's longest exposure brings the
darkest value of the regions to the noise floor's SNR (`gonio.bench.measure.hdr.choose_bracket`),
so it grows as 1 / s, s the darkest channel's f_r cos(theta_i) (radiance per unit irradiance);
it is the first rung of the ladder (factors of 2) that reaches it: up to twice what s needs.
`RestModel` fits the upper envelope rest <= a + b / s to the journalled points: a the least rest;
over the darker half (there the exposure is most of the rest), b the larger of the largest
(rest - a) s and twice its median (that ratio, a rung over the need, lies in [1, 2)); never less
than the brighter half's longest rest (a saturated probe is taken again, shorter).
A candidate's rest comes from the fitted model's s there, divided by how far the fit overstated s
at the measured points, and is never more than a + 2 exposure_max_s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["RestModel", "darkest"]


def darkest(f, theta_i_deg) -> np.ndarray:
    """s: the darkest channel's f_r cos(theta_i) of each point ((N, C) or (C,) f_r, (N,) or
    scalar theta_i in deg); non-finite values count as 0."""
    f = np.atleast_2d(np.asarray(f, float))
    c = np.clip(np.cos(np.radians(np.atleast_1d(np.asarray(theta_i_deg, float)))), 0.0, 1.0)
    return np.nan_to_num(np.min(f, axis=-1) * c, nan=0.0, posinf=0.0, neginf=0.0)


@dataclass(frozen=True)
class RestModel:
    """rest(s) = min(max(a + b / (q s), floor), cap), s (:func:`darkest`) as the fitted model
    predicts it.

    a, b : the envelope's least rest (s) and exposure coefficient (s x f_r); floor: the brighter
    half's longest rest; q in (0, 1]: the fit's
    worst overstatement of s at the measured points (their measured s over the predicted, the
    10th percentile); cap: a + 2 exposure_max_s. ``n``: the points it was fitted to (0: none,
    every point then costs ``a``, the plan's ``overhead_s``)."""

    a: float
    b: float
    q: float
    cap: float
    n: int = 0
    floor: float = 0.0

    @classmethod
    def fit(cls, rest, s_meas, s_pred, *, overhead_s: float, exposure_max_s: float) -> "RestModel":
        """From the journalled points' rest (their time less their move, s), their measured s
        and the fitted model's s there (None: no fit yet; q is then 1)."""
        rest, s_meas = np.asarray(rest, float), np.asarray(s_meas, float)
        ok = np.isfinite(rest) & np.isfinite(s_meas)
        rest, s_meas = rest[ok], s_meas[ok]
        if not len(rest):
            return cls(float(overhead_s), 0.0, 1.0, float(overhead_s), 0)
        a = max(0.0, float(np.min(rest)))
        lit = s_meas > 0
        b, floor = 0.0, float(np.max(rest))         # nothing lit: every point as the longest seen
        if lit.any():
            # a point measured at or below 0 (its darkest channel in the noise) counts as dark as
            # the darkest lit one: its time then raises b, not ignored (the same points otherwise)
            s_eff = np.where(lit, s_meas, np.min(s_meas[lit]))
            dark = s_eff <= np.median(s_eff)
            c = (rest[dark] - a) * s_eff[dark]
            b = max(0.0, float(np.max(c)), 2.0 * float(np.median(c)))
            floor = max(a, float(np.max(rest[~dark]))) if (~dark).any() else a
        q = 1.0
        if s_pred is not None:
            s_pred = np.asarray(s_pred, float)[ok]
            use = lit & np.isfinite(s_pred) & (s_pred > 0)
            if use.any():
                q = float(np.clip(np.percentile(s_meas[use] / s_pred[use], 10), 1e-3, 1.0))
        cap = a + 2.0 * float(exposure_max_s)
        return cls(a, b, q, max(cap, float(np.max(rest))), int(len(rest)), floor)

    def __call__(self, s) -> np.ndarray:
        """The rest (s) of points whose predicted :func:`darkest` is ``s``; ``cap`` where s <= 0."""
        s = np.asarray(s, float) * self.q
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(np.isfinite(s) & (s > 0), self.a + self.b / np.where(s > 0, s, 1.0), math.inf)
        return np.minimum(np.maximum(t, self.floor), self.cap)
