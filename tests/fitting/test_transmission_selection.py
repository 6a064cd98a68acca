"""Fitting transmitted data: the diffuse transmitter, ``--model auto``'s transmission
candidates and the R + T <= 1 energy quadrature."""

import math
from types import SimpleNamespace

import numpy as np
import pytest

import gonio.models as gm
from gonio.bench.plan.plans import load_plan
from gonio.core.geometry import directions_deg
from gonio.fitting.measurements import Measurements
from gonio.fitting.optimise.energy import _AlbedoQuadrature, energy_directions
from gonio.fitting.optimise.space import ParameterSpace
from gonio.fitting.selection.by_data import CANDIDATES, candidates_for, select
from gonio.models.catalogue.roughdielectric import reflectance_transmittance

TAU = {"transmittance": [0.2, 0.5, 0.7]}


def _sphere(rng, n):
    w = rng.normal(size=(n, 3))
    return w / np.linalg.norm(w, axis=1)[:, None]


def test_difftrans_against_its_twin_and_energy():
    m = gm.get("difftrans")
    rng = np.random.default_rng(11)
    wi, wo = _sphere(rng, 400), _sphere(rng, 400)
    wi[:, 2] = np.abs(wi[:, 2])
    f = m.eval(wi, wo, TAU)
    through = wo[:, 2] < 0
    np.testing.assert_allclose(f[through], np.broadcast_to(np.array(TAU["transmittance"]) / math.pi, f[through].shape))
    assert np.all(f[~through] == 0.0)
    mi = pytest.importorskip("mitsuba")
    from gonio.models.mitsuba import eval_cos, mitsuba_variant

    with mi.scoped_set_variant(mitsuba_variant()):
        got = eval_cos(mi.load_dict(m.to_mitsuba(TAU)), wi, wo)
    np.testing.assert_allclose(got, f * wi[:, 2:3], rtol=2e-6, atol=1e-7)
    with pytest.raises(ValueError):
        m.eval(wi, wo, {"transmittance": [1.5, 0.5, 0.5]})


def _problem(name, **opts):
    m = gm.get(name, **opts)
    return SimpleNamespace(model=m, space=ParameterSpace(m, 3), meas=SimpleNamespace(n_channels=3),
                           eval=SimpleNamespace(fast=False))


def test_energy_quadrature_counts_both_faces():
    wo = energy_directions()
    pr = _problem("difftrans")
    c = _AlbedoQuadrature(pr, wo)(pr.space.from_params(TAU)).reshape(-1, 3) + 1.0
    np.testing.assert_allclose(c, np.broadcast_to(TAU["transmittance"], c.shape), rtol=1e-9)   # T = tau, R = 0
    pr = _problem("roughdielectric", distribution="ggx")
    c = _AlbedoQuadrature(pr, wo)(pr.space.from_params({"alpha": 0.3, "int_ior": 1.5})).reshape(-1, 3)[:, 1] + 1.0
    R, T = reflectance_transmittance("ggx", 0.3, 1.5, wo)      # over microfacet normals (its docstring)
    np.testing.assert_allclose(c, R + T, atol=2e-3)
    assert np.all(c < 1.0)
    pr = _problem("diffuse")                                       # a reflector keeps its albedo over wi
    c = _AlbedoQuadrature(pr, wo)(pr.space.from_params({"reflectance": [0.2, 0.5, 0.7]})) + 1.0
    np.testing.assert_allclose(c.reshape(-1, 3), np.broadcast_to([0.2, 0.5, 0.7], (len(wo), 3)), rtol=1e-9)


def _data(name, opts, params, rng):
    a = load_plan("transmission").angles                      # the transmission preset's directions
    wi, wo = directions_deg(a[:, 0], a[:, 1]), directions_deg(a[:, 2], a[:, 3])
    f = gm.get(name, **opts).eval(wi, wo, params)
    sd = 0.01 * f + 1e-3
    return Measurements(wi, wo, f + sd * rng.standard_normal(f.shape), sd, np.ones(f.shape, bool))


def test_auto_considers_transmission_models():
    rng = np.random.default_rng(5)
    frosted = _data("roughdielectric", {"distribution": "ggx"}, {"alpha": 0.3, "int_ior": 1.5}, rng)
    names = candidates_for(frosted)
    assert names == (("roughdielectric", {"distribution": "beckmann"}), ("roughdielectric", {"distribution": "ggx"}),
                     ("difftrans", {}), ("roughslab", {"distribution": "beckmann"}), ("roughslab", {"distribution": "ggx"}))
    reflect = Measurements(frosted.wi, frosted.wo * [1, 1, -1], frosted.brdf, frosted.brdf_std, frosted.use)
    assert candidates_for(reflect) == CANDIDATES
    best, ranking = select(frosted, rng=np.random.default_rng(0))
    assert (best.model.name, best.model.options["distribution"]) == ("roughdielectric", "ggx")
    assert abs(best.params["alpha"] - 0.3) < 3 * best.std[0]
    diffuser = _data("difftrans", {}, TAU, rng)
    best, _ = select(diffuser, rng=np.random.default_rng(0))
    assert best.model.name == "difftrans"
    np.testing.assert_allclose(best.params["transmittance"], TAU["transmittance"], rtol=0.01)


def test_budget_carries_each_sides_certificate():
    from gonio.fitting.uncertainty.budget import budget_from_attrs

    a = load_plan("both-sides").angles
    wi, wo = directions_deg(a[:, 0], a[:, 1]), directions_deg(a[:, 2], a[:, 3])
    f = gm.get("roughdielectric", distribution="ggx").eval(wi, wo, {"alpha": 0.3, "int_ior": 1.5})
    through = a[:, 2] > 90
    meas = Measurements(wi, wo, f, 0.01 * f + 1e-4, np.ones(f.shape, bool),
                        attrs={"scale_rel_std": 0.005, "open_beam_rel_std": 0.02})
    b = {c.name: c for c in budget_from_attrs(meas).components}
    assert set(b) == {"statistical", "reference_certificate", "open_beam_certificate"}
    ref, beam = b["reference_certificate"].value, b["open_beam_certificate"].value
    np.testing.assert_allclose(ref[~through], 0.005 * f[~through])
    np.testing.assert_allclose(beam[through], 0.02 * f[through])
    assert np.all(ref[through] == 0.0) and np.all(beam[~through] == 0.0)
    assert b["open_beam_certificate"].gum_type == "B" and b["open_beam_certificate"].correlation == "full"
    # a BRDF keeps its one certificate line over every point
    refl = Measurements(wi[~through], wo[~through], f[~through], 0.01 * f[~through] + 1e-4,
                        np.ones(f[~through].shape, bool), attrs={"scale_rel_std": 0.005, "open_beam_rel_std": 0.02})
    b = budget_from_attrs(refl)
    assert [c.name for c in b.components][1:] == ["reference_certificate"] and b.source == "scale_rel_std attribute"
