"""The report's figures on both sides of a transmitting sample (issue 37): the in-plane plot
spans the whole plane of incidence, the transmitted hemisphere gets its own polar figure, and
the albedo panel shows R, T and R + T, whose quadrature is checked against Fresnel's
normal-incidence reflectance ((n - 1) / (n + 1))^2 (Born & Wolf, Principles of Optics, 1.5.3)."""

from __future__ import annotations

import io

import numpy as np
import pytest

import gonio.models as gm
from gonio.bench.report import figures
from gonio.core.geometry import directions
from gonio.fitting.measurements import Measurements
from gonio.fitting.plots import plot_in_plane, transmits


def _transmitted(model, params):
    """In-plane and out-of-plane points on both sides at theta_i 0, 20, 40 deg."""
    ti, to, po = np.meshgrid([0.0, 20.0, 40.0], np.arange(5.0, 180.0, 10.0), [0.0, 60.0, 180.0], indexing="ij")
    ti, to, po = ti.ravel(), to.ravel(), po.ravel()
    wi = directions(np.radians(ti), np.zeros_like(ti))
    wo = directions(np.radians(to), np.radians(po))
    f = np.asarray(model.eval(wi, wo, params), dtype=float)
    return Measurements(wi=wi, wo=wo, brdf=f, brdf_std=0.01 * f + 1e-6, use=np.ones_like(f, bool))


@pytest.fixture(scope="module")
def frosted():
    model = gm.get("roughdielectric", distribution="ggx")
    params = model.validate({"alpha": 0.3, "int_ior": 1.5})
    return model, params, _transmitted(model, params)


def test_in_plane_spans_both_sides(frosted):
    import matplotlib.pyplot as plt

    model, params, meas = frosted
    assert transmits(meas) and transmits(meas, model)
    fig = plot_in_plane(meas, model, params)
    axes = [ax for ax in fig.axes if ax.get_subplotspec() is not None]
    assert all(ax.get_xlim() == (-180.0, 180.0) for ax in axes)
    x = np.concatenate([ln.get_xdata() for ln in axes[1].get_lines()])
    assert x.max() > 170 and x.min() < -170          # the fit's curve runs into the transmitted side
    plt.close(fig)
    reflector = gm.get("diffuse")
    only_up = Measurements(wi=meas.wi[:3], wo=np.abs(meas.wo[:3]), brdf=meas.brdf[:3], brdf_std=meas.brdf_std[:3],
                           use=meas.use[:3])
    assert not transmits(only_up, reflector)


def test_polar_draws_each_side(frosted):
    model, params, meas = frosted
    out = figures.polar(meas, model, params)
    assert set(out) == {"polar.png", "polar_transmitted.png"}
    up = meas.wo[:, 2] > 0
    reflected = Measurements(wi=meas.wi[up], wo=meas.wo[up], brdf=meas.brdf[up], brdf_std=meas.brdf_std[up],
                             use=meas.use[up])
    assert set(figures.polar(reflected, model, params)) == {"polar.png"}
    from PIL import Image

    assert Image.open(io.BytesIO(out["polar_transmitted.png"])).size[0] > 300


@pytest.mark.parametrize("name, options, params", [
    ("roughdielectric", {"distribution": "ggx"}, {"alpha": 0.02, "int_ior": 1.5}),
    ("roughdielectric", {"distribution": "beckmann"}, {"alpha": 0.3, "int_ior": 1.5}),
    ("roughslab", {"distribution": "ggx"}, {"alpha": 0.3, "int_ior": 1.5, "tau": 0.7}),
    ("dielectric", {}, {"int_ior": 1.5}),
    ("thindielectric", {}, {"int_ior": 1.5}),
    ("difftrans", {}, {"transmittance": 0.8}),
])
def test_reflectance_transmittance_of_each_transmitter(name, options, params):
    """The albedo panel's R and T (the Mitsuba twin sampled in importance mode) against each
    model's own figures: the catalogue's quadratures for the rough interface and the slab;
    Fresnel's R (Born & Wolf 1.5.3) for the smooth interface, 2R / (1 + R) of the unpolarised R for the
    thin sheet (its inter-reflections summed, as Mitsuba's thindielectric does); T = tau for difftrans. 65536
    stratified samples: a standard error of about 1e-3, the bound 5e-3. The slab's twin in
    importance mode was 2.25 = eta^2 too dim before its inner face was held in radiance mode."""
    from gonio.core.geometry import directions
    from gonio.models.catalogue.roughdielectric import reflectance_transmittance as rough_rt
    from gonio.models.catalogue.roughslab import slab_reflectance_transmittance as slab_rt

    model = gm.get(name, **options)
    p = model.validate(params)
    theta = np.radians([0.0, 30.0, 60.0])
    R, T = figures.reflectance_transmittance(model, p, theta)
    if name == "roughdielectric":
        ref = [rough_rt(options["distribution"], params["alpha"], 1.5, directions(np.array([t]), np.zeros(1)))
               for t in theta]
    elif name == "roughslab":
        ref = [slab_rt("ggx", 0.3, 1.5, 0.7, directions(np.array([t]), np.zeros(1))) for t in theta]
    elif name == "difftrans":
        ref = [(0.0, 0.8)] * 3
    else:
        ci = np.cos(theta)
        ct = np.sqrt(1.0 - np.sin(theta) ** 2 / 1.5 ** 2)
        rs = ((ci - 1.5 * ct) / (ci + 1.5 * ct)) ** 2
        rp = ((1.5 * ci - ct) / (1.5 * ci + ct)) ** 2
        r = 0.5 * (rs + rp)
        r = r if name == "dielectric" else 2 * r / (1 + r)   # Mitsuba sums the series on the unpolarised R
        ref = list(zip(r, 1.0 - r))
    ref = np.array([[float(np.ravel(a)[0]), float(np.ravel(b)[0])] for a, b in ref])
    np.testing.assert_allclose(R[:, 1], ref[:, 0], atol=5e-3)
    np.testing.assert_allclose(T[:, 1], ref[:, 1], atol=5e-3)


def test_albedo_figure_of_a_transmitter(frosted):
    model, params, _ = frosted
    assert "albedo.png" in figures.albedo(model, params)
