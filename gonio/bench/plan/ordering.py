"""Move ordering: visit a plan's points in the order that minimises total stage travel time.

Cost model: each axis follows a trapezoidal profile (maxspeed ``v`` deg/s, acceleration and
deceleration ``a`` deg/s^2): a move of ``d`` degrees takes ``d / v + v / a`` when
``d >= v^2 / a`` and ``2 sqrt(d / a)`` otherwise; the axes move at once, so a move costs the
maximum over the axes. Each point has two stage solutions, ``(yaw, tilt, az, L)`` and its
mirror ``(-yaw, -tilt, az + 180, -L)``. The order is found by nearest neighbour, then 2-opt
and or-opt alternated with an exact dynamic programme choosing each point's solution, then
seeded double-bridge kicks (iterated local search). A Held-Karp lower bound (Held & Karp
1970) bounds the travel time of any order from below.
"""

# The cost is concave in d, so it obeys the triangle inequality. The mirror solution (the lamp
# arm on the other side of the camera) is a 180 degree turn of the whole instrument about the
# camera axis. 2-opt, or-opt and the dynamic programme (for the current order) alternate until
# neither improves; the kicks keep the best order.
# Lower bound: 1-trees with subgradient multipliers on the open path from the start pose
# through all points, with each edge at its cheapest pair of solutions: no order, whatever
# solutions it picks, can be faster.

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

from gonio.bench.settings import AXES

__all__ = ["move_time", "cost_matrix", "mirror", "OrderResult", "order_moves", "path_time", "lower_bound", "tour"]


def move_time(d_deg, vmax, accel):
    """Trapezoidal move time (s) for distances ``d_deg`` (degrees), speed (deg/s), accel (deg/s^2)."""
    d = np.abs(np.asarray(d_deg, float))
    d_full = vmax * vmax / accel
    return np.where(d >= d_full, d / vmax + vmax / accel, 2.0 * np.sqrt(d / accel))


def mirror(stage_deg) -> np.ndarray:
    """The other stage solution of the same (wi, wo): ``(-yaw, -tilt, az + 180, -L)``."""
    s = np.array(stage_deg, float)
    s[..., 0] *= -1
    s[..., 1] *= -1
    s[..., 2] = (s[..., 2] + 360.0) % 360.0 - 180.0
    s[..., 3] *= -1
    return s


def _limits(settings):
    return np.array([[settings["axes"][n][2], settings["axes"][n][3]] for n in AXES], float)


def _within(stage, lim):
    return np.all((stage >= lim[:, 0] - 1e-9) & (stage <= lim[:, 1] + 1e-9), axis=-1)


def cost_matrix(a, b, settings) -> np.ndarray:
    """Move times (s) from every stage pose in ``a`` (N, 4) to every pose in ``b`` (M, 4), degrees."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    out = np.zeros((a.shape[0], b.shape[0]))
    for j, name in enumerate(AXES):
        v, acc = settings["motion"][name]
        np.maximum(out, move_time(a[:, None, j] - b[None, :, j], v, acc), out=out)
    return out


def path_time(stages, settings, start=None) -> float:
    """Total move time (s) through the poses ``stages`` (N, 4) in order, from ``start`` if given."""
    s = np.asarray(stages, float)
    if start is not None:
        s = np.vstack([np.asarray(start, float)[None], s])
    if len(s) < 2:
        return 0.0
    t = np.zeros(len(s) - 1)
    for j, name in enumerate(AXES):
        v, acc = settings["motion"][name]
        t = np.maximum(t, move_time(np.diff(s[:, j]), v, acc))
    return float(t.sum())


@dataclass(frozen=True)
class OrderResult:
    """An ordered plan.

    Attributes
    ----------
    order : ndarray of int (N,)
        Plan indices in visiting order.
    stage_deg : ndarray (N, 4)
        The stage pose of each plan point (indexed like the plan, not like ``order``).
    naive_s, ordered_s, bound_s : float
        Move time in the plan's own order (lamp on the +Y side), after ordering, and the lower bound, s.
    """

    order: np.ndarray
    stage_deg: np.ndarray
    naive_s: float
    ordered_s: float
    bound_s: float

    @property
    def gain(self) -> float:
        """Fraction of the naive move time saved."""
        return 1.0 - self.ordered_s / self.naive_s if self.naive_s > 0 else 0.0

    @property
    def over_bound(self) -> float:
        """How far above the lower bound the ordered time is (fraction)."""
        return self.ordered_s / self.bound_s - 1.0 if self.bound_s > 0 else 0.0


def _variants(stage, settings):
    """(N, 2, 4) poses and (N, 2) validity: the plan's solution and its mirror."""
    lim = _limits(settings)
    var = np.stack([stage, mirror(stage)], 1)
    ok = _within(var, lim)
    ok[:, 0] |= ~ok.any(1)           # a point with no valid variant keeps its own (checked elsewhere)
    return var, ok


def _choose_variants(seq, var, ok, settings, start):
    """Exact DP: the variant of each point along ``seq`` that minimises the path time."""
    n = len(seq)
    big = 1e18
    cost = np.where(ok[seq[0]], cost_matrix(start[None], var[seq[0]], settings)[0], big)
    back = np.zeros((n, 2), int)
    for k in range(1, n):
        c = cost_matrix(var[seq[k - 1]], var[seq[k]], settings)          # (2, 2)
        tot = cost[:, None] + c
        back[k] = np.argmin(tot, 0)
        cost = np.where(ok[seq[k]], tot[back[k], [0, 1]], big)
    choice = np.zeros(n, int)
    choice[-1] = int(np.argmin(cost))
    for k in range(n - 1, 0, -1):
        choice[k - 1] = back[k, choice[k]]
    return choice


def _local_search(seq, D, start_cost, max_passes: int = 50):
    """2-opt and or-opt (segments of 1..3) on an open path from a fixed start.

    The path is closed as ``start -> seq -> end`` with a free end node, so both moves are
    ordinary moves on a path with fixed endpoints. Vectorised over the second index.
    """
    n = len(seq)
    if n < 3:
        return np.asarray(seq, int)
    m = n + 2
    E = np.zeros((m, m))               # node n: start, node n + 1: free end
    E[:n, :n] = D
    E[n, :n] = E[:n, n] = start_cost
    path = np.concatenate([[n], seq, [n + 1]]).astype(int)
    eps = 1e-9
    for _ in range(max_passes):
        improved = False
        # 2-opt: reverse path[i..j], 1 <= i < j <= n
        for i in range(1, n):
            a, b = path[i - 1], path[i]
            c = path[i + 1:n + 1]
            d = path[i + 2:n + 2]
            delta = E[a, c] + E[b, d] - E[a, b] - E[c, d]
            k = int(np.argmin(delta))
            if delta[k] < -eps:
                j = i + 1 + k
                path[i:j + 1] = path[i:j + 1][::-1].copy()
                improved = True
        # or-opt: move path[i:i+seg] between two other neighbours, either way round
        for seg in (1, 2, 3):
            i = 1
            while i + seg - 1 <= n:
                blk = path[i:i + seg]
                prev, nxt = path[i - 1], path[i + seg]
                gain = E[prev, blk[0]] + E[blk[-1], nxt] - E[prev, nxt]
                rest = np.concatenate([path[:i], path[i + seg:]])
                p, q = rest[:-1], rest[1:]
                base = E[p, q]
                add_f = E[p, blk[0]] + E[blk[-1], q] - base
                add_r = E[p, blk[-1]] + E[blk[0], q] - base
                kf, kr = int(np.argmin(add_f)), int(np.argmin(add_r))
                best_add, k, rev = (add_f[kf], kf, False) if add_f[kf] <= add_r[kr] else (add_r[kr], kr, True)
                if gain - best_add > eps:
                    ins = blk[::-1] if rev else blk
                    path = np.concatenate([rest[:k + 1], ins, rest[k + 1:]])
                    improved = True
                else:
                    i += 1
        if not improved:
            break
    return path[1:-1].copy()


def _nearest_neighbour(D, start_cost):
    n = len(start_cost)
    seq = [int(np.argmin(start_cost))]
    left = np.ones(n, bool)
    left[seq[0]] = False
    for _ in range(n - 1):
        row = np.where(left, D[seq[-1]], np.inf)
        k = int(np.argmin(row))
        seq.append(k)
        left[k] = False
    return np.array(seq, int)


def tour(stage_deg, settings: Mapping, start=None) -> np.ndarray:
    """The order (indices into ``stage_deg``, (N, 4) degrees) that visits these poses, each as
    given (no mirror solution), from ``start`` (default home, all zero) in the least move time
    the local search finds: nearest neighbour, then 2-opt and or-opt; exact (every order) for
    N <= 8. For a subset of a plan whose poses the session has already fixed."""
    stage = np.asarray(stage_deg, float).reshape(-1, 4)
    n = len(stage)
    start = np.zeros(4) if start is None else np.asarray(start, float)
    if n < 2:
        return np.arange(n)
    D = cost_matrix(stage, stage, settings)
    s0 = cost_matrix(start[None], stage, settings)[0]
    if n <= 8:
        from itertools import permutations

        orders = np.array(list(permutations(range(n))))
        cost = s0[orders[:, 0]] + D[orders[:, :-1], orders[:, 1:]].sum(1)
        return orders[int(np.argmin(cost))]
    return _local_search(_nearest_neighbour(D, s0), D, s0)


def _prim(W: np.ndarray) -> tuple[float, np.ndarray]:
    """Minimum spanning tree of the complete graph with weights W (dense, symmetric), O(n^2).

    Returns its weight and each node's degree in it.
    """
    n = W.shape[0]
    in_tree = np.zeros(n, bool)
    in_tree[0] = True
    best = W[0].copy()
    parent = np.zeros(n, int)
    deg = np.zeros(n)
    total = 0.0
    for _ in range(n - 1):
        cand = np.where(in_tree, np.inf, best)
        k = int(np.argmin(cand))
        total += cand[k]
        deg[k] += 1
        deg[parent[k]] += 1
        in_tree[k] = True
        closer = W[k] < best
        best = np.where(closer, W[k], best)
        parent = np.where(closer, k, parent)
    return float(total), deg


def lower_bound(var, ok, settings, start, iterations: int | None = None) -> float:
    """Held-Karp lower bound (s) on any open path from ``start`` through all points.

    Edges cost the cheapest pair of valid variants. The open path is closed into a tour with a
    dummy node joined at zero cost to every node; tours in which the start is not next to the
    dummy only widen the set minimised over, so the bound stays valid. The bound is the best
    Lagrangian 1-tree (node 0 = the dummy) found by subgradient steps: each is a lower bound.
    """
    n = var.shape[0]
    if n == 0:
        return 0.0
    if iterations is None:                      # ~1 s for 1000 points
        iterations = int(min(200, max(60, 60000 // n)))
    big = 1e9
    D = _min_matrix(var, ok, settings)
    s0 = np.min(np.where(ok, cost_matrix(np.asarray(start)[None], var.reshape(-1, 4), settings)[0].reshape(n, 2), big), 1)
    # nodes: 0 dummy, 1 start, 2.. points. dummy-start and dummy-point edges cost 0.
    m = n + 2
    W = np.zeros((m, m))
    W[2:, 2:] = D
    W[1, 2:] = W[2:, 1] = s0
    W[0, 1:] = W[1:, 0] = 0.0
    pi = np.zeros(m)
    best = 0.0
    step = None
    for it in range(iterations):
        Wp = W + pi[:, None] + pi[None, :]
        np.fill_diagonal(Wp, 0.0)
        tree, deg = _prim(Wp[1:, 1:])
        deg = np.concatenate([[0.0], deg])
        # two cheapest edges at the dummy
        e0 = np.sort(Wp[0, 1:])[:2]
        two = np.argsort(Wp[0, 1:])[:2] + 1
        deg[0] = 2
        deg[two] += 1
        val = tree + float(e0.sum()) - 2.0 * pi.sum()
        best = max(best, val)
        g = deg - 2
        if not np.any(g):
            break
        if step is None:
            step = 0.01 * max(val, 1e-6) / max(1, np.sum(g * g)) * 10
        pi += step * g
        if it % 20 == 19:
            step *= 0.7
    return float(best)


def _min_matrix(var, ok, settings):
    """Move time (s) between points at their cheapest valid pair of solutions, (N, N)."""
    n = var.shape[0]
    big = 1e9
    D = np.full((n, n), np.inf)
    for p in range(2):
        for q in range(2):
            c = cost_matrix(var[:, p], var[:, q], settings)
            c[~ok[:, p], :] = big
            c[:, ~ok[:, q]] = big
            D = np.minimum(D, c)
    return D


def _polish(seq, var, ok, settings, start):
    """Alternate local search (fixed solutions) and the exact choice of solutions until stable."""
    n = len(seq)
    best_t, best_seq, best_choice = np.inf, seq, np.zeros(n, int)
    for _ in range(6):
        ch_seq = _choose_variants(seq, var, ok, settings, start)
        choice = np.zeros(n, int)
        choice[seq] = ch_seq
        t = path_time(var[seq, choice[seq]], settings, start)
        if t >= best_t - 1e-9:
            break
        best_t, best_seq, best_choice = t, seq.copy(), choice
        cur = var[np.arange(n), choice]
        seq = _local_search(seq, cost_matrix(cur, cur, settings), cost_matrix(start[None], cur, settings)[0])
    return best_t, best_seq, best_choice


def order_moves(stage_deg, settings: Mapping, start=None, *, kicks: int | None = None,
                seed: int = 0) -> OrderResult:
    """Order plan points (their stage poses, (N, 4) degrees) to minimise move time.

    Parameters
    ----------
    stage_deg : array_like (N, 4)
        ``(yaw, tilt, azimuth, lamp)`` of each point (the lamp on the +Y side, as `inverse` gives).
    settings : dict
        Instrument settings (``axes`` limits, ``motion`` speeds).
    start : array_like (4,), optional
        The pose the stages start from (default all zero: the home position).
    kicks : int, optional
        Random double-bridge restarts after the first descent (default: 10 up to 200 points,
        none above, where one descent takes about a second). Seeded by ``seed``: the same plan always gets the same order.

    Returns
    -------
    OrderResult

    Notes
    -----
    Two descents are started, one on the cheapest-solution matrix, one with every point's own
    solution; each alternates 2-opt/or-opt with the exact solution choice. Then double-bridge
    kicks (iterated local search) keep the best order found.
    """
    stage = np.asarray(stage_deg, float)
    n = stage.shape[0]
    start = np.zeros(4) if start is None else np.asarray(start, float)
    naive = path_time(stage, settings, start)
    if n == 0:
        return OrderResult(np.zeros(0, int), stage, 0.0, 0.0, 0.0)
    var, ok = _variants(stage, settings)
    Dmin = _min_matrix(var, ok, settings)
    s0min = np.min(np.where(ok, cost_matrix(start[None], var.reshape(-1, 4), settings)[0].reshape(n, 2), 1e9), 1)
    D0 = cost_matrix(stage, stage, settings)
    s00 = cost_matrix(start[None], stage, settings)[0]
    best = (np.inf, None, None)
    for D, s0 in ((Dmin, s0min), (D0, s00)):
        seq = _local_search(_nearest_neighbour(D, s0), D, s0)
        res = _polish(seq, var, ok, settings, start)
        if res[0] < best[0]:
            best = res
    if kicks is None:
        kicks = 10 if n <= 200 else 0
    rng = np.random.default_rng(seed)
    for _ in range(kicks if n >= 8 else 0):
        seq = best[1]
        i, j, k = np.sort(rng.choice(np.arange(1, n), 3, replace=False))
        seq = np.concatenate([seq[:i], seq[j:k], seq[i:j], seq[k:]])       # double bridge
        seq = _local_search(seq, Dmin, s0min)
        res = _polish(seq, var, ok, settings, start)
        if res[0] < best[0] - 1e-9:
            best = res
    t, seq, choice = best
    chosen = var[np.arange(n), choice]
    bound = lower_bound(var, ok, settings, start)
    return OrderResult(seq, chosen, naive, t, min(bound, t))
