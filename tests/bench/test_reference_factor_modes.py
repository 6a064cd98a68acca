"""The reference factor's line propagates the covariance of gonio calibrate's fit (issue 34).

gonio calibrate fits the reference's non-Lambertian factor F = 1 - a (s_i + s_o) / 2 + b s_i s_o
(s = sin^2 theta; gonio/bench/measure/alignment.reference_factor_model) with a covariance of
(a, b). The law of propagation (JCGM 100:2008 5.2.2) gives the covariance of two values' relative
errors as D_A C D_B^T, D = dF/d(a, b) / F. The line used to be one input of magnitude u_F(theta)
at every point (correlation +1 between any two points, "sign taken as common to all points"): a
grazing point where an error of a lowers F and one where b raises it were made to move together,
and the adequacy test's nuisance could absorb only that one pattern (calibrated demo chain,
seeds 1-30: T/dof 1.052 +- 0.017, 6 of 30 at p < 0.05).
"""

import numpy as np
import pytest

from gonio.bench.dataset.budget import calibration_components
from gonio.bench.measure.alignment import fit_reference_factor, reference_factor_model

# points of a quick-plan-like geometry: (theta_i, theta_o) in degrees
POINTS = np.array([[0.0, 0.0], [30.0, 30.0], [60.0, 0.0], [60.0, 60.0], [75.0, 10.0], [20.0, 75.0], [45.0, 45.0]])


def _calibration(rng):
    """A fit of the factor from noisy reference signals over the calibration's 5 x 5 grid."""
    g = np.array([0.0, 20.0, 40.0, 60.0, 75.0])
    ti, to = (v.ravel() for v in np.meshgrid(g, g, indexing="ij"))
    truth = reference_factor_model(ti, to, 0.05, 0.06)
    u = np.full(ti.shape, 2e-3)
    fit = fit_reference_factor(ti, to, 1.7 * truth + u * rng.standard_normal(ti.shape), 1.7 * u)
    ref = {"reflectance": 0.99, "factor_theta_i": fit["grid_deg"], "factor_theta_o": fit["grid_deg"],
           "factor": fit["factor"], "u_factor": fit["u_factor"], "factor_a": fit["a"], "factor_b": fit["b"],
           "factor_cov_ab": fit["cov_ab"]}
    return ref, np.asarray(fit["cov_ab"]), fit


def _line(ref):
    rows = [{"theta_i": float(a), "theta_o": float(b)} for a, b in POINTS]
    brdf = np.full((len(rows), 3), 0.2)
    comps = [c for c in calibration_components(rows, {"reference": ref}, brdf) if c.name == "reference_factor"]
    assert len(comps) == 1
    v = np.asarray(comps[0].value, float)
    v = v[None] if v.ndim == 2 else v                      # (inputs, N, C)
    return v[:, :, 0] / 0.2                                 # relative, one channel


def test_the_line_carries_the_covariance_of_the_fit():
    rng = np.random.default_rng(34)
    ref, C, fit = _calibration(rng)
    rel = _line(ref)
    got = rel.T @ rel                                       # sum over inputs of v v^T: (N, N)
    si2, so2 = (np.sin(np.radians(POINTS[:, k])) ** 2 for k in (0, 1))
    F = reference_factor_model(POINTS[:, 0], POINTS[:, 1], fit["a"], fit["b"])
    D = np.stack([-0.5 * (si2 + so2), si2 * so2], -1) / F[:, None]
    want = D @ C @ D.T
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12 * np.abs(want).max())
    corr = want / np.sqrt(np.outer(np.diag(want), np.diag(want)) + 1e-300)
    # the law of propagation gives some pairs a correlation well below +1 (the old line's for all)
    off = corr[np.triu_indices(len(POINTS), 1)][np.isfinite(corr[np.triu_indices(len(POINTS), 1)])]
    assert off.min() < 0.5


def test_without_the_covariance_the_line_is_the_table_and_says_so():
    rng = np.random.default_rng(35)
    ref, _, _ = _calibration(rng)
    ref.pop("factor_cov_ab")
    rows = [{"theta_i": float(a), "theta_o": float(b)} for a, b in POINTS]
    comps = [c for c in calibration_components(rows, {"reference": ref}, np.full((len(rows), 3), 0.2))
             if c.name == "reference_factor"]
    assert np.asarray(comps[0].value).ndim == 2 and "common to all points" in comps[0].source


@pytest.mark.parametrize("bad", [[[1.0, 0.0]], [[1.0, 2.0], [0.0, 1.0]], [[np.nan, 0.0], [0.0, 1.0]],
                                 [[-1.0, 0.0], [0.0, 1.0]]])
def test_a_damaged_covariance_is_refused(bad):
    from gonio.bench.measure.calpoint import reference_factor_modes

    with pytest.raises(ValueError, match="factor_cov_ab"):
        reference_factor_modes({"reference": {"factor_cov_ab": bad}}, POINTS[:, 0], POINTS[:, 1])


def test_the_factor_fit_states_its_response_to_shared_inputs():
    """ab_shifts is the weighted fit's change of (a, b) for each input's relative data change:
    a refit of the shifted data moves (a, b) by it (linear in the data; to 1e-6 of the shift)."""
    g = np.array([0.0, 20.0, 40.0, 60.0, 75.0])
    ti, to = (v.ravel() for v in np.meshgrid(g, g, indexing="ij"))
    y = 1.7 * reference_factor_model(ti, to, 0.05, 0.06)
    u = 1e-3 * y
    shifts = np.stack([-np.tan(np.radians(ti)) * np.radians(0.02), 1e-3 * np.sin(np.radians(to))], -1)
    base = fit_reference_factor(ti, to, y, u, shifts=shifts)
    for k in range(2):
        moved = fit_reference_factor(ti, to, y * (1 + 1e-3 * shifts[:, k]), u * (1 + 1e-3 * shifts[:, k]))
        want = (np.array([moved["a"], moved["b"]]) - [base["a"], base["b"]]) / 1e-3
        np.testing.assert_allclose(base["ab_shifts"][k], want, rtol=2e-3, atol=1e-9)


def test_the_budget_moves_values_by_the_factor_each_angle_input_left():
    """angle_uncertainty's irradiance modes gain D(theta) (ab per degree)^T (the modes' degrees) / F
    (the reference factor's dF / F for +1 sigma of each shared input)."""
    from gonio.bench.measure.calpoint import SHARED_INPUTS, angle_uncertainty

    stage = np.array([[20.0, 0.0, 0.0, 50.0], [40.0, 5.0, 30.0, 100.0], [60.0, -5.0, 90.0, 130.0]])
    align = {"yaw_zero_deg": 0.0, "tilt_zero_deg": 0.0, "holder_tilt_x_deg": 0.0, "holder_tilt_y_deg": 0.0,
             "cov_deg2": (np.diag([0.02, 0.03, 0.04, 0.05]) ** 2).tolist(), "lamp_zero_u_deg": 0.01,
             "wedge_u_deg": 0.05}
    ab = np.arange(14, dtype=float).reshape(7, 2) * 1e-3
    ref = {"factor_a": 0.05, "factor_b": 0.06, "factor_ab_per_deg": ab.tolist()}
    plain = angle_uncertainty({"alignment": align}, stage)
    with_f = angle_uncertainty({"alignment": align, "reference": ref}, stage)
    a = plain["angles"]
    si2, so2 = np.sin(np.radians(a[:, 0])) ** 2, np.sin(np.radians(a[:, 2])) ** 2
    D = np.stack([-0.5 * (si2 + so2), si2 * so2], -1)
    F = reference_factor_model(a[:, 0], a[:, 2], 0.05, 0.06)
    cs = np.zeros((7, 7))
    cs[:4, :4] = align["cov_deg2"]
    cs[4, 4], cs[5, 5], cs[6, 6] = 0.01 ** 2, 0.05 ** 2, 0.05 ** 2
    # basis-free: the added modes' covariance is (D P / F) cs (D P / F)^T, P = ab^T
    extra = with_f["irradiance_modes"] - plain["irradiance_modes"]
    M = (D @ ab.T) / F[:, None]
    np.testing.assert_allclose(extra @ extra.T, M @ cs @ M.T, rtol=1e-9, atol=1e-15)
    assert len(SHARED_INPUTS) == 7
    with pytest.raises(ValueError, match="factor_ab_per_deg"):
        angle_uncertainty({"alignment": align, "reference": {**ref, "factor_ab_per_deg": [[0.0, 0.0]]}}, stage)
