"""Angle shifts at a pole (normal incidence, straight through): phi is undefined there, so a
tilt's move across the pole was lost (its theta change cancels in a central difference, its phi
slope is 0). The dataset's shift times the budget's slope must give the change a small holder
tilt really makes (first order), at poles and off them; GGX alpha 0.3, eta 1.5 transmitted."""

import numpy as np
import pytest

import gonio.models as gm
from gonio.bench.measure import calpoint
from gonio.bench.plan import kinematics
from gonio.core.geometry import tangent_basis
from gonio.fitting.uncertainty.budget import slope


@pytest.mark.parametrize("geometry", [(0.0, 0.0, 180.0, 0.0), (0.0, 0.0, 165.0, 180.0), (20.0, 0.0, 172.0, 180.0),
                                      (0.0, 0.0, 30.0, 180.0)])
def test_shift_times_slope_is_the_tilts_effect(geometry):
    model = gm.get("roughdielectric", distribution="ggx")
    params = model.validate({"alpha": 0.3, "int_ior": 1.5})
    stage = kinematics.inverse(*np.array(geometry)[:, None])
    rear = kinematics.detector_of(np.array([geometry[2]]))
    p = np.zeros(4)
    wi, wo = calpoint._directions(stage, p, rear=rear)
    S = slope(model, params, wi, wo)                                    # (1, C, 4) per degree
    for k in (2, 3):                                                    # holder tilt x, y
        J = calpoint._jacobian(stage, p, [f"p{k}"], rear=rear)[:, :, 0]    # (1, 4) degrees per degree
        delta = 1e-3
        pk = p.copy()
        pk[k] = delta
        a, b = calpoint._directions(stage, pk, rear=rear)
        actual = (model.eval(a, b, params) - model.eval(wi, wo, params)) / delta
        predicted = np.einsum("nca,na->nc", S, J)
        assert np.all(np.isfinite(J))
        np.testing.assert_allclose(predicted, actual, rtol=0.02, atol=1e-4 * np.max(np.abs(model.eval(wi, wo, params))))
    pole = tangent_basis(wi)[2] | tangent_basis(wo)[2]
    if geometry[0] == 0.0:
        assert pole.all()


def test_a_tilt_moves_the_straight_through_value():
    """The case the old shifts lost: at normal incidence straight through, a tilt of the holder
    about y changes f_t at first order (the lobe's peak moves off the camera), so a budget that
    gives it 0 there under-covers (issue 37: the adequacy test rejected the true model)."""
    model = gm.get("roughdielectric", distribution="ggx")
    params = model.validate({"alpha": 0.3, "int_ior": 1.5})
    stage = kinematics.inverse(*np.array([0.0, 0.0, 172.0, 180.0])[:, None])
    rear = np.array([True])
    wi, wo = calpoint._directions(stage, np.zeros(4), rear=rear)
    a, b = calpoint._directions(stage, np.array([0.0, 0.0, 0.0, 1e-3]), rear=rear)
    assert abs(float((model.eval(a, b, params) - model.eval(wi, wo, params))[0, 0])) > 1e-6
