"""The ``alc`` batch criterion of the adaptive plan: points that most reduce the integrated
predictive variance of f_r cos(theta_i), allowing for the model's discrepancy.

f_r (luminance) is a Gaussian process: the fitted model linearised in its parameters (prior
1-sigma: each parameter's own size) plus a discrepancy whose 1-sigma is a fraction tau of f_r,
correlated over ``discrepancy_length`` in (wi, wo) (Kennedy & O'Hagan 2001), tau estimated from
the fit's residuals beyond the noise. A batch is chosen greedily by active learning Cohn (Cohn
1996; Gramacy 2020, sec. 6.2): each pick maximises the drop of the posterior variance of
f_r cos(theta_i) summed over an equal-solid-angle reference grid, which is what the Ngan error
integrates (I-optimality), per second of overhead and the run's move (``travel``). Where the
model fits (tau small) the picks pin its parameters where f_r cos is large; where it cannot,
the discrepancy keeps a floor of uncertainty away from the measured points, so the picks spread
over the body of the BRDF. Public: `alc_batch`, `reference_grid`, `discrepancy_rel`.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg

from gonio.core.channels import SRGB_Y


__all__ = ["alc_batch", "reference_grid", "discrepancy_rel", "TAU_MIN"]

#: the least relative discrepancy assumed, however well the model fits the points so far
TAU_MIN = 0.02
#: luminance weights of linear sRGB (IEC 61966-2-1)
LUM = np.array(SRGB_Y)


def reference_grid(theta_max_deg: float = 80.0, n_theta_i: int = 6, n_theta_o: int = 8, n_phi: int = 12):
    """(wi, wo) at the centres of equal-solid-angle cells (uniform in cos theta and phi; phi_i = 0,
    the domain of an isotropic BRDF), every pair of equal weight."""
    from gonio.core.geometry import directions

    cmax = np.cos(np.radians(theta_max_deg))
    ci = 1.0 - (1.0 - cmax) * (np.arange(n_theta_i) + 0.5) / n_theta_i
    co = 1.0 - (1.0 - cmax) * (np.arange(n_theta_o) + 0.5) / n_theta_o
    po = -np.pi + 2.0 * np.pi * (np.arange(n_phi) + 0.5) / n_phi
    ti, to, phi = np.meshgrid(np.arccos(ci), np.arccos(co), po, indexing="ij")
    return directions(ti.ravel(), np.zeros(ti.size)), directions(to.ravel(), phi.ravel())


def _features(wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
    """(N, 6): wi turned to phi = 0 and wo by the same rotation, its y mirrored (isotropy)."""
    phi_i = np.arctan2(wi[:, 1], wi[:, 0])
    c, s = np.cos(phi_i), np.sin(phi_i)
    xi = np.stack([np.hypot(wi[:, 0], wi[:, 1]), np.zeros(len(wi)), wi[:, 2]], -1)
    xo = np.stack([c * wo[:, 0] + s * wo[:, 1], np.abs(-s * wo[:, 0] + c * wo[:, 1]), wo[:, 2]], -1)
    return np.concatenate([xi, xo], -1)


def discrepancy_rel(f_meas: np.ndarray, s_meas: np.ndarray, f_fit: np.ndarray) -> float:
    """tau: the relative RMS of the residuals beyond their noise, (|f - fit|^2 - s^2) / fit^2
    averaged (each term at most 1), at least :data:`TAU_MIN`."""
    ok = np.isfinite(f_meas) & np.isfinite(s_meas) & np.isfinite(f_fit) & (np.abs(f_fit) > 0)
    if not ok.any():
        return TAU_MIN
    r = ((f_meas[ok] - f_fit[ok]) ** 2 - s_meas[ok] ** 2) / f_fit[ok] ** 2
    return max(TAU_MIN, float(np.sqrt(max(0.0, np.mean(np.clip(r, -1.0, 1.0))))))


def _lum_model(plan, x, wi, wo):
    """Luminance f_r (N,) and its Jacobian (N, P) in parameters scaled to their own size."""
    space, model = plan.space, plan.model
    lo, hi = space.lower, space.upper
    scale = np.maximum(np.abs(x), 1e-3 * (hi - lo))
    f0 = np.asarray(model.eval(wi, wo, space.to_params(x)), np.float64) @ LUM
    J = np.empty((len(f0), space.size))
    for j in range(space.size):
        h = 1e-4 * scale[j]
        xp, xm = x.copy(), x.copy()
        xp[j], xm[j] = min(x[j] + h, hi[j]), max(x[j] - h, lo[j])
        fp = np.asarray(model.eval(wi, wo, space.to_params(xp)), np.float64) @ LUM
        fm = np.asarray(model.eval(wi, wo, space.to_params(xm)), np.float64) @ LUM
        J[:, j] = (fp - fm) / (xp[j] - xm[j]) * scale[j]
    return np.nan_to_num(f0), np.nan_to_num(J)


def alc_batch(plan, x, basis, queue, free, n_new, results, sigma_rel, sigma_floor) -> list[int]:
    """The next ``n_new`` of ``free`` for the adaptive plan ``plan`` (an `AdaptivePlan`) given the
    fit ``x`` of ``basis`` (module notes); the pending queued points count as measured with the
    predicted noise."""
    wr, wor = reference_grid()
    f_c, J_c = _lum_model(plan, x, plan.wi, plan.wo)
    f_r, J_r = _lum_model(plan, x, wr, wor)
    basis = [int(i) for i in basis]
    fm = np.array([np.asarray(results[i][0], float) @ LUM for i in basis])
    sm = np.array([np.sqrt(np.asarray(results[i][1], float) ** 2 @ LUM ** 2) for i in basis])
    angle_var = plan._angle_var(x, weights=LUM)                 # (N,) or 0: the stage angles' errors
    sm = np.sqrt(sm ** 2 + (angle_var[basis] if np.ndim(angle_var) else 0.0))
    tau = discrepancy_rel(fm, sm, f_c[basis])
    ell2 = plan.discrepancy_length ** 2
    x_c, x_r = _features(plan.wi, plan.wo), _features(wr, wor)

    def kern(Ja, fa, xa, Jb, fb, xb):
        d2 = np.sum(xa ** 2, 1)[:, None] + np.sum(xb ** 2, 1)[None] - 2.0 * xa @ xb.T
        return Ja @ Jb.T + tau ** 2 * np.outer(fa, fb) * np.exp(-0.5 * np.maximum(d2, 0.0) / ell2)

    noise_c = (sigma_rel * f_c) ** 2 + sigma_floor ** 2 + angle_var   # predicted variance of a new point
    pending = [int(i) for i in queue if i not in set(basis)]
    S = basis + pending
    noise_s = np.concatenate([np.where(np.isfinite(sm) & (sm > 0), sm, np.sqrt(noise_c[basis])) ** 2,
                              noise_c[pending]])
    known = np.isfinite(noise_s)                                # infinite noise (no slope): it tells nothing
    S, noise_s = [i for i, k in zip(S, known) if k], noise_s[known]
    K_rc = kern(J_r, f_r, x_r, J_c, f_c, x_c)
    K_cc_diag = np.sum(J_c ** 2, 1) + tau ** 2 * f_c ** 2
    if S:
        K_ss = kern(J_c[S], f_c[S], x_c[S], J_c[S], f_c[S], x_c[S]) + np.diag(noise_s)
        K_ss += 1e-10 * max(float(np.trace(K_ss)) / len(S), 1e-30) * np.eye(len(S))
        cho = scipy.linalg.cho_factor(K_ss, lower=True)
        K_rs, K_cs = K_rc[:, S], kern(J_c, f_c, x_c, J_c[S], f_c[S], x_c[S])
        solved = scipy.linalg.cho_solve(cho, K_cs.T)              # (S, N)
        post_rc = K_rc - K_rs @ solved
        post_cc = K_cc_diag - np.sum(K_cs * solved.T, 1)
    else:
        K_cs, solved, post_rc, post_cc = None, None, K_rc, K_cc_diag
    w = np.clip(wr[:, 2], 0.0, 1.0) ** 2                        # f_r cos(theta_i): its variance
    free = np.asarray(free, int)
    left = np.ones(len(free), bool)
    last = int(queue[-1]) if len(queue) else None
    chosen: list[int] = []
    rows: list[tuple[np.ndarray, float]] = []                   # per pick: its posterior row, variance
    for _ in range(n_new):
        if not left.any():
            break
        gain = (w @ post_rc[:, free] ** 2) / (post_cc[free] + noise_c[free])         # 0 where noise_c is inf
        gain = np.where(np.isfinite(gain) & (gain > 0), gain, 0.0)
        score = np.where(left, gain / plan._cost(last, free), -np.inf)
        k = int(np.argmax(score))
        c = int(free[k])
        chosen.append(c)
        left[k] = False
        last = c
        # c's posterior covariance with every candidate (given the basis and this batch's
        # picks before it), then the rank-one update of c measured with its noise
        k_c = kern(J_c[[c]], f_c[[c]], x_c[[c]], J_c, f_c, x_c)[0]
        if solved is not None:
            k_c = k_c - K_cs[c] @ solved
        for u, v in rows:
            k_c = k_c - u[c] * u / v
        var_c = post_cc[c] + noise_c[c]
        rows.append((k_c, var_c))
        post_rc = post_rc - np.outer(post_rc[:, c], k_c) / var_c
        post_cc = post_cc - k_c ** 2 / var_c
    return chosen
