"""Rough transmittance / internal reflectance tables of roughplastic."""

from __future__ import annotations

import time

import numpy as np
import pytest

from gonio.models import fresnel_dielectric
from gonio.models._rough_tables import RES, lerp_table, rough_tables


def fdr_deon_irving(eta):
    """Diffuse (hemispherical) Fresnel reflectance from outside, fit of d'Eon & Irving
    2011 (eq. of Mitsuba ``fresnel_diffuse_reflectance``; <0.1 % for 1 < eta < 2)."""
    i = 1 / eta
    return 0.919317 - 3.4793 * i + 6.75335 * i**2 - 7.80989 * i**3 + 4.98554 * i**4 - 1.36881 * i**5


@pytest.mark.parametrize("kind", ["beckmann", "ggx"])
def test_smooth_limit(kind):
    t, r_int = rough_tables(kind, 1e-4, 1.5)
    # at normal incidence a smooth interface transmits 1 - F(0) = 0.96
    assert t[-1] == pytest.approx(0.96, abs=1e-6)
    mu = np.linspace(0, 1, RES)
    np.testing.assert_allclose(t[1:], 1 - fresnel_dielectric(mu[1:], 1.5)[0], atol=2e-3)
    # internal reflectance: 1 - (1 - Fdr) / eta^2 for a smooth interface (Stokes); Mitsuba's
    # 64-point mean is a coarse quadrature, within 2 %
    smooth = 1 - (1 - fdr_deon_irving(1.5)) / 1.5**2
    assert r_int == pytest.approx(smooth, rel=0.02)


@pytest.mark.parametrize("kind", ["beckmann", "ggx"])
def test_tables_physical(kind):
    for alpha in (1e-4, 0.05, 0.3, 1.0):
        for eta in (1.0001, 1.3, 2.0, 4.0):
            t, r = rough_tables(kind, alpha, eta)
            # <= 1 up to the quadrature and the rational Beckmann G1 (which Mitsuba also uses)
            assert np.all(np.isfinite(t)) and np.all((t >= 0) & (t <= 1 + 1e-4))
            assert 0 <= r <= 1


def test_cache_and_speed():
    rough_tables.cache_clear()
    t0 = time.perf_counter()
    a = rough_tables("ggx", 0.123, 1.456)
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    b = rough_tables("ggx", 0.123, 1.456)
    again = time.perf_counter() - t0
    assert a is b and again < first
    with pytest.raises(ValueError):
        a[0][0] = 1.0  # read-only


def test_lerp_table():
    table = np.linspace(0, 1, RES) ** 2
    x = np.array([0.0, 1.0, 0.5, 1 / (RES - 1), -0.1, 1.1])
    out = lerp_table(table, x)
    assert out[0] == 0 and out[1] == 1 and out[3] == pytest.approx(table[1])
    assert out[4] == 0 and out[5] == 1
    assert out[2] == pytest.approx(0.5 * (table[31] + table[32]))
