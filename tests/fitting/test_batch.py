"""Dask batch fitting equals the serial fits (same seeds), on a 2-worker local cluster."""

import numpy as np
import pytest

import gonio.models as gm
from gonio.fitting._batch import fit_batch, fit_serial

from _simdata import simulate


@pytest.mark.slow
def test_batch_equals_serial():
    model = gm.get("roughplastic", distribution="ggx")
    truth = {"diffuse_reflectance": np.array([0.5, 0.35, 0.2]), "alpha": 0.2, "int_ior": 1.5}
    data = [simulate(model, truth, np.random.default_rng(s), n=100) for s in range(6)]
    serial = fit_serial(data, model, rng_seed=3)
    batch = fit_batch(data, model, n_workers=2, rng_seed=3)
    assert len(batch) == len(serial)
    for a, b in zip(batch, serial):
        np.testing.assert_allclose(a.x, b.x, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(a.std, b.std, rtol=1e-6)
        assert a.chi2 == pytest.approx(b.chi2, rel=1e-9)
