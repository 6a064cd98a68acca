"""Is a model adequate to its data? A chi-square test with a stated level (issue 34).

:func:`adequacy_test`: the residuals of a chi2 fit against the covariance its uncertainty
budget states (gonio.fitting.uncertainty.budget's components: point-wise lines in a block per
point, each shared input a nuisance parameter with a standard normal prior, profiled out),
the generalised least-squares chi^2, chi^2 distributed with M - rank(J) degrees of freedom
under the budget; :func:`nominal_test`: any other loss's chi^2 against its dof. Both at level
:data:`ADEQUACY_ALPHA`, their false-alarm rate (tests/fitting/test_adequacy.py measures it and
the power against a wrong family).
"""

# Why not chi^2 against E + 4 sd (E, sd its mean and spread under the budget, the rule before):
# a few large shared inputs make chi^2 under the null a sum of a few scaled chi^2_1 terms, sd ~
# E, and the rule passed a wrong family at chi^2/dof 50. Profiling the shared inputs out instead
# gives a statistic whose law does not depend on their size.

from __future__ import annotations

import numpy as np

from gonio.fitting.likelihood import loss as _loss
from gonio.fitting.likelihood.problem import Problem
from gonio.fitting.optimise.result import loss_jacobian

__all__ = ["adequacy_test", "nominal_test", "chi2_refiner", "ADEQUACY_ALPHA", "TEST_BUDGET", "TEST_NOMINAL"]

#: The adequacy test's level: its false-alarm rate, the probability that a model that describes
#: the data within their stated budget is called inadequate (fitfile's ``goodness.adequacy``).
ADEQUACY_ALPHA = 1e-3
#: names of the adequacy tests (fitfile's ``goodness.adequacy.test``)
TEST_BUDGET = "budget_chi2"
TEST_NOMINAL = "chi2"


def _shared_columns(c, a: np.ndarray, use: np.ndarray) -> list:
    """The columns (N, C) each, in whitened units, of a component whose errors are shared
    across points: one per input for ``full``, per input and channel for ``channel``, per
    input and label for ``group``."""
    cols = []
    for ak in (a[None] if a.ndim == 2 else a):
        if c.correlation == "full":
            cols.append(ak)
        elif c.correlation == "channel":
            for ch in range(ak.shape[1]):
                col = np.zeros_like(ak)
                col[:, ch] = ak[:, ch]
                cols.append(col)
        else:
            labels = np.broadcast_to(c.groups, ak.shape)
            for lab in np.unique(labels[use]):
                cols.append(np.where(labels == lab, ak, 0.0))
    return cols


def adequacy_test(result, meas, comps, J, r, drdy, alpha: float = ADEQUACY_ALPHA, refine=None,
                  angles=None) -> dict:
    """Is the model adequate to the data within their budget? A chi-square test at level
    ``alpha`` of the fit's residuals against the budget's covariance.

    Statistic: T = min over (dx, e) of ||L^-1 (r - J dx - U e)||^2 + ||e||^2 in the fit's
    whitened units (r the chi2 residuals at the optimum, J their Jacobian, ``drdy`` the
    residuals' derivative by the data): B = L L^T the point-wise covariance (the components
    whose errors are independent between points, ``none`` and ``point``: type A with its
    channel correlation, the angles' repeatability times the slope), U one column per shared
    input (``full``, ``channel``, ``group``: the certificate, the colour matrix, the shared
    angle errors times the slope, ...), each a nuisance parameter with a standard normal prior.
    T is the generalised least-squares chi^2 of the residuals against V = B + U U^T
    (r^T V^-1 r after the parameters' own directions are removed), and, for data that scatter
    as the budget says, chi^2 distributed with M - rank(J) degrees of freedom (to first order
    in the model; exactly for a linear one) whatever the size of the shared inputs: so its
    p-value is exact and a test at ``alpha`` calls a right model inadequate with probability
    ``alpha``. A wrong model leaves residuals no nuisance direction can absorb, and T grows
    with their square. Without shared inputs T is the fit's chi^2.

    ``refine(x, jacobian)``: the chi2 residuals at parameters x (M,), with their Jacobian
    ``(J, r)`` when ``jacobian``; given, a model the first-order statistic rejects is tested
    again at the minimum of the non-linear objective (Gauss-Newton from the fit): a shared error
    of several sigma moves the weighted fit off (to a bound: chi^2/dof 30-100 on a right family
    with a 7-sigma shared line), where the first-order T was too large (19 of 500 draws at
    p < 1e-3 instead of 0.5).

    ``angles`` (the budget's, with ``shared`` (K, N, 4): the angle change per input): with
    ``refine``, the shared angle inputs (the ``angle_shared`` line) are then refitted through
    the model itself, f at the displaced directions (:func:`_displaced`), not through their
    first-order columns: an uncalibrated capture's 0.2 deg holder tilt moves a lobe's values by
    more than their slope says (uncalibrated standard-plan captures under the typical simulator:
    3 of 8 at p < 1e-3 to first order).

    Points whose cones (the declared apertures widened by 3 sigma of their angle law) reach a
    cutoff of f_r leave the test, listed in ``left_out`` (:func:`_cutoff_points`): there the
    budget's first-order line is 0 while the measured value may hold part of the lobe."""
    from scipy import stats

    use = meas.use
    N, C = use.shape
    D = np.zeros(use.shape)
    D[use] = drdy
    B = np.zeros((N, C, C))
    cols, angle_cols = [], []
    centre = np.zeros(use.shape)          # a line of known mean: its prior centred there
    for c in comps:
        a = np.where(use, np.asarray(c.value, float), 0.0) * D
        if getattr(c, "mean", 0.0):
            centre += c.mean * (a if a.ndim == 2 else a.sum(axis=0))
        if c.correlation == "none":
            B[:, np.arange(C), np.arange(C)] += (a * a if a.ndim == 2 else (a * a).sum(axis=0))
        elif c.correlation == "point":
            for ak in (a[None] if a.ndim == 2 else a):
                B += ak[:, :, None] * ak[:, None, :]
        else:
            new = _shared_columns(c, a, use)
            cols += new
            angle_cols += [c.name == "angle_shared"] * len(new)
    # the unused values carry nothing: unit variance, zero residual, zero Jacobian
    unused = ~use
    B[:, np.arange(C), np.arange(C)] += np.where(unused, 1.0, 0.0)
    for ch in range(C):
        B[unused[:, ch], ch, :] = 0.0
        B[unused[:, ch], :, ch] = 0.0
        B[unused[:, ch], ch, ch] = 1.0
    # values whose angle law reaches a cutoff of f_r leave the test: an effectively infinite
    # variance (their whitened rows vanish), their dof removed
    cut = _cutoff_points(result, meas, angles)
    left = cut[:, None] & use
    if left.any():
        full_r = np.zeros(use.shape)
        full_r[use] = np.asarray(r, float).reshape(-1)
        full_j = np.zeros(use.shape)
        full_j[use] = np.abs(np.asarray(J, float).reshape(len(full_r[use]), -1)).max(axis=1, initial=0.0)
        big = 1e16 * max(1.0, float(np.max(full_r[left] ** 2)), float(np.max(full_j[left] ** 2)),
                         float(np.max(np.abs(B))))
        B[cut] = np.eye(C)[None] * np.where(use[cut], big, 1.0)[:, :, None]
    L = np.linalg.cholesky(B)

    def whiten(x):                                    # L^-1 x per point, x (N, C, K)
        return np.linalg.solve(L, x)

    def flat(values):                                 # (M,) or (M, P) at the used values -> whitened (N C, ...)
        full = np.zeros(use.shape + np.shape(values)[1:])
        full[use] = values
        return whiten(full if full.ndim == 3 else full[..., None]).reshape(N * C, -1)

    nU = len(cols)
    Ut = whiten(np.stack(cols, axis=-1)).reshape(N * C, nU) if nU else np.zeros((N * C, 0))
    prior = np.hstack([np.zeros((nU, J.shape[1])), np.eye(nU)])

    def statistic(rt, Jt):
        """min over (dx, e) of ||rt + Jt dx - Ut e||^2 + ||e||^2, and the step dx."""
        scale = np.linalg.norm(Jt, axis=0)
        scale = np.where(scale > 0, scale, 1.0)
        A = np.vstack([np.hstack([Jt / scale, -Ut]), prior])
        b = np.concatenate([-rt, np.zeros(nU)])
        sol = np.linalg.lstsq(A, b, rcond=None)[0]
        return float(np.sum((b - A @ sol) ** 2)), sol[:J.shape[1]] / scale

    def profiled(rt):
        """min over e alone: the objective at fixed parameters."""
        A = np.vstack([-Ut, np.eye(nU)])
        b = np.concatenate([-rt, np.zeros(nU)])
        sol = np.linalg.lstsq(A, b, rcond=None)[0] if nU else np.zeros(0)
        return float(np.sum((b - A @ sol) ** 2))

    Jt = flat(J)
    sc = np.linalg.norm(Jt, axis=0)
    Js = Jt / np.where(sc > 0, sc, 1.0)
    rank = int(np.linalg.matrix_rank(Js, tol=1e-10 * max(1.0, float(np.abs(Js).max(initial=0.0))) * max(Js.shape)))
    dof = int(use.sum()) - int(left.sum()) - rank
    # e ~ N(mean, 1) for a line of known mean: e = mean + e', the residuals less its expected part
    offset = whiten(centre[..., None]).reshape(N * C)
    T, dx = statistic(flat(r)[:, 0] - offset, Jt)
    p = float(stats.chi2.sf(T, dof)) if dof > 0 else float("nan")
    refined = 0
    if p < alpha and refine is not None:
        # rejected to first order: the statistic is the minimum of the non-linear model, which
        # the weighted fit's linearisation misses where a large shared error pushed that fit far
        # off (or onto a bound); Gauss-Newton on (parameters, shared errors) from the fit,
        # steps halved until the objective falls, parameters kept in their box
        x = np.asarray(result.x, float).copy()
        lo, hi = result.space.lower, result.space.upper
        J_x, r_x = refine(x, True)
        best = profiled(flat(r_x)[:, 0] - offset)
        for _ in range(20):
            _, dx = statistic(flat(r_x)[:, 0] - offset, flat(J_x))
            for step in (1.0, 0.5, 0.25, 0.125, 0.0625):
                xn = np.clip(x + step * dx, lo, hi)
                cand = profiled(flat(refine(xn, False))[:, 0] - offset)
                if cand < best:
                    break
            else:
                break
            gain, best, x = best - cand, cand, xn
            refined += 1
            if gain <= 1e-9 * best:
                break
            J_x, r_x = refine(x, True)
        T = min(T, best)
        shifts = None if angles is None else angles.get("shared")
        if shifts is not None and np.size(shifts) and sum(angle_cols) == len(shifts) and not stats.chi2.sf(T, dof) >= alpha:
            keep = ~np.asarray(angle_cols, bool)
            T = min(T, _angles_refitted(result, meas, angles, whiten, flat, Ut[:, keep], offset, x))
        p = float(stats.chi2.sf(T, dof)) if dof > 0 else float("nan")
    return {"test": TEST_BUDGET if nU or len(comps) > 1 else TEST_NOMINAL,
            "statistic": T, "dof": dof, "p_value": p, "alpha": float(alpha),
            "adequate": bool(not (p < alpha)), "nuisance_inputs": nU, "refined_steps": refined,
            "left_out": np.flatnonzero(cut & use.any(axis=1)).tolist()}


#: how far (in the angle law's standard deviations) a point's directions are probed for a cutoff
CUTOFF_REACH_SIGMA = 3.0


def _cutoff_points(result, meas, angles) -> np.ndarray:
    """(N,) bool: points whose declared aperture cones, widened by CUTOFF_REACH_SIGMA times
    their angle law's standard deviation (the budget's shared and independent angle inputs in
    quadrature), hold both zero and non-zero f_r at the fitted parameters (issue 37: a lobe's
    cutoff, where f_r jumps, so its first-order line, value x slope, is 0 while the values
    drawn from the law reach the lobe: JCGM 101 5.11's warning on the law of propagation)."""
    from gonio.core.geometry import angles as _angles
    from gonio.fitting.likelihood.aperture import reaches_cutoff

    N = meas.use.shape[0]
    attrs = getattr(meas, "attrs", {}) or {}
    try:
        src = float(attrs.get("aperture_source_half_deg", 0.0) or 0.0)
        det = float(attrs.get("aperture_detector_half_deg", 0.0) or 0.0)
    except (TypeError, ValueError):
        src = det = float("nan")
    ti, _ = _angles(meas.wi)
    to, _ = _angles(meas.wo)
    var_i, var_o = np.zeros(N), np.zeros(N)
    for key in ("shared", "independent"):
        a = None if not angles else angles.get(key)
        if a is None or not np.size(a):
            continue
        a = np.asarray(a, float)
        if a.ndim == 4:                                    # per (point, wavelength): the largest
            a = np.abs(a).max(axis=2)
        if a.shape[1] != N:
            continue
        var_i += (a[..., 0] ** 2 + (np.sin(ti) * a[..., 1]) ** 2).sum(axis=0)
        var_o += (a[..., 2] ** 2 + (np.sin(to) * a[..., 3]) ** 2).sum(axis=0)
    if not (np.isfinite(src) and np.isfinite(det)) or src < 0 or det < 0 or src > 20 or det > 20:
        raise ValueError(f"aperture half-angles {src:g}, {det:g} deg are not in [0, 20]; fix the dataset's "
                         "aperture_source_half_deg / aperture_detector_half_deg")
    if not (src > 0 or det > 0 or var_i.any() or var_o.any()):
        return np.zeros(N, bool)
    k = CUTOFF_REACH_SIGMA
    return reaches_cutoff(result.model, meas.wi, meas.wo, result.params,
                          src + k * np.sqrt(var_i), det + k * np.sqrt(var_o))


def _displaced(result, meas, angles):
    """``model_e(x, e)``: the fitted model's f_r (N, C) at parameters x with the directions
    displaced by the K shared angle inputs e (gonio.fitting.uncertainty.angle_shifts.moved),
    times the sample's own irradiance change (1 + sum e_k irr_k) where the budget states one."""
    from gonio.fitting.uncertainty.angle_shifts import moved, shared_moves

    moves = shared_moves(meas.wi, meas.wo, angles)

    def model_e(x, e):
        wi, wo, g = moved(meas.wi, meas.wo, moves, e)
        return np.asarray(result.model.eval(wi, wo, result.space.to_params(x)), float) * g[:, None]
    return model_e, moves[0].shape[0]


def _angles_refitted(result, meas, angles, whiten, flat, U_other, offset, x0) -> float:
    """min over (x, e) of ||L^-1 r(x, e) - offset - U e_other||^2 + ||e_other||^2 + ||e||^2 with
    r the chi2 residuals of the model at the directions the shared angle inputs e displace
    (:func:`_displaced`), the other shared inputs profiled linearly: Gauss-Newton with
    finite-difference Jacobians, steps halved until the objective falls, x kept in its box."""
    model_e, K = _displaced(result, meas, angles)
    lo, hi = result.space.lower, result.space.upper
    nO, P = U_other.shape[1], len(x0)

    def rt(z):
        return flat(_loss.residuals("chi2", model_e(z[:P], z[P:]), meas))[:, 0] - offset

    def objective(z):
        v = rt(z)
        A = np.vstack([-U_other, np.eye(nO)])
        b = np.concatenate([-v, np.zeros(nO)])
        sol = np.linalg.lstsq(A, b, rcond=None)[0] if nO else np.zeros(0)
        return float(np.sum((b - A @ sol) ** 2) + np.sum(z[P:] ** 2))

    z = np.concatenate([np.asarray(x0, float), np.zeros(K)])
    best = objective(z)
    step_x = 1e-6 * np.maximum(np.abs(z[:P]), 1e-3 * (hi - lo))
    for _ in range(15):
        v = rt(z)
        cols = []
        for j in range(P + K):
            h = step_x[j] if j < P else 1e-4
            zp, zm = z.copy(), z.copy()
            zp[j] += h
            zm[j] -= h
            if j < P:
                zp[j], zm[j] = min(zp[j], hi[j]), max(zm[j], lo[j])
                h2 = zp[j] - zm[j]
            else:
                h2 = 2 * h
            cols.append((rt(zp) - rt(zm)) / h2 if h2 > 0 else np.zeros_like(v))
        Jz = np.stack(cols, axis=1)
        # rows: the residuals, the other inputs' priors, the angle inputs' priors (e + de)
        A = np.vstack([np.hstack([Jz, -U_other]),
                       np.hstack([np.zeros((nO, P + K)), np.eye(nO)]),
                       np.hstack([np.zeros((K, P)), np.eye(K), np.zeros((K, nO))])])
        b = np.concatenate([-v, np.zeros(nO), -z[P:]])
        dz = np.linalg.lstsq(A, b, rcond=None)[0][:P + K]
        for step in (1.0, 0.5, 0.25, 0.125):
            cand_z = z + step * dz
            cand_z[:P] = np.clip(cand_z[:P], lo, hi)
            cand = objective(cand_z)
            if cand < best:
                break
        else:
            break
        gain, best, z = best - cand, cand, cand_z
        if gain <= 1e-9 * best:
            break
    return best


def nominal_test(result, alpha: float = ADEQUACY_ALPHA) -> dict:
    """The adequacy test of a fit without a budget to test against (losses other than chi2):
    its chi^2 against the chi^2 distribution with its dof, at level ``alpha``."""
    from scipy import stats

    chi2, dof = float(result.chi2), int(result.dof)
    p = float(stats.chi2.sf(chi2, dof)) if np.isfinite(chi2) else 0.0
    return {"test": TEST_NOMINAL, "statistic": chi2, "dof": dof, "p_value": p, "alpha": float(alpha),
            "adequate": bool(not (p < alpha)), "nuisance_inputs": 0}


def chi2_refiner(result, meas):
    """``refine(x, jacobian)`` of :func:`adequacy_test`: the chi2 residuals at x (and their
    Jacobian), as the fit computes them."""
    problem = Problem(meas, result.model, result.space, "chi2")

    def refine(x, jacobian):
        if jacobian:
            return loss_jacobian(problem, x, "chi2")
        return _loss.residuals("chi2", problem.f_x(x), meas)

    return refine
