"""The instrument's uncorrected systematics: type-B inputs of a capture made without calibration.

``[systematics]`` of the instrument description (gonio/bench/instrument.toml for a bench, the
error model's preset for the simulator: :func:`from_error_model`) states each systematic error
that gonio calibrate would measure, with its size and source. A session without ``[alignment]``
carries them in its budget (gonio/bench/dataset/budget.py): the stage zero offsets, the holder's
tilt, the sample's wedge, per-move repeatability and lost motion as angle inputs
(:func:`alignment_table`, read by calibrate.angle_uncertainty), the stray-light floor and the
detector's non-linearity as bounds (rectangular: :func:`settings_for_budget`; a non-linearity
known to compress lies in [0, bound]: its mean is a correction, GUM 4.3.7). The lamp's drift
needs no term: sample and reference share every frame, so it cancels in their ratio.
"""

from __future__ import annotations

import math
from typing import Mapping

__all__ = ["KEYS", "from_error_model", "for_session", "alignment_table", "settings_for_budget", "describe"]

#: the keys of ``[systematics]`` (1-sigma unless said; degrees for angles) and what they mean
KEYS = {
    "zero_deg": "stage zero offsets, 1-sigma per axis [yaw, tilt, azimuth, lamp] (deg)",
    "holder_tilt_deg": "holder normal against the azimuth axis, 1-sigma per component (deg)",
    "wedge_deg": "sample face against its back, 1-sigma per component (deg)",
    "repeat_deg": "per-move repeatability, 1-sigma (deg)",
    "backlash_deg": "full lost motion on a reversal (deg); the load lags by half of it",
    "stray_floor": "upper bound of the stray-light floor (white-Lambertian fraction), rectangular [0, bound]",
    "linearity_gamma": "bound of the detector's integral non-linearity at full scale, rectangular [-bound, bound]",
    "linearity_compressive": "true: the non-linearity is known to compress (the response falls below linear toward "
                             "full scale), so gamma lies in [0, bound]; false or absent: sign unknown, [-bound, bound]",
    "source": "where the sizes come from (text)",
}


def from_error_model(model) -> dict:
    """The simulator's description: ``{"systematics": ..., "aperture": ..., "reference": ...}``
    from its error model (gonio/sim/physics/errors.py; the virtual instrument's data sheet).

    Drawn terms (zero offsets, holder tilt, wedge, repeatability) enter as their 1-sigma; fixed
    ones as their stated size: backlash and gamma as bounds the truth reaches. The stray floor's
    level (``[stray]``, removed at capture; a rectangular bound left rho +0.5 u_c high on a
    glossy sample), the apertures (a design property, modelled by the fit) and the reference's
    non-Lambertian factor (its certificate's, ``factor_a``/``factor_b`` of gonio.sim's Spectralon
    form) are stated, not carried. The ideal instrument's table states zeros: a capture merges
    its settings over the defaults (gonio/bench/settings.merge_settings), which put back
    instrument.toml's [systematics] where the table was left out (an ideal capture carried a
    0.2 deg holder tilt and a stray bound 260 times its noise; its adequacy statistic fell to
    0.6 of its dof).
    """
    st, al, ap = model.stages, model.alignment, model.aperture
    sysm = {"zero_deg": [float(v) for v in st.zero_deg], "holder_tilt_deg": float(al.tilt_deg),
            "wedge_deg": float(al.wedge_deg), "repeat_deg": float(st.repeat_deg),
            "backlash_deg": float(st.backlash_deg), "linearity_gamma": float(model.linearity.gamma),
            "linearity_compressive": bool(model.linearity.gamma),   # the simulator's DN - black go as s (1 - gamma s)
            "stray_floor": 0.0}                        # stated as [stray] below, not carried as a bound
    active = any(v for k, v in sysm.items() if k not in ("zero_deg", "linearity_compressive")) or any(sysm["zero_deg"])
    out = {"systematics": {**sysm, "source": f"gonio.sim error model, preset {model.preset!r} "
                                             + ("(gonio/sim/physics/errors.py: NIST STARR, PTB, Zaber, EMVA 1288)"
                                                if active else "(no systematic errors)")}}
    if ap.source_half_deg or ap.detector_half_deg:
        out["aperture"] = {"source_half_deg": float(ap.source_half_deg),
                           "detector_half_deg": float(ap.detector_half_deg), "profile": "uniform disk"}
    if model.stray.floor:
        # the model states the floor's level (not drawn): removed at capture, as gonio calibrate's is
        out["stray"] = {"floor": float(model.stray.floor), "u_floor": 0.0}
    amp = float(model.reference.non_lambertian)
    if amp:
        # gonio.sim.spectralon_factor: 1 + A (-0.05 (si2 + so2) / 2 + 0.06 si2 so2)
        out["reference"] = {"factor_a": 0.05 * amp, "factor_b": 0.06 * amp}
    return out


def for_session(settings: Mapping) -> dict:
    """``settings`` of a simulated capture with its description merged where nothing is
    calibrated (no ``[alignment]``): ``[systematics]`` replaced by the error model's (removed
    for the ideal instrument), ``[aperture]`` and the reference's factor added. A calibrated
    session is returned as it is."""
    if isinstance(settings.get("alignment"), Mapping):
        return dict(settings)
    import gonio.sim

    desc = from_error_model(gonio.sim.error_model(settings.get("errors")))
    out = {k: v for k, v in settings.items() if k != "systematics"}
    if "systematics" in desc:
        out["systematics"] = desc["systematics"]
    for key in ("aperture", "stray"):
        if key in desc and not isinstance(settings.get(key), Mapping):
            out[key] = desc[key]
    ref = dict(settings.get("reference", {}))
    if "reference" in desc and "factor" not in ref and "factor_a" not in ref:
        out["reference"] = {**ref, **desc["reference"]}
    return out


def _get(sysm: Mapping, key: str) -> float:
    v = sysm.get(key, 0.0)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
        raise ValueError(f"[systematics] {key} must be a finite number >= 0")
    return float(v)


def _zero(sysm: Mapping) -> list:
    z = sysm.get("zero_deg", [0.0] * 4)
    if (not isinstance(z, (list, tuple)) or len(z) != 4
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v >= 0
                       for v in z)):
        raise ValueError("[systematics] zero_deg must be 4 finite numbers >= 0 (yaw, tilt, azimuth, lamp)")
    return [float(v) for v in z]


def alignment_table(settings: Mapping) -> dict | None:
    """An ``[alignment]``-shaped table of nothing corrected (zero offsets 0) whose covariance is
    ``[systematics]``'s, for calibrate.angle_uncertainty; None with an ``[alignment]`` (the
    calibration's terms apply) or without ``[systematics]``.

    Yaw and tilt zero offsets and the holder's tilt are the shared inputs p0..p3, the wedge its
    two, the repeatability per move; the lost motion (not measured) is one signed input per axis
    of half the backlash (``backlash_deg``). The azimuth's zero offset rotates both directions
    about the normal (no effect on an isotropic sample) and the lamp arm's is surveyed at
    assembly: neither is carried."""
    sysm = settings.get("systematics")
    if isinstance(settings.get("alignment"), Mapping) or not isinstance(sysm, Mapping):
        return None
    z = _zero(sysm)
    t = _get(sysm, "holder_tilt_deg")
    cov = [[z[0] ** 2, 0.0, 0.0, 0.0], [0.0, z[1] ** 2, 0.0, 0.0], [0.0, 0.0, t * t, 0.0], [0.0, 0.0, 0.0, t * t]]
    return {"yaw_zero_deg": 0.0, "tilt_zero_deg": 0.0, "holder_tilt_x_deg": 0.0, "holder_tilt_y_deg": 0.0,
            "cov_deg2": cov, "repeat_deg": _get(sysm, "repeat_deg"), "wedge_u_deg": _get(sysm, "wedge_deg"),
            "backlash_deg": _get(sysm, "backlash_deg"), "lamp_zero_u_deg": 0.0}


def settings_for_budget(settings: Mapping) -> dict:
    """``settings`` with ``[systematics]``'s stray floor and non-linearity as the budget's
    uncorrected lines where no calibration states them: ``[stray] floor`` without ``u_floor``
    (a bound, nothing removed: calibrate.u_stray_rel) and ``[linearity] u_gamma`` without
    ``gamma`` (nothing linearised): bound / sqrt(3) of unknown sign, or for a non-linearity
    known to compress bound / sqrt(12) about ``gamma_mean`` = bound / 2 (GUM 4.3.7: the
    midpoint of [0, bound])."""
    sysm = settings.get("systematics")
    if not isinstance(sysm, Mapping) or isinstance(settings.get("alignment"), Mapping):
        return dict(settings)
    out = dict(settings)
    floor = _get(sysm, "stray_floor")
    if floor > 0 and not isinstance(settings.get("stray"), Mapping):
        out["stray"] = {"floor": floor}
    g = _get(sysm, "linearity_gamma")
    compressive = sysm.get("linearity_compressive", False)
    if not isinstance(compressive, bool):
        raise ValueError("[systematics] linearity_compressive must be true or false")
    if g > 0 and not isinstance(settings.get("linearity"), Mapping):
        # sign unknown: gamma in [-g, g], mean 0, u = g / sqrt(3); known to compress: gamma in [0, g],
        # mean g / 2 (gamma_mean: the budget states it and the fit corrects for it) and u = g / sqrt(12)
        out["linearity"] = ({"u_gamma": g / math.sqrt(12.0), "gamma_mean": g / 2.0} if compressive
                            else {"u_gamma": g / math.sqrt(3.0)})
    return out


def describe(settings: Mapping) -> str:
    """One line: where the uncalibrated type-B sizes come from (``[systematics] source``)."""
    sysm = settings.get("systematics") or {}
    return str(sysm.get("source", "the instrument description [systematics]"))
