"""Sequential-design plan strategy ``"adaptive"``: measure where the fit learns the most.

A first pass takes a spread subset of the candidate plan (farthest-point sampling in an
isotropic (wi, wo) feature space); then, batch by batch, the model is fitted to the results
so far (`gonio.fitting.fit`) and the unmeasured candidates that raise log det of the Fisher
information J^T W J the most (D-optimality, greedy within a batch; Atkinson, Donev & Tobias
2007, ch. 10-12) are queued, per second of stage travel and point overhead when ``travel``
is on (`gonio.bench.plan.ordering` times the moves). It stops at ``points`` or once every
fitted parameter's relative 1-sigma is below ``target_rel_u``; :attr:`AdaptivePlan.stopped_by`
says which. Each batch is chosen from the results of the points queued before it, less the
last one (the stages are moving to it meanwhile), so a resume replays the same choices.

Public: `AdaptivePlan`, `DEFAULTS`, `cli_strategy`; registered in
`gonio.bench.plan.strategy.STRATEGIES` on import.
"""

from __future__ import annotations

import math
import time
from typing import Any, Mapping, Sequence

import numpy as np

from gonio.bench.plan import kinematics
from gonio.bench.plan.ordering import cost_matrix, mirror
from gonio.bench.plan.plans import Plan
from gonio.bench.plan.strategy import Result, register_strategy

__all__ = ["AdaptivePlan", "DEFAULTS", "cli_strategy", "spread_subset"]

#: session.toml's ``[strategy]`` keys and their defaults (``name = "adaptive"`` besides).
DEFAULTS: dict[str, Any] = {
    "points": 24,                 # the budget: the most points measured
    "target_rel_u": 0.0,          # stop once every parameter's 1-sigma / |value| is below this (0: never)
    "first": 0,                   # first-pass points (0: max(P + 1, min(points // 2, 8)))
    "batch": 3,                   # points chosen per fit
    "model": "roughplastic",
    "options": {"distribution": "ggx"},
    "fixed": {},                  # parameters held at a value
    "n_starts": 4,                # the fit's stratified starts (few: it runs while the stages move)
    "seed": 0,                    # the fits' starts draw from Generator([seed, batch])
    "travel": True,               # score = information gain / (overhead_s + travel time)
    "overhead_s": 5.0,            # per-point settle, bracket and reduction time, s
    "model_rel_u": 0.0,           # relative 1-sigma of what the noise leaves out (model, systematics)
}


def _features(angles: np.ndarray) -> np.ndarray:
    """(N, 6) points of an isotropic BRDF's domain: wi turned to phi = 0, wo by the same
    rotation with its y mirrored (f(phi_d) = f(-phi_d))."""
    t_i, p_i, t_o, p_o = np.radians(angles.T)
    phi_d = p_o - p_i
    wi = np.stack([np.sin(t_i), np.zeros_like(t_i), np.cos(t_i)], -1)
    wo = np.stack([np.sin(t_o) * np.cos(phi_d), np.abs(np.sin(t_o) * np.sin(phi_d)), np.cos(t_o)], -1)
    return np.concatenate([wi, wo], -1)


def spread_subset(angles: np.ndarray, n: int, taken: Sequence[int] = ()) -> list[int]:
    """``n`` more candidates by farthest-point sampling (Gonzalez 1985) in `_features` space,
    after ``taken`` (none: starting from the candidate nearest the pool's centroid); ties go to
    the lower index."""
    x = _features(np.asarray(angles, float))
    ref = [int(i) for i in taken]
    chosen: list[int] = []
    if not ref and n > 0:
        chosen.append(int(np.argmin(np.sum((x - x.mean(0)) ** 2, 1))))
    d = np.full(len(x), np.inf)
    for k in ref + chosen:
        d = np.minimum(d, np.sum((x - x[k]) ** 2, 1))
    d[ref + chosen] = -1.0
    while len(chosen) < n:
        k = int(np.argmax(d))
        if not d[k] > 0:
            break
        chosen.append(k)
        d = np.minimum(d, np.sum((x - x[k]) ** 2, 1))
        d[k] = -1.0
    return chosen


class AdaptivePlan:
    """The ``adaptive`` strategy (module notes); ``table`` is session.toml's ``[strategy]``.

    Attributes
    ----------
    batches : list of list of int
        The points chosen so far, batch by batch (batch 0 is the first pass).
    log : list of dict
        Per batch chosen after the first: the points it was chosen from (``n``), the fit
        (``params``, ``rel_u``), ``fit_s`` and ``choose_s`` (wall seconds), ``chosen``.
    stopped_by : str or None
        ``"budget"``, ``"target"`` or ``"candidates"`` once the strategy adds nothing more.
    """

    name = "adaptive"

    def __init__(self, plan: Plan, order: Sequence[int], table: Mapping):
        import gonio.models as gm
        from gonio.fitting.optimise.space import ParameterSpace

        unknown = set(table) - set(DEFAULTS) - {"name"}
        if unknown:
            raise ValueError(f"[strategy] adaptive: unknown key {sorted(unknown)[0]!r}; known: {', '.join(DEFAULTS)}")
        t = {**DEFAULTS, **{k: v for k, v in table.items() if k != "name"}}
        self.plan = plan
        self.points = _int(t, "points", 1)
        self.batch = _int(t, "batch", 1)
        self.n_starts = _int(t, "n_starts", 1)
        self.seed = _int(t, "seed", 0)
        self.target_rel_u = float(t["target_rel_u"])
        self.overhead_s = float(t["overhead_s"])
        self.model_rel_u = float(t["model_rel_u"])
        if not (self.model_rel_u >= 0 and math.isfinite(self.model_rel_u)):
            raise ValueError(f"[strategy] model_rel_u = {t['model_rel_u']!r}: give a number >= 0")
        if not (self.target_rel_u >= 0 and math.isfinite(self.target_rel_u)):
            raise ValueError(f"[strategy] target_rel_u = {t['target_rel_u']!r}: give a number >= 0")
        if not self.overhead_s > 0:
            raise ValueError(f"[strategy] overhead_s = {t['overhead_s']!r}: give a time > 0 s")
        self.travel = bool(t["travel"])
        self.options, self.fixed = dict(t["options"]), dict(t["fixed"])
        try:
            self.model = gm.get(str(t["model"]), **self.options)
        except Exception as exc:
            raise ValueError(f"[strategy] model {t['model']!r}: {exc}") from None
        self.model_name = str(t["model"])
        self.space = ParameterSpace(self.model, 3, self.fixed)
        first = _int(t, "first", 0) or max(self.space.size + 1, min(self.points // 2, 8))
        self.first_n = min(first, self.points, len(plan))
        a = plan.angles
        self.wi = _dirs(a[:, 0], a[:, 1])
        self.wo = _dirs(a[:, 2], a[:, 3])
        self.stage = np.nan_to_num(kinematics.inverse(*a.T))
        rank = {int(i): k for k, i in enumerate(order)}
        spread = spread_subset(a, self.first_n)
        self.batches: list[list[int]] = [sorted(spread, key=lambda i: (rank.get(i, len(rank)), i))]
        self._motion = _motion()
        self.log: list[dict] = []
        self.stopped_by: str | None = None

    # -- the protocol ---------------------------------------------------------------------
    @property
    def budget(self) -> int:
        return min(self.points, len(self.plan))

    def first(self, done: set[int]) -> list[int]:
        return [i for i in self.batches[0] if i not in done]

    def more(self, results: Mapping[int, Result], queued: Sequence[int]) -> list[int]:
        self._replay(results)
        q = set(int(i) for i in queued)
        return [i for b in self.batches for i in b if i not in results and i not in q]

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "points": self.points, "target_rel_u": self.target_rel_u, "first": self.first_n,
                "batch": self.batch, "model": self.model_name, "options": self.options, "fixed": self.fixed,
                "n_starts": self.n_starts, "seed": self.seed, "travel": self.travel, "overhead_s": self.overhead_s,
                "model_rel_u": self.model_rel_u}

    def state(self) -> dict[str, Any]:
        """What the strategy did: ``stopped_by``, the points per batch, the last fit, the
        seconds per choice (for a journal event or a summary)."""
        last = self.log[-1] if self.log else {}
        return {"stopped_by": self.stopped_by, "batches": self.batches, "params": last.get("params"),
                "rel_u": last.get("rel_u"), "choose_s": [e["fit_s"] + e["choose_s"] for e in self.log]}

    # -- the choices ----------------------------------------------------------------------
    def _replay(self, results: Mapping[int, Result]) -> None:
        """Choose every batch the results allow: the next once at most one queued point lacks a
        result, from the queued points' results less the last queued point's."""
        while self.stopped_by is None:
            queue = [i for b in self.batches for i in b]
            if len(queue) >= self.budget:
                self.stopped_by = "budget"
                break
            if sum(i not in results for i in queue) > 1:
                break
            basis = [i for i in queue[:-1] if i in results]
            self._choose(basis, queue, results)

    def _choose(self, basis: list[int], queue: list[int], results: Mapping[int, Result]) -> None:
        n_new = min(self.batch, self.budget - len(queue))
        t0 = time.perf_counter()
        entry: dict[str, Any] = {"n": len(basis)}
        fitted = self._fit(basis, results, len(self.batches))
        t1 = time.perf_counter()
        taken = set(queue)
        free = np.array([i for i in range(len(self.plan)) if i not in taken], int)
        if fitted is None:                      # no fit yet: keep spreading the points
            entry["params"] = entry["rel_u"] = None
            chosen = spread_subset(self.plan.angles, n_new, queue)
        else:
            x, std, rel_u, sigma_rel, sigma_floor = fitted
            entry["params"] = dict(zip(self.space.names, x.tolist()))
            entry["rel_u"] = dict(zip(self.space.names, rel_u.tolist()))
            if self.target_rel_u > 0 and np.all(rel_u < self.target_rel_u):
                self.stopped_by = "target"
                entry.update(fit_s=t1 - t0, choose_s=0.0, chosen=[])
                self.log.append(entry)
                return
            chosen = self._d_optimal(x, basis, queue, free, n_new, results, sigma_rel, sigma_floor)
        entry.update(fit_s=t1 - t0, choose_s=time.perf_counter() - t1, chosen=chosen)
        self.log.append(entry)
        if not chosen:
            self.stopped_by = "candidates"
            return
        self.batches.append(chosen)

    def _fit(self, basis, results, k):
        """(x, std, rel_u, relative sigma, sigma floor) of the model fitted to ``basis``, or None
        where it cannot be fitted (too few usable values, a failed fit)."""
        from gonio.fitting import Measurements, fit

        if not basis:
            return None
        f = np.array([results[i][0] for i in basis], float)
        s = np.array([results[i][1] for i in basis], float)
        use = np.isfinite(f) & np.isfinite(s) & (s > 0)
        if use.sum() <= self.space.size:
            return None
        f, s = np.where(use, f, 0.0), np.where(use, s, 1.0)
        try:
            meas = Measurements(self.wi[basis], self.wo[basis], f, s, use)
            res = fit(meas, self.model, rng=np.random.default_rng([self.seed, k]), fixed=self.fixed or None,
                      n_starts=self.n_starts, n_local=1)
        except (ValueError, ArithmeticError, np.linalg.LinAlgError):
            return None
        x, std = np.asarray(res.x, float), np.asarray(res.std, float)
        with np.errstate(divide="ignore", invalid="ignore"):
            rel_u = np.where(np.abs(x) > 0, std / np.abs(x), np.inf)
            ratio = s[use] / np.abs(f[use])
        sigma_rel = float(np.median(ratio[np.isfinite(ratio)])) if np.isfinite(ratio).any() else 0.05
        sigma_floor = float(np.percentile(s[use], 10))
        return x, std, rel_u, sigma_rel, sigma_floor

    def _rows(self, x, sigma_rel, sigma_floor) -> tuple[np.ndarray, np.ndarray]:
        """Whitened Jacobian rows (N, 3, P) of f_r at every candidate (one array shape: the
        compiled kernel is built once) and the predicted sigma (N, 3): central differences in
        parameters scaled to their own size (the D-optimal choice does not depend on it)."""
        lo, hi = self.space.lower, self.space.upper
        scale = np.maximum(np.abs(x), 1e-3 * (hi - lo))
        f0 = self.model.eval(self.wi, self.wo, self.space.to_params(x))
        sigma = np.sqrt(((sigma_rel ** 2 + self.model_rel_u ** 2) * f0 ** 2) + sigma_floor ** 2)
        J = np.empty(f0.shape + (self.space.size,))
        for j in range(self.space.size):
            h = 1e-4 * scale[j]
            xp, xm = x.copy(), x.copy()
            xp[j], xm[j] = min(x[j] + h, hi[j]), max(x[j] - h, lo[j])
            fp = self.model.eval(self.wi, self.wo, self.space.to_params(xp))
            fm = self.model.eval(self.wi, self.wo, self.space.to_params(xm))
            J[..., j] = (fp - fm) / (xp[j] - xm[j]) * scale[j]
        return np.nan_to_num(J / sigma[..., None]), sigma

    def _d_optimal(self, x, basis, queue, free, n_new, results, sigma_rel, sigma_floor) -> list[int]:
        """Greedy D-optimal batch: each pick maximises log det(I + A F^-1 A^T) (A: its whitened
        rows; F: the information of the basis at its measured sigma, of the pending queued
        points and of the picks so far at the predicted one), divided by overhead plus travel
        from the previous pose when ``travel`` is on."""
        rows, pred = self._rows(x, sigma_rel, sigma_floor)
        pending = [i for i in queue if i not in basis]
        s = np.array([results[i][1] for i in basis], float).reshape(len(basis), -1)
        f = np.array([results[i][0] for i in basis], float).reshape(len(basis), -1)
        s = np.sqrt(s ** 2 + (self.model_rel_u * f) ** 2)
        ok = np.isfinite(s) & (s > 0)
        A_b = rows[basis] * np.where(ok, pred[basis] / np.where(ok, s, 1.0), 0.0)[..., None]
        A_p = rows[pending]
        F = np.einsum("ncp,ncq->pq", A_b, A_b) + np.einsum("ncp,ncq->pq", A_p, A_p)
        F += 1e-9 * max(np.trace(F), 1.0) * np.eye(F.shape[0])
        cand = rows[free]
        travel = np.zeros(len(free))
        left = np.ones(len(free), bool)
        last = self.stage[queue[-1]] if queue else None
        chosen: list[int] = []
        for _ in range(n_new):
            if not left.any():
                break
            M = np.einsum("ncp,pq,ndq->ncd", cand, np.linalg.inv(F), cand) + np.eye(cand.shape[1])
            sign, gain = np.linalg.slogdet(M)
            gain = np.where(sign > 0, gain, 0.0)
            if self.travel and last is not None:
                travel = np.minimum(cost_matrix(last[None], self.stage[free], self._motion)[0],
                                    cost_matrix(last[None], mirror(self.stage[free]), self._motion)[0])
            score = np.where(left, gain / (self.overhead_s + travel), -np.inf)
            k = int(np.argmax(score))
            chosen.append(int(free[k]))
            left[k] = False
            F = F + cand[k].T @ cand[k]
            last = self.stage[free[k]]
        return chosen


def _dirs(theta_deg, phi_deg) -> np.ndarray:
    from gonio.core.geometry import directions_deg

    return directions_deg(theta_deg, phi_deg)


def _int(t: Mapping, key: str, least: int) -> int:
    v = t[key]
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < least:
        raise ValueError(f"[strategy] {key} = {v!r}: give a whole number >= {least}")
    return int(v)


def _motion() -> dict:
    """The default rig's axis speeds and accelerations (the strategy sees no session settings)."""
    from gonio.bench.settings import default_settings

    return {"motion": default_settings()["motion"]}


def cli_strategy(plan: str, *, points: int | None, target_rel_u: float | None, candidates: str | None,
                 seed: int) -> tuple[str, dict | None]:
    """``gonio capture``'s plan options as (the plan to load, the ``[strategy]`` table): ``--plan
    adaptive`` draws from ``--candidates`` (default the ``dense`` preset); a fixed plan takes
    none of the adaptive options (ValueError naming the first given)."""
    if plan != "adaptive":
        for flag, v in (("--points", points), ("--target-rel-u", target_rel_u), ("--candidates", candidates)):
            if v is not None:
                raise ValueError(f"{flag} goes with --plan adaptive")
        return plan, None
    table: dict[str, Any] = {"name": "adaptive", "seed": int(seed)}
    if points is not None:
        table["points"] = int(points)
    if target_rel_u is not None:
        table["target_rel_u"] = float(target_rel_u)
    return candidates or "dense", table


register_strategy("adaptive", AdaptivePlan)
