"""The instrument's shared angle errors estimated with the fit, as nuisance inputs (issue 38).

A bench dataset states, for +1 sigma of each shared input (stage zero offsets, holder tilt,
wedge: the same error at every point), the change of each point's angles
(``angle_shift_shared``, gonio/bench/measure/calpoint.py); the fitted model's slope turns each
into a line U_k of f_r (:func:`gonio.fitting.uncertainty.budget.angle_components`). With those
inputs b ~ N(0, I), the data are y = f(x) + U b + e. One variable-projection Gauss-Newton step
on the joint problem, linearised at the fit (Golub & Pereyra 2003, Inverse Problems 19 R1),
gives b = (I + U'PU)^-1 U'P r: r the whitened residual, P the projection off the model's own
directions (its Jacobian at the fit), so the inputs take only what the parameters cannot. The
data are corrected by U b and refitted; the budget then carries the inputs' posterior
C = (I + U'PU)^-1 in place of their prior (lines U L, C = L L'), which to first order gives
the joint estimate's covariance exactly (the noise and b's error are uncorrelated after P).
"""

from __future__ import annotations

import dataclasses

import numpy as np

__all__ = ["with_shared_angles", "profile_inputs", "posterior_budget", "applied"]


def _jacobian(result, meas) -> np.ndarray:
    """d f_r / d x (P, N, C) at the fit, by differences of its free parameters: central inside
    their bounds, one-sided at a bound (a step past it is not a parameter the model takes)."""
    x = np.asarray(result.x, float)
    lo, hi = result.space.lower, result.space.upper
    cols = []
    for j in range(len(x)):
        h = 1e-6 * max(1.0, abs(x[j]))
        xp, xm = x.copy(), x.copy()
        xp[j] = min(x[j] + h, hi[j])
        xm[j] = max(x[j] - h, lo[j])
        fp = result.model.eval(meas.wi, meas.wo, result.space.to_params(xp))
        fm = result.model.eval(meas.wi, meas.wo, result.space.to_params(xm))
        cols.append((np.asarray(fp, float) - np.asarray(fm, float)) / (xp[j] - xm[j]))
    return np.stack(cols) if cols else np.zeros((0,) + meas.brdf.shape)


def profile_inputs(U, J, resid, whiten, use, b0=None) -> tuple[np.ndarray, np.ndarray]:
    """(b, C): the shared inputs (sigma units) and their posterior covariance from the lines
    ``U`` (K, N, C), the model's Jacobian ``J`` (P, N, C), the residual (N, C) of the model at
    ``b0`` (default 0), the whitening sqrt(weight) / sigma (N, C) and the values used (N, C):
    one Gauss-Newton step b = b0 + C (U'P r - b0) of |r - U db - J dx|^2 + |b0 + db|^2."""
    Uw = (U * whiten[None])[:, use]                   # (K, M)
    Jw = (J * whiten[None])[:, use].T                 # (M, P)
    r = (resid * whiten)[use]
    if Jw.shape[1]:
        Q, _ = np.linalg.qr(Jw)
        Uw = Uw - (Uw @ Q) @ Q.T
        r = r - Q @ (Q.T @ r)
    C = np.linalg.inv(np.eye(len(Uw)) + Uw @ Uw.T)
    C = 0.5 * (C + C.T)
    b0 = np.zeros(len(Uw)) if b0 is None else np.asarray(b0, float)
    return b0 + C @ (Uw @ r - b0), C


def _displaced(result, meas, angles, b) -> np.ndarray:
    """f_r of the fitted model where the inputs ``b`` (sigma units) put each point: its
    directions moved along the shared shifts (:func:`gonio.core.geometry.angle_tangents`,
    exact in the direction, not linearised in f_r), times the wedge's irradiance change."""
    from gonio.core.geometry import angle_tangents, unit_vectors
    from gonio.fitting.uncertainty.angle_shifts import per_point

    one = per_point(angles)
    t_i, t_o = angle_tangents(meas.wi, meas.wo, one["shared"])
    f = np.asarray(result.model.eval(unit_vectors(meas.wi + np.einsum("k,knj->nj", b, t_i)),
                                     unit_vectors(meas.wo + np.einsum("k,knj->nj", b, t_o)), result.params), float)
    irr = one.get("shared_irradiance")
    return f if irr is None else f * (1.0 + np.einsum("k,kn->n", b, np.asarray(irr, float)))[:, None]


def with_shared_angles(meas, budget, result, refit, rounds: int = 3):
    """``result`` refitted with the dataset's shared angle inputs estimated (module docstring),
    where the budget states them; otherwise everything unchanged. ``refit(meas)`` -> FitResult.

    Each round: the residual of the data against the fitted model at the inputs so far, one
    Gauss-Newton step for the inputs, the data corrected by the model's change between the
    displaced and the nominal directions, a refit; until the inputs move by less than 0.05 sigma.

    Returns (result, meas, budget): the corrected data, the budget with the inputs' posterior,
    and the result's ``shared_angles`` (the fit file's record: each input's estimate and
    posterior 1-sigma in units of its stated 1-sigma, the largest correction relative to the value
    or, where that is within its 1-sigma, to the 1-sigma)."""
    from gonio.fitting.uncertainty.budget import angle_components

    angles = getattr(budget, "angles", None) or {}
    shared = angles.get("shared")
    if shared is None or not np.size(shared):
        return result, meas, budget
    whiten = np.sqrt(meas.relative_weight())[:, None] / np.where(meas.brdf_std > 0, meas.brdf_std, np.inf)
    use = meas.use & np.isfinite(meas.brdf) & (meas.brdf_std > 0)
    y0 = meas.brdf
    first = result                                     # its instrument-response record stays with the refits
    b = np.zeros(len(shared))
    m = meas
    for _ in range(rounds):
        lines = next(c for c in angle_components(result, meas, angles) if c.name == "angle_shared").value
        b_new, C = profile_inputs(lines, _jacobian(result, meas), y0 - _displaced(result, meas, angles, b),
                                  whiten, use, b)
        if not np.all(np.isfinite(b_new)) or not np.all(np.isfinite(C)):
            raise ValueError("the shared angle inputs could not be estimated (non-finite lines or slope at the fit)")
        step, b = float(np.max(np.abs(b_new - b))), b_new
        f0 = np.asarray(result.model.eval(meas.wi, meas.wo, result.params), float)
        shift = _displaced(result, meas, angles, b) - f0
        m = dataclasses.replace(meas, brdf=y0 - shift)
        result = refit(m)
        if step < 0.05:
            break
    L = np.linalg.cholesky(C + 1e-12 * np.eye(len(C)))
    info = {"inputs": int(len(b)), "estimate_sigma": b.tolist(), "posterior_sigma": np.sqrt(np.diag(C)).tolist(),
            "max_correction": float(np.max(np.abs(shift[use]) / np.maximum(np.abs(y0[use]), meas.brdf_std[use]))),
            "method": "Gauss-Newton on the inputs (prior N(0, 1) each) with the fit's own directions projected out; "
                      "the data corrected by the model at the displaced directions"}
    result = dataclasses.replace(result, shared_angles=info, shared_angles_fix=(shift, L), response=first.response,
                                 response_factor=first.response_factor)
    return result, m, posterior_budget(budget, L)


def posterior_budget(budget, L):
    """``budget`` with its shared angle inputs' lines turned to their posterior (``L``, the
    Cholesky factor of C)."""
    post = dict(budget.angles)
    post["shared"] = np.einsum("kj,k...->j...", L, np.asarray(post["shared"], float))
    if post.get("shared_irradiance") is not None:
        post["shared_irradiance"] = np.einsum("kj,k...->j...", L, np.asarray(post["shared_irradiance"], float))
    return dataclasses.replace(budget, angles=post)


def applied(meas, budget, result):
    """The dataset as opened, with ``result``'s shared-angle correction applied again (none: as
    given): for a fit file built from the dataset rather than from the fit's own data."""
    fix = getattr(result, "shared_angles_fix", None)
    if fix is None:
        return meas, budget
    shift, L = fix
    return dataclasses.replace(meas, brdf=meas.brdf - shift), posterior_budget(budget, L)
