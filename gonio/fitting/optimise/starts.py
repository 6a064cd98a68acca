"""Starting points of a fit: stratified (Latin hypercube) starts, their scores, and the
choice of the best ones in distinct basins."""

from __future__ import annotations

import numpy as np

__all__ = ["SCORE_ROWS", "BASIN_DISTANCE", "START_RATIO", "choose_starts", "global_starts", "stratified"]

#: Rows used to score global-stage starts (the local stage always uses all data).
SCORE_ROWS = 3000
#: Starts closer than this (unit-box distance, max norm) count as one basin.
BASIN_DISTANCE = 0.15
#: Starts scoring worse than this factor times the best start are not refined.
START_RATIO = 30.0


def stratified(rng, n, d):
    """n Latin-hypercube points in [0, 1]^d."""
    if n <= 0 or d == 0:
        return np.zeros((0, d))
    cut = (np.arange(n)[:, None] + rng.random((n, d))) / n
    for j in range(d):
        cut[:, j] = cut[rng.permutation(n), j]
    return cut


def _channel_costs(problem, x):
    """Objective per colour channel at x (affine parameters projected out first)."""
    if problem.varpro:
        x = problem.solve_linear(x)
    r = problem.residuals_x(x)
    if problem.loss == "robust":
        r2 = 2.0 * (np.sqrt(1.0 + r * r) - 1.0)
    else:
        r2 = r * r
    full = np.zeros(problem.meas.brdf.shape)
    full[problem.use] = r2
    return full.sum(axis=0)


def global_starts(problem, free, u_default, n_starts, rng):
    """Stratified starts over the searched coordinates ``free`` and their scores.

    Shared coordinates get a Latin hypercube. Per-channel nonlinear coordinates (conductor
    eta and k, Cook-Torrance f0) only change their own channel, so each channel picks its
    best candidate independently: K evaluations search K^C combinations.
    """
    space = problem.space
    shared = [int(i) for i in free if space.entries[i].channel < 0]
    block = [int(i) for i in free if space.entries[i].channel >= 0]
    pos = {int(i): k for k, i in enumerate(free)}
    if n_starts is None:
        n_starts = min(24, 4 + 4 * len(shared)) if block else min(24, 4 + 4 * int(free.size))
    if not free.size:
        return [u_default[free]], np.zeros(1)
    projected = _projected_coords(problem, free)
    if projected and set(block) <= projected:
        # the per-channel coordinates are affine parameters the loss does not project out
        # (log, robust): each start gets them from the data (``problem.solve_linear``) instead
        # of from a per-channel search over a few stratified values, so that a start's score
        # ranks its shared coordinates, not how well its random albedos happened to match
        S = np.vstack([u_default[shared][None, :], stratified(rng, n_starts, len(shared))])
        starts = [_with_affine(problem, u_default, free, shared, row) for row in S]
        scores = np.array([_safe_sum(_score(problem, u_default, free, v)) for v in starts])
        return starts, scores
    if not block:
        starts = [u_default[free]] + list(stratified(rng, n_starts, free.size))
        scores = np.array([_safe_sum(_score(problem, u_default, free, v)) for v in starts])
        return starts, scores
    C = space.n_channels
    names = sorted({space.entries[i].param for i in block})
    by_channel = [[i for n in names for i in block if space.entries[i].param == n and space.entries[i].channel == c]
                  for c in range(C)]
    n_k = min(24, 4 + 4 * len(names))
    S = np.vstack([u_default[shared][None, :], stratified(rng, n_starts, len(shared))]) if shared else np.zeros((1, 0))
    K = [np.vstack([u_default[idx][None, :], stratified(rng, n_k, len(names))]) for idx in by_channel]
    starts, scores = [], []
    for s_row in S:
        costs = np.full((n_k + 1, C), np.inf)
        for k in range(n_k + 1):
            v = u_default[free].copy()
            for j, i in enumerate(shared):
                v[pos[i]] = s_row[j]
            for c, idx in enumerate(by_channel):
                for j, i in enumerate(idx):
                    v[pos[i]] = K[c][k, j]
            costs[k] = _score(problem, u_default, free, v)
        best_k = np.argmin(np.where(np.isfinite(costs), costs, np.inf), axis=0)
        v = u_default[free].copy()
        for j, i in enumerate(shared):
            v[pos[i]] = s_row[j]
        for c, idx in enumerate(by_channel):
            for j, i in enumerate(idx):
                v[pos[i]] = K[c][best_k[c], j]
        starts.append(v)
        scores.append(float(sum(costs[best_k[c], c] for c in range(C))))
    return starts, np.array(scores)


def _projected_coords(problem, free):
    """Indices (of ``free``) of affine per-channel parameters that the problem searches
    rather than projects out (``problem.linear`` without variable projection), else empty."""
    if getattr(problem, "varpro", True) or not getattr(problem, "linear", None):
        return set()
    lin = {int(i) for g in problem.linear for i in g["index"]}
    return {int(i) for i in free if int(i) in lin}


def _with_affine(problem, u_default, free, shared, row):
    """The start ``row`` of the shared coordinates, its affine parameters solved by the
    problem's weighted linear least squares (bounded), in the searched coordinates."""
    u = u_default.copy()
    u[shared] = row
    try:
        u = problem.space.to_unit(problem.solve_linear(problem.space.from_unit(u)))
    except (FloatingPointError, ValueError, np.linalg.LinAlgError):
        pass  # the model misbehaves here: the start keeps the defaults and scores inf or worse
    return u[free]


def _score(problem, u_default, free, v):
    u = u_default.copy()
    u[free] = v
    try:
        c = _channel_costs(problem, space_x(problem, u))
    except FloatingPointError:
        return np.full(problem.space.n_channels, np.inf)
    return np.where(np.isfinite(c), c, np.inf)


def space_x(problem, u):
    return problem.space.from_unit(u)


def _safe_sum(c):
    v = float(np.sum(c))
    return v if np.isfinite(v) else np.inf


def choose_starts(starts, scores, n_local, start_ratio=START_RATIO, basin_distance=BASIN_DISTANCE):
    """Indices of the best-scoring starts that lie in distinct basins (unit-box distance
    >= ``basin_distance``), at most ``n_local``, none worse than ``start_ratio`` x the best."""
    chosen = []
    for k in np.argsort(scores, kind="stable"):
        if chosen and not scores[k] <= start_ratio * scores[chosen[0]] + 10.0:
            break  # far worse than the best start: not worth a local run
        if all(np.max(np.abs(starts[k] - starts[j])) >= basin_distance for j in chosen):
            chosen.append(int(k))
        if len(chosen) >= max(1, n_local):
            break
    return chosen
