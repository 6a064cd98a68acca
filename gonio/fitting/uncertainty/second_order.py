"""The shared angle errors' second-order effect on fitted parameters (GUM 5.1.2 note), the
budget's ``angle_shared_second_order`` line: :func:`second_order`, called by
:func:`gonio.fitting.uncertainty.budget.propagate`."""

from __future__ import annotations

import numpy as np

from gonio.core.geometry import angle_tangents, unit_vectors

__all__ = ["second_order"]


def second_order(result, meas, shifts, G: np.ndarray, use: np.ndarray,
                 elasticity: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The shared angle errors' second-order effect on the parameters (GUM 5.1.2 note: the
    higher-order terms of a Taylor series where the model is markedly non-linear).

    With e ~ N(0, I) the K shared inputs (``shifts`` (K, N, 4): each one's angle change for +1
    sigma), the data change by f(angles(e)) - f(angles) and the fitted parameters by G times
    that: a e + (1/2) e^T H e with H_p (K x K) = G_p d^2 f / de_k de_l (central differences of
    the fitted model at steps of 1 sigma, the directions displaced along each input's tangent:
    :func:`gonio.core.geometry.angle_tangents`). The first-order part a is the ``angle_shared``
    line; the quadratic part has mean b_p = tr(H_p) / 2 and covariance tr(H_p H_q) / 2. Its mean does not vanish: an
    error of the sample normal (the wedge the alignment cannot see, 0.05 deg) moves a narrow
    lobe off the specular direction the fit assumes, and the fit broadens the lobe to follow it
    whichever way the normal tilted (GGX alpha 0.05: b = +0.2 of alpha's u_c on average, up to
    +0.6 in a session, where the linear term sees nothing).

    ``elasticity`` (kappa = d ln sigma / d ln f_r, :attr:`Budget.sigma_elasticity`): a chi^2 fit
    whose sigma is measured from each value's own signal reweighs its values when a shared
    error moves them: with w = 1/sigma^2 and dw = -2 kappa w d / f the normal equations
    J^T W (f(x) - y) = 0 gain the second-order term sum dw J (J dx1 - d), so the estimate moves
    by -2 kappa G [(d / f) eps] more, eps = d - J dx1 the part of the shift d the parameters
    cannot absorb (H_p gains -2 kappa G_p [(a_k eps_l + a_l eps_k) / f], a_k the data's
    first-order change for input k). Values pushed down weigh more, so a narrow lobe that a
    tilted normal moves off the fit's specular direction loses height whichever way it tilted:
    glossy GGX alpha 0.05 under the typical simulator, int_ior's mean error was -0.26 u_c
    (+0.03 at zero wedge; 236 sessions regressed on the drawn wedge), the data-curvature term
    alone predicting +0.04 (budget_coverage.py). Returns (b (P,), the quadratic part's second
    moment about zero b b^T + tr(H_p H_q) / 2 (P, P), H (P, K, K))."""
    shifts = np.asarray(shifts, float)
    K, P = shifts.shape[0], G.shape[0]
    if K == 0:
        return np.zeros(P), np.zeros((P, P)), np.zeros((P, 0, 0))
    t_i, t_o = angle_tangents(meas.wi, meas.wo, shifts)
    model, params = result.model, result.params

    def f(ci, co):
        return model.eval(unit_vectors(meas.wi + np.einsum("k,knj->nj", ci, t_i)),
                          unit_vectors(meas.wo + np.einsum("k,knj->nj", co, t_o)), params)

    def proj(v):
        return np.einsum("pnc,nc->p", np.where(use, G, 0.0), np.where(use, v, 0.0))

    zero = np.zeros(K)
    f0 = f(zero, zero)
    H = np.zeros((P, K, K))
    eye = np.eye(K)
    for k in range(K):
        H[:, k, k] = proj(f(eye[k], eye[k]) + f(-eye[k], -eye[k]) - 2.0 * f0)
        for m in range(k):
            pp, mm = eye[k] + eye[m], eye[k] - eye[m]
            H[:, k, m] = H[:, m, k] = proj(f(pp, pp) - f(mm, mm) - f(-mm, -mm) + f(-pp, -pp)) / 4.0
    if elasticity > 0.0:
        # the data's first-order change per input (a_k), the parameters' (G a_k) and the part of
        # a_k the model cannot follow (eps_k = a_k - J G a_k, J = df/dx by central differences)
        a = np.stack([0.5 * (f(eye[k], eye[k]) - f(-eye[k], -eye[k])) for k in range(K)])      # (K, N, C)
        dx1 = np.stack([proj(a[k]) for k in range(K)])                                           # (K, P)
        x0 = np.asarray(result.x, float)
        step = 1e-4 * np.maximum(np.abs(x0), 1e-3 * (result.space.upper - result.space.lower))
        jf = []
        for p in range(P):
            # central differences, one-sided at a bound (a parameter fitted at its bound)
            xp, xm = x0.copy(), x0.copy()
            xp[p] = min(x0[p] + step[p], result.space.upper[p])
            xm[p] = max(x0[p] - step[p], result.space.lower[p])
            jf.append((model.eval(meas.wi, meas.wo, result.space.to_params(xp))
                       - model.eval(meas.wi, meas.wo, result.space.to_params(xm))) / (xp[p] - xm[p]))
        eps = a - np.einsum("kp,pnc->knc", dx1, np.stack(jf))
        inv_f = 1.0 / np.maximum(np.abs(f0), 1e-12 * max(float(np.max(np.abs(f0[use]))), 1e-300))
        for k in range(K):
            for m in range(k + 1):
                Hw = -2.0 * elasticity * proj((a[k] * eps[m] + a[m] * eps[k]) * inv_f)
                H[:, k, m] += Hw
                if m != k:
                    H[:, m, k] += Hw
    b = 0.5 * np.trace(H, axis1=1, axis2=2)
    cov = np.outer(b, b) + 0.5 * np.einsum("pkl,qlk->pq", H, H)
    return b, cov, H
