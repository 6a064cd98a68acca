"""The per-point uncertainty budget of ``dataset.nc`` (GUM, JCGM 100:2008; docs/interfaces.md 5.1).

Every value of ``brdf`` carries its standard uncertainty split by component: one variable
``u_<component>`` (point, channel) each, in sr^-1, with attributes ``gum_type`` (``"A"``,
JCGM 100 4.2, or ``"B"``, 4.3), ``correlation`` (``"none"``, ``"point"``, ``"full"``,
``"channel"`` or ``"group:<var>"``) and ``source``. A correlated component's values are
signed, c_k u(x) (JCGM 100 5.1.3); a value's standard uncertainty from it is its magnitude.
``u_combined`` is the root sum of squares over the components at each value (JCGM 100
5.1.2), and the type-A components add up to ``brdf_std`` exactly.

Components assembled here: ``shot_read`` and ``fixed_pattern`` (A, none) and
``reference_certificate`` (B, full by default). Other modules supply further components as
:class:`Component` values: ``budget_variables(..., extra=[...])``.
"""

# Attributes. gum_type "A": evaluated from the scatter of this session's own observations;
# "B": from other information (a certificate, a calibration, a model). correlation says how
# the component's errors are shared across values: "none" (independent from value to value),
# "point" (one error per point, shared by its channels, independent between points), "full"
# (one common error: every value moves together), "channel" (one common error per colour
# channel, independent between channels) or "group:<var>" (one common error per integer label
# of the variable <var>, on point or (point, channel)). source: what the figure comes from.
#
# A correlated component's signed value c_k u(x) is the change of brdf when the shared input x
# moves by +1 standard uncertainty (sensitivity coefficient times standard uncertainty), so a
# reader can propagate it to anything fitted. Correlations between values do not enter one
# value's own variance (hence u_combined). u_shot_read^2 + u_fixed_pattern^2 = brdf_std^2, so
# a reader of brdf_std alone sees what it saw before.
#
# shot_read: the HDR merge's shot + read noise model of the sample and reference regions.
# fixed_pattern: the pixel scatter beyond that model, the sensor's fixed pattern and the flat
# field's residual. reference_certificate: the reference's certified reflectance, relative
# 1-sigma [reference] rel_std; rel_std_correlation = "channel" in the settings declares
# per-channel certificates. The source monitor needs no term: sample and reference are in
# every frame, so a lamp change cancels in their ratio (the monitor only suspends a point whose
# bracket the lamp changed within). Components from other modules: angle x slope, aperture,
# stray light, linearity, colour matrix.

from __future__ import annotations

import dataclasses
import math
import re

import numpy as np

from gonio.bench import calibrate
from gonio.bench.measure.point import ReferenceModel

__all__ = ["Component", "budget_variables", "CORRELATIONS", "BUDGET_FORMAT"]

BUDGET_FORMAT = "gonio-budget/1"
CORRELATIONS = ("none", "point", "full", "channel")
_NAME = re.compile(r"^[a-z][a-z0-9_]{0,40}$")


@dataclasses.dataclass
class Component:
    """One line of the budget: ``value`` (N, 3) in sr^-1 (signed where correlated).

    ``groups``: integer labels (N,) or (N, 3), only for ``correlation = "group"``: values with
    the same label share one error (written as the variable ``u_<name>_group``).
    """

    name: str
    value: np.ndarray
    gum_type: str
    correlation: str
    source: str
    groups: np.ndarray | None = None

    def check(self, shape) -> None:
        if not _NAME.match(self.name) or self.name == "combined":
            raise ValueError(f"budget component name {self.name!r} must be lower-case letters, digits and _")
        if self.gum_type not in ("A", "B"):
            raise ValueError(f"budget component {self.name}: gum_type must be 'A' or 'B', not {self.gum_type!r}")
        if self.correlation not in CORRELATIONS + ("group",):
            raise ValueError(f"budget component {self.name}: correlation must be one of "
                             f"{', '.join(CORRELATIONS)} or group, not {self.correlation!r}")
        if np.shape(self.value) != tuple(shape):
            raise ValueError(f"budget component {self.name}: shape {np.shape(self.value)} is not {tuple(shape)}")
        if (self.correlation == "group") != (self.groups is not None):
            raise ValueError(f"budget component {self.name}: groups are given exactly when correlation is 'group'")
        if self.groups is not None and np.shape(self.groups) not in ((shape[0],), tuple(shape)):
            raise ValueError(f"budget component {self.name}: groups must have shape ({shape[0]},) or {tuple(shape)}")


def _detail(rows, key, fallback):
    return np.array([r["detail"].get(key, fallback) for r in rows], float)


def type_a(rows, brdf: np.ndarray, brdf_std: np.ndarray) -> list[Component]:
    """``shot_read`` and ``fixed_pattern`` from the journalled region statistics.

    The noise model's relative standard error of the sample/reference ratio (``se_model``) is
    capped at the empirical one (``se``), whose square is split exactly: shot/read the model's
    share, fixed pattern the excess. A journal without ``se_model`` puts it all in shot_read.
    """
    nan3 = [np.nan] * 3
    rel2_model = np.zeros_like(brdf)
    for k in ("sample", "reference"):
        mean = _detail(rows, f"{k}_mean", nan3)
        se_model = _detail(rows, f"{k}_se_model", nan3)
        with np.errstate(invalid="ignore", divide="ignore"):
            rel2_model += (se_model / mean) ** 2
    with np.errstate(invalid="ignore", divide="ignore"):
        model = np.abs(brdf) * np.sqrt(rel2_model)
    shot = np.where(np.isfinite(model), np.minimum(model, brdf_std), brdf_std)
    fixed = np.sqrt(np.clip(brdf_std ** 2 - shot ** 2, 0.0, None))
    return [Component("shot_read", shot, "A", "none",
                      "HDR merge noise model (shot + read noise) of the sample and reference regions"),
            Component("fixed_pattern", fixed, "A", "none",
                      "pixel scatter in the regions beyond the noise model (fixed pattern, flat-field residual)")]


def certificate(settings, brdf: np.ndarray) -> list[Component]:
    """``reference_certificate``: brdf x the certificate's relative 1-sigma (one per channel
    or one for all); correlation ``full`` unless ``[reference] rel_std_correlation``
    says ``channel``. No component when the certificate states none."""
    ref = settings.get("reference", {})
    rel = np.broadcast_to(np.asarray(ref.get("rel_std", 0.0), float), (brdf.shape[1],))
    if not np.any(rel > 0):
        return []
    corr = str(ref.get("rel_std_correlation", "full"))
    return [Component("reference_certificate", brdf * rel, "B", corr,
                      "reference certificate: relative 1-sigma [reference] rel_std of its reflectance")]


def _levels(rows, settings, key):
    """Each point's signal level of one square as a fraction of full scale (N, 3), at the
    longest exposure of its bracket that left the square unsaturated: x t P / FS with x the
    merged radiance (DN / (s W), gonio/bench/measure/hdr.py), FS = 2^bits (an estimate: the black level
    is neglected)."""
    fs = float(2 ** int(settings.get("camera", {}).get("bits", 14)))
    sat = float(settings.get("capture", {}).get("saturation_fraction", 0.9))
    out = []
    for r in rows:
        x = np.asarray(r["detail"].get(f"{key}_mean", [np.nan] * 3), float)
        levels = [x * float(e.get("seconds", 0.0)) * float(e.get("power", 0.0)) / fs
                  for e in r["detail"].get("exposures", [])]
        ok = [lv for lv in levels if np.all(np.isfinite(lv)) and np.max(lv) < sat]
        out.append(max(ok, key=np.max) if ok else np.zeros(3))
    return np.array(out, float).reshape(len(rows), 3)


def calibration_components(rows, settings, brdf: np.ndarray) -> list[Component]:
    """The type-B lines a calibration (gonio calibrate, merged into the session's settings)
    states, each brdf x its relative uncertainty, correlated across points (one fit each):
    ``reference_factor`` (the reference's non-Lambertian factor table, calibrate.u_reference_factor),
    ``linearity`` (calibrate.u_linearity_rel of the two squares' signal levels), ``stray_light``
    (with ``[stray] u_floor``, gonio calibrate's: the capture removed the floor's level from both
    squares and the line is its u, signed, calibrate.stray_shift_rel, none where u_floor is 0;
    without it: calibrate.u_stray_rel, the floor known only to lie in [0, floor]). Only those the
    settings hold."""
    out = []
    ref = settings.get("reference", {})
    lin = settings.get("linearity", {})
    floor = float(settings.get("stray", {}).get("floor", 0.0) or 0.0)
    if "u_factor" not in ref and not float(lin.get("u_gamma", 0.0) or 0.0) > 0 and not floor > 0:
        return out
    ti = np.array([r["theta_i"] for r in rows], float)
    to = np.array([r["theta_o"] for r in rows], float)
    if "u_factor" in ref:
        model = ReferenceModel(ref)
        factor = np.array([model.factor(a, b) for a, b in zip(ti, to)])
        rel = np.asarray(calibrate.u_reference_factor(settings, ti, to), float) / factor
        out.append(Component("reference_factor", brdf * rel[:, None], "B", "full",
                             "reference factor table's fit (gonio calibrate); sign taken as common to all points"))
    if float(lin.get("u_gamma", 0.0) or 0.0) > 0:
        rel = calibrate.u_linearity_rel(_levels(rows, settings, "sample"), _levels(rows, settings, "reference"),
                                        float(lin["u_gamma"]))
        out.append(Component("linearity", brdf * rel, "B", "full",
                             "detector linearity gamma's 1-sigma (gonio calibrate) x |level_sample - level_reference|"))
    stray = settings.get("stray", {})
    u_floor = float(stray.get("u_floor", 0.0) or 0.0)
    if floor > 0 and ("u_floor" not in stray or u_floor > 0):
        cos_i = np.cos(np.radians(ti))[:, None]
        model = ReferenceModel(ref) if "reflectance" in ref else None
        if "u_floor" in stray:
            # the capture removed the stated floor (gonio/bench/session/run.py): what is left is its u, signed
            # (brighter than the reference: down; darker: up)
            f_ref = (np.array([model.f_r(a, b) for a, b in zip(ti, to)]) if model is not None
                     else np.full((len(ti), 3), 1.0 / math.pi))
            rel = calibrate.stray_shift_rel(np.abs(brdf) * cos_i, f_ref * cos_i, u_floor)
            out.append(Component("stray_light", brdf * rel, "B", "full",
                                 "stray-light floor's u ([stray] u_floor) after its level was removed from both squares"))
        else:
            rho_ref = model.rho if model is not None else np.ones(3)
            rel = calibrate.u_stray_rel(np.abs(brdf) * cos_i, rho_ref[None] / math.pi * cos_i, floor)
            out.append(Component("stray_light", brdf * rel, "B", "full",
                                 "stray-light floor in [0, floor] (rectangular; no level stated, nothing corrected)"))
    return out


def move_history(rows) -> tuple[np.ndarray, np.ndarray]:
    """(labels, last_dir), each (N, 4) over (yaw, tilt, azimuth, lamp), in the rows' order, from
    the order the points were taken (``finished``; the rows' order where a row has none):
    ``labels`` counts each axis's moves up to the point (points with one label were taken
    without moving that axis in between, so they share its per-move error: a stage that is not
    sent anywhere stays where it was); ``last_dir`` the sign of the axis's last move (0 before
    its first move from the first point's position, which the journal does not see)."""
    stage = np.array([[r[k] for k in ("yaw", "tilt", "azimuth", "lamp")] for r in rows], float).reshape(-1, 4)
    t = np.array([float(r.get("finished", i)) for i, r in enumerate(rows)], float)
    order = np.argsort(t, kind="stable")
    step = np.diff(stage[order], axis=0)
    moved = np.abs(step) > 1e-9
    labels, last = np.zeros(stage.shape, np.int64), np.zeros(stage.shape)
    labels[order[1:]] = np.cumsum(moved, axis=0)
    d = np.zeros(4)
    for k, n in enumerate(order[1:]):
        d = np.where(moved[k], np.sign(step[k]), d)
        last[n] = d
    return labels, last


def angle_variables(rows, settings) -> dict:
    """``angle_shift_shared`` (angle_input, point, angle) with ``irradiance_shift_shared``
    (angle_input, point), ``angle_shift_independent``
    (axis_input, point, angle) and ``angle_shift_independent_group`` (axis_input, point),
    degrees: the change of each point's (theta_i, phi_i, theta_o, phi_o) for +1 sigma of each
    shared error (calibrate.angle_uncertainty's signed modes, with each axis's lost motion
    signed by the direction of its last move) and of each axis's per-move error (yaw, tilt,
    azimuth, lamp), which points taken without moving that axis share (the group labels:
    :func:`move_history`). Empty without an [alignment]."""
    if not isinstance(settings.get("alignment"), dict):
        return {}
    stage = np.array([[r[k] for k in ("yaw", "tilt", "azimuth", "lamp")] for r in rows], float)
    labels, last = move_history(rows)
    u = calibrate.angle_uncertainty(settings, stage, last_dir=last)
    attrs = {"units": "degree", "angles": "theta_i phi_i theta_o phi_o"}
    return {"angle_shift_shared": (("angle_input", "point", "angle"), np.transpose(u["shared_modes"], (2, 0, 1)),
                                   {**attrs, "correlation": "full (each input)",
                                    "long_name": "change of the angles for +1 sigma of each shared calibration error"}),
            "irradiance_shift_shared": (("angle_input", "point"), np.transpose(u["irradiance_modes"]),
                                        {"units": "1", "correlation": "full (each input, with angle_shift_shared)",
                                         "long_name": "relative change of the sample's irradiance, not the "
                                                      "reference's, for +1 sigma of each shared calibration "
                                                      "error (the sample's wedge: -tan(theta_i) d theta_i)"}),
            "angle_shift_independent": (("axis_input", "point", "angle"),
                                        np.transpose(u["independent_modes"], (2, 0, 1)),
                                        {**attrs, "axes": "yaw tilt azimuth lamp",
                                         "correlation": "group:angle_shift_independent_group (each axis)",
                                         "long_name": "change of the angles for +1 sigma of each axis's per-move error"}),
            "angle_shift_independent_group": (("axis_input", "point"), labels.T.astype(np.int32),
                                              {"long_name": "each axis's move count: points with one label share "
                                                            "that axis's per-move error"})}


def budget_variables(rows, settings, brdf: np.ndarray, brdf_std: np.ndarray, extra=()) -> dict:
    """The budget's dataset variables: ``u_<component>`` for type A, the certificate, the
    calibration's lines (:func:`calibration_components`) and ``extra`` (more :class:`Component`),
    their ``_group`` labels, ``u_combined``, and the angles' shifts (:func:`angle_variables`;
    the fit multiplies them by its model's slope).

    Raises ValueError when a component is malformed or holds NaN where ``brdf`` is finite.
    """
    comps = (type_a(rows, brdf, brdf_std) + certificate(settings, brdf) + calibration_components(rows, settings, brdf)
             + list(extra))
    seen, out = set(), {}
    total = np.zeros_like(brdf)
    finite = np.isfinite(brdf)
    for c in comps:
        c.check(brdf.shape)
        if c.name in seen:
            raise ValueError(f"budget component {c.name} given twice")
        seen.add(c.name)
        v = np.asarray(c.value, float)
        if not np.all(np.isfinite(v[finite])):
            raise ValueError(f"budget component {c.name} is NaN or infinite where brdf is finite")
        corr = c.correlation
        if c.groups is not None:
            g = np.asarray(c.groups, np.int64)
            out[f"u_{c.name}_group"] = (("point",) if g.ndim == 1 else ("point", "channel"), g,
                                        {"long_name": f"labels of the values sharing one {c.name} error"})
            corr = f"group:u_{c.name}_group"
        out[f"u_{c.name}"] = (("point", "channel"), v, {
            "units": "sr^-1", "gum_type": c.gum_type, "correlation": corr, "source": c.source,
            "long_name": f"standard uncertainty of brdf from {c.name.replace('_', ' ')}"
                         + (" (signed: the change for +1 sigma of the shared input)" if corr != "none" else "")})
        total += v * v
    out["u_combined"] = (("point", "channel"), np.sqrt(total), {
        "units": "sr^-1", "budget_format": BUDGET_FORMAT, "components": " ".join(sorted(seen)),
        "long_name": "combined standard uncertainty of brdf (root sum of squares of the u_ components)"})
    out.update(angle_variables(rows, settings))
    return out
