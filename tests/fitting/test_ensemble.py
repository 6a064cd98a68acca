"""fitting._ensemble.Ensemble: emcee's EnsembleSampler's chains, bit for bit."""

from __future__ import annotations

import emcee
import numpy as np
import pytest

from gonio.fitting.uncertainty.ensemble import Ensemble

PRECISION = np.array([[4.0, 1.5, 0.0], [1.5, 2.0, 0.3], [0.0, 0.3, 1.0]])


def _log_prob(xs):
    """A correlated Gaussian cut off outside [-1, 1]^ndim: rejections by the bound and by
    the density both occur."""
    xs = np.atleast_2d(xs)
    A = PRECISION[:xs.shape[1], :xs.shape[1]]
    lp = -0.5 * np.einsum("ki,ij,kj->k", xs, A, xs)
    return np.where(np.all(np.abs(xs) <= 1.0, axis=1), lp, -np.inf)


MOVES = {"de+snooker": lambda: [(emcee.moves.DEMove(), 0.8), (emcee.moves.DESnookerMove(), 0.2)],
         "stretch": lambda: [(emcee.moves.StretchMove(), 1.0)]}


@pytest.mark.parametrize("moves", MOVES)
@pytest.mark.parametrize("ndim,n_walkers", [(1, 8), (2, 8), (3, 12)])
def test_chains_equal_emcee_bit_for_bit(moves, ndim, n_walkers):
    start = 0.05 * np.random.default_rng(ndim).standard_normal((n_walkers, ndim))
    seed = 1234 + ndim
    sampler = emcee.EnsembleSampler(n_walkers, ndim, _log_prob, vectorize=True, moves=MOVES[moves]())
    sampler.random_state = np.random.RandomState(seed).get_state()
    ensemble = Ensemble(_log_prob, start, MOVES[moves](), seed)
    state = start
    for chunk in (40, 40, 25):  # in chunks, as sample_posterior drives it
        state = sampler.run_mcmc(state, chunk, progress=False)
        ensemble.run(chunk)
    assert ensemble.iteration == sampler.iteration == 105
    assert np.array_equal(ensemble.backend.get_chain(), sampler.get_chain())
    assert np.array_equal(ensemble.backend.get_log_prob(), sampler.get_log_prob())
    assert np.array_equal(ensemble.acceptance_fraction, sampler.acceptance_fraction)
    assert 0.05 < np.mean(sampler.acceptance_fraction) < 0.95  # both outcomes exercised
    assert np.array_equal(ensemble.random.get_state()[1], sampler.random_state[1])


def test_non_finite_position_and_nan_log_prob_raise():
    start = 0.05 * np.random.default_rng(0).standard_normal((8, 2))
    ensemble = Ensemble(lambda xs: np.full(xs.shape[0], np.nan), start, MOVES["stretch"](), 0)
    with pytest.raises(ValueError, match="NaN"):
        ensemble.run(1)
    start[3, 1] = np.inf
    with pytest.raises(ValueError, match="condition number"):
        Ensemble(_log_prob, start, MOVES["stretch"](), 0).run(1)
