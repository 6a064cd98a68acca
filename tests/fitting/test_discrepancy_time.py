"""The discrepancy loss's fit (gonio/fitting/likelihood/discrepancy.py) refits the model
several times; its FitResult counts them all: time, evaluations and CPU seconds alike."""

import numpy as np

import gonio.models as gm
from gonio.fitting import fit
from gonio.fitting.likelihood.discrepancy import fit_discrepancy

from _runs import recording
from _simdata import simulate


def test_a_discrepancy_fits_cpu_seconds_are_all_its_refits():
    """cpu_s is counted over what time_s counts (FitResult): every inner fit, not the last
    one's alone (it was: 0.001 s of 0.08 s, 60 points)."""
    model = gm.get("diffuse")
    truth = {"reflectance": np.array([0.5, 0.3, 0.2])}
    meas = simulate(model, truth, np.random.default_rng(3), n=60)
    inner = []
    res = fit_discrepancy(meas, model, recording(fit, inner), rng=np.random.default_rng(0))
    assert len(inner) >= 2 and all(r.cpu_s is not None for r in inner)
    assert res.n_evals == sum(r.n_evals for r in inner)
    assert res.time_s >= sum(r.time_s for r in inner)
    assert res.cpu_s is not None and res.cpu_s >= sum(r.cpu_s for r in inner)
