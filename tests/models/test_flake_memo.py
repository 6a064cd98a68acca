"""flake_memo (issue 35): what flakepaint and gratingpaint reuse within a fit changes no number.

The reference is each model computed afresh (nothing remembered: MAX_POINTS 0), compared bit
for bit; the memo is keyed on the directions' values, so arrays changed in place, or a
replaced lobe function (the twin tests' mutants), are never served a stale result.
"""

from __future__ import annotations

import numpy as np
import pytest

import gonio.models as gm
import gonio.models.catalogue.flake_memo as fm

from models_testutil import random_hemisphere

PAINT = {"alpha": 0.05, "eta": 1.5, "haze_alpha": 0.08, "flake_alpha": 0.25, "flake_exponent": 0.4,
         "flake_widen": 0.5, "flake_reflectance": [0.1, 0.2, 0.3], "grating_period": 0.65, "grating_width": 0.1,
         "grating_reflectance": [0.05, 0.03, 0.02]}
MODELS = [("flakepaint", {"distribution": "ggx"}), ("flakepaint", {"distribution": "beckmann", "spread": "wavelength"}),
          ("gratingpaint", {"distribution": "beckmann"}), ("gratingpaint", {"distribution": "ggx", "ring": "table"})]


def _params(model):
    p = {k: v for k, v in PAINT.items() if k in {q.name for q in model.parameters}}
    return model.validate({**p, **{f"ring_{k}": [0.1 * k, 0.05, 0.02] for k in range(17)}}
                          if model.options.get("ring") == "table" else p)


@pytest.mark.parametrize("name, options", MODELS, ids=[f"{n}-{'-'.join(o.values())}" for n, o in MODELS])
def test_remembered_equals_afresh_bit_for_bit(name, options, monkeypatch):
    """eval and jacobian_reference, twice each (the second from the memo), equal the same calls
    with nothing remembered; a colour changed between calls (the shapes reused) too."""
    model = gm.get(name, **options)
    rng = np.random.default_rng(7)
    wi, wo = random_hemisphere(rng, 500), random_hemisphere(rng, 500)
    p = _params(model)
    q = {**p, "flake_reflectance": np.asarray(p["flake_reflectance"]) * 0.5}
    got = [model.eval(wi, wo, p), model.eval(wi, wo, p), model.eval(wi, wo, q), model.jacobian_reference(wi, wo, p)]
    monkeypatch.setattr(fm, "MAX_POINTS", 0)
    want = [model.eval(wi, wo, p), model.eval(wi, wo, p), model.eval(wi, wo, q), model.jacobian_reference(wi, wo, p)]
    for a, b in zip(got[:3], want[:3]):
        assert np.array_equal(a, b)
    assert np.array_equal(got[3][0], want[3][0])
    for k in want[3][1]:
        assert np.array_equal(got[3][1][k], want[3][1][k]), k


def test_directions_changed_in_place_are_not_served_stale():
    """The caller's arrays changed after a call: the next call sees the new directions."""
    model = gm.get("gratingpaint", distribution="ggx")
    rng = np.random.default_rng(8)
    wi, wo = random_hemisphere(rng, 300), random_hemisphere(rng, 300)
    p = _params(model)
    model.eval(wi, wo, p)
    wi[:] = random_hemisphere(rng, 300)
    fresh = gm.get("gratingpaint", distribution="ggx").eval(wi.copy(), wo.copy(), p)
    assert np.array_equal(model.eval(wi, wo, p), fresh)


def test_remembered_arrays_are_read_only():
    """What the memo hands out cannot be changed by a caller (it is shared between calls)."""
    model = gm.get("flakepaint", distribution="ggx")
    rng = np.random.default_rng(9)
    wi, wo = random_hemisphere(rng, 200), random_hemisphere(rng, 200)
    base, coat, haze, flake = model._terms(wi, wo, _params(model))
    with pytest.raises(ValueError):
        coat[0, 0] = 1.0
