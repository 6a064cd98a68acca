"""Helpers shared by the gonio.models tests (imported by name: tests/models has no __init__)."""

from __future__ import annotations

import numpy as np


def random_hemisphere(rng, n, dtype=np.float64):
    """n directions uniform on the upper hemisphere, shape (n, 3)."""
    v = rng.normal(size=(n, 3))
    v[:, 2] = np.abs(v[:, 2])
    v /= np.linalg.norm(v, axis=1)[:, None]
    return v.astype(dtype)


def sphere(rng, n):
    """n directions uniform on the whole sphere, rounded to float32 (as Mitsuba sees them)."""
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1)[:, None]
    return v.astype(np.float32).astype(np.float64)


def incidence(theta_deg):
    """Directions (N, 3) at polar angles ``theta_deg`` in the x-z plane (phi 0)."""
    t = np.radians(np.atleast_1d(np.asarray(theta_deg, dtype=float)))
    return np.stack([np.sin(t), np.zeros_like(t), np.cos(t)], axis=1)


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




#: The float32 contract of ``Model.eval`` (float32 directions in, float32 out): relative error
#: against the float64 reference on the same float32 directions wherever f_r cos(theta_i) >
#: F32_FLOOR (the threshold of the Mitsuba agreement tests). float32's unit roundoff is 6e-8
#: and a model's kernel takes ~100 roundings (its relative condition, with roughplastic's
#: float32 tables); measured worst case 6.2e-6 (roughconductor Beckmann), so 2e-5 is ~3x margin.
F32_RTOL = 2e-5
F32_FLOOR = 1e-6


def assert_float32_agrees(got, ref, wi):
    """``got`` (float32) against the float64 ``ref`` on the same directions: F32_RTOL relative
    where ref cos(theta_i) > F32_FLOOR, F32_RTOL of the batch's largest value absolute
    everywhere, exact zeros where the reference is 0 (below the horizon, non-finite rows)."""
    assert got.dtype == np.float32 and got.shape == ref.shape
    assert np.all(np.isfinite(got)) and np.all(got >= 0)
    big = ref * np.clip(np.nan_to_num(np.asarray(wi, np.float64)[:, 2:3]), 0, None) > F32_FLOOR
    np.testing.assert_allclose(got[big], ref[big], rtol=F32_RTOL, atol=0)
    np.testing.assert_allclose(got, ref, rtol=0, atol=F32_RTOL * max(float(ref.max(initial=0.0)), F32_FLOOR))
    assert np.all(got[ref == 0] == 0)
