"""Diffuse terms: Lambert and Oren-Nayar."""

from __future__ import annotations

import math

import numpy as np

import gonio.models as gm
from gonio.models import lambert, oren_nayar

from models_testutil import random_hemisphere


def sph(theta, phi):
    return np.array([[math.sin(theta) * math.cos(phi), math.sin(theta) * math.sin(phi), math.cos(theta)]])


def test_lambert_is_rho_over_pi():
    # Lambert's law: f_r = rho / pi (pbrt-v4 sec. 9.2), albedo = rho
    f = lambert(np.array([0.2, 0.5, 1.0]), 4)
    np.testing.assert_allclose(f, np.tile([0.2 / math.pi, 0.5 / math.pi, 1 / math.pi], (4, 1)), rtol=1e-15)


def test_oren_nayar_reference_formula():
    # Oren & Nayar 1994 eq. 30 written with angles: A + B max(0, cos(phi_i - phi_o)) sin(alpha) tan(beta)
    rho, sigma = np.array([0.8, 0.5, 0.2]), 0.4
    s2 = sigma**2
    A, B = 1 - s2 / (2 * (s2 + 0.33)), 0.45 * s2 / (s2 + 0.09)
    for ti, pi_, to, po in [(0.3, 0.0, 1.0, 0.5), (1.2, 1.0, 0.2, 0.9), (0.7, 0.0, 0.7, math.pi), (1.5, 2.0, 1.4, 2.1)]:
        al, be = max(ti, to), min(ti, to)
        ref = rho / math.pi * (A + B * max(0.0, math.cos(pi_ - po)) * math.sin(al) * math.tan(be))
        np.testing.assert_allclose(oren_nayar(sph(ti, pi_), sph(to, po), rho, sigma)[0], ref, rtol=1e-12)


def test_oren_nayar_limits(rng):
    wi, wo = random_hemisphere(rng, 1000), random_hemisphere(rng, 1000)
    rho = np.array([0.3, 0.6, 0.9])
    # sigma = 0 is Lambert
    np.testing.assert_allclose(oren_nayar(wi, wo, rho, 0.0), lambert(rho, 1000), rtol=1e-15)
    # reciprocal, finite at the horizon
    np.testing.assert_array_equal(oren_nayar(wi, wo, rho, 0.5), oren_nayar(wo, wi, rho, 0.5))
    h = np.array([[1.0, 0.0, 0.0]])
    assert np.all(np.isfinite(oren_nayar(h, h, rho, 1.0)))


def test_orennayar_albedo_below_rho():
    # rough diffuse surfaces darken (Oren & Nayar 1994 fig. 10): albedo <= rho for every view
    m = gm.get("orennayar")
    wo = np.stack([np.sin(np.linspace(0, 1.5, 6)), 0 * np.ones(6), np.cos(np.linspace(0, 1.5, 6))], 1)
    a = m.albedo(wo, {"reflectance": 1.0, "sigma": 0.5})
    assert np.all(a <= 1.0) and np.all(a > 0.7)
