"""The alignment's peak estimator and the lamp zero's place in the angle budget (gonio/bench/measure/alignment.py,
gonio/bench/measure/calpoint.py), on synthetic scans whose truth is known.

Why: over 48 seeded typical instruments (tests/bench/alignment_coverage.py) the holder tilt's
rms z was 1.13 and 1.28 (+- 0.12): each peak was the mean of an up and a down pass fitted
apart, their u combined as independent, but the passes share noise at each commanded angle
(the same pixels: fixed-pattern noise; residual correlation 0.38 in those scans), which cancels
in their difference and not in their mean; and each point's abscissa has the stage's
repeatability. ``fit_passes`` fits the passes' mean (its residuals hold the shared noise) with
the abscissa's effective variance.

Statistics of the coverage test: the z of a centre whose u comes from its own residuals
(10 degrees of freedom) follows Student's t_10, not N(0, 1); each z is mapped through
Phi^-1(F_t10(z)) to a standard normal w, and sum w^2 over N scans is chi^2_N for an honest u:
the test fails at its upper 1e-3 point (one-sided: u too small), so a correct estimator fails it
by chance about once in 1000 seeds (to the extent z follows t_10: a nonlinear fit). Power: the
former estimator (passes fitted apart) fails it on the same scans (checked below); for that the
synthetic scans exaggerate the shared part (correlation 0.96, the simulator's 0.38, where the
former u was about 12 % small: N = 200 scans would not resolve it reliably, the 48-seed
study did). Runtime about 20 s.
"""

import math

import numpy as np
import pytest
from gonio.bench.measure import alignment as al
from gonio.bench import calibrate as C
from scipy import stats

N, DOF, ALPHA = 200, 10, 1e-3
SHARED, INDEPENDENT, REPEAT, BACKLASH = 0.002, 0.0004, 0.01, 0.02


def _peak(x, x0):
    """A yaw scan's ratio in the simulator, normalised: GGX-like, w 0.3, exponent 8.6."""
    d = np.radians(x - x0)
    return 1.0 / (np.cos(d) ** 4 * (1.0 + (np.tan(d) / 0.3) ** 2) ** 8.6)


def _scans(seed=20261202):
    rng = np.random.default_rng(seed)
    xs = np.arange(-7.0, 7.01, 1.0)
    for _ in range(N):
        x0 = rng.uniform(-0.5, 0.5)
        shared = SHARED * rng.standard_normal(xs.size)
        up, down = (_peak(xs + REPEAT * rng.standard_normal(xs.size) + lag, x0) + shared
                    + INDEPENDENT * rng.standard_normal(xs.size) for lag in (-0.5 * BACKLASH, 0.5 * BACKLASH))
        yield xs, up, down, x0


def _chi2_of_t(z) -> float:
    w = stats.norm.isf(stats.t.sf(np.asarray(z), DOF))
    return float(np.sum(w ** 2))


def test_the_centre_u_covers_shared_noise_and_stage_repeatability():
    new, old, back = [], [], []
    for xs, up, down, x0 in _scans():
        c, uc, b, ub = al.fit_passes(xs, up, down, u_x=REPEAT)
        new.append((c - x0) / uc)
        back.append((b - BACKLASH) / ub)
        (a, ua, _), (d, ud, _) = al.fit_peak(xs, up), al.fit_peak(xs, down)
        old.append((0.5 * (a + d) - x0) / (0.5 * math.hypot(ua, ud)))
    limit = stats.chi2.isf(ALPHA, N)
    assert _chi2_of_t(new) < limit, (np.sqrt(np.mean(np.square(new))), limit)
    assert _chi2_of_t(old) > limit, np.sqrt(np.mean(np.square(old)))      # power: the former u fails
    assert _chi2_of_t(back) < limit                                         # the backlash's u (conservative)


def test_abscissa_jitter_alone_is_in_the_centre_u():
    """Stage repeatability as the only noise (the flanks noisiest): the effective variance
    covers it; a pooled residual variance understates it (rms z 1.3)."""
    rng = np.random.default_rng(5)
    xs = np.arange(-7.0, 7.01, 1.0)
    z_new, z_old = [], []
    for _ in range(N):
        x0 = rng.uniform(-0.5, 0.5)
        y = _peak(xs + REPEAT * rng.standard_normal(xs.size), x0) + 1e-5 * rng.standard_normal(xs.size)
        c, uc, _ = al.fit_peak(xs, y, u_x=REPEAT)
        z_new.append((c - x0) / uc)
        c, uc, _ = al.fit_peak(xs, y)
        z_old.append((c - x0) / uc)
    limit = stats.chi2.isf(ALPHA, N)
    assert _chi2_of_t(z_new) < limit, np.sqrt(np.mean(np.square(z_new)))
    assert _chi2_of_t(z_old) > limit, np.sqrt(np.mean(np.square(z_old)))


def test_the_lamp_zero_moves_peaks_as_half_a_yaw_zero_and_the_budget_carries_it():
    """Specular scans cannot see the lamp arm's zero: a lamp at L + dL gives the peaks of a yaw
    zero dL / 2 smaller. The calibration carries its prior u as one shared error (the lamp by
    dL, the true yaw by dL / 2 from the fitted zero): in plane, theta_i and theta_o both move by
    dL / 2, fully correlated."""
    p = np.array([0.05, -0.03, 0.2, -0.1])
    for az in (0.0, 90.0, 200.0):
        with_lamp = al.predicted_peaks(p, az, 60.0 + 0.1, yaw_at_tilt_scan=30.0)
        as_yaw = al.predicted_peaks(p - [0.05, 0, 0, 0], az, 60.0, yaw_at_tilt_scan=30.0)
        assert with_lamp == pytest.approx(as_yaw, abs=1e-9)
    cal = {"alignment": {"lamp_zero_u_deg": 0.02}}
    u = C.angle_uncertainty(cal, [(20.0, 0.0, 0.0, 60.0), (35.0, 0.0, 90.0, 80.0)])
    assert u["u_theta_i"] == pytest.approx([0.01, 0.01], rel=1e-4)
    assert u["u_theta_o"] == pytest.approx([0.01, 0.01], rel=1e-4)
    assert u["cov_shared"][:, 0, 2] == pytest.approx([1e-4, 1e-4], rel=1e-4)     # correlated, +1
    fit = al.fit_alignment([{"azimuth": a, "lamp": 60.0, "yaw": 30.0, "u_yaw": 0.003, "tilt": 0.0, "u_tilt": 0.003,
                             "yaw_scan_at": 30.0} for a in (0.0, 90.0, 180.0, 270.0)], lamp_zero_u_deg=0.02)
    assert fit["cov"][0][0] == pytest.approx(fit["cov_fit"][0][0] + 1e-4)     # the yaw zero's stated u has it
