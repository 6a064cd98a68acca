"""The instrument's shared angle errors estimated with the fit, as nuisance inputs (issue 38).

A bench dataset states, for +1 sigma of each shared input (stage zero offsets, holder tilt,
wedge: the same error at every point), the change of each point's angles
(``angle_shift_shared``, gonio/bench/measure/calpoint.py); the fitted model's slope turns each
into a line U_k of f_r (:func:`gonio.fitting.uncertainty.budget.angle_components`). With those
inputs b ~ N(0, I), the data are y = f(x) + U b + e. One variable-projection Gauss-Newton step
on the joint problem, linearised at the fit (Golub & Pereyra 2003, Inverse Problems 19 R1),
gives b = (I + U'PU)^-1 U'P r: r the whitened residual, P the projection off the model's own
directions (its Jacobian at the fit), so the inputs take only what the parameters cannot; the
budget's other shared lines are marginalised the same way. The data are then refitted at the
directions (and the wedge's irradiance) the inputs give them, and the next step's slopes are taken
there; the budget carries the inputs' posterior C (lines U L, C = L L') at those directions in
place of their prior. An estimate the stated errors make implausible (a model
whose misfit passes for angle errors) is not applied.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

__all__ = ["with_shared_angles", "profile_inputs", "posterior_budget", "applied", "as_estimated",
           "plausible_bound"]


def plausible_bound(k: int) -> float:
    """The largest |b|^2 of K inputs stated N(0, I) that the estimate may reach: chi2's 99.9 %
    quantile (a correct model and budget exceed it one time in a thousand)."""
    from scipy import stats

    return float(stats.chi2.ppf(0.999, k))


def _jacobian(result, meas) -> np.ndarray:
    """d f_r / d x (P, N, C) at the fit: the fit's own chi2 Jacobian
    (:func:`gonio.fitting.optimise.result.jacobian_chi2`: exact where the model gives derivatives,
    else differences, one-sided at a bound) without its weights; 0 at values not used."""
    from gonio.fitting.likelihood.loss import value_weight
    from gonio.fitting.likelihood.problem import Problem
    from gonio.fitting.optimise.result import jacobian_chi2

    try:
        Jw, _ = jacobian_chi2(Problem(meas, result.model, result.space, "chi2"), np.asarray(result.x, float))
    except FloatingPointError:
        raise ValueError("the shared angle inputs could not be estimated (a non-finite Jacobian at the fit)") from None
    w = np.broadcast_to(value_weight(meas) / meas.brdf_std, meas.brdf.shape)
    J = np.zeros((Jw.shape[1],) + meas.brdf.shape)
    J[:, meas.use] = Jw.T / w[meas.use]
    return J


def profile_inputs(U, J, resid, whiten, use, b0=None, V=None) -> tuple[np.ndarray, np.ndarray, float]:
    """(b, C, s): the shared inputs (sigma units), their posterior covariance and the residual's
    scale s from the lines
    ``U`` (K, N, C), the model's Jacobian ``J`` (P, N, C), the residual (N, C) of the model at
    ``b0`` (default 0), the whitening (N, C) and the values used (N, C): one Gauss-Newton step
    of |r - U db - J dx - V c|^2 + |b0 + db|^2 + |c|^2, the budget's other shared lines ``V``
    (L, N, C; prior N(0, 1) each) marginalised with the parameters. Where the whitened residual
    left after the step is larger than noise (s, its mean square per degree of freedom, > 1: a
    model that cannot follow the data, a term the budget lacks) the data weigh 1 / s, once:
    the inputs then take no more than the residual the model leaves supports, and C says so."""
    K = len(U)
    W = np.concatenate([U, V], axis=0) if V is not None and len(V) else np.asarray(U, float)
    Ww = (W * whiten[None])[:, use]                   # (K + L, M)
    Jw = (J * whiten[None])[:, use].T                 # (M, P)
    r = (resid * whiten)[use]
    if Jw.shape[1]:
        Q, _ = np.linalg.qr(Jw)
        Ww = Ww - (Ww @ Q) @ Q.T
        r = r - Q @ (Q.T @ r)
    b0 = np.zeros(K) if b0 is None else np.asarray(b0, float)
    prior = np.concatenate([b0, np.zeros(len(W) - K)])
    scale = 1.0
    for _ in range(2):                  # again with the weights scaled where the residual is not noise
        A = np.linalg.inv(np.eye(len(W)) + Ww @ Ww.T / scale)
        step = A @ (Ww @ r / scale - prior)
        dof = max(len(r) - Jw.shape[1] - len(W) + float(np.trace(A)), 1.0)     # the prior keeps tr(A) of them
        left = float(np.sum((r - Ww.T @ step) ** 2)) / dof
        if left <= 1.0 or scale > 1.0:
            break
        scale = left
    C = 0.5 * (A[:K, :K] + A[:K, :K].T)
    return b0 + step[:K], C, scale


def _other_terms(budget, result, meas):
    """The budget's terms besides the shared angle inputs and the statistical 1-sigma: (V (L, N,
    C): each shared input's line (``full``; ``channel``: one per channel), their means (L,),
    the variance (N, C) of the terms that differ from value to value (``none``, ``point``,
    ``group``; their correlations left out of the weights))."""
    from gonio.fitting.uncertainty.budget import angle_components

    comps = list(budget.components) + angle_components(result, meas, budget.angles)
    V, means, var = [], [], np.zeros(meas.brdf.shape)
    for c in comps:
        if c.name == "angle_shared" or c.statistical or (c.gum_type == "A" and c.correlation in ("none", "point")):
            continue                # brdf_std: the statistical 1-sigma, whole or split into type A lines
        val = np.nan_to_num(np.asarray(c.value, float))
        vals = val if val.ndim == 3 else val[None]
        if c.correlation == "full":
            V += list(vals)
            means += [float(c.mean)] * len(vals)
        elif c.correlation == "channel":
            for ch in range(val.shape[-1]):
                v = np.zeros(meas.brdf.shape)
                v[:, ch] = val[..., ch].reshape(-1, meas.n_points).sum(0) if val.ndim == 3 else val[:, ch]
                V.append(v)
                means.append(float(c.mean))
        else:
            var += (vals ** 2).sum(0)
    return (np.stack(V) if V else np.zeros((0,) + meas.brdf.shape)), np.asarray(means, float), var


def _moved(meas, moves, b):
    """``meas`` where the inputs ``b`` (sigma units) put each point
    (:func:`gonio.fitting.uncertainty.angle_shifts.moved`), its values and 1-sigma divided by the
    wedge's irradiance change: the data as measured, at the geometry they were measured at.
    Returns (meas, that change (N,))."""
    from gonio.fitting.uncertainty.angle_shifts import moved

    wi, wo, g = moved(meas.wi, meas.wo, moves, b)
    return _at(meas, wi, wo, g), g


def _at(meas, wi, wo, g):
    """``meas`` at the directions ``wi``, ``wo``, its values and 1-sigma over the irradiance
    change ``g`` (N,)."""
    return dataclasses.replace(meas, wi=wi, wo=wo, brdf=meas.brdf / g[:, None], brdf_std=meas.brdf_std / g[:, None])


def _budget_at(budget, g):
    """``budget`` with its components (values in f_r's units, (N, C) or (K, N, C)) over the
    irradiance change ``g`` (N,), as :func:`_at` divides the values they describe."""
    return dataclasses.replace(budget, components=[
        dataclasses.replace(k, value=np.asarray(k.value, float) / g.reshape((-1, 1))) for k in budget.components])


#: the most a round may move the inputs (sigma units, Euclidean): a trust region for the
#: Gauss-Newton step, linearised at a fit that may be far off (an uncorrected 0.5 deg tilt on
#: a 3 deg lobe); an undamped first step overshot to 10-14 sigma where the truth lay at 3
ROUND_REACH = 1.0

#: rounds before an estimate that has not settled (steps of 0.05 sigma or more) is not applied
ROUNDS = 20


def with_shared_angles(meas, budget, result, refit, rounds: int = ROUNDS, raw=None):
    """``result`` refitted with the dataset's shared angle inputs estimated (module docstring),
    where the budget states them; otherwise everything unchanged. ``refit(meas, near)`` ->
    FitResult: ``meas`` fitted from ``near`` (the fit so far) by a local search: the geometry
    moves by a fraction of a degree and the optimum as little, where a fresh global search can
    land in another basin (on 12 points, a lobe narrowed to a spike through one moved value).

    Each round: the data at the geometry the inputs so far put them (:func:`_moved`), corrected
    for the instrument's angular response there where ``result`` modelled one and ``raw`` gives
    the data and budget before that correction (the aperture ratio at the moved directions and
    the fit so far, as the corrected data had it at the nominal ones), the model's slope there
    (the lines and the fit's Jacobian: an input whose slope vanishes at the nominal directions,
    as a tilt across a lobe measured in its plane, has one once moved), one Gauss-Newton step for
    the inputs, at most :data:`ROUND_REACH` sigma long, shortened while the steps turn back on
    each other (halved each time, to a quarter: the inputs' step and the refit can overshoot
    each other in turn) and lengthened again (doubled, to the whole) while they go on the same
    way, then a refit at the moved geometry; until the full step is under 0.05 sigma. An
    estimate that has not settled within ``rounds``, or that settles where the stated errors
    make it implausible, is not applied.

    Returns (result, meas, budget): the data at the estimated geometry, the budget with the
    inputs' posterior, and the result's ``shared_angles`` (the fit file's record: each input's
    estimate and posterior 1-sigma in units of its stated 1-sigma, the rounds taken, the largest
    direction change, the largest change of the model's value it makes relative to the value
    or, where that is within its 1-sigma, to the 1-sigma)."""
    from gonio.fitting.likelihood.aperture import aperture_ratio, corrected
    from gonio.fitting.uncertainty.angle_shifts import moved, shared_moves
    from gonio.fitting.uncertainty.budget import angle_components

    angles = getattr(budget, "angles", None) or {}
    shared = angles.get("shared")
    if shared is None or not np.size(shared):
        return result, meas, budget
    V, v_mean, v_var = _other_terms(budget, result, meas)
    sd = np.sqrt(meas.brdf_std ** 2 + v_var)
    whiten = np.sqrt(meas.relative_weight())[:, None] / np.where(sd > 0, sd, np.inf)
    use = meas.use & np.isfinite(meas.brdf) & (meas.brdf_std > 0)
    known = np.einsum("l,lnc->nc", v_mean, V)            # the other inputs' known means, in the data
    first = result                                     # its instrument-response record stays with the refits
    c = c_before = getattr(result, "response_factor", None)
    if c is None or raw is None:
        raw = None
    else:
        raw, raw_budget = raw
        apertures = (float(result.response["source_half_deg"]), float(result.response["detector_half_deg"]))
    b = np.zeros(len(shared))
    m, g = meas, np.ones(meas.n_points)
    moves = shared_moves(meas.wi, meas.wo, angles)
    as_without = "; the fit and its budget are as without the estimate"

    def refused(reason, **extra):
        return dataclasses.replace(first, shared_angles={"inputs": int(len(b)), "applied": False, **extra,
                                                         "reason": reason + as_without}), meas, budget

    step, taken, last, relax = float("inf"), 0, None, 1.0
    while taken < rounds and step >= 0.05:
        taken += 1
        lines = next(k for k in angle_components(result, m, angles) if k.name == "angle_shared").value
        resid = m.brdf - known / g[:, None] - np.asarray(result.model.eval(m.wi, m.wo, result.params), float)
        try:
            b_new, C, scale = profile_inputs(lines, _jacobian(result, m), resid, whiten, use, b, V)
        except (ValueError, np.linalg.LinAlgError) as exc:
            return refused(str(exc))
        if not (np.all(np.isfinite(b_new)) and np.all(np.isfinite(C))):
            return refused("the shared angle inputs could not be estimated (non-finite lines or slope at the fit)")
        move = b_new - b
        step = float(np.max(np.abs(move)))
        if step >= 0.05:
            if last is not None:    # a step that turns back: the alternation overshoots, so take less of each
                relax = max(0.5 * relax, 0.25) if float(move @ last) < 0.0 else min(2.0 * relax, 1.0)
            move = relax * move
            length = float(np.linalg.norm(move))
            if length > ROUND_REACH:
                move *= ROUND_REACH / length
        last, b = move, b + move
        if float(b @ b) > 4.0 * plausible_bound(len(b)):     # walked far past the bound: no need to go on
            break
        wi, wo, g = moved(meas.wi, meas.wo, moves, b)
        if raw is not None:                               # the response corrected where the data now lie
            c_before, c = c, aperture_ratio(result.model, wi, wo, result.params, *apertures)
        m = _at(meas if raw is None else corrected(raw, None, c)[0], wi, wo, g)
        try:
            result = refit(m, result)
        except ValueError as exc:       # the fit at the moved geometry refused: the one before it stands
            return refused(f"the refit at the estimated geometry failed ({' '.join(str(exc).split())[:200]})",
                           estimate_sigma=b.tolist(), residual_scale=scale)
    if float(b @ b) > plausible_bound(len(b)):
        return refused(f"the inputs' estimate lies {math.sqrt(float(b @ b)):.1f} sigma from their stated errors "
                       f"(beyond the 99.9 % chi2 bound {math.sqrt(plausible_bound(len(b))):.1f}): the model does not "
                       "follow the data closely enough to tell an angle error from its own misfit",
                       estimate_sigma=b.tolist(), residual_scale=scale)
    if step >= 0.05:
        return refused(f"the inputs' estimate had not settled after {taken} rounds "
                       f"(its last full step {step:.2f} sigma)", estimate_sigma=b.tolist(), residual_scale=scale)
    L = np.linalg.cholesky(C + 1e-12 * np.eye(len(C)))
    f0 = np.asarray(result.model.eval(meas.wi, meas.wo, result.params), float)
    change = np.asarray(result.model.eval(m.wi, m.wo, result.params), float) * g[:, None] - f0
    turn = np.degrees(np.arccos(np.clip(np.minimum(np.sum(m.wi * meas.wi, 1), np.sum(m.wo * meas.wo, 1)), -1.0, 1.0)))
    info = {"inputs": int(len(b)), "applied": True, "estimate_sigma": b.tolist(), "posterior_sigma": np.sqrt(np.diag(C)).tolist(),
            "residual_scale": scale, "rounds": taken, "max_direction_change_deg": float(np.max(turn)),
            "max_correction": float(np.max(np.abs(change[use]) / np.maximum(np.abs(meas.brdf[use]), meas.brdf_std[use]))),
            "method": "Gauss-Newton on the inputs (prior N(0, 1) each; steps of at most "
                      f"{ROUND_REACH:g} sigma) with the fit's own directions projected out, the slopes at the moved "
                      "directions; the data refitted at the directions and irradiance the estimate gives them"
                      + (", corrected for the apertures there" if raw is not None else "")}
    response = first.response
    if raw is not None:
        response = {**first.response, "max_correction": float(np.max(np.abs(c - 1.0)[meas.use])),
                    "last_change": float(np.max(np.abs(c - c_before)[meas.use])),
                    "method": first.response["method"] + "; again at each round of the shared-angle estimate, "
                              "at the directions it gave the data"}
        budget = corrected(raw, raw_budget, c)[1]
    result = dataclasses.replace(result, shared_angles=info, shared_angles_fix=(m.wi, m.wo, g, L), response=response,
                                 response_factor=c)
    return result, m, posterior_budget(_budget_at(budget, g), L)


def posterior_budget(budget, L):
    """``budget`` with its shared angle inputs' lines turned to their posterior (``L``, the
    Cholesky factor of C)."""
    post = dict(budget.angles)
    post["shared"] = np.einsum("kj,k...->j...", L, np.asarray(post["shared"], float))
    if post.get("shared_irradiance") is not None:
        post["shared_irradiance"] = np.einsum("kj,k...->j...", L, np.asarray(post["shared_irradiance"], float))
    return dataclasses.replace(budget, angles=post)


def applied(meas, budget, result):
    """The dataset as opened, at the geometry and irradiance ``result``'s shared-angle estimate
    gave it (none: as given), with the budget's posterior: for a fit file built from the dataset
    rather than from the fit's own data."""
    fix = getattr(result, "shared_angles_fix", None)
    if fix is None:
        return meas, budget
    wi, wo, g, L = fix
    if np.shape(wi) != meas.wi.shape:
        raise ValueError(f"the shared-angle estimate was made on {len(wi)} points, this dataset has {meas.n_points}")
    return _at(meas, wi, wo, g), posterior_budget(_budget_at(budget, g), L)


def as_estimated(meas, angles, record):
    """``meas`` (a dataset as opened, its stated shared inputs ``angles``) at the directions and
    irradiance a fit file's ``shared_angles`` ``record`` gave it: the data the fit's parameters
    were fitted to, for a figure or a residual read from the fit file; ``meas`` itself where no
    estimate was applied. ValueError where the record does not fit the dataset."""
    from gonio.fitting.uncertainty.angle_shifts import shared_moves

    if not record or not record.get("applied"):
        return meas
    shared = (angles or {}).get("shared")
    try:
        b = np.asarray(record.get("estimate_sigma") or [], float)
    except (TypeError, ValueError):
        raise ValueError("the fit file's shared-angle estimate_sigma is not a list of numbers") from None
    if shared is None or b.shape != (len(shared),) or not np.all(np.isfinite(b)):
        bad = "" if np.all(np.isfinite(b)) else ", not all finite"
        raise ValueError(f"the fit file's shared-angle estimate ({b.size} inputs{bad}) does not fit this dataset "
                         f"({0 if shared is None else len(shared)} shared angle inputs)")
    return _moved(meas, shared_moves(meas.wi, meas.wo, angles), b)[0]
