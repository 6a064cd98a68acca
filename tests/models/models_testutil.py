"""Helpers shared by the gonio.models tests (imported by name: tests/models has no __init__)."""

from __future__ import annotations

import numpy as np


def random_hemisphere(rng, n, dtype=np.float64):
    """n directions uniform on the upper hemisphere, shape (n, 3)."""
    v = rng.normal(size=(n, 3))
    v[:, 2] = np.abs(v[:, 2])
    v /= np.linalg.norm(v, axis=1)[:, None]
    return v.astype(dtype)


def random_params(model, rng, alpha_range=(1e-3, 1.0)):
    """A random parameter set inside the model's box (roughness log-uniform)."""
    p = {}
    for par in model.parameters:
        lo, hi = par.lower, par.upper
        if par.name.startswith("alpha"):
            lo, hi = max(lo, alpha_range[0]), min(hi, alpha_range[1])
            draw = lambda size=None: np.exp(rng.uniform(np.log(lo), np.log(hi), size))  # noqa: E731
        else:
            draw = lambda size=None: rng.uniform(lo, hi, size)  # noqa: E731
        p[par.name] = draw(3) if par.per_channel else float(draw())
    return p


