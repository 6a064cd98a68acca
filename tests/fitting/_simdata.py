"""Simulated captures for the fitting tests: directions from the caller's rng, f_r from the
model itself, Gaussian noise sigma = rel * f_r + floor; Monte Carlo directions over an aperture."""

import numpy as np

from gonio.fitting import Measurements, direction


def cone_directions(w, d, n, rng):
    """``n`` directions uniform over the disk of angular radius ``d`` (rad) about the unit ``w``
    in its tangent plane, as the simulator's and the fit's apertures are defined
    (gonio.sim.physics.errors, gonio.fitting.likelihood.aperture): the tests' Monte Carlo
    reference for their quadrature rules."""
    t1 = np.cross(w, [0.0, 1.0, 0.0])
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(w, t1)
    r, ph = d * np.sqrt(rng.random(n)), 2 * np.pi * rng.random(n)
    v = w + np.tan(r)[:, None] * (np.cos(ph)[:, None] * t1 + np.sin(ph)[:, None] * t2)
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def directions(rng, n, theta_max_deg=80.0, specular_fraction=0.5, spread=0.15, theta_min_deg=0.0):
    """n (wi, wo) pairs; a fraction near the mirror configuration (spread ~ lobe width)."""
    mu_lo, mu_hi = np.cos(np.radians(theta_max_deg)), np.cos(np.radians(theta_min_deg))
    wi = direction(np.arccos(rng.uniform(mu_lo, mu_hi, n)), rng.uniform(-np.pi, np.pi, n))
    wo = direction(np.arccos(rng.uniform(mu_lo, mu_hi, n)), rng.uniform(-np.pi, np.pi, n))
    k = int(specular_fraction * n)
    if k:
        mirror = wi[:k] * np.array([-1.0, -1.0, 1.0])
        wo[:k] = mirror + spread * rng.standard_normal((k, 3))
        wo[:k, 2] = np.clip(np.abs(wo[:k, 2]), 1e-3, None)
        wo[:k] /= np.linalg.norm(wo[:k], axis=1)[:, None]
    return wi, wo


def simulate(model, truth, rng, n=300, rel=0.02, floor=1e-3, **geometry):
    wi, wo = directions(rng, n, **geometry)
    f = model.eval(wi, wo, truth)
    sigma = rel * f + floor
    return Measurements(wi, wo, f + sigma * rng.standard_normal(f.shape), sigma, np.ones(f.shape, bool))
