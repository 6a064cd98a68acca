"""emcee's ensemble sampler without its per-step bookkeeping, draw for draw.

:class:`Ensemble` advances the walkers exactly as ``emcee.EnsembleSampler(n_walkers, ndim,
log_prob, vectorize=True, moves=moves)`` with ``random_state`` set and driven by
``run_mcmc`` in chunks (emcee 3.1.6): the same move chosen by the same draw, emcee's own
proposals (``move.get_proposal``), the same uniform draws in the same order for the
acceptance tests, and the chain stored in emcee's own ``Backend``. The chains are equal bit
for bit (``tests/fitting/test_ensemble.py`` checks them against emcee's). What it leaves out
is the general sampler's per-step bookkeeping; the acceptance test is vectorised.

Only red-blue moves (emcee's ``RedBlueMove`` subclasses: ``DEMove``, ``DESnookerMove``,
``StretchMove``, ...) without tuning, and a vectorised log probability without blobs.
"""

# Followed from emcee 3.1.6: EnsembleSampler.sample, RedBlueMove.propose, Move.update,
# EnsembleSampler.compute_log_prob.
# Left out: per step a copy of the RandomState's state for State.random_state
# (EnsembleSampler.random_state), the acceptance test one walker at a time in Python, a new
# State per half-ensemble, and per log-probability call the blob detection, which walks the
# results one walker at a time and falls through an exception when there are none.
# Vectorised acceptance: lnpdiff > log(u) per walker, with the walker's uniform drawn in
# walker order as emcee draws them one by one (RandomState.rand(n) is n successive rand()),
# and the same IEEE operations. Figures: docs/performance.md, gonio.fitting.uncertainty.ensemble.

from __future__ import annotations

import numpy as np
from emcee import State, walkers_independent
from emcee.backends import Backend

__all__ = ["Ensemble"]


class Ensemble:
    """The walkers, their chain (``backend``, emcee's in-memory ``Backend``) and the random state.

    Parameters
    ----------
    log_prob : callable
        ``log_prob(xs (K, ndim)) -> (K,)``, the log posterior of K walkers at once.
    start : ndarray, shape (n_walkers, ndim)
        The walkers' starting positions.
    moves : list of (move, weight)
        emcee red-blue moves and their probabilities (normalised as emcee does).
    seed : int
        Seeds the ``numpy.random.RandomState`` that makes every draw (emcee's ``_random``).
    """

    def __init__(self, log_prob, start, moves, seed):
        self.log_prob = log_prob
        self.moves = [m for m, _ in moves]
        self.weights = np.atleast_1d([w for _, w in moves]).astype(float)
        self.weights /= np.sum(self.weights)
        self.random = np.random.RandomState(seed)
        self.coords = np.array(start, dtype=float)
        self.lp = None
        self.backend = Backend()
        self.backend.reset(*self.coords.shape)

    @property
    def iteration(self) -> int:
        return self.backend.iteration

    @property
    def acceptance_fraction(self) -> np.ndarray:
        return self.backend.accepted / float(self.backend.iteration)

    def run(self, n_steps: int):
        """Advance ``n_steps`` steps, each stored in ``backend`` (one ``run_mcmc(state, n_steps)``)."""
        if not walkers_independent(self.coords):
            raise ValueError("Initial state has a large condition number. Make sure that your walkers are "
                             "linearly independent for the best performance")
        if self.lp is None:
            self.lp = self._log_prob(self.coords)
        self.backend.grow(n_steps, None)
        for _ in range(n_steps):
            # emcee: random.choice(moves, p=weights); the index takes the same single draw
            move = self.moves[self.random.choice(len(self.moves), p=self.weights)]
            accepted = self._propose(move)
            self.backend.save_step(State(self.coords, log_prob=self.lp), accepted)

    def _propose(self, move):
        """One step of a red-blue move (``RedBlueMove.propose`` and ``Move.update``) on the
        walkers in place; returns which walkers moved."""
        coords, lp, random = self.coords, self.lp, self.random
        move.setup(coords)
        accepted = np.zeros(coords.shape[0], dtype=bool)
        inds = np.arange(coords.shape[0]) % move.nsplits
        if move.randomize_split:
            random.shuffle(inds)
        splits = [inds == j for j in range(move.nsplits)]
        for split, members in enumerate(splits):
            sets = [coords[m] for m in splits]  # after the previous half-ensembles' moves
            q, factors = move.get_proposal(sets[split], sets[:split] + sets[split + 1:], random)
            new_lp = self._log_prob(q)
            walkers = np.flatnonzero(members)
            take = factors + new_lp - lp[walkers] > np.log(random.rand(walkers.size))
            moved = walkers[take]
            coords[moved] = q[take]
            lp[moved] = new_lp[take]
            accepted[moved] = True
        return accepted

    def _log_prob(self, xs):
        """The log posterior at xs, with ``compute_log_prob``'s checks (finite positions, no NaN)."""
        if not np.isfinite(xs).all():
            raise ValueError("a walker's position is not finite")
        lp = np.asarray(self.log_prob(xs), dtype=float)
        if lp.shape != (xs.shape[0],):
            raise ValueError(f"log_prob returned shape {lp.shape} for {xs.shape[0]} walkers")
        if np.isnan(lp).any():
            raise ValueError("Probability function returned NaN")
        return lp
