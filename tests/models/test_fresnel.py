"""Fresnel terms against reference values and independent formulas."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gonio.models import fresnel_conductor, fresnel_dielectric, fresnel_schlick


def hecht(theta_i, n):
    """Reference: Fresnel's sine/tangent laws with Snell's law (Hecht, *Optics*,
    4th ed., eqs. 4.42-4.43), for light from the index-1 side."""
    theta_t = np.arcsin(np.sin(theta_i) / n)
    rs = -np.sin(theta_i - theta_t) / np.sin(theta_i + theta_t)
    rp = np.tan(theta_i - theta_t) / np.tan(theta_i + theta_t)
    return rs**2, rp**2


def test_normal_incidence_glass():
    # ((n - 1) / (n + 1))^2 = 0.04 for n = 1.5 (Hecht eq. 4.67; Mitsuba test_fresnel.py)
    F, cos_t, eta_it, eta_ti = fresnel_dielectric(1.0, 1.5)
    assert F == pytest.approx(0.04, abs=1e-15)
    assert cos_t == pytest.approx(-1.0) and eta_it == 1.5 and eta_ti == pytest.approx(1 / 1.5)


def test_45_degrees_air_to_glass():
    # n = 1.5 at 45 deg: R_s = 0.0920, R_p = 0.0085 (Hecht fig. 4.49 / eqs. 4.42-4.43)
    rs, rp = hecht(math.radians(45.0), 1.5)
    assert rs == pytest.approx(0.0920, abs=5e-5) and rp == pytest.approx(0.00847, abs=5e-5)
    F = fresnel_dielectric(math.cos(math.radians(45.0)), 1.5)[0]
    assert F == pytest.approx(0.5 * (rs + rp), rel=1e-13)
    assert F == pytest.approx(0.05024, abs=5e-5)


def test_brewster_angle():
    # At Brewster's angle tan(theta_B) = n, R_p = 0, so F = R_s / 2 (Hecht sec. 8.6.2)
    n = 1.5
    tb = math.atan(n)
    rs, rp = hecht(tb, n)
    assert rp < 1e-30
    F = fresnel_dielectric(math.cos(tb), n)[0]
    assert F == pytest.approx(rs / 2, rel=1e-13)
    # F has no minimum there but R_p does: F is larger just off Brewster by less than R_s
    assert F == pytest.approx(0.073964, abs=1e-6)


def test_matches_sine_tangent_laws_over_angles():
    theta = np.linspace(1e-3, math.pi / 2 - 1e-3, 200)
    for n in (1.0001, 1.33, 1.5, 2.4, 4.0):
        rs, rp = hecht(theta, n)
        F = fresnel_dielectric(np.cos(theta), n)[0]
        np.testing.assert_allclose(F, 0.5 * (rs + rp), rtol=1e-9, atol=1e-15)


def test_critical_angle_and_total_internal_reflection():
    # from inside glass: sin(theta_c) = 1 / n, theta_c = 41.81 deg for n = 1.5
    n = 1.5
    tc = math.asin(1 / n)
    assert math.degrees(tc) == pytest.approx(41.8103, abs=1e-4)
    theta = np.array([tc + 1e-9, tc + 0.1, math.pi / 2 - 1e-9])
    F, cos_t, _, _ = fresnel_dielectric(-np.cos(theta), n)
    np.testing.assert_array_equal(F, 1.0)
    np.testing.assert_array_equal(cos_t, 0.0)
    Fb = fresnel_dielectric(-np.cos(tc - 1e-3), n)[0]
    assert 0.5 < Fb < 1.0


def test_inside_out_equals_outside_in():
    # Stokes relations: reflectance is the same along a ray path reversed
    theta_i = np.linspace(0.0, math.pi / 2 - 1e-3, 50)
    F, cos_t, _, _ = fresnel_dielectric(np.cos(theta_i), 1.7)
    F_back = fresnel_dielectric(cos_t, 1.7)[0]  # from inside (cos < 0) along the refracted ray
    np.testing.assert_allclose(F_back, F, rtol=1e-10, atol=1e-14)


def test_special_cases():
    assert fresnel_dielectric(0.3, 1.0)[0] == 0.0  # index matched
    assert fresnel_dielectric(0.0, 1.5)[0] == 1.0  # grazing
    F = fresnel_dielectric(np.array([1.0, 0.5, 0.0]), np.array([1.0001, 4.0, 2.0]))[0]
    assert np.all(np.isfinite(F)) and np.all((F >= 0) & (F <= 1))


def test_gold_at_550nm():
    # Au at 550 nm: n = 0.3504, k = 2.7141 -> R(0) = ((n-1)^2 + k^2) / ((n+1)^2 + k^2) = 0.8475
    # (optical constants: Johnson & Christy, PRB 6, 4370 (1972), via refractiveindex.info)
    assert fresnel_conductor(1.0, 0.3504, 2.7141) == pytest.approx(0.8475, abs=5e-5)


def test_conductor_reduces_to_dielectric_for_k_zero():
    c = np.linspace(0.0, 1.0, 101)
    for n in (1.2, 1.5, 3.0):
        np.testing.assert_allclose(fresnel_conductor(c, n, 0.0), fresnel_dielectric(c, n)[0], rtol=1e-10, atol=1e-14)


def test_conductor_matches_complex_amplitudes():
    # independent: complex Snell's law and Fresnel amplitudes (Born & Wolf sec. 14.2)
    rng = np.random.default_rng(1)
    for _ in range(20):
        n = complex(rng.uniform(0.05, 5), rng.uniform(0, 10))
        th = rng.uniform(0, math.pi / 2 - 1e-6)
        ci = math.cos(th)
        ct = np.sqrt(1 - (math.sin(th) / n) ** 2 + 0j)
        rs = (ci - n * ct) / (ci + n * ct)
        rp = (ct - n * ci) / (ct + n * ci)
        ref = 0.5 * (abs(rs) ** 2 + abs(rp) ** 2)
        assert fresnel_conductor(ci, n.real, n.imag) == pytest.approx(ref, rel=1e-9)


def test_conductor_per_channel_and_grazing():
    F = fresnel_conductor(np.array([[0.0], [0.5], [1.0]]), np.array([0.2, 1.0, 4.0]), np.array([3.0, 10.0, 0.0]))
    assert F.shape == (3, 3)
    np.testing.assert_allclose(F[0], 1.0)
    assert np.all((F >= 0) & (F <= 1))


def test_schlick():
    assert fresnel_schlick(1.0, 0.04) == pytest.approx(0.04)
    assert fresnel_schlick(0.0, 0.04) == pytest.approx(1.0)
    # Schlick 1994: close to the exact dielectric term for glass; worst near grazing
    # (about 0.035 absolute at 84 deg), within 0.02 up to 78 deg
    c = np.linspace(0, 1, 201)
    err = np.abs(fresnel_schlick(c, 0.04) - fresnel_dielectric(c, 1.5)[0])
    assert err.max() < 0.04 and err[c >= 0.2].max() < 0.02
    # exponent 5 (not 4): at cos = 0.5 the exact value is 0.04 + 0.96 / 32
    assert fresnel_schlick(0.5, 0.04) == pytest.approx(0.04 + 0.96 / 32)
