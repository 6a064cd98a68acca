"""The adequacy test refits large shared angle errors through the model (issue 34).

An uncalibrated capture carries the stages' zero offsets and the holder's tilt (0.1-0.2 deg)
as shared angle inputs. Their first-order columns (slope x shift) miss the curvature of a
narrow lobe, so the right family was called inadequate: uncalibrated standard-plan captures
under the typical simulator, 5 of 11 at p < 1e-3 (seed 8: T/dof 1.55, p 4e-9). Refitted
through the model at the displaced directions the same capture gives T/dof 1.23.

Here (cheap, seeded draws): a narrow GGX lobe (alpha 0.05) whose incidence is off by one
shared input drawn at 2.5 sigma of 0.3 deg, 1 % noise. N_DRAWS = 12 draws; the right family
may be called inadequate at most once: false alarm P(Binomial(12, 1e-3) >= 2) = 6.6e-5 if the
test holds its level. Power against the defect: the first-order statistic alone rejects every
one of these draws (checked below on the first, parameters refitted but the angle inputs to
first order, as before: p < 1e-6).
"""

import numpy as np

import gonio.models as gm
from gonio.fitting import fit, fit_document
from gonio.fitting.uncertainty.budget import Budget, BudgetComponent

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from _simdata import directions  # noqa: E402

TRUTH = {"diffuse_reflectance": np.array([0.3, 0.3, 0.3]), "alpha": 0.05, "int_ior": 1.5}
N_DRAWS = 12
U_DEG = 0.3
E_TRUE = 2.5


def _draw(seed):
    rng = np.random.default_rng([seed, 34])
    model = gm.get("roughplastic", distribution="ggx")
    wi, wo = directions(rng, 300, theta_max_deg=70.0, specular_fraction=0.6, spread=0.05)
    shifts = np.zeros((1, len(wi), 4))
    shifts[0, :, 0] = U_DEG                       # theta_i off by U_DEG per +1 sigma of the input
    ti, pi_ = np.arccos(wi[:, 2]), np.arctan2(wi[:, 1], wi[:, 0])
    t = ti + np.radians(E_TRUE * U_DEG)
    wi_true = np.stack([np.sin(t) * np.cos(pi_), np.sin(t) * np.sin(pi_), np.cos(t)], axis=1)
    f = model.eval(wi_true, wo, TRUTH)
    sigma = 0.01 * f + 1e-3
    from gonio.fitting import Measurements

    meas = Measurements(wi, wo, f + sigma * rng.standard_normal(f.shape), sigma, np.ones(f.shape, bool))
    budget = Budget([BudgetComponent("statistical", sigma, "A", "none")], angles={"shared": shifts})
    return model, meas, budget


def test_large_shared_angle_errors_do_not_make_the_right_family_inadequate():
    rejected, first_order = [], None
    for seed in range(N_DRAWS):
        model, meas, budget = _draw(seed)
        result = fit(meas, model, rng=np.random.default_rng(seed))
        a = fit_document(result, meas, seed=seed, budget=budget)["goodness"]["adequacy"]
        rejected.append(a["verdict"] == "inadequate")
        if seed == 0:
            # the angle inputs to first order (the parameters refitted): what the test said before
            from gonio.fitting.uncertainty.adequacy import adequacy_test, chi2_refiner
            from gonio.fitting.uncertainty.budget import _loss_sensitivities, angle_components

            J, drdy, r = _loss_sensitivities(result, meas, residuals=True)
            comps = list(budget.components) + angle_components(result, meas, budget.angles)
            first_order = adequacy_test(result, meas, comps, J, r, drdy, refine=chi2_refiner(result, meas))["p_value"]
    print(f"\nrejected {sum(rejected)} of {N_DRAWS}; first-order p of draw 0: {first_order:.2g}")
    assert first_order < 1e-6
    assert sum(rejected) <= 1
