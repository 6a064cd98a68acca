"""The simulated captures every ``gonio bench fit`` row is measured on (:mod:`gonio.perf.fit`)."""

from __future__ import annotations

import numpy as np

#: (name, options, truth) of the benchmarked models
MODELS = (("roughplastic", {"distribution": "ggx"},
           {"diffuse_reflectance": [0.6, 0.3, 0.15], "alpha": 0.15, "int_ior": 1.6}),
          ("roughconductor", {"distribution": "ggx"},
           {"eta": [0.2, 0.9, 1.1], "k": [3.0, 2.5, 2.0], "alpha": 0.2}))


def simulate_capture(model, truth, n, rng, rel=0.02, floor=1e-3):
    """Simulated capture: (Measurements, noiseless f_r)."""
    from gonio.fitting.measurements import Measurements, direction

    wi = direction(np.arccos(rng.uniform(0.1, 1.0, n)), rng.uniform(-np.pi, np.pi, n))
    wo = direction(np.arccos(rng.uniform(0.1, 1.0, n)), rng.uniform(-np.pi, np.pi, n))
    k = n // 2
    wo[:k] = wi[:k] * np.array([-1.0, -1.0, 1.0]) + 0.15 * rng.standard_normal((k, 3))
    wo[:k, 2] = np.clip(np.abs(wo[:k, 2]), 1e-3, None)
    wo[:k] /= np.linalg.norm(wo[:k], axis=1)[:, None]
    f = model.eval(wi, wo, truth)
    sigma = rel * f + floor
    return Measurements(wi, wo, f + sigma * rng.standard_normal(f.shape), sigma, np.ones(f.shape, bool)), f
