"""The calibration's mathematics: specular peaks, the alignment fit, linearity, the reference factor.

Geometry (gonio/bench/plan/kinematics): the sample's orientation is ``Rz(yaw) Ry(tilt) B Rz(azimuth)``,
the camera along ``c = (1, 0, 0)``, the lamp at ``l(L) = (cos L, sin L, 0)``. The bench's error
parameters ``p = (dyaw, dtilt, ax, ay)`` (degrees): true yaw and tilt are commanded + (dyaw,
dtilt), and the holder's normal is ``H e_z`` with ``H = Rx(ax) Ry(ay)`` in the azimuth stage's
frame (so the true orientation is ``R H``). A glossy sample reflects most where its normal is
closest to the bisector ``b = (c + l) / |c + l|``; the maximum of ``n . b`` over one stage's
scan has a closed form (:func:`predicted_peaks`), so the peaks found at several azimuths fit
``p`` by weighted least squares (scipy), as in the mirror-based alignment of
gonioreflectometers (Huenerhoff et al. 2006, Metrologia 43 S11; Barnes et al. 1998, Appl. Opt.
37 6655). The azimuth stage's zero and the lamp arm's zero are not identified; the lamp zero's
prior standard uncertainty ``lamp_zero_u_deg`` is carried into the yaw zero and the angles.
"""

# The zeros the fit does not identify: the azimuth stage's own zero only turns the tilt's
# direction (the fit reports the tilt in the azimuth counter's frame, which is what the bench
# uses); the lamp arm's zero moves every peak by half of it like -dyaw (the fit finds
# dyaw - dL / 2). The lamp zero is surveyed against the direct beam at assembly and its prior
# standard uncertainty (lamp_zero_u_deg) is carried: into the yaw zero's stated u (half of it)
# and, as one error shared by every point that moves the lamp by dL and the yaw by dL / 2
# together, into each point's angles (gonio.bench.measure.calpoint.angle_uncertainty).

from __future__ import annotations

import math

import numpy as np
from scipy.optimize import least_squares

__all__ = ["fit_peak", "fit_passes", "predicted_peaks", "fit_alignment", "holder_rotation", "fit_linearity",
           "fit_reference_factor", "reference_factor_model"]

_B = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def _rz(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _ry(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rx(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def holder_rotation(ax_deg: float, ay_deg: float) -> np.ndarray:
    """``H = Rx(ax) Ry(ay)``: the holder's true frame in the azimuth stage's frame."""
    return _rx(math.radians(ax_deg)) @ _ry(math.radians(ay_deg))


def fit_peak(x, y, u=None, u_x: float = 0.0) -> tuple[float, float, dict]:
    """Centre of a symmetric peak: ``A / (cos^4 d (1 + (tan d / w)^2)^m) + c``, ``d = x - x0``.

    The GGX (Trowbridge-Reitz) distribution's shape ``D(theta_h)`` with a free exponent (m = 2
    is GGX, Walter et al. 2007 eq. 33; other m cover Pearson VII-like lobes), fitted by least
    squares; a scan in yaw or tilt moves the half-vector angle one for one.

    Parameters
    ----------
    x, y : array_like
        Stage angles (deg) and signal (any unit, > 0 near the peak).
    u : array_like, optional
        Standard uncertainties of ``y`` (default: one unknown ``s_y`` for every point, estimated
        from the residuals).
    u_x : float
        Standard uncertainty of each abscissa (deg), independent per point: the stage's
        repeatability, a fresh draw at every move of the scan.

    Returns
    -------
    x0, u_x0 : float
        Peak centre and its standard uncertainty (deg).
    info : dict
        ``chi2``, ``dof``, ``params``, ``s_y`` (the ordinate noise used).

    Notes
    -----
    An abscissa error ``dx_i`` moves the signal by ``f'(x_i) dx_i``: a point on the flank,
    where the centre's information lies, is noisier than one on the top or in the tails. Each
    point's variance is the effective variance ``s_y^2 + (f'(x_i) u_x)^2`` (Orear 1982, Am. J.
    Phys. 50 912; errors in variables to first order) and the fit is weighted by it, so the
    centre's covariance is ``(J^T W J)^-1`` with the flanks' real noise. With ``u`` None, ``s_y``
    is the value that makes chi^2 equal its degrees of freedom (0 when the abscissa's jitter
    already explains the residuals; ``u_x`` is then kept, a data-sheet bound). With ``u`` given,
    the covariance is scaled by chi^2 / dof where that exceeds 1 (a shape the model misses).
    A pooled residual variance with ``u_x`` ignored (unweighted least squares) understates the
    centre's uncertainty by ``sqrt(n sum g^4 / (sum g^2)^2)`` when the abscissa's noise
    dominates (``g`` the slopes; 1.3 for a GGX peak of alpha 0.1 sampled every degree over
    +-7 deg, tests/bench/test_alignment_peak.py); in the calibration's scans the ordinate's
    noise dominates and the term moves the holder tilt's rms z by about 0.1.
    """
    x, y = np.asarray(x, float), np.asarray(y, float)
    if x.size < 6 or not np.all(np.isfinite(y)):
        raise ValueError("a peak scan needs at least 6 finite points")
    k = int(np.argmax(y))
    top, floor = float(y[k]), float(np.min(y))
    half = x[y > floor + 0.5 * (top - floor)]
    w0 = max(0.5 * (half.max() - half.min()), 0.5 * float(np.median(np.diff(np.sort(x)))))
    dof = max(x.size - 5, 1)

    def model(p, xx):
        x0, lw, lA, c, lm = p
        d = np.radians(xx - x0)
        return np.exp(lA) / (np.cos(d) ** 4 * (1.0 + (np.tan(d) / np.exp(lw)) ** 2) ** np.exp(lm)) + c

    def slope(p):
        h = 1e-4
        return (model(p, x + h) - model(p, x - h)) / (2 * h)

    def solve(p0, sd):
        return least_squares(lambda p: (model(p, x) - y) / sd, p0, x_scale="jac", method="lm", max_nfev=4000)

    p0 = [float(x[k]), math.log(math.radians(w0)), math.log(max(top - floor, 1e-300)), floor, math.log(2.0)]
    scale_y = max(float(np.std(y)) * 1e-3, 1e-300)
    sol = solve(p0, np.full_like(y, scale_y) if u is None else np.asarray(u, float))
    s_y = None
    for _ in range(3 if u_x > 0 else 0):          # effective variance, refitted with its weights
        r2, gx2 = (model(sol.x, x) - y) ** 2, (slope(sol.x) * u_x) ** 2
        if u is None:
            s_y = _chi2_matching_floor(r2, gx2, dof)
            var = s_y ** 2 + gx2
        else:
            var = np.asarray(u, float) ** 2 + gx2
        sol = solve(sol.x, np.sqrt(np.maximum(var, 1e-300 * scale_y)))
    J = sol.jac
    cov = np.linalg.pinv(J.T @ J)
    chi2 = float(np.sum(sol.fun ** 2))
    # u None without u_x: the pooled residual variance (unweighted least squares); otherwise the
    # weights are the noise model, scaled only where the residuals exceed it
    scale = chi2 / dof if (u is None and u_x <= 0) else max(1.0, chi2 / dof)
    x0 = float(sol.x[0])
    if not (np.isfinite(x0) and x.min() <= x0 <= x.max()):
        raise ValueError("the peak lies outside the scan; centre the scan on the specular direction")
    return x0, float(math.sqrt(cov[0, 0] * scale)), {"chi2": chi2, "dof": dof, "params": sol.x.tolist(),
                                                     "s_y": s_y}


def fit_passes(x, up, down, u=None, u_x: float = 0.0) -> tuple[float, float, float, float]:
    """Peak centre and backlash from one scan up and one down over the same commanded angles.

    Parameters
    ----------
    x : array_like
        Commanded angles (deg), the same for both passes.
    up, down : array_like
        The signal at ``x`` in the upward and the downward pass (``down`` in the order of ``x``).
    u : array_like, optional
        Standard uncertainty of one pass's signal at each ``x`` (default: from the residuals).
    u_x : float
        Each abscissa's standard uncertainty (deg): the stage's repeatability, drawn per move.

    Returns
    -------
    centre, u_centre, backlash, u_backlash : float
        Degrees. ``backlash`` is the upward pass's peak minus the downward's (the load lags the
        motor by half the lost motion in the direction of travel).

    Notes
    -----
    The centre is the peak of the passes' mean at each commanded angle, fitted with
    :func:`fit_peak` (``u_x / sqrt 2``: two independent draws): the passes lag by plus and
    minus half the backlash, so their mean is symmetric about the true centre, and the noise the
    passes share at one commanded angle (the same pixels of the same squares: fixed-pattern
    noise, the scene's sampling) stays in that fit's residuals, hence in its u. Fitting each pass
    and averaging the two centres as independent misses the shared part, which cancels in their
    difference but not in their mean: in the calibration's scans of typical instruments the
    passes' residuals share about a quarter of their variance, and over 48 seeds that left the
    holder tilt's rms z at 1.13 and 1.28 (tests/bench/alignment_coverage.py). The backlash is the
    difference of the passes' own peaks, where the shared noise cancels (its u, from each pass's
    whole residuals, is then conservative).
    """
    x, up, down = (np.asarray(v, float) for v in (x, up, down))
    one = None if u is None else np.asarray(u, float)
    a, ua, _ = fit_peak(x, up, one, u_x)
    b, ub, _ = fit_peak(x, down, one, u_x)
    # the mean's u: a pass's u over sqrt 2 would assume nothing shared; with u given it is an
    # upper bound (everything shared), the conservative reading
    c, uc, _ = fit_peak(x, 0.5 * (up + down), one, u_x / math.sqrt(2.0))
    return c, uc, a - b, math.hypot(ua, ub)


def _chi2_matching_floor(r2, gx2, dof) -> float:
    """The ``s >= 0`` with ``sum r2 / (s^2 + gx2) = dof`` (0 when ``s = 0`` already gives less)."""
    def chi2(s2):
        return float(np.sum(r2 / np.maximum(s2 + gx2, 1e-300)))
    if chi2(0.0) <= dof:
        return 0.0
    lo, hi = 0.0, float(np.sum(r2)) / dof
    for _ in range(80):                           # chi2 falls monotonically in s^2
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if chi2(mid) > dof else (lo, mid)
    return math.sqrt(hi)


def _normal_pre_yaw(tilt_deg, az_deg, p):
    return _ry(math.radians(tilt_deg + p[1])) @ _B @ _rz(math.radians(az_deg)) @ holder_rotation(p[2], p[3])[:, 2]


def predicted_peaks(p, azimuth_deg, lamp_deg, tilt_at_yaw_scan=0.0, yaw_at_tilt_scan=None, lamp_side=0.0):
    """Where a yaw scan and a tilt scan find the specular peak, for error parameters ``p``.

    Returns ``(yaw_peak, tilt_peak)`` in commanded degrees: the yaw maximising ``n . b`` with
    the tilt stage at ``tilt_at_yaw_scan``, and the tilt maximising it with the yaw stage at
    ``yaw_at_tilt_scan`` (default the predicted yaw peak). ``p[4]``, when given, is the lamp
    arm's backlash: reached from below (``lamp_side`` -1) the arm stands ``p[4] / 2`` short.
    Closed forms: a rotation about lab Z (Y) by t maximises ``(R(t) v) . b`` at the difference
    of the two vectors' angles in the XY (XZ) plane.
    """
    L = math.radians(lamp_deg + (0.5 * lamp_side * p[4] if len(p) > 4 else 0.0))
    b = np.array([1.0 + math.cos(L), math.sin(L), 0.0])
    b /= np.linalg.norm(b)
    v = _normal_pre_yaw(tilt_at_yaw_scan, azimuth_deg, p)
    yaw_true = math.atan2(b[1], b[0]) - math.atan2(v[1], v[0])
    yaw_peak = math.degrees(yaw_true) - p[0]
    ys = yaw_peak if yaw_at_tilt_scan is None else yaw_at_tilt_scan
    u = _B @ _rz(math.radians(azimuth_deg)) @ holder_rotation(p[2], p[3])[:, 2]
    bb = _rz(-math.radians(ys + p[0])) @ b
    # Ry(t) maps (x, z) -> (cos t x + sin t z, -sin t x + cos t z): maximise against bb's (x, z)
    t_true = math.atan2(u[2] * bb[0] - u[0] * bb[2], u[0] * bb[0] + u[2] * bb[2])
    return yaw_peak, math.degrees(t_true) - p[1]


def fit_alignment(peaks, lamp_zero_u_deg: float = 0.0) -> dict:
    """Fit ``p = (dyaw, dtilt, ax, ay, lamp backlash)`` (deg) to specular peaks at several azimuths.

    The lamp arm is reached from below at some azimuths and from above at others
    (``lamp_side``), so its backlash is a parameter; with it the yaw zero is free of it.

    Parameters
    ----------
    peaks : list of dict
        One per azimuth: ``azimuth``, ``lamp``, ``yaw``, ``u_yaw`` (from the yaw scan at tilt
        ``tilt_scan_at``), ``tilt``, ``u_tilt`` (from the tilt scan at yaw ``yaw_scan_at``).
    lamp_zero_u_deg : float
        Standard uncertainty of the lamp arm's surveyed zero. Specular scans cannot identify it:
        a lamp zero ``dL`` moves every peak like a yaw zero of ``-dL / 2``, so the fitted yaw
        zero is ``dyaw - dL / 2``; its prior u is carried, half of it into dyaw's u.

    Returns
    -------
    dict
        ``p`` (4 or 5,), ``cov`` (deg^2, the peaks' and the lamp zero's: the uncertainty of
        each value as an estimate of the true offset), ``cov_fit`` (the peaks' alone; the lamp
        zero enters a point's angles as one error moving the lamp by ``dL`` and the yaw by
        ``dL / 2`` together, gonio/bench/measure/calpoint.angle_uncertainty), ``chi2``, ``dof``, ``names``.
    """
    if len(peaks) < 2:
        raise ValueError("the alignment needs peaks at two azimuths at least (four recommended)")

    def resid(p):
        r = []
        for pk in peaks:
            y, t = predicted_peaks(p, pk["azimuth"], pk["lamp"], pk.get("tilt_scan_at", 0.0), pk["yaw_scan_at"],
                                   pk.get("lamp_side", 0.0))
            r += [(y - pk["yaw"]) / pk["u_yaw"], (t - pk["tilt"]) / pk["u_tilt"]]
        return np.array(r)

    n = 5 if len({pk.get("lamp_side", 0.0) for pk in peaks}) > 1 else 4
    sol = least_squares(resid, np.zeros(n), method="lm", x_scale=1.0)
    J = sol.jac
    cov_fit = np.linalg.inv(J.T @ J)
    cov = cov_fit.copy()
    cov[0, 0] += (0.5 * lamp_zero_u_deg) ** 2
    names = ["yaw_zero_deg", "tilt_zero_deg", "holder_tilt_x_deg", "holder_tilt_y_deg", "backlash_lamp_deg"]
    return {"names": names[:n], "p": sol.x.tolist(), "cov": cov.tolist(), "cov_fit": cov_fit.tolist(),
            "chi2": float(np.sum(sol.fun ** 2)), "dof": int(len(sol.fun) - n)}


def fit_linearity(exposure, signal, u_signal, full_scale: float) -> dict:
    """Integral non-linearity from an exposure ladder at constant radiance.

    Model: ``signal = d + a t (1 - gamma a t / full_scale)`` (black-subtracted DN,
    monitor-normalised; ``d`` what the black level leaves, dark signal and offsets), linear in
    ``(d, a, q = gamma a^2 / full_scale)``; weighted least squares (covariance scaled by
    the Birge ratio when chi^2 / dof > 1), gamma's uncertainty by first-order propagation.

    Returns ``{"gamma", "u_gamma", "a", "chi2", "dof"}``.
    """
    t, y, u = (np.asarray(v, float) for v in (exposure, signal, u_signal))
    if t.size < 4:
        raise ValueError("the linearity ladder needs four exposures at least")
    A = np.stack([np.ones_like(t), t, -t * t], -1) / u[:, None]
    coef, *_ = np.linalg.lstsq(A, y / u, rcond=None)
    cov = np.linalg.inv(A.T @ A)
    chi2 = float(np.sum((A @ coef - y / u) ** 2))
    cov = cov * max(1.0, chi2 / max(t.size - 3, 1))       # Birge ratio (monitor noise, lamp drift)
    _, a, q = coef
    g = q * full_scale / (a * a)
    grad = np.array([0.0, -2.0 * q * full_scale / a ** 3, full_scale / (a * a)])
    return {"gamma": float(g), "u_gamma": float(math.sqrt(grad @ cov @ grad)), "a": float(a),
            "chi2": chi2, "dof": int(t.size - 3)}


def reference_factor_model(theta_i_deg, theta_o_deg, a: float, b: float):
    """``1 - a (sin^2 ti + sin^2 to) / 2 + b sin^2 ti sin^2 to`` (1 at normal incidence and view)."""
    si2 = np.sin(np.radians(theta_i_deg)) ** 2
    so2 = np.sin(np.radians(theta_o_deg)) ** 2
    return 1.0 - a * 0.5 * (si2 + so2) + b * si2 * so2


def fit_reference_factor(theta_i, theta_o, signal, u_signal, grid=(0.0, 20.0, 40.0, 60.0, 75.0),
                         shifts=None) -> dict:
    """The reference's non-Lambertian factor from its own signal across geometries.

    ``signal`` is the reference square's radiance per unit irradiance up to one unknown
    constant K (monitor-normalised, divided by cos(theta_i)); the model ``K F(ti, to)`` with
    :func:`reference_factor_model` is linear in ``(K, K a, K b)``. Returns the fitted ``a``,
    ``b``, their covariance, and the table ``factor`` over ``grid`` x ``grid`` (rows theta_i,
    columns theta_o) with its standard uncertainties ``u_factor`` (the
    ``[reference] factor`` form of gonio/bench/measure/point.ReferenceModel).

    ``shifts`` (M, K), optional: the signal's relative change for +1 sigma of each of K inputs
    shared by the points (the alignment's angle errors); ``ab_shifts`` (K, 2) is then the fitted
    (a, b)'s change for each (the weighted fit's linear response).
    """
    ti, to, y, u = (np.asarray(v, float) for v in (theta_i, theta_o, signal, u_signal))
    si2, so2 = np.sin(np.radians(ti)) ** 2, np.sin(np.radians(to)) ** 2
    A = np.stack([np.ones_like(ti), -0.5 * (si2 + so2), si2 * so2], -1) / u[:, None]
    coef, *_ = np.linalg.lstsq(A, y / u, rcond=None)
    cov = np.linalg.inv(A.T @ A)
    chi2 = float(np.sum((A @ coef - y / u) ** 2))
    dof = int(ti.size - 3)
    cov = cov * max(1.0, chi2 / max(dof, 1))      # Birge ratio: what the smooth form misses
    K = coef[0]
    ab = coef[1:] / K
    # (a, b) = (c1 / K, c2 / K): Jacobian of the ratio
    Jr = np.array([[-coef[1] / K ** 2, 1.0 / K, 0.0], [-coef[2] / K ** 2, 0.0, 1.0 / K]])
    cov_ab = Jr @ cov @ Jr.T
    g = np.asarray(grid, float)
    GI, GO = np.meshgrid(g, g, indexing="ij")
    table = reference_factor_model(GI, GO, *ab)
    s2i, s2o = np.sin(np.radians(GI)) ** 2, np.sin(np.radians(GO)) ** 2
    D = np.stack([-0.5 * (s2i + s2o), s2i * s2o], -1)
    u_table = np.sqrt(np.einsum("...i,ij,...j->...", D, cov_ab, D))
    out = {"a": float(ab[0]), "b": float(ab[1]), "cov_ab": cov_ab.tolist(), "grid_deg": g.tolist(),
           "factor": table.tolist(), "u_factor": u_table.tolist(), "chi2": chi2, "dof": dof}
    if shifts is not None:
        dy = np.asarray(shifts, float) * y[:, None] / u[:, None]           # whitened data change (M, K)
        dcoef = np.linalg.lstsq(A, dy, rcond=None)[0]                     # (3, K)
        out["ab_shifts"] = (Jr @ dcoef).T.tolist()
    return out
