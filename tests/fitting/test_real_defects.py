"""Issue 16's defects on real-material fits, each pinned by a test that fails without its fix.

Synthetic stand-ins keep them fast; the real RGL files are used where present
(../shared/data/rgl) by tests/fitting/test_real_materials.py.
"""

import dataclasses

import nlopt
import numpy as np
import pytest

import gonio.models as gm
from gonio.fitting import fit

from _simdata import simulate

#: a Cook-Torrance sample brighter than energy allows: rho_d = 0.95 plus a strong lobe;
#: its albedo exceeds 1 (Lambert 0.95 alone is 0.95; the lobe adds ~0.3 at normal incidence)
BRIGHT = {"diffuse_reflectance": [0.95, 0.95, 0.95], "specular_reflectance": [0.6, 0.6, 0.6],
          "roughness": 0.3, "f0": [0.9, 0.9, 0.9]}


class _FailingOpt:
    """nlopt.opt whose optimize() raises nlopt.runtime_error (what nlopt 2.11 throws on a
    badly scaled objective: not a subclass of Python's RuntimeError)."""

    def __init__(self, *a):
        self._real = _REAL_OPT(*a)

    def __getattr__(self, name):
        return getattr(self._real, name)

    def optimize(self, u):
        raise nlopt.runtime_error("nlopt failure")


_REAL_OPT = nlopt.opt


@pytest.mark.parametrize("loss", ["chi2", "log"])
def test_energy_holds_even_when_slsqp_fails(monkeypatch, loss):
    model = gm.get("cooktorrance")
    meas = simulate(model, BRIGHT, np.random.default_rng(3), n=200)
    assert float(np.max(model.albedo(np.array([[0.0, 0.0, 1.0]]), BRIGHT))) > 1.05   # the truth breaks energy
    monkeypatch.setattr(nlopt, "opt", _FailingOpt)
    res = fit(meas, model, rng=np.random.default_rng(0), loss=loss)       # no traceback
    assert res.energy["enforced"] is True
    assert res.energy["holds"] is True, res.energy
    assert res.energy["max_albedo"] <= 1.0 + 1e-4
    assert "SLSQP failed" in res.message and "scaled" in res.message
