"""flakepaint's Mitsuba twin (issue 39: a spectral fit's export loads and renders in scalar_spectral).

The twin ``gonio_flakepaint`` (gonio/models/catalogue/flakepaint.py) evaluates the numpy model's
formulas in Dr.Jit, each colour and a per-wavelength spread a Mitsuba spectrum. Checked here:
eval against ``FlakePaint.eval`` in the RGB variant (the float32 allowance of
test_mitsuba_agreement.py, tol 1e-5) and in ``scalar_spectral`` at single wavelengths (Mitsuba's
irregular spectrum is exact at its nodes: mitsuba3 src/spectra/irregular.cpp), and ``sample``
against ``pdf``: the mean sample weight is the integral of f cos over the light hemisphere.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import gonio.models as gm
from gonio.core.channels import spectral, use

from models_testutil import random_hemisphere

mi = pytest.importorskip("mitsuba")
from gonio.models.mitsuba import interaction, mitsuba_variant, select_variant  # noqa: E402
from test_mitsuba_agreement import K_NOISE, compare, float32_noise  # noqa: E402

pytestmark = pytest.mark.codegen

OPTIONS = [{"distribution": d, "spread": s} for d in ("ggx", "beckmann") for s in ("shared", "wavelength")]
WL = np.arange(400.0, 701.0, 50.0)
#: the flake paint of tests/fitting/test_spectral_fit.py: a spread and a colour per wavelength
FLAKE = {"diffuse_reflectance": np.linspace(0.02, 0.08, WL.size), "specular_reflectance": 0.9, "alpha": 0.02,
         "eta": 1.5, "flake_widen": 0.3, "haze_reflectance": 0.01, "haze_alpha": 0.05,
         "flake_reflectance": np.array([0.05, 0.15, 0.3, 0.2, 0.08, 0.05, 0.05]),
         "flake_alpha": np.linspace(0.12, 0.45, WL.size), "flake_exponent": 0.3}


def _id(o):
    return f"{o['distribution']}-{o['spread']}"


@pytest.mark.parametrize("options", OPTIONS, ids=[_id(o) for o in OPTIONS])
def test_eval_matches_the_numpy_model_in_rgb(options):
    """f_r cos of the twin against the numpy model: 4 random parameter sets x 2e4 random pairs
    (llvm; 500 in scalar), within 1e-5 relative plus the float32 allowance of
    test_mitsuba_agreement.compare. Measured 2026-12-04: at most 2.0e-6 relative."""
    model = gm.get("flakepaint", **options)
    rng = np.random.default_rng(sum(map(ord, _id(options))))
    n = 20_000 if mitsuba_variant().startswith("llvm") else 500
    worst, frac, excess, where = compare(model, rng, n, 1e-5, n_sets=4)
    assert excess <= 0.0, where



@pytest.mark.parametrize("target", ["half_vector_lobe", "fresnel_conductor"])
def test_a_1e_4_error_is_detected(target, monkeypatch):
    """The allowance is not so wide that a wrong formula passes (test_mitsuba_agreement's
    mutants): the numpy model's haze and flake lobes, or the coat's Fresnel, 1e-4 relative off
    make the comparison fail. Measured 2026-12-04: excess over the allowance 8.6e-5 (lobes) and
    7.6e-5 (Fresnel) against the 5e-5 asserted."""
    import gonio.models.catalogue.flakepaint as fp

    fn = getattr(fp, target)
    monkeypatch.setattr(fp, target, lambda *a, **k: fn(*a, **k) * (1.0 + 1e-4))
    model = gm.get("flakepaint", distribution="ggx", spread="wavelength")
    n = 20_000 if mitsuba_variant().startswith("llvm") else 500
    worst, frac, excess, where = compare(model, np.random.default_rng(1), n, 1e-5, n_sets=2)
    assert excess > 0.5e-4, (excess, worst)

@pytest.mark.parametrize("distribution", ["ggx", "beckmann"])
def test_a_spectral_fit_evaluates_per_wavelength_in_scalar_spectral(distribution):
    """The 7-wavelength paint (a colour and a spread per wavelength) loads in scalar_spectral and
    its eval at 450, 500, 600 and 650 nm is the numpy model's f_r cos at those channels: 1e-5
    relative plus the float32 allowance (K x our float64 sensitivity). Measured: 5e-7."""
    if "scalar_spectral" not in mi.variants():
        pytest.skip("this Mitsuba build has no scalar_spectral variant")
    model = gm.get("flakepaint", distribution=distribution, spread="wavelength")
    p = model.validate({k: np.asarray(v, np.float32).astype(np.float64) for k, v in FLAKE.items()})
    rng = np.random.default_rng(39)
    wi = random_hemisphere(rng, 300, np.float32).astype(np.float64)
    wo = random_hemisphere(rng, 300, np.float32).astype(np.float64)
    select_variant()            # a variant to return to (scoped_set_variant cannot restore none)
    with mi.scoped_set_variant("scalar_spectral"), use(spectral(WL)):
        d = model.to_mitsuba(p)             # registers the plugin for this variant
        assert d["flake_alpha"]["type"] == "spectrum" and d["flake_reflectance"]["type"] == "spectrum"
        bsdf = mi.load_dict(d)
        si = mi.SurfaceInteraction3f()
        si.sh_frame = mi.Frame3f(mi.Normal3f(0.0, 0.0, 1.0))
        si.wavelengths = mi.Spectrum([450.0, 500.0, 600.0, 650.0])
        got = []
        for a, b in zip(wi.tolist(), wo.tolist()):
            si.wi = mi.Vector3f(*b)                      # Mitsuba's si.wi points to the sensor: gonio's wo
            got.append(list(bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(*a))))
    ref = np.array(got)
    cols = [1, 2, 4, 5]
    ours = (model.eval(wi, wo, p) * wi[:, 2:3])[:, cols]
    assert np.all(np.isfinite(ref)) and np.all(ref >= 0)
    mask = ref > 1e-6
    assert mask.mean() > 0.9
    rel = np.where(mask, np.abs(ours - ref) / np.where(mask, ref, 1.0), 0.0)
    noise = float32_noise(model, p, wi, wo, rng)[:, cols]
    assert np.all(rel <= 1e-5 + K_NOISE * noise), rel.max()
    assert np.all(np.abs(ours[~mask]) <= 2e-6)


def _quadrature(model, p, cam, n_theta=192, n_phi=384):
    """Integral of f_r(wl, cam) cos(theta_l) over the light hemisphere (Gauss-Legendre in theta,
    midpoints in phi), per channel."""
    x, w = np.polynomial.legendre.leggauss(n_theta)
    th = 0.25 * np.pi * (x + 1.0)
    wt = 0.25 * np.pi * w * np.sin(th) * np.cos(th)
    ph = (np.arange(n_phi) + 0.5) * 2.0 * np.pi / n_phi
    T_, P_ = np.meshgrid(th, ph, indexing="ij")
    wl = np.stack([np.sin(T_) * np.cos(P_), np.sin(T_) * np.sin(P_), np.cos(T_)], -1).reshape(-1, 3)
    f = model.eval(wl, np.broadcast_to(cam, wl.shape), p).reshape(n_theta, n_phi, -1)
    return (f * wt[:, None, None]).sum(axis=(0, 1)) * 2.0 * np.pi / n_phi


SAMPLED = [({"distribution": "ggx", "spread": "shared"},
            {"diffuse_reflectance": [0.05, 0.1, 0.2], "alpha": 0.1, "haze_reflectance": 0.05, "haze_alpha": 0.2,
             "flake_reflectance": [0.3, 0.2, 0.1], "flake_alpha": 0.3, "flake_exponent": 0.3, "flake_widen": 0.5}),
           ({"distribution": "beckmann", "spread": "wavelength"},
            {"diffuse_reflectance": [0.3, 0.1, 0.0], "alpha": 0.15, "eta": 1.8, "haze_reflectance": 0.1,
             "haze_alpha": 0.1, "flake_reflectance": [0.1, 0.2, 0.4], "flake_alpha": [0.1, 0.3, 0.6],
             "flake_exponent": 0.8, "flake_widen": 1.0})]


@pytest.mark.parametrize("options,params", SAMPLED, ids=[_id(o) for o, _ in SAMPLED])
def test_sample_weights_average_to_the_integral_of_f_cos(options, params):
    """``sample``'s weights (eval / pdf at the sampled light direction) average to the integral of
    f cos over light directions, by quadrature of the numpy model: a density that differs from
    ``pdf`` biases a render. 1e5 samples per camera direction (0, 40, 75 deg), 3 channels:
    |mean - integral| < 4 sigma + 5e-4 (float32, quadrature): false alarm 6e-5 a comparison for
    a Gaussian mean (5e-4 over the 9 of a case). Measured 2026-12-04: |z| <= 1.92 here. Power: a
    pdf 1 % too large (the mean 1 % too small) gave |z| 2.5-18 (sigma 2.5e-4 to 1.8e-3) and
    failed 15 of the 18 comparisons, each case at its first camera direction."""
    model = gm.get("flakepaint", **options)
    assert_sampling_unbiased(model, model.validate(params), np.random.default_rng(3))


def assert_sampling_unbiased(model, p, rng, n=100_000):
    """The twin's ``sample`` weights average to the integral of f cos (the quadrature of the numpy
    model) at camera elevations 0, 40, 75 deg, with ``pdf`` the density drawn from; the bounds of
    :func:`test_sample_weights_average_to_the_integral_of_f_cos`."""
    if not mitsuba_variant().startswith(("llvm", "cuda")):
        pytest.skip("1e5 samples a camera direction in one wavefront: a vectorised Mitsuba variant")
    with mi.scoped_set_variant(mitsuba_variant()):
        bsdf = mi.load_dict(model.to_mitsuba(p))
        for theta in (0.0, 40.0, 75.0):
            t = math.radians(theta)
            cam = np.array([math.sin(t), 0.0, math.cos(t)])
            si, _ = interaction(np.tile(cam, (n, 1)), np.tile(cam, (n, 1)))
            bs, weight = bsdf.sample(mi.BSDFContext(), si, mi.Float(rng.random(n)), mi.Point2f(rng.random((2, n))))
            w = np.array(weight).reshape(3, n)
            assert np.all(np.isfinite(w)) and np.all(w >= 0)
            pdf = np.array(bsdf.pdf(mi.BSDFContext(), si, bs.wo))
            np.testing.assert_allclose(np.array(bs.pdf), pdf, rtol=1e-6)
            want = _quadrature(model, p, cam)
            sigma = w.std(axis=1) / math.sqrt(n)
            assert np.all(np.abs(w.mean(axis=1) - want) < 4.0 * sigma + 5e-4), (theta, w.mean(axis=1), want, sigma)


def test_hostile_values_are_refused_in_one_line():
    """A NaN, an out-of-box spread, a spread per wavelength of the wrong length: ValueError,
    one line, before Mitsuba sees anything."""
    model = gm.get("flakepaint", spread="wavelength")
    for bad in ({"flake_alpha": float("nan")}, {"flake_alpha": [0.3, 0.3, 2.0]}, {"eta": 0.5},
                {"flake_alpha": [0.3, 0.3]}, {"diffuse_reflectance": [0.1, float("inf"), 0.1]}):
        with pytest.raises(ValueError) as info:
            model.to_mitsuba(bad)
        assert "\n" not in str(info.value), bad


def test_a_spectral_fit_renders_in_scalar_spectral(flat_sample_luminance):
    """Issue 39's requirement: the twin of a 7-wavelength fit renders in scalar_spectral. A flat
    sample under a directional lamp (irradiance 1) seen by a radiance meter reads L = f_r cos
    (direct integrator); with every spectrum flat the luminance film reads that one value (the
    wavelengths drawn per sample, 256 spp: 1 %, as tests/fitting/test_spectral_fit.py's
    roughplastic; spectra are 0 outside 400-700 nm, which the luminance weights little)."""
    if "scalar_spectral" not in mi.variants():
        pytest.skip("this Mitsuba build has no scalar_spectral variant")
    model = gm.get("flakepaint", distribution="ggx", spread="wavelength")
    flat = {k: (np.full(WL.size, float(np.mean(v))) if np.ndim(v) else v) for k, v in FLAKE.items()}
    p = model.validate(flat)
    ti, to = np.radians(30.0), np.radians(25.0)
    wi, wo = np.array([np.sin(ti), 0.0, np.cos(ti)]), np.array([-np.sin(to), 0.0, np.cos(to)])     # on the flake lobe
    select_variant()
    with mi.scoped_set_variant("scalar_spectral"), use(spectral(WL)):
        value = flat_sample_luminance(model.to_mitsuba(p), wi, wo)
    want = float(model.eval(wi[None], wo[None], p)[0, 0]) * wi[2]
    assert value == pytest.approx(want, rel=0.01), (value, want)      # measured 2026-12-04: +0.21 %
