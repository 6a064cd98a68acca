"""The instrument's angular response in the forward model: f_r averaged over the aperture cones.

A measured value is not f_r at one direction pair but its mean over the cones the source and
the detector subtend: with half-angles a_s, a_d a gonioreflectometer measures
``<f_r cos theta_i> / <cos theta_i>`` over a disk of directions around wi (radius a_s) and one
around wo (radius a_d) (Nicodemus et al. 1977, NBS Monograph 160, the "instrument function";
Barnes, Early & Parr 1998 for STARR's 0.5-1 deg apertures). Each disk is integrated with the
7-point degree-5 rule for the disk (Stroud 1971, S2 5-1), so 49 direction pairs a value;
where f_r is 0 at some of them and not at others (a cutoff) with 256 sunflower points a disk.

The fit uses it by correction (:func:`aperture_corrected`): at the fitted parameters the
ratio c = <f>/f of each value is computed, the data (values, sigma and the budget's
components) are divided by it and the model is refitted once (the fit says how far c moved).
"""

# Stroud's S2 5-1: the centre with weight 1/4, six points at radius sqrt(2/3) with weight 1/8.
# c depends on the parameters only weakly, so one repetition converges. Where the lobe is wide
# against the apertures c = 1 to within the noise and nothing changes.

from __future__ import annotations

import dataclasses
import math

import numpy as np

from gonio.fitting.measurements import Measurements

__all__ = ["disk_rule", "cone", "aperture_mean", "aperture_ratio", "corrected", "with_instrument_response",
           "reaches_cutoff"]


def disk_rule():
    """Points (7, 2) and weights (7,) of Stroud's S2 5-1 on the unit disk (weights sum to 1)."""
    r = math.sqrt(2.0 / 3.0)
    ang = np.arange(6) * math.pi / 3.0
    pts = np.vstack([[0.0, 0.0], np.column_stack([r * np.cos(ang), r * np.sin(ang)])])
    return pts, np.r_[0.25, np.full(6, 0.125)]


def cone(w: np.ndarray, half_rad: float, pts=None) -> np.ndarray:
    """The rule's directions (or the unit-disk points ``pts``, (K, 2)) in a cone of half-angle
    ``half_rad`` around each unit ``w`` (N, 3): (7 or K, N, 3), via the tangent plane (exact to
    O(half^2) in solid angle)."""
    pts = disk_rule()[0] if pts is None else pts
    helper = np.where(np.abs(w[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    t1 = np.cross(w, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(w, t1)
    t = math.tan(half_rad)
    d = w[None] + t * (pts[:, 0, None, None] * t1[None] + pts[:, 1, None, None] * t2[None])
    return d / np.linalg.norm(d, axis=2, keepdims=True)


def aperture_mean(model, wi, wo, params, source_half_deg: float, detector_half_deg: float) -> np.ndarray:
    """<f_r cos theta_i> / <cos theta_i> over the two disks (N, C): what the instrument measures."""
    _, w = disk_rule()
    ci = cone(wi, math.radians(source_half_deg)) if source_half_deg > 0 else wi[None]
    co = cone(wo, math.radians(detector_half_deg)) if detector_half_deg > 0 else wo[None]
    wa = w if len(ci) > 1 else np.ones(1)
    wb = w if len(co) > 1 else np.ones(1)
    num, den = 0.0, 0.0
    zero = nonzero = False
    for a, da in zip(wa, ci):
        cos_i = np.clip(da[:, 2], 0.0, None)[:, None]
        for b, db in zip(wb, co):
            f = np.asarray(model.eval(da, db, params), float)
            zero, nonzero = zero | (f == 0.0).any(axis=1), nonzero | (f != 0.0).any(axis=1)
            num = num + a * b * f * cos_i
            den = den + a * b * cos_i
    out = np.where(den > 0, num / np.maximum(den, 1e-300), 0.0)
    jump = np.flatnonzero(np.asarray(zero & nonzero)) if len(ci) * len(co) > 1 else []
    for n in jump:
        # f_r jumps to 0 between the rule's pairs (a lobe's cutoff): the rule weights a whole
        # 1/64 on a corner pair, so the mean is taken over equal-weight sunflower points instead
        # (the simulator's rule there, gonio/sim/physics/errors.py)
        u = _sunflower(DENSE_POINTS)
        di = cone(wi[n:n + 1], math.radians(source_half_deg), u)[:, 0] if len(ci) > 1 else wi[n:n + 1]
        do = cone(wo[n:n + 1], math.radians(detector_half_deg), u)[:, 0] if len(co) > 1 else wo[n:n + 1]
        a, b = np.repeat(di, len(do), axis=0), np.tile(do, (len(di), 1))
        cos_i = np.clip(a[:, 2], 0.0, None)
        den_n = cos_i.sum()
        out[n] = (np.asarray(model.eval(a, b, params), float) * cos_i[:, None]).sum(axis=0) / den_n if den_n > 0 else 0.0
    return out


#: Points a disk of the dense rule used where f_r jumps inside the cones (pairs: its square).
DENSE_POINTS = 256


def _sunflower(n: int) -> np.ndarray:
    """``n`` equal-weight points on the unit disk, one per equal-area ring, turned by the golden
    angle (Vogel 1979, Math. Biosci. 44 179)."""
    k = np.arange(n) + 0.5
    r, a = np.sqrt(k / n), k * math.pi * (3.0 - math.sqrt(5.0))
    return np.stack([r * np.cos(a), r * np.sin(a)], -1)


def reaches_cutoff(model, wi, wo, params, half_i_deg, half_o_deg) -> np.ndarray:
    """(N,) bool: f_r is 0 at some and non-zero at other direction pairs within cones of
    half-angle ``half_i_deg`` around wi and ``half_o_deg`` around wo ((N,) or scalars, deg;
    probed at the rule's seven and six rim points of each disk, paired: 169 pairs a point).
    There f_r has a cutoff (GGX's transmission lobe jumps to 0 where its half-vector crosses
    the surface, a side's horizon): a jump, not a slope, so no first-order line describes it."""
    n = len(wi)
    pts, _ = disk_rule()
    rim = np.column_stack([np.cos(np.arange(6) * math.pi / 3 + math.pi / 6),
                           np.sin(np.arange(6) * math.pi / 3 + math.pi / 6)])
    pts = np.vstack([pts, rim])

    def dirs(w, half_deg):
        helper = np.where(np.abs(w[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
        t1 = np.cross(w, helper)
        t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
        t2 = np.cross(w, t1)
        t = np.tan(np.radians(np.broadcast_to(np.asarray(half_deg, float), (n,))))[None, :, None]
        d = w[None] + t * (pts[:, 0, None, None] * t1[None] + pts[:, 1, None, None] * t2[None])
        return d / np.linalg.norm(d, axis=2, keepdims=True)           # (13, N, 3)

    di, do = dirs(np.asarray(wi, float), half_i_deg), dirs(np.asarray(wo, float), half_o_deg)
    zero = np.zeros(n, bool)
    nonzero = np.zeros(n, bool)
    for da in di:
        for db in do:
            f = np.asarray(model.eval(da, db, params), float)
            zero |= (f == 0.0).any(axis=1)
            nonzero |= (f != 0.0).any(axis=1)
    return zero & nonzero


def aperture_ratio(model, wi, wo, params, source_half_deg: float, detector_half_deg: float) -> np.ndarray:
    """c = <f_r> / f_r (N, C) at ``params``; 1 where f_r is 0 (nothing to correct)."""
    f = model.eval(wi, wo, params)
    m = aperture_mean(model, wi, wo, params, source_half_deg, detector_half_deg)
    ok = np.abs(f) > 1e-12 * max(float(np.max(np.abs(f))), 1e-300)
    return np.where(ok, m / np.where(ok, f, 1.0), 1.0)


def corrected(meas, budget, c: np.ndarray):
    """``meas`` and ``budget`` with every value (f_r, sigma, the components) divided by ``c``; every
    other field of ``meas`` (weights, clusters) as it was."""
    m = dataclasses.replace(meas, brdf=meas.brdf / c, brdf_std=meas.brdf_std / c,
                            attrs={**meas.attrs, "aperture_corrected": True})
    if budget is None:
        return m, None
    comps = [dataclasses.replace(k, value=k.value / c) for k in budget.components]
    return m, dataclasses.replace(budget, components=comps)


def with_instrument_response(meas, budget, result, refit, repeats: int = 2):
    """``result`` refitted with the angular response where ``meas.attrs`` declares apertures
    (``aperture_source_half_deg``, ``aperture_detector_half_deg`` > 0; gonio/bench/calibrate's
    ``instrument_response``); otherwise everything unchanged. ``refit(meas)`` -> FitResult.

    Returns (result, meas, budget): the corrected data and budget where corrected, and the
    result's ``response`` (the fit file's ``instrument_response``) saying what was done.
    """
    src = float(meas.attrs.get("aperture_source_half_deg", 0.0) or 0.0)
    det = float(meas.attrs.get("aperture_detector_half_deg", 0.0) or 0.0)
    if not (np.isfinite(src) and np.isfinite(det)) or src < 0 or det < 0 or src > 20 or det > 20:
        raise ValueError(f"aperture half-angles {src:g}, {det:g} deg are not in [0, 20]; fix the dataset's "
                         "aperture_source_half_deg / aperture_detector_half_deg")
    if src == 0.0 and det == 0.0:
        return result, meas, budget
    first = result
    c = np.ones_like(meas.brdf)
    m, b, change = meas, budget, 0.0
    for _ in range(repeats):
        c_new = aperture_ratio(result.model, meas.wi, meas.wo, result.params, src, det)
        change = float(np.max(np.abs(c_new - c)[meas.use]))
        c = c_new
        m, b = corrected(meas, budget, c)
        result = refit(m)
    info = {"source_half_deg": src, "detector_half_deg": det, "profile": "uniform disk (Stroud S2 5-1, 7 x 7 points)",
            "method": f"data divided by c = <f_r>/f_r at the fitted parameters, refitted {repeats} times",
            "max_correction": float(np.max(np.abs(c - 1.0)[meas.use])), "last_change": change,
            "point_model_params": dict(zip(first.space.names, np.asarray(first.x).tolist()))}
    return dataclasses.replace(result, response=info, response_factor=c), m, b
