"""Using a calibration (gonio/bench/calibrate.py writes it): each point's true angles and the
standard uncertainties the calibration implies, for export and the GUM budget.

All functions take the calibration document or settings it was merged into (tables
``[alignment]``, ``[reference]``, ``[aperture]``); docs/interfaces.md 5.2. The names are public
through :mod:`gonio.bench.calibrate`.
"""

from __future__ import annotations

import math
from typing import Mapping

import numpy as np

from gonio.bench.measure import alignment as al
from gonio.bench.plan import kinematics
from gonio.core.geometry import tangent_basis

__all__ = ["calibrated_angles", "lost_motion", "angle_uncertainty", "angle_modes", "hand_angle_modes", "u_reference_factor", "reference_factor_modes",
           "u_linearity_rel",
           "linearity_shift_rel", "u_stray_rel",
           "stray_fraction", "stray_corrected", "stray_shift_rel",
           "dataset_angles", "instrument_response"]


def _p(cal: Mapping) -> np.ndarray:
    a = cal.get("alignment", {})
    return np.array([float(a.get(k, 0.0)) for k in ("yaw_zero_deg", "tilt_zero_deg", "holder_tilt_x_deg",
                                                     "holder_tilt_y_deg")])


def _directions(stage, p, axis_err=None, wedge=(0.0, 0.0), rear=False):
    """wi, wo (N, 3) in the sample's frame for stage angles with errors (:func:`_angles`)."""
    s = np.array(stage, dtype=float, copy=True)
    s[..., 0] += p[0]
    s[..., 1] += p[1]
    if axis_err is not None:
        s = s + axis_err
    wi, wo = kinematics.forward(s, rear)             # rear: the camera on the rear stop (theta_o > 90)
    H = al.holder_rotation(p[2], p[3])
    if any(wedge):
        H = H @ al.holder_rotation(*wedge)
    return wi @ H, wo @ H                         # H.T @ w, row-wise: into the holder's (sample's) frame


def _angles(stage, p, axis_err=None, wedge=(0.0, 0.0), rear=False):
    wi, wo = _directions(stage, p, axis_err, wedge, rear)
    ti, pi_ = kinematics.angles_of(wi)
    to, po = kinematics.angles_of(wo)
    return np.stack([ti, pi_, to, po], -1)


#: the alignment's shared angle inputs, in the order of its covariance: yaw and tilt zero, holder
#: tilt x and y (``cov_deg2``), the lamp arm's zero, the sample's wedge x and y
SHARED_INPUTS = ("p0", "p1", "p2", "p3", "lamp", "wedge0", "wedge1")

#: the axes whose lost motion gonio calibrate measures (scans both ways): alignment keys by axis
_MEASURED_BACKLASH = {0: "backlash_yaw_deg", 1: "backlash_tilt_deg", 3: "backlash_lamp_deg"}


def lost_motion(cal: Mapping, last_dir) -> np.ndarray:
    """The correction (N, 4) in degrees for each axis's lost motion: ``-b / 2`` times the sign of
    the axis's last move (the load lags the motor), with ``b`` the calibration's measured
    backlash of yaw, tilt and lamp; 0 for the azimuth (not scanned) and where the direction is
    unknown (0: before the axis's first move in the journal)."""
    d = np.asarray(last_dir, float)
    a = cal.get("alignment", {})
    out = np.zeros(d.shape)
    for k, key in _MEASURED_BACKLASH.items():
        if key in a:
            out[..., k] = -0.5 * abs(float(a[key])) * d[..., k]
    return out


def calibrated_angles(cal: Mapping, stage_deg, last_dir=None, rear=False) -> np.ndarray:
    """The angles points at commanded ``stage_deg`` (..., 4) really had: ``(theta_i, phi_i,
    theta_o, phi_o)`` (..., 4) in degrees, with the calibration's zero offsets and holder tilt,
    and with ``last_dir`` (..., 4; the sign of each axis's last move, gonio/bench/dataset/budget.move_history)
    each measured axis's lost motion (:func:`lost_motion`): a known systematic error is corrected
    (GUM 3.2.4), not carried as an uncertainty around zero (it biased alpha by +0.4 u_c).

    With an empty calibration this is ``kinematics.forward_angles``.
    """
    stage = np.atleast_2d(np.asarray(stage_deg, float))
    return _angles(stage, _p(cal), None if last_dir is None else lost_motion(cal, np.broadcast_to(last_dir, stage.shape)),
                   rear=rear)


def _jacobian(stage, p, which, h=1e-3, rear=False):
    """d angles / d (error ``which``) by central differences, (N, 4) per error, degrees/degree.
    At a pole (theta 0 or 180 deg: normal incidence, straight through), where phi is undefined,
    the pair is the direction's displacement along the fixed tangents of
    :func:`gonio.core.geometry.tangent_basis` (degrees of arc), as the budget's slopes read it."""
    base = _directions(stage, p, rear=rear)
    bases = [tangent_basis(b) for b in base]
    out = []
    for k in range(len(which)):
        d = np.zeros(len(which))
        d[k] = h
        plus, minus = _eval_errors(stage, p, which, d, rear), _eval_errors(stage, p, which, -d, rear)
        diff = plus - minus
        diff[..., 1::2] = (diff[..., 1::2] + 180.0) % 360.0 - 180.0    # phi differences wrap
        diff = diff / (2 * h)
        if any(np.any(b[2]) for b in bases):
            vp, vm = _eval_errors(stage, p, which, d, rear, vectors=True), _eval_errors(stage, p, which, -d, rear,
                                                                                       vectors=True)
            for j, (e_t, e_p, pole) in enumerate(bases):
                move = np.degrees((vp[j] - vm[j]) / (2 * h))               # arc, degrees per degree
                diff[pole, 2 * j] = np.einsum("nk,nk->n", move, e_t)[pole]
                diff[pole, 2 * j + 1] = np.einsum("nk,nk->n", move, e_p)[pole]
        out.append(diff)
    return np.stack(out, -1)                                          # (N, 4, K)


def _eval_errors(stage, p, which, d, rear=False, vectors=False):
    pp, ax, wd = p.copy(), np.zeros(4), np.zeros(2)
    for name, v in zip(which, d):
        if name in ("p0", "p1", "p2", "p3"):
            pp[int(name[1])] += v
        elif name == "lamp":                 # the lamp zero: the fitted yaw zero is off by half of it
            ax[3] += v
            pp[0] += 0.5 * v
        elif name.startswith("axis"):
            ax[int(name[4])] += v
        else:
            wd[int(name[5])] += v
    return (_directions if vectors else _angles)(stage, pp, ax, tuple(wd), rear)


def angle_uncertainty(cal: Mapping, stage_deg, last_dir=None, rear=False) -> dict:
    """Covariance of each point's calibrated angles ``(theta_i, phi_i, theta_o, phi_o)``, deg^2.

    Returns
    -------
    dict
        ``angles`` (N, 4); ``cov_shared`` (N, 4, 4): the alignment fit's covariance (zero
        offsets, holder tilt: ``cov_deg2``, the peaks' part), the lamp arm's surveyed zero
        (``lamp_zero_u_deg``; not identifiable from specular scans, its prior carried as one
        error that moves the lamp by ``dL`` and the true yaw by ``dL / 2`` from the fitted yaw
        zero, which absorbed ``-dL / 2``) and the sample's wedge (not seen by the artefact's
        scan), the same errors at every point, hence correlated across points;
        ``cov_independent`` (N, 4, 4): each move's repeatability and half the backlash, drawn
        anew per point; ``shared_modes`` (N, 4, K): the signed change of each point's angles
        when one of K independent shared errors moves by +1 sigma (``cov_shared`` = sum of the
        modes' outer products; the budget's correlated components, ``full`` each, after
        multiplying by df_r/dangle); ``irradiance_modes`` (N, K): with each shared mode, the
        relative change of the sample's irradiance that the reference does not share (the
        wedge's, -tan(theta_i) d theta_i; 0 for the others), which the budget multiplies by f_r;
        ``u_theta_i``, ``u_theta_o``, ``u_phi_i``, ``u_phi_o``
        (N,): the combined standard uncertainties. Multiply by the local slope of f_r (the
        budget's ``u_angle``). ``independent_modes`` (N, 4, 4): the change of each point's
        angles for +1 sigma of each axis's (yaw, tilt, azimuth, lamp) own per-move error
        (``cov_independent`` = the sum of their outer products).

    ``last_dir`` (N, 4), optional: the sign of each axis's last move before each point (+1, -1;
    0 unknown), from the order the points were taken. With it an axis's lost motion is not a
    per-point error but the same -b/2 for every point its axis last reached moving up and +b/2
    moving down: the angles are corrected by the measured backlash (:func:`lost_motion`; yaw,
    tilt, lamp) and what is left is one shared error per axis, the measurement's
    ``u_backlash_<axis>_deg`` / 2 (a mode, signed by the direction); the azimuth's, not
    measured, stays a mode of its assumed b/2. Without it (or where 0) half the backlash stays in
    the per-point part and nothing is corrected. ``rear`` (N,) or a bool: points taken with the
    camera on the rear stop (transmission; `kinematics.forward`'s ``rear``).
    """
    stage = np.atleast_2d(np.asarray(stage_deg, float))
    a = cal.get("alignment", {})
    p = _p(cal)
    cov_p = np.asarray(a.get("cov_deg2", np.zeros((4, 4))), float)
    shared = list(SHARED_INPUTS)
    cs = np.zeros((7, 7))
    cs[:4, :4] = cov_p
    cs[4, 4] = float(a.get("lamp_zero_u_deg", 0.0)) ** 2
    cs[5, 5] = cs[6, 6] = float(a.get("wedge_u_deg", 0.0)) ** 2
    rep = float(a.get("repeat_deg", 0.0))
    # an axis the calibration did not scan: the data sheet's ``backlash_deg`` (uncalibrated: all)
    spec_b = 0.5 * abs(float(a.get("backlash_deg", 0.0)))
    half_b = [0.5 * abs(float(a.get(f"backlash_{n}_deg", 2 * spec_b))) for n in ("yaw", "tilt")]
    half_b += [max(half_b), 0.5 * abs(float(a.get("backlash_lamp_deg", max(half_b) * 2)))]   # azimuth: not scanned
    d = np.zeros(stage.shape) if last_dir is None else np.broadcast_to(np.asarray(last_dir, float), stage.shape)
    known = d != 0
    # the lost motion left after the correction: the measured axes' u(b)/2, the azimuth's b/2
    left_b = list(half_b)
    for k, key in _MEASURED_BACKLASH.items():
        if key in a:
            left_b[k] = 0.5 * abs(float(a.get("u_" + key, 0.0)))
    sd_i = np.sqrt(rep ** 2 + np.where(known, 0.0, np.asarray(half_b) ** 2))      # (N, 4) per axis
    rear = np.broadcast_to(np.asarray(rear, bool), stage.shape[:1])     # per point: the rear stop's kinematics
    Js = _jacobian(stage, p, shared, rear=rear)
    Ji = _jacobian(stage, p, ["axis0", "axis1", "axis2", "axis3"], rear=rear)
    w, V = np.linalg.eigh(cs)
    modes = np.einsum("nak,km->nam", Js, V * np.sqrt(np.clip(w, 0.0, None)))      # (N, 4, 7)
    keep = np.sqrt(np.clip(w, 0.0, None)) > 0
    modes = modes[:, :, keep]
    # the wedge tilts the sample's face alone: its irradiance goes as the cosine of the incidence
    # on that face, while the reference square beside it (same holder, same stages) keeps its
    # own, so the ratio the bench measures changes by cos(theta_i') / cos(theta_i) as well as
    # by f_r's own angles: d ln E = -tan(theta_i) d theta_i (radians) for the wedge's inputs,
    # nothing for the errors both squares share (they cancel in the ratio)
    angles = _angles(stage, p, lost_motion(cal, d), rear=rear)
    ti = np.radians(angles[:, 0])
    Jr = np.zeros((stage.shape[0], len(shared)))
    for k in (shared.index("wedge0"), shared.index("wedge1")):
        Jr[:, k] = -np.tan(ti) * np.radians(Js[:, 0, k])
    irradiance = (Jr @ (V * np.sqrt(np.clip(w, 0.0, None))))[:, keep]                 # (N, K)
    # the reference square sees the same errors but not the sample's wedge: its incidence
    # angle's change per degree of each named shared input (gonio calibrate's factor fit divides
    # by its cosine), and the reference factor that fit left per degree of each (``[reference]
    # factor_ab_per_deg``, one row per name of SHARED_INPUTS) moves every value by dF / F in each
    # mode: a relative change the budget multiplies by f_r
    ref_theta_i = Js[:, 0, :].copy()
    ref_theta_i[:, [shared.index("wedge0"), shared.index("wedge1")]] = 0.0
    ab_deg = cal.get("reference", {}).get("factor_ab_per_deg")
    if ab_deg is not None:
        ab_deg = np.asarray(ab_deg, float)
        if ab_deg.shape != (len(shared), 2) or not np.all(np.isfinite(ab_deg)):
            raise ValueError(f"[reference] factor_ab_per_deg must be {len(shared)} x 2 finite numbers "
                             f"(gonio calibrate's, one row per input {', '.join(shared)}); recalibrate")
        si2, so2 = np.sin(np.radians(angles[:, 0])) ** 2, np.sin(np.radians(angles[:, 2])) ** 2
        D = np.stack([-0.5 * (si2 + so2), si2 * so2], -1)
        a_b = [float(cal["reference"].get(k, 0.0)) for k in ("factor_a", "factor_b")]
        F = 1.0 - a_b[0] * 0.5 * (si2 + so2) + a_b[1] * si2 * so2
        per_mode = (ab_deg.T @ (V * np.sqrt(np.clip(w, 0.0, None))))[:, keep]               # (2, K)
        irradiance = irradiance + (D @ per_mode) / F[:, None]
    lost = [Ji[:, :, k] * (-left_b[k] * d[:, k])[:, None] for k in range(4)
            if left_b[k] > 0 and np.any(known[:, k])]                            # the sim: error -b/2 x dir
    if lost:
        modes = np.concatenate([modes, np.stack(lost, -1)], axis=-1)
        irradiance = np.concatenate([irradiance, np.zeros((stage.shape[0], len(lost)))], axis=-1)
    indep = Ji * sd_i[:, None, :]                                                 # (N, 4 angles, 4 axes)
    cov_s = np.einsum("nak,nbk->nab", modes, modes)
    cov_i = np.einsum("nak,nbk->nab", indep, indep)
    tot = np.sqrt(np.diagonal(cov_s + cov_i, axis1=1, axis2=2))
    return {"angles": angles, "cov_shared": cov_s, "cov_independent": cov_i,
            "shared_modes": modes, "irradiance_modes": irradiance, "independent_modes": indep,
            "reference_theta_i_per_input": ref_theta_i,
            "u_theta_i": tot[:, 0], "u_phi_i": tot[:, 1], "u_theta_o": tot[:, 2], "u_phi_o": tot[:, 3]}


def u_reference_factor(cal: Mapping, theta_i, theta_o) -> np.ndarray:
    """Standard uncertainty of the reference's factor at (theta_i, theta_o) deg (bilinear in
    the calibration's ``u_factor`` table; 0 without one). Correlated across points (one fit)."""
    ref = cal.get("reference", {})
    if "u_factor" not in ref:
        return np.zeros(np.broadcast(np.asarray(theta_i), np.asarray(theta_o)).shape)
    gi, go = np.asarray(ref["factor_theta_i"], float), np.asarray(ref["factor_theta_o"], float)
    tab = np.asarray(ref["u_factor"], float)
    from scipy.interpolate import RegularGridInterpolator

    f = RegularGridInterpolator((gi, go), tab, bounds_error=False, fill_value=None)
    ti, to = np.broadcast_arrays(np.clip(theta_i, gi[0], gi[-1]), np.clip(theta_o, go[0], go[-1]))
    return f(np.stack([ti, to], -1))


def reference_factor_modes(cal: Mapping, theta_i, theta_o) -> np.ndarray | None:
    """The reference factor's change at (theta_i, theta_o) deg (..., in the factor's own units) for
    +1 sigma of each of the two independent inputs of gonio calibrate's fit (K = 2, ...): the
    fitted form 1 - a (sin^2 ti + sin^2 to) / 2 + b sin^2 ti sin^2 to
    (alignment.reference_factor_model) moved along the eigenvectors of the covariance of (a, b),
    ``[reference] factor_cov_ab``. Its two terms have different shapes and an error of a moves
    grazing points one way where b's moves them the other: one line of magnitude u_factor
    everywhere (:func:`u_reference_factor`, all of one sign) is not the error the fit left. None
    without ``factor_cov_ab`` (a certificate's table, or a calibration file from before it)."""
    ref = cal.get("reference", {})
    cov = ref.get("factor_cov_ab")
    if cov is None:
        return None
    cov = np.asarray(cov, float)
    if cov.shape != (2, 2) or not np.all(np.isfinite(cov)) or not np.allclose(cov, cov.T, rtol=1e-9, atol=0.0):
        raise ValueError("[reference] factor_cov_ab must be a finite symmetric 2 x 2 matrix (gonio calibrate's fit)")
    w, V = np.linalg.eigh(cov)
    if w.min() < -1e-12 * max(abs(w).max(), 1e-300):
        raise ValueError("[reference] factor_cov_ab must be positive semi-definite (gonio calibrate's fit)")
    si2 = np.sin(np.radians(np.asarray(theta_i, float))) ** 2
    so2 = np.sin(np.radians(np.asarray(theta_o, float))) ** 2
    D = np.stack([-0.5 * (si2 + so2), si2 * so2], -1)                           # d factor / d (a, b)
    return np.moveaxis(D @ (V * np.sqrt(np.clip(w, 0.0, None))), -1, 0)


def u_linearity_rel(level_sample, level_reference, u_gamma: float) -> np.ndarray:
    """Relative standard uncertainty of the sample/reference ratio left by the linearity
    correction: ``u_gamma |l_s - l_r|`` for signal levels as fractions of full scale (each
    square's merged DN / (white - black) at the exposure that dominated its merge).
    Correlated across points (one gamma)."""
    return float(u_gamma) * np.abs(np.asarray(level_sample, float) - np.asarray(level_reference, float))


def linearity_shift_rel(level_sample, level_reference, u_gamma: float) -> np.ndarray:
    """Relative change of the sample/reference ratio for ``u_gamma`` more compression at full
    scale (signed): ``u_gamma (l_r - l_s)``, levels as fractions of full scale. A detector whose
    DN go as s (1 - gamma l) gives the ratio (1 - gamma l_s) / (1 - gamma l_r) ~ 1 - gamma
    (l_s - l_r): one gamma moves the diffuse values (sample darker than the reference) up and a
    specular peak (brighter) down. Correlated across points (one gamma): the budget's
    ``linearity`` line, whose magnitude is :func:`u_linearity_rel`."""
    return float(u_gamma) * (np.asarray(level_reference, float) - np.asarray(level_sample, float))


def stray_fraction(radiance_reference, floor: float) -> np.ndarray:
    """The stray light's share q = (floor / pi) / (L_r + floor / pi) of the reference square's
    signal, L_r its radiance per unit irradiance (rho F cos theta_i / pi, sr^-1): the floor adds
    floor / pi to both squares (gonio/sim/physics/errors.py ``stray``: light the lamp-off darks miss)."""
    s = float(floor) / math.pi
    return s / (np.asarray(radiance_reference, float) + s)


def stray_corrected(ratio, q) -> np.ndarray:
    """The sample/reference ratio with a known stray floor removed from both squares:
    ``(R - q) / (1 - q)`` with q = :func:`stray_fraction`. The measured R = (L_s + s) / (L_r + s)
    becomes L_s / L_r exactly (s = floor / pi)."""
    q = np.asarray(q, float)
    return (np.asarray(ratio, float) - q) / (1.0 - q)


def stray_shift_rel(radiance_sample, radiance_reference, u_floor: float) -> np.ndarray:
    """Relative change of the stray-corrected ratio when the true floor is ``u_floor`` above the
    one corrected for (signed, first order): ``u_floor / pi (1 / L_s - 1 / L_r)``, radiances per
    unit irradiance. Correlated across points (one floor): the budget's ``stray_light`` line of a
    corrected session."""
    ls = np.maximum(np.asarray(radiance_sample, float), 1e-300)
    lr = np.maximum(np.asarray(radiance_reference, float), 1e-300)
    return float(u_floor) / math.pi * (1.0 / ls - 1.0 / lr)


def u_stray_rel(radiance_sample, radiance_reference, floor: float) -> np.ndarray:
    """Relative standard uncertainty of the ratio from a stray-light floor known only to lie in
    [0, ``floor``] (rectangular): ``floor / pi |1 / L_s - 1 / L_r| / sqrt(3)``, radiances per
    unit irradiance (f_r cos theta_i, sr^-1). Correlated across points (one floor). Only for a
    ``[stray]`` table without ``u_floor`` (a calibration that states a bound, not a level, and
    corrects nothing); gonio calibrate's tables state the level and its u (:func:`stray_corrected`)."""
    ls = np.maximum(np.asarray(radiance_sample, float), 1e-300)
    lr = np.maximum(np.asarray(radiance_reference, float), 1e-300)
    return float(floor) / math.pi * np.abs(1.0 / ls - 1.0 / lr) / math.sqrt(3.0)


def dataset_angles(settings: Mapping, stage_deg, last_dir=None, rear=False) -> tuple[dict, dict, dict]:
    """What export writes for a calibrated session: ``(coords, variables, attrs)``.

    Without an ``[alignment]`` table in the session's settings all three are empty. With one,
    the coordinates ``theta_i``, ``phi_i``, ``theta_o``, ``phi_o`` become the calibrated angles,
    the nominal ones (gonio/bench/plan/kinematics without calibration) stay as ``<angle>_nominal``, each
    angle's combined standard uncertainty is ``<angle>_u`` (deg; ``angle_uncertainty`` splits
    it into shared and independent parts), and the attributes carry the calibration
    (``angle_calibration``, JSON) and :func:`instrument_response`.
    """
    import json

    if not isinstance(settings.get("alignment"), Mapping):
        return {}, {}, {}
    stage = np.atleast_2d(np.asarray(stage_deg, float))
    u = angle_uncertainty(settings, stage, last_dir=last_dir, rear=rear)
    nominal = calibrated_angles({}, stage, rear=rear)
    names = ("theta_i", "phi_i", "theta_o", "phi_o")
    deg = {"units": "degree"}
    coords = {k: ("point", u["angles"][:, j], {**deg, "long_name": f"{k}, calibrated (gonio calibrate)"})
              for j, k in enumerate(names)}
    data = {}
    for j, k in enumerate(names):
        data[f"{k}_nominal"] = ("point", nominal[:, j], {**deg, "long_name": f"{k} from the kinematics, uncalibrated"})
        data[f"{k}_u"] = ("point", u[f"u_{k}"], {**deg, "long_name": f"standard uncertainty of the calibrated {k}"})
    a = settings["alignment"]
    keys = ("yaw_zero_deg", "tilt_zero_deg", "holder_tilt_x_deg", "holder_tilt_y_deg", "cov_deg2", "repeat_deg",
            "backlash_yaw_deg", "backlash_tilt_deg", "backlash_lamp_deg", "lamp_zero_u_deg", "wedge_u_deg")
    attrs = {"angle_calibration": json.dumps({k: a[k] for k in keys if k in a}, sort_keys=True),
             **instrument_response(settings)}
    return coords, data, attrs


def instrument_response(cal: Mapping) -> dict:
    """The instrument's angular response for a forward model: source and detector half-angles
    (deg) and their profile (``uniform disk``: f_r is averaged over a disk of directions around
    wi and one around wo). Dataset/session attributes ``aperture_*``."""
    ap = cal.get("aperture", {})
    return {"aperture_source_half_deg": float(ap.get("source_half_deg", 0.0)),
            "aperture_detector_half_deg": float(ap.get("detector_half_deg", 0.0)),
            "aperture_profile": str(ap.get("profile", "uniform disk"))}


def angle_modes(settings: Mapping, stage_deg):
    """(N, 4, K): the change of each stage pose's (theta_i, phi_i, theta_o, phi_o), deg, for +1
    sigma of each shared and per-move input of the dataset's angle lines
    (gonio.bench.dataset.budget.angle_variables: the calibration's ``[alignment]``, else
    ``[systematics]`` uncorrected; lost motion per point, the move order unknown); None without
    either."""
    from gonio.bench.measure import systematics

    uncal = systematics.alignment_table(settings)
    cal = {"alignment": uncal} if uncal is not None else settings
    if not isinstance(cal.get("alignment"), Mapping):
        return None
    u = angle_uncertainty(cal, stage_deg)
    return np.concatenate([u["shared_modes"], u["independent_modes"]], axis=2)


def hand_angle_modes(strategy, settings: Mapping, stage_deg):
    """``strategy``, handed :func:`angle_modes` (its ``use_angle_modes``) where it has
    ``angle_noise`` on (gonio.bench.plan.adaptive) and the settings state the angles' errors:
    by the run, and by the capture before it writes anything, so that a bad ``[systematics]``
    is refused first. ValueError, one line, for bad settings."""
    if getattr(strategy, "angle_noise", False):
        modes = angle_modes(settings, stage_deg)
        if modes is None:
            raise ValueError("[strategy] angle_noise needs the angles' errors: give the settings an [alignment] "
                             "(gonio calibrate) or [systematics], or angle_noise = false")
        strategy.use_angle_modes(modes)
    return strategy
