"""``gonio perf real``'s specular gloss (ASTM D523, 60 deg): which dE00 limit a material gets."""

import math

import numpy as np

from gonio.models.physics.gloss import GLOSS_APERTURE_DEG, MATTE_BELOW_GU, specular_gloss


def _lambert(rho):
    return lambda wi, wo: np.full((len(wi), 3), rho / math.pi)


def test_a_white_lambertian_reads_its_analytic_gloss():
    """rho / pi x cos(theta) integrated over the 4.4 x 11.7 deg receptor, over the black glass
    standard's Fresnel reflectance at 60 deg (n 1.567: 0.100056, Fresnel's equations by hand):
    2.49 GU for rho = 1, well inside the matte class (D523: below 10 GU at 60 deg)."""
    d_in, d_out = (math.radians(a) for a in GLOSS_APERTURE_DEG)
    # the cos theta_o over the in-plane width, integrated exactly: sin(60 + d/2) - sin(60 - d/2)
    exact = (math.sin(math.radians(60) + d_in / 2) - math.sin(math.radians(60) - d_in / 2)) * d_out / math.pi
    expect = 100 * exact / 0.100056
    got = specular_gloss(_lambert(1.0))
    assert abs(got - expect) < 1e-3 * expect, (got, expect)
    assert 2.4 < got < 2.6 and got < MATTE_BELOW_GU


def test_gloss_is_linear_and_reads_a_narrow_lobe_as_glossy():
    """Half the albedo halves the gloss; a GGX conductor lobe (alpha 0.01, eta 0.2 + 3i) reads
    between 80 % and 100 % of its Fresnel reflectance at 60 deg over the standard's (0.9184 /
    0.100056: 918 GU): GGX's tails outside the receptor hold the rest (P(tan theta_h < 1.9
    alpha) = 0.78 on the narrow side), hundreds of GU: glossy."""
    assert abs(specular_gloss(_lambert(0.5)) - 0.5 * specular_gloss(_lambert(1.0))) < 1e-9
    import gonio.models as gm

    m = gm.get("roughconductor", distribution="ggx")
    p = m.validate({"alpha": 0.01})
    g = specular_gloss(lambda wi, wo: m.eval(wi, wo, p), n=61)
    n = 0.2 + 3j
    root = np.sqrt(n * n - 0.75)
    fresnel = 0.5 * (abs((0.5 - root) / (0.5 + root)) ** 2 + abs((n * n * 0.5 - root) / (n * n * 0.5 + root)) ** 2)
    ideal = 100 * fresnel / 0.100056
    assert 0.8 * ideal < g < ideal, (g, ideal)


def test_a_brdf_not_finite_in_the_receptor_is_refused():
    """NaN would compare as 'not matte' and give the looser limit silently: refused instead."""
    import pytest

    with pytest.raises(ValueError, match="not finite"):
        specular_gloss(lambda wi, wo: np.full((len(wi), 3), np.nan))
