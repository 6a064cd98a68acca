"""The sides of a measurement are declared once (gonio.core.sides) and every mask reads them.

Reference values: a Lambertian surface's f_r is rho / pi wherever it scatters (Lambert 1760;
Mitsuba 3 ``diffuse``), 0 on a side it does not hold.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from gonio.models.engine import fast as _fast
from gonio.bench.plan.plans import plan_from_dict
from gonio.core.errors import PlanError
from gonio.core.geometry import directions_deg
from gonio.core.sides import REFLECTION_ONLY, Side, parse_sides, side_of, sides_mask
from gonio.models.catalogue.lambertian import Diffuse
from gonio.models.registry import _REGISTRY


def test_masks_split_the_sphere_into_reflection_transmission_and_neither():
    cos_i = np.array([0.5, 0.5, 0.5, -0.5, 0.0, 0.5])
    cos_o = np.array([0.5, -0.5, 0.0, 0.5, 0.5, 1e-12])
    np.testing.assert_array_equal(side_of(cos_i, cos_o), [0, 1, -1, -1, -1, 0])
    np.testing.assert_array_equal(Side.REFLECT.mask(cos_i, cos_o, 1e-9), [1, 0, 0, 0, 0, 0])
    np.testing.assert_array_equal(sides_mask(tuple(Side), cos_i, cos_o), [1, 1, 0, 0, 0, 1])
    assert Side.REFLECT.holds_theta_o([0.0, 89.9, 90.0]).tolist() == [True, True, False]
    assert Side.TRANSMIT.holds_theta_o([90.0, 90.1, 180.0]).tolist() == [False, True, True]
    with pytest.raises(ValueError):
        sides_mask((), cos_i, cos_o)


def test_sides_parse_from_files_with_one_line_errors():
    assert parse_sides("reflect", "x") == REFLECTION_ONLY
    assert parse_sides(["transmit", "reflect", "transmit"], "x") == (Side.TRANSMIT, Side.REFLECT)
    assert parse_sides(np.array(["reflect", "transmit"]), "x") == (Side.REFLECT, Side.TRANSMIT)
    for bad in ("refract", [], 3, ["reflect", None]):
        with pytest.raises(ValueError, match="x: "):
            parse_sides(bad, "x")


class _TwoSided(Diffuse):
    """A Lambertian scatterer on both faces: only its ``sides`` declaration differs."""

    name = "diffuse_two_sided_test"

    @property
    def structure(self):
        return dataclasses.replace(super().structure, sides=(Side.REFLECT, Side.TRANSMIT))


@pytest.mark.parametrize("backend", ["numpy", "drjit"])
def test_every_evaluation_path_reads_the_models_sides(backend, monkeypatch):
    monkeypatch.setitem(_REGISTRY, _TwoSided.name, _TwoSided)   # the compiled path finds models by name
    rho = np.array([0.2, 0.5, 0.8])
    wi = directions_deg(np.full(4, 30.0), np.zeros(4))
    wo = directions_deg(np.array([40.0, 140.0, 60.0, 170.0]), np.array([180.0, 180.0, 10.0, 10.0]))
    one = Diffuse()
    two = _TwoSided()
    if backend == "drjit" and not _fast.available():
        pytest.skip("Dr.Jit's LLVM backend is not available here")
    f1 = one.eval(wi, wo, {"reflectance": rho}, backend=backend)
    f2 = two.eval(wi, wo, {"reflectance": rho}, backend=backend)
    below = wo[:, 2] < 0
    np.testing.assert_allclose(f1[~below], np.tile(rho / math.pi, (2, 1)), rtol=1e-12)
    assert (f1[below] == 0).all()
    np.testing.assert_allclose(f2, np.tile(rho / math.pi, (4, 1)), rtol=1e-12)


def test_a_plan_declares_its_sides_and_its_angles_are_checked_against_them():
    pts = [[30.0, 0.0, 40.0, 180.0], [30.0, 0.0, 150.0, 180.0]]
    with pytest.raises(PlanError, match=r"theta outside \[0, 90\)"):
        plan_from_dict({"name": "p", "points": pts})
    p = plan_from_dict({"name": "p", "sides": ["reflect", "transmit"], "points": pts})
    assert p.sides == (Side.REFLECT, Side.TRANSMIT)
    assert plan_from_dict(p.to_dict()).sides == p.sides
    assert "sides" not in plan_from_dict({"name": "p", "points": pts[:1]}).to_dict()
    with pytest.raises(PlanError, match="theta_o outside \\(90, 180\\]"):
        plan_from_dict({"name": "p", "sides": "transmit", "points": pts})
    with pytest.raises(PlanError, match="unknown side"):
        plan_from_dict({"name": "p", "sides": "refract", "points": pts})
