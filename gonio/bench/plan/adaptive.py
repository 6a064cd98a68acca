"""Sequential-design plan strategy ``"adaptive"``: measure where the fit learns the most.

A first pass takes a spread subset of the candidate plan (farthest-point sampling in (wi, wo));
then, batch by batch, the model is fitted to the results so far (`gonio.fitting.fit`; with
``candidates``, the family they need, gonio.bench.plan.family) and the unmeasured candidates that
raise log det of the Fisher information J^T W J the most (D-optimality, greedy within a batch;
Atkinson, Donev & Tobias 2007, ch. 10-12; ``criterion = "alc"``: the predicted variance of f_r
cos, gonio.bench.plan.alc) are queued, per second of overhead and the run's move (``travel``).
It stops at ``points``, at ``budget_s`` of the journalled instrument time (a batch is cut to
what fits in what is left by gonio.bench.plan.point_time's estimate), or at its targets
(``target_rel_u``, ``target_de00``: `albedo_de00_u`); :attr:`AdaptivePlan.stopped_by` says which.
Its dataset weights each point by its design weight (gonio.bench.plan.design_weights). Each batch
is chosen from the results and times of the points queued before it, less the last one (the
stages move to it meanwhile), so a resume replays the same choices; registered on import.
"""

from __future__ import annotations

import math
import time
from typing import Any, Mapping, Sequence

import numpy as np

from gonio.bench.plan import family, kinematics
from gonio.bench.plan.point_time import RestModel, darkest
from gonio.bench.plan.design_weights import ON_BY_DEFAULT
from gonio.bench.plan.ordering import cost_matrix, mirror, tour
from gonio.bench.plan.plans import Plan
from gonio.bench.plan.strategy import Result, register_strategy

__all__ = ["AdaptivePlan", "DEFAULTS", "CRITERIA", "spread_subset", "albedo_de00_u"]

#: session.toml's ``[strategy]`` keys and their defaults (``name = "adaptive"`` besides).
DEFAULTS: dict[str, Any] = {
    "points": 24,                 # the budget: the most points measured (0 with budget_s: every candidate)
    "budget_s": 0.0,              # the most instrument time, s (0: none): preparation and points, as journalled
    "target_rel_u": 0.0,          # stop once every parameter's 1-sigma / |value| is below this (0: never)
    "target_de00": 0.0,           # stop once the albedo colour's predicted CIEDE2000 1-sigma is below this (0: never)
    "first": 0,                   # first-pass points (0: max(P + 1, min(points // 2, 8)))
    "batch": 3,                   # points chosen per fit
    "model": "roughplastic",
    "options": {"distribution": "ggx"},
    "fixed": {},                  # parameters held at a value
    "n_starts": 4,                # the fit's starts, few: it runs while the stages move (the affine path scores 256)
    "seed": 0,                    # the fits' starts draw from Generator([seed, batch])
    "travel": True,               # score = information gain / (overhead_s + travel time)
    "overhead_s": 5.0,            # a point's time before the journal has any; the scores' charge besides the move
    "model_rel_u": 0.0,           # relative 1-sigma of what the noise leaves out (model, systematics)
    "angle_noise": False,         # the design's sigma adds the stage angles' errors times f_r's slope
    "criterion": "d-optimal",     # "d-optimal" (the parameters) or "alc" (the predicted f_r cos, with discrepancy)
    "discrepancy_length": 0.7,    # "alc": correlation length of the model's discrepancy in (wi, wo), unit vectors
    "design_weights": ON_BY_DEFAULT,  # dataset.nc weights each point by its share of the evaluation measure
    "candidates": [],             # families chosen among by BIC before each batch (gonio.bench.plan.family; []: model)
}

#: the batch criteria ``criterion`` names
CRITERIA = ("d-optimal", "alc")


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
        ``"budget"`` (points), ``"time"`` (``budget_s``), ``"target"`` or ``"candidates"`` once
        the strategy adds nothing more; :meth:`stop_line` says it in words.
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
        self.budget_s = _positive(t, "budget_s")
        self.target_de00 = _positive(t, "target_de00")
        self.points = _int(t, "points", 0 if self.budget_s > 0 else 1)
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
        self.criterion = t["criterion"]
        if self.criterion not in CRITERIA:
            raise ValueError(f"[strategy] criterion = {str(self.criterion)[:40]!r}: give one of {', '.join(CRITERIA)}")
        v = t["discrepancy_length"]
        if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) or not (
                math.isfinite(v) and v > 0):
            raise ValueError(f"[strategy] discrepancy_length = {v!r}: give a length > 0 (unit vectors)")
        self.discrepancy_length = float(v)
        if not isinstance(t["design_weights"], (bool, np.bool_)):
            raise ValueError(f"[strategy] design_weights = {str(t['design_weights'])[:40]!r}: give true or false")
        self.design_weights = bool(t["design_weights"])
        if not isinstance(t["angle_noise"], (bool, np.bool_)):
            raise ValueError(f"[strategy] angle_noise = {str(t['angle_noise'])[:40]!r}: give true or false")
        self.angle_noise = bool(t["angle_noise"])
        self._angle_modes = None                        # `use_angle_modes`: (N, 4, K) shifts per +1 sigma
        self.options, self.fixed = dict(t["options"]), dict(t["fixed"])
        self.candidates = family.parse(t["candidates"])
        if self.candidates and self.fixed:
            raise ValueError("[strategy] fixed holds parameters of one model: give candidates = [] with it")
        try:
            self.model = gm.get(str(t["model"]), **self.options)
        except Exception as exc:
            raise ValueError(f"[strategy] model {t['model']!r}: {exc}") from None
        self.model_name = str(t["model"])
        if self.candidates:                             # the simplest candidate until the data chooses
            self.model = gm.get(self.candidates[0][0], **self.candidates[0][1])
        self.space = ParameterSpace(self.model, 3, self.fixed)
        first = _int(t, "first", 0) or max(self.space.size + 1, min(self.budget // 2, 8))
        self.first_n = min(first, self.budget)
        a = plan.angles
        self.wi = _dirs(a[:, 0], a[:, 1])
        self.wo = _dirs(a[:, 2], a[:, 3])
        self.stage = np.nan_to_num(kinematics.inverse(*a.T))
        rig = _rig()
        self._motion = {"motion": rig["motion"]}
        self._poses, self._run_motion = None, self._motion     # `use_session`: the moves the run makes
        self._exposure_max_s = float(rig["capture"]["exposure_max_s"])
        spread = spread_subset(a, self.first_n)
        toured = self._toured(spread)
        while self.budget_s > 0 and (need := self._path_s(toured)) > self.budget_s:
            if len(spread) <= self.space.size + 1:       # the fewest points a fit needs
                raise ValueError(f"[strategy] budget_s = {self.budget_s:g} s: the first pass alone ({len(spread)} "
                                 f"points) takes about {need:.0f} s by the plan's estimate; give more time")
            spread = spread[:-1]                        # the farthest-point order: a prefix stays spread
            toured = self._toured(spread)
        self.first_n = len(spread)
        self.batches: list[list[int]] = [toured]
        self.log: list[dict] = []
        self.stopped_by: str | None = None
        self.times: dict[int, float] = {}                 # `account`: each journalled point's instrument time
        self.preparations: list[tuple[int, float]] = []   # (points kept before it, s) per preparation
        self.spent_s = 0.0                                # the instrument time counted at the last choice
        self.next_s = 0.0                                 # the estimate that did not fit (``time``)
        self.estimates: dict[int, float] = {}             # each chosen point's estimated time, s (``budget_s``)

    # -- the protocol ---------------------------------------------------------------------
    @property
    def budget(self) -> int:
        return min(self.points or len(self.plan), len(self.plan))

    def account(self, times: Mapping[int, float], preparations: Sequence[tuple[int, float]]) -> None:
        """The instrument time so far (the run calls this before asking for points): each
        journalled point's, s, and each preparation's as (points kept before it, s)."""
        self.times = {int(i): float(v) for i, v in times.items()}
        self.preparations = [(int(n), float(v)) for n, v in preparations]

    def use_session(self, stage_deg, settings: Mapping | None = None) -> None:
        """The pose the run moves to at each point (session.toml's ``[order] stage_deg``: the
        solution the move order chose, not always the nearer one) and the session's settings
        (axis speeds, the longest exposure), so the time budget counts the run's own moves."""
        poses = np.asarray(stage_deg, float)
        if poses.shape != self.stage.shape or not np.all(np.isfinite(poses)):
            raise ValueError(f"[order] stage_deg: give {self.stage.shape[0]} finite stage poses of 4 angles, one per "
                             f"point of the plan (got shape {poses.shape})")
        self._poses = poses
        if settings and isinstance(settings.get("motion"), Mapping):
            self._run_motion = {"motion": settings["motion"]}
        self.batches[0] = self._toured(self.batches[0])
        v = (settings or {}).get("capture", {}).get("exposure_max_s")
        if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0:
            self._exposure_max_s = float(v)

    def use_angle_modes(self, modes) -> None:
        """(N, 4, K): the change of each point's (theta_i, phi_i, theta_o, phi_o), deg, for +1
        sigma of each input of the dataset's angle lines (the run gives it from the session's
        settings: gonio.bench.measure.calpoint.angle_modes); kept with ``angle_noise``."""
        m = np.asarray(modes, float)
        if m.ndim != 3 or m.shape[:2] != (len(self.plan), 4) or not np.all(np.isfinite(m)):
            raise ValueError(f"angle modes: give {len(self.plan)} points x 4 angles x inputs of finite shifts "
                             f"(got shape {m.shape})")
        self._angle_modes = m if self.angle_noise else None

    def _angle_var(self, x, at=slice(None), weights=None) -> np.ndarray | float:
        """The variance of f_r (N, C) at candidates ``at`` from the stage angles' errors (every
        shared and per-move input of the budget's angle lines, each as if drawn per point) times
        the fitted model's slope; with ``weights`` (C,), of the channels' weighted sum (N,);
        inf where the slope is not finite; 0 without ``angle_noise`` or `use_angle_modes`."""
        if self._angle_modes is None:
            return 0.0
        from gonio.fitting.uncertainty.angle_shifts import slope

        S = slope(self.model, self.space.to_params(x), self.wi[at], self.wo[at])
        d = np.einsum("nca,nak->nck", S, self._angle_modes[at])
        var = (d ** 2).sum(-1) if weights is None else (np.einsum("nck,c->nk", d, weights) ** 2).sum(-1)
        return np.where(np.isfinite(var), var, np.inf)      # no slope: a point the design does not trust

    def first(self, done: set[int]) -> list[int]:
        return [i for i in self.batches[0] if i not in done]

    def more(self, results: Mapping[int, Result], queued: Sequence[int]) -> list[int]:
        self._replay(results)
        q = set(int(i) for i in queued)
        return [i for b in self.batches for i in b if i not in results and i not in q]

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "points": self.points, "budget_s": self.budget_s, "target_rel_u": self.target_rel_u,
                "target_de00": self.target_de00, "first": self.first_n, "batch": self.batch, "model": self.model_name, "options": self.options, "fixed": self.fixed,
                "n_starts": self.n_starts, "seed": self.seed, "travel": self.travel, "overhead_s": self.overhead_s,
                "model_rel_u": self.model_rel_u, "angle_noise": self.angle_noise, "criterion": self.criterion,
                "discrepancy_length": self.discrepancy_length, "design_weights": self.design_weights,
                "candidates": family.as_doc(self.candidates)}

    def state(self) -> dict[str, Any]:
        """What the strategy did: ``stopped_by``, the points per batch, the last fit, the
        seconds per choice (for a journal event or a summary)."""
        last = self.log[-1] if self.log else {}
        return {"stopped_by": self.stopped_by, "batches": self.batches, "model": last.get("model"),
                "params": last.get("params"),
                "rel_u": last.get("rel_u"), "de00_u": last.get("de00_u"), "spent_s": self.spent_s,
                "choose_s": [e["fit_s"] + e["choose_s"] for e in self.log]}

    def stop_line(self) -> str:
        """Why the strategy stopped, in one line ("" while it has not)."""
        last = self.log[-1] if self.log else {}
        if self.stopped_by == "budget":
            return f"{self.name} plan: stopped at its budget of {self.budget} points"
        if self.stopped_by == "time":
            return (f"{self.name} plan: stopped at its time budget: {self.spent_s:.0f} s of {self.budget_s:.0f} s of "
                    f"instrument time used, the next point (about {self.next_s:.0f} s) would not fit")
        if self.stopped_by == "target":
            met = []
            if self.target_rel_u > 0:
                met.append(f"every parameter's relative 1-sigma below {self.target_rel_u:g} "
                           f"(largest {max(last['rel_u'].values()):.3g})")
            if self.target_de00 > 0:
                met.append(f"the albedo colour's predicted CIEDE2000 1-sigma {last['de00_u']:.3g} below "
                           f"{self.target_de00:g}")
            return f"{self.name} plan: reached its target: " + " and ".join(met)
        if self.stopped_by == "candidates":
            return f"{self.name} plan: stopped: no candidate point is worth adding"
        return ""

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
            x, std, rel_u, sigma_rel, sigma_floor, cov = fitted
            entry["model"] = family.label(self.model.name, self.model.options)
            entry["params"] = dict(zip(self.space.names, x.tolist()))
            entry["rel_u"] = dict(zip(self.space.names, rel_u.tolist()))
            met = []
            if self.target_rel_u > 0:
                met.append(bool(np.all(rel_u < self.target_rel_u)))
            if self.target_de00 > 0:
                entry["de00_u"] = albedo_de00_u(self.model, self.space, x, cov)
                met.append(entry["de00_u"] < self.target_de00)
            if met and all(met):
                self.stopped_by = "target"
                entry.update(fit_s=t1 - t0, choose_s=0.0, chosen=[])
                self.log.append(entry)
                return
            chosen = self._pick(x, basis, queue, free, n_new, results, sigma_rel, sigma_floor, cov)
        if self.budget_s > 0 and chosen:
            f_all = None if fitted is None else self.model.eval(self.wi, self.wo, self.space.to_params(fitted[0]))
            chosen = self._within_time(chosen, basis, queue, results, f_all)
            if not chosen:
                self.stopped_by = "time"
        entry.update(fit_s=t1 - t0, choose_s=time.perf_counter() - t1, chosen=chosen)
        self.log.append(entry)
        if not chosen:
            self.stopped_by = self.stopped_by or "candidates"
            return
        self.batches.append(chosen)

    # -- instrument time ----------------------------------------------------------------
    def _moves(self, a: int, b) -> np.ndarray:
        """The moves (s) from candidate ``a`` to each of ``b`` as the run makes them: between the
        session's poses (`use_session`) at its speeds; before those are known, the faster of each
        point's two stage solutions."""
        b = np.atleast_1d(np.asarray(b, int))
        if self._poses is None:
            to = self.stage[b]
            return np.minimum(cost_matrix(self.stage[a][None], to, self._motion)[0],
                              cost_matrix(self.stage[a][None], mirror(to), self._motion)[0])
        return cost_matrix(self._poses[a][None], self._poses[b], self._run_motion)[0]

    def _toured(self, points: Sequence[int]) -> list[int]:
        """``points`` in the order of least move time from home (gonio.bench.plan.ordering.tour)
        between the poses the run moves to (before `use_session`: each point's first solution);
        as the session does, the reflected points first, then the transmitted ones from stage
        zero (the open beam's pose): the camera moves to the rear stop once."""
        pts = [int(i) for i in points]
        poses = self.stage if self._poses is None else self._poses
        rear = kinematics.detector_of(self.plan.angles[pts, 2]) if pts else np.zeros(0, bool)
        out = []
        for side, start in ((False, None), (True, np.zeros(4))):
            part = [i for i, r in zip(pts, rear) if bool(r) == side]
            out += [part[k] for k in tour(poses[part], self._run_motion, start)] if part else []
        return out

    def _move_s(self, a: int, b: int) -> float:
        return float(self._moves(a, [b])[0])

    def _cost(self, last: int | None, free) -> np.ndarray:
        """The charge the batch criteria divide a pick's gain by, s: ``overhead_s`` plus the move
        from ``last`` (an index; None: none) when ``travel`` is on. Not the point's estimated time
        (`_rest`): with it the picks crowd where moves are short and fit worse
        (docs/performance.md, "The adaptive plan's score per second ...")."""
        free = np.atleast_1d(np.asarray(free, int))
        move = self._moves(last, free) if self.travel and last is not None else np.zeros(len(free))
        return self.overhead_s + move

    def _path_s(self, points: Sequence[int], after: int | None = None, per_point=None) -> float:
        """The plan's estimate of the instrument time of ``points`` in order (from ``after``):
        ``per_point(i)`` (default ``overhead_s``) each, plus the moves between them."""
        path = ([after] if after is not None else []) + [int(i) for i in points]
        each = sum(self.overhead_s if per_point is None else per_point(int(i)) for i in points)
        return each + sum(self._move_s(a, b) for a, b in zip(path, path[1:]))

    def _within_time(self, chosen: list[int], basis: list[int], queue: list[int], results=None,
                     f_all=None) -> list[int]:
        """The longest prefix of ``chosen`` whose estimated time fits in what ``budget_s`` leaves
        after the time counted so far: every preparation journalled with at most ``len(basis)``
        points kept, the basis points' journalled times, the other queued points' estimates
        (each its move plus `_rest`'s envelope at the fitted model's ``f_all``)."""
        rest = self._rest(basis, queue, results or {}, f_all)
        spent = sum(s for n, s in self.preparations if n <= len(basis))
        for k, i in enumerate(queue):
            known = self.times.get(i) if i in basis else None
            spent += known if known is not None else self._path_s([i], queue[k - 1] if k else None, rest)
        self.spent_s = spent
        out: list[int] = []
        for i in chosen:
            need = self._path_s([i], (out or queue)[-1], rest)
            self.estimates[i] = need
            if spent + need > self.budget_s:
                self.next_s = need
                break
            spent += need
            out.append(i)
        return out

    def _rest(self, basis: list[int], queue: list[int], results: Mapping[int, Result], f_all=None):
        """A point's time besides its move, s, by candidate (gonio.bench.plan.point_time): the
        envelope fitted to the basis points with a journalled time (not the first of the queue or
        of a run: their move is not from the point before), at the fitted model's darkest channel
        (``f_all``: its f_r at every candidate; None: the darkest point measured)."""
        at = {i: k for k, i in enumerate(queue)}
        after_prep = {n for n, _ in self.preparations}
        pts = [i for i in basis if i in self.times and at.get(i, 0) > 0 and at[i] not in after_prep and i in results]
        rest = [self.times[i] - self._move_s(queue[at[i] - 1], i) for i in pts]
        s_meas = darkest([np.asarray(results[i][0], float) for i in pts], self.plan.angles[pts, 0]) if pts else []
        s_all = None if f_all is None else darkest(np.asarray(f_all, float), self.plan.angles[:, 0])
        model = RestModel.fit(rest, s_meas, None if s_all is None else s_all[pts], overhead_s=self.overhead_s,
                              exposure_max_s=self._exposure_max_s)
        dark = float(np.min(s_meas)) if len(s_meas) else 0.0
        return lambda i: float(model(dark if s_all is None else s_all[i]))

    def _fit(self, basis, results, k):
        """(x, std, rel_u, relative sigma, sigma floor, covariance) of the model fitted to ``basis``, or None
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
            rng = np.random.default_rng([self.seed, k])
            if self.candidates:                         # the family the points so far need (module notes)
                res = family.choose(meas, self.candidates, rng=rng, n_starts=self.n_starts, n_local=1)[0]
                self.model, self.space = res.model, res.space
            else:
                res = fit(meas, self.model, rng=rng, fixed=self.fixed or None, n_starts=self.n_starts, n_local=1)
        except (ValueError, ArithmeticError, np.linalg.LinAlgError):
            return None
        x, std, cov = np.asarray(res.x, float), np.asarray(res.std, float), np.asarray(res.cov, float)
        with np.errstate(divide="ignore", invalid="ignore"):
            rel_u = np.where(np.abs(x) > 0, std / np.abs(x), np.inf)
            ratio = s[use] / np.abs(f[use])
        sigma_rel = float(np.median(ratio[np.isfinite(ratio)])) if np.isfinite(ratio).any() else 0.05
        sigma_floor = float(np.percentile(s[use], 10))
        return x, std, rel_u, sigma_rel, sigma_floor, cov

    def _rows(self, x, sigma_rel, sigma_floor, angle_var=0.0) -> tuple[np.ndarray, np.ndarray]:
        """Whitened Jacobian rows (N, 3, P) of f_r at every candidate (one array shape: the
        compiled kernel is built once) and the predicted sigma (N, 3), ``angle_var`` (`_angle_var`)
        in it: central differences in parameters scaled to their own size (the D-optimal choice
        does not depend on it)."""
        lo, hi = self.space.lower, self.space.upper
        scale = np.maximum(np.abs(x), 1e-3 * (hi - lo))
        f0 = self.model.eval(self.wi, self.wo, self.space.to_params(x))
        sigma = np.sqrt(((sigma_rel ** 2 + self.model_rel_u ** 2) * f0 ** 2) + sigma_floor ** 2 + angle_var)
        J = np.empty(f0.shape + (self.space.size,))
        for j in range(self.space.size):
            h = 1e-4 * scale[j]
            xp, xm = x.copy(), x.copy()
            xp[j], xm[j] = min(x[j] + h, hi[j]), max(x[j] - h, lo[j])
            fp = self.model.eval(self.wi, self.wo, self.space.to_params(xp))
            fm = self.model.eval(self.wi, self.wo, self.space.to_params(xm))
            J[..., j] = (fp - fm) / (xp[j] - xm[j]) * scale[j]
        return np.nan_to_num(J / sigma[..., None]), sigma

    def _pick(self, x, basis, queue, free, n_new, results, sigma_rel, sigma_floor, cov) -> list[int]:
        """The next batch from ``free`` given the fit ``x`` (``cov`` its covariance): D-optimal
        here (or by `alc` with ``criterion = "alc"``); a strategy built on this one
        (gonio.bench.plan.ndf_seeded) places them otherwise."""
        if self.criterion == "alc":
            from gonio.bench.plan.alc import alc_batch

            return alc_batch(self, x, basis, queue, free, n_new, results, sigma_rel, sigma_floor)
        return self._d_optimal(x, basis, queue, free, n_new, results, sigma_rel, sigma_floor)

    def _d_optimal(self, x, basis, queue, free, n_new, results, sigma_rel, sigma_floor) -> list[int]:
        """Greedy D-optimal batch: each pick maximises log det(I + A F^-1 A^T) (A: its whitened
        rows; F: the information of the basis at its measured sigma, of the pending queued
        points and of the picks so far at the predicted one), divided by `_cost` from the
        previous pick."""
        angle_var = self._angle_var(x)                  # (N, C) or 0: every candidate's, the basis's too
        rows, pred = self._rows(x, sigma_rel, sigma_floor, angle_var)
        pending = [i for i in queue if i not in basis]
        s = np.array([results[i][1] for i in basis], float).reshape(len(basis), -1)
        f = np.array([results[i][0] for i in basis], float).reshape(len(basis), -1)
        s = np.sqrt(s ** 2 + (self.model_rel_u * f) ** 2 + (angle_var[basis] if np.ndim(angle_var) else 0.0))
        ok = np.isfinite(s) & (s > 0)
        A_b = rows[basis] * np.where(ok, pred[basis] / np.where(ok, s, 1.0), 0.0)[..., None]
        A_p = rows[pending]
        F = np.einsum("ncp,ncq->pq", A_b, A_b) + np.einsum("ncp,ncq->pq", A_p, A_p)
        F += 1e-9 * max(np.trace(F), 1.0) * np.eye(F.shape[0])
        cand = rows[free]
        left = np.ones(len(free), bool)
        last = queue[-1] if queue else None
        chosen: list[int] = []
        for _ in range(n_new):
            if not left.any():
                break
            M = np.einsum("ncp,pq,ndq->ncd", cand, np.linalg.inv(F), cand) + np.eye(cand.shape[1])
            sign, gain = np.linalg.slogdet(M)
            gain = np.where(sign > 0, gain, 0.0)
            score = np.where(left, gain / self._cost(last, free), -np.inf)
            k = int(np.argmax(score))
            chosen.append(int(free[k]))
            left[k] = False
            F = F + cand[k].T @ cand[k]
            last = int(free[k])
        return chosen


def _dirs(theta_deg, phi_deg) -> np.ndarray:
    from gonio.core.geometry import directions_deg

    return directions_deg(theta_deg, phi_deg)


def albedo_de00_u(model, space, x: np.ndarray, cov: np.ndarray) -> float:
    """A cheap proxy for how far a fit's rendered colour is from settled: the predicted CIEDE2000
    1-sigma of its albedo colour. The directional albedo at normal view (`Model.albedo`), its RGB
    taken as linear sRGB (D65, white = 1), to CIELAB (`gonio.fitting.colour`); each principal axis
    of the parameter covariance moves ``x`` by +-1 sigma (within the bounds), and the mean of the
    two CIEDE2000 differences from the fit's colour is summed in quadrature over the axes. Not a
    render: the rendered colour also depends on the lighting and view. inf where the covariance
    is not finite."""
    from gonio.fitting.colour import delta_e00, linear_srgb_lab

    cov = 0.5 * (cov + cov.T)
    if not np.all(np.isfinite(cov)) or not np.all(np.isfinite(x)):
        return math.inf
    wo = np.array([[0.0, 0.0, 1.0]])
    lo, hi = space.lower, space.upper

    def lab(v):
        return linear_srgb_lab(np.asarray(model.albedo(wo, space.to_params(np.clip(v, lo, hi))), float)[0])

    base = lab(x)
    w, vecs = np.linalg.eigh(cov)
    total = 0.0
    for k in np.flatnonzero(w > 0):
        step = math.sqrt(w[k]) * vecs[:, k]
        total += (0.5 * float(delta_e00(base, lab(x + step)) + delta_e00(base, lab(x - step)))) ** 2
    return math.sqrt(total)


def _positive(t: Mapping, key: str) -> float:
    """A table's value >= 0 (0: off), finite."""
    v = t[key]
    if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) or not (
            math.isfinite(v) and v >= 0):
        raise ValueError(f"[strategy] {key} = {v!r}: give a number >= 0 (0: none)")
    return float(v)


def _int(t: Mapping, key: str, least: int) -> int:
    v = t[key]
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < least:
        raise ValueError(f"[strategy] {key} = {v!r}: give a whole number >= {least}")
    return int(v)


def _rig() -> dict:
    """The default rig's settings (axis speeds and accelerations, the longest exposure), until
    `AdaptivePlan.use_session` gives the session's."""
    from gonio.bench.settings import default_settings

    return default_settings()


register_strategy("adaptive", AdaptivePlan)
