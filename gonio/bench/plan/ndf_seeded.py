"""NDF-seeded plan strategy ``"ndf"``: a retro-reflection first pass, then points where the lobe is.

After Dupuy & Jakob (2018, sec. 4): a first pass measures near retro-reflection (wi close to
wo, where the half vector is the direction itself, so f_r there traces the NDF D(theta_h)) at
every incidence the candidates offer, completed by a spread of the rest; the model is fitted to
it; then each batch is drawn among the unmeasured candidates with probability proportional to
the fitted f_r cos(theta_o) (the light the lobe sends: its own importance sampling, as pgII
places samples by the fitted microfacet model's warping) times one plus the fit's predicted
relative uncertainty there, without replacement, from ``Generator([seed, batch, 7])``, so a
resume replays the same choices. Stops, budgets and the ``[strategy]`` keys are the
``adaptive`` strategy's (gonio.bench.plan.adaptive), which this one extends.
"""

# Reference: Dupuy, J., Jakob, W. (2018). An adaptive parameterization for efficient material
# acquisition and rendering. ACM TOG 37(6), 274: the retro-reflection pass (sec. 4.1) and the
# warped sampling of the second (sec. 4.2). A gonioreflectometer cannot put the detector on the
# source: "near" retro is the closest pair the candidate plan offers at each incidence, within
# RETRO_MAX_DEG.

from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

from gonio.core.channels import SRGB_Y

from gonio.bench.plan.adaptive import AdaptivePlan, spread_subset
from gonio.bench.plan.plans import Plan
from gonio.bench.plan.strategy import register_strategy

__all__ = ["NDFSeededPlan", "RETRO_MAX_DEG", "retro_points"]

#: the widest angle between wi and wo a first-pass point may have
RETRO_MAX_DEG = 20.0


def retro_points(wi: np.ndarray, wo: np.ndarray, theta_i_deg: np.ndarray, most: int) -> list[int]:
    """At each distinct incidence (theta_i to 1 deg), the candidate whose wo is closest to wi,
    where within :data:`RETRO_MAX_DEG`; at most ``most`` of them, spread over theta_i."""
    gap = np.degrees(np.arccos(np.clip(np.sum(wi * wo, axis=1), -1.0, 1.0)))
    key = np.round(theta_i_deg).astype(int)
    best = {}
    for i in np.argsort(gap, kind="stable"):
        if gap[i] <= RETRO_MAX_DEG and key[i] not in best:
            best[key[i]] = int(i)
    picks = [best[k] for k in sorted(best)]
    if len(picks) > most > 0:
        picks = [picks[int(round(j))] for j in np.linspace(0, len(picks) - 1, most)]
    return picks[:most] if most > 0 else []


class NDFSeededPlan(AdaptivePlan):
    """The ``ndf`` strategy (module notes); ``table`` is session.toml's ``[strategy]``."""

    name = "ndf"

    def __init__(self, plan: Plan, order: Sequence[int], table: Mapping):
        super().__init__(plan, order, table)
        if self.angle_noise:
            raise ValueError("[strategy] angle_noise: the ndf plan draws its points from the lobe, not by a "
                             "design's sigma; give angle_noise = false (or name = \"adaptive\")")
        rank = {int(i): k for k, i in enumerate(order)}
        n = len(self.batches[0])                 # the adaptive first pass's size, trimmed to budget_s
        retro = retro_points(self.wi, self.wo, plan.angles[:, 0], max(n - 2, 0) if n > 2 else n)
        first = retro + spread_subset(plan.angles, n - len(retro), retro)
        self.batches[0] = sorted(first, key=lambda i: (rank.get(i, len(rank)), i))
        self.retro = list(retro)

    def _pick(self, x, basis, queue, free, n_new, results, sigma_rel, sigma_floor, cov) -> list[int]:
        p = self.space.to_params(x)
        lum = np.array(SRGB_Y)
        f = np.asarray(self.model.eval(self.wi[free], self.wo[free], p), dtype=np.float64)
        light = np.clip(f, 0.0, None) @ lum * np.clip(self.wo[free, 2], 0.0, None)
        rel = self._predicted_rel_u(x, free, cov, f)
        w = light * (1.0 + rel)
        w = np.where(np.isfinite(w) & (w > 0), w, 0.0)
        k = min(n_new, int(np.count_nonzero(w)))
        if k == 0:
            return []
        rng = np.random.default_rng([self.seed, len(self.batches), 7])
        drawn = rng.choice(len(free), size=k, replace=False, p=w / w.sum())
        return self._by_travel([int(free[j]) for j in drawn], queue)

    def _predicted_rel_u(self, x, free, cov, f) -> np.ndarray:
        """The fit's relative 1-sigma of f_r (luminance) at each free candidate, from its
        covariance by central differences (0 where it has none)."""
        if cov is None or not np.all(np.isfinite(cov)):
            return np.zeros(len(free))
        lum = np.array(SRGB_Y)
        lo, hi = self.space.lower, self.space.upper
        J = np.empty((len(free), self.space.size))
        for j in range(self.space.size):
            h = 1e-4 * max(abs(x[j]), 1e-3 * (hi[j] - lo[j]))
            xp, xm = x.copy(), x.copy()
            xp[j], xm[j] = min(x[j] + h, hi[j]), max(x[j] - h, lo[j])
            fp = np.asarray(self.model.eval(self.wi[free], self.wo[free], self.space.to_params(xp))) @ lum
            fm = np.asarray(self.model.eval(self.wi[free], self.wo[free], self.space.to_params(xm))) @ lum
            J[:, j] = (fp - fm) / (xp[j] - xm[j])
        var = np.einsum("np,pq,nq->n", J, cov, J)
        base = np.abs(f @ lum)
        return np.where(base > 0, np.sqrt(np.clip(var, 0.0, None)) / np.where(base > 0, base, 1.0), 0.0)

    def _by_travel(self, picks: list[int], queue: Sequence[int]) -> list[int]:
        """``picks`` in nearest-neighbour order of the run's moves from the last queued pose."""
        out, left = [], list(picks)
        last = queue[-1] if queue else None
        while left:
            if last is None:
                nxt = left[0]
            else:
                nxt = left[int(np.argmin(self._moves(last, left)))]
            out.append(nxt)
            left.remove(nxt)
            last = nxt
        return out


register_strategy("ndf", NDFSeededPlan)
