"""The per-point uncertainty budget of ``dataset.nc`` (GUM, JCGM 100:2008; docs/interfaces.md 5.1).

Every value of ``brdf`` carries its standard uncertainty split by component: one variable
``u_<component>`` (point, channel) each, in sr^-1, with attributes ``gum_type`` (``"A"``,
JCGM 100 4.2, or ``"B"``, 4.3), ``correlation`` (``"none"``, ``"point"``, ``"full"``,
``"channel"`` or ``"group:<var>"``) and ``source``. A correlated component's values are
signed, c_k u(x) (JCGM 100 5.1.3); a value's standard uncertainty from it is its magnitude.
``u_combined`` is the root sum of squares over the components at each value (JCGM 100
5.1.2), and the type-A components add up to ``brdf_std`` exactly.

Components assembled here: ``shot_read`` and ``fixed_pattern`` (A, none), ``dark_frame`` (A,
full, one input per correlated mode: ``u_dark_frame`` (point, channel, dark_input)) and
``reference_certificate`` (B, full by default); others come as :class:`Component` values
(``budget_variables(..., extra=[...])``). Transmitted points (the rear stop) have no reference
square: the open beam's lines (:func:`open_beam_components`) stand in for the certificate.
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
from gonio.bench.measure.hdr import NoiseModel, dark_sensitivity
from gonio.bench.measure import systematics
from gonio.bench.measure.calpoint import linearity_shift_rel
from gonio.bench.measure.point import ReferenceModel
from gonio.bench.plan.markers import roi_masks_fast

__all__ = ["Component", "budget_variables", "CORRELATIONS", "BUDGET_FORMAT"]

BUDGET_FORMAT = "gonio-budget/1"
CORRELATIONS = ("none", "point", "full", "channel")
_NAME = re.compile(r"^[a-z][a-z0-9_]{0,40}$")


@dataclasses.dataclass
class Component:
    """One line of the budget: ``value`` (N, 3) in sr^-1 (signed where correlated).

    ``groups``: integer labels (N,) or (N, 3), only for ``correlation = "group"``: values with
    the same label share one error (written as the variable ``u_<name>_group``).
    ``mean``: a ``full`` line's input's expected value in its own standard uncertainties
    (written as ``input_mean``): a systematic effect of known sign left in the data, whose
    expected effect ``mean x value`` the fit corrects for (0: none).
    """

    name: str
    value: np.ndarray
    gum_type: str
    correlation: str
    source: str
    groups: np.ndarray | None = None
    mean: float = 0.0

    def check(self, shape) -> None:
        if not _NAME.match(self.name) or self.name == "combined":
            raise ValueError(f"budget component name {self.name!r} must be lower-case letters, digits and _")
        if self.gum_type not in ("A", "B"):
            raise ValueError(f"budget component {self.name}: gum_type must be 'A' or 'B', not {self.gum_type!r}")
        if self.correlation not in CORRELATIONS + ("group",):
            raise ValueError(f"budget component {self.name}: correlation must be one of "
                             f"{', '.join(CORRELATIONS)} or group, not {self.correlation!r}")
        vshape = np.shape(self.value)
        if vshape != tuple(shape) and not (len(vshape) == 3 and vshape[1:] == tuple(shape) and vshape[0] >= 1
                                           and self.correlation == "full"):
            raise ValueError(f"budget component {self.name}: shape {vshape} is not {tuple(shape)} (or "
                             f"(inputs, {', '.join(map(str, shape))}) for a 'full' line of several inputs)")
        if (self.correlation == "group") != (self.groups is not None):
            raise ValueError(f"budget component {self.name}: groups are given exactly when correlation is 'group'")
        if not np.isfinite(self.mean) or (self.mean != 0.0 and self.correlation != "full"):
            raise ValueError(f"budget component {self.name}: a mean is a finite number, for a 'full' line only")
        if self.groups is not None and np.shape(self.groups) not in ((shape[0],), tuple(shape)):
            raise ValueError(f"budget component {self.name}: groups must have shape ({shape[0]},) or {tuple(shape)}")


def _detail(rows, key, fallback):
    return np.array([r["detail"].get(key, fallback) for r in rows], float)


def rear_rows(rows) -> np.ndarray:
    """(N,) bool: the rows measured on the rear stop (theta_o > 90: transmitted light)."""
    return np.array([float(r.get("theta_o", 0.0)) > 90.0 for r in rows], bool)


def type_a(rows, brdf: np.ndarray, brdf_std: np.ndarray, dark_var: np.ndarray | None = None) -> list[Component]:
    """``shot_read`` and ``fixed_pattern`` from the journalled region statistics.

    The noise model's relative standard error of the sample/reference ratio (``se_model``) is
    capped at the empirical one (``se``), whose square is split exactly: shot/read the model's
    share, fixed pattern the excess. A journal without ``se_model`` puts it all in shot_read.
    ``dark_var`` (N, 3): the share of the model's variance that the dark frames' noise makes
    and the ``dark_frame`` line carries (:func:`dark_frame`), taken out of shot_read. A
    transmitted point has the sample region alone, and its monitor reading's scatter
    (``monitor_rel_u``, which the reference square cancels on the front stop): a ``monitor``
    line (A, none), where the session has such points.
    """
    nan3 = [np.nan] * 3
    rear = rear_rows(rows)[:, None]
    rel2_model = np.zeros_like(brdf)
    for k in ("sample", "reference"):
        mean = _detail(rows, f"{k}_mean", nan3)
        se_model = _detail(rows, f"{k}_se_model", nan3)
        with np.errstate(invalid="ignore", divide="ignore"):
            rel2_model += np.where(rear, 0.0, (se_model / mean) ** 2) if k == "reference" else (se_model / mean) ** 2
    with np.errstate(invalid="ignore", divide="ignore"):
        model = np.abs(brdf) * np.sqrt(rel2_model)
        monitor = np.where(rear, np.abs(brdf) * _detail(rows, "monitor_rel_u", 0.0)[:, None], 0.0)
    monitor = np.where(np.isfinite(monitor), np.minimum(monitor, brdf_std), 0.0)
    left = np.sqrt(np.clip(brdf_std ** 2 - monitor ** 2, 0.0, None)) if rear.any() else brdf_std
    shot = np.where(np.isfinite(model), np.minimum(model, left), left)
    fixed = np.sqrt(np.clip(left ** 2 - shot ** 2, 0.0, None))
    if dark_var is not None:
        shot = np.sqrt(np.clip(shot ** 2 - dark_var, 0.0, None))
    return [Component("shot_read", shot, "A", "none",
                      "HDR merge noise model (shot + read noise) of the sample and reference regions"
                      + (", the dark frames' share apart (dark_frame)" if dark_var is not None else "")),
            Component("fixed_pattern", fixed, "A", "none",
                      "pixel scatter in the regions beyond the noise model (fixed pattern, flat-field residual)")] + (
        [Component("monitor", monitor, "A", "none", "the lamp monitor's reading scatter at a transmitted point "
                   "(the open beam normalises it, no reference square in its frame); 0 on the front stop")]
        if rear.any() else [])


#: the dark frames' correlated modes kept as shared inputs: those whose variance, in units of
#: the values' own brdf_std^2, is at least this (the rest stays in shot_read, independent)
DARK_MODE_MIN = 0.01
#: raw pixels behind each super-pixel value of the RGGB mosaic (gonio/bench/drivers/raw.py)
_N_RAW = np.array([1.0, 2.0, 1.0])
#: the most cells of the overlap grid (super-pixels, or blocks of them on a large sensor)
_CELLS = 1 << 16


def _padded_exposures(rows):
    """(seconds, power, present) (N, K): each point's exposures, padded with absent ones."""
    exps = [r["detail"].get("exposures") or [] for r in rows]
    K = max((len(e) for e in exps), default=0)
    t, p, ok = np.ones((len(rows), K)), np.ones((len(rows), K)), np.zeros((len(rows), K), bool)
    for i, e in enumerate(exps):
        for k, d in enumerate(e):
            t[i, k], p[i, k], ok[i, k] = float(d.get("seconds", np.nan)), float(d.get("power", np.nan)), True
    return t, p, ok & np.isfinite(t) & np.isfinite(p) & (t > 0) & (p > 0)


def _dark_rate(x, n, se_model, t, kk, ok, noise) -> np.ndarray:
    """The darks' level as a rate (DN/s, per channel) that makes the merge's noise model give
    the journalled se_model of the regions (least squares in log over every region; the level
    is not journalled): the dark current's shot noise is half a dark value's variance at the
    long exposures."""
    grid = np.concatenate([[0.0], np.logspace(-2, 5, 141)])
    out = np.zeros(3)
    for c in range(3):
        good = np.isfinite(x[..., c]) & (n[..., c] > 0) & np.isfinite(se_model[..., c]) & (se_model[..., c] > 0)
        if not good.any():
            continue
        best = None
        for rate in grid:
            var, _ = dark_sensitivity(x[..., c], kk, rate * t, noise, _N_RAW[c], ok[..., c])
            with np.errstate(invalid="ignore", divide="ignore"):
                err = np.log(np.sqrt(var / np.maximum(n[..., c], 1.0))) - np.log(se_model[..., c])
            cost = float(np.nansum(np.where(good, err, 0.0) ** 2))
            if best is None or cost < best[0]:
                best = (cost, rate)
        out[c] = best[1]
    return out


def _overlap_cells(rows, settings):
    """Each point's sample and reference regions as cell counts (N, cells) each, for their
    overlaps; None where the rows carry no stage angles."""
    if (not all(k in r for r in rows for k in ("yaw", "tilt", "azimuth", "lamp"))
            or not {"sample_half", "offset"} <= set(settings.get("holder", {}))
            or not {"pixel_size", "width", "height"} <= set(settings.get("camera", {}))):
        return None
    cache, S, R = {}, [], []
    for r in rows:
        stage = np.array([r[k] for k in ("yaw", "tilt", "azimuth", "lamp")], float)
        key = tuple(stage[:3])
        if key not in cache:
            sm, rm = roi_masks_fast(stage, settings)
            f = max(1, int(np.ceil(np.sqrt(sm.size / _CELLS))))
            if f > 1:                       # a large sensor: counts on blocks of f x f super-pixels
                h, w = (sm.shape[0] // f) * f, (sm.shape[1] // f) * f
                sm = sm[:h, :w].reshape(h // f, f, w // f, f).sum(axis=(1, 3))
                rm = rm[:h, :w].reshape(h // f, f, w // f, f).sum(axis=(1, 3))
            cache[key] = (np.asarray(sm, float).ravel(), np.asarray(rm, float).ravel(), f * f)
        S.append(cache[key][0])
        R.append(cache[key][1])
    area = next(iter(cache.values()))[2]
    return np.array(S), np.array(R), area


def dark_frame(rows, settings, brdf: np.ndarray, brdf_std: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """``dark_frame``: the dark frames' noise, shared by every point that subtracts them, as
    (values (K, N, 3), signed, one per shared input; the variance they carry (N, 3)); None
    where the journal lacks what it takes (exposures, region statistics, stage angles).

    One dark frame a rung is taken per session (gonio/bench/session/calframes.py), and each
    point's merge subtracts it from every value of its regions: its noise (read noise and the
    dark current's shot noise, as much as a value's own at zero signal) moves the region's
    mean by coef x its mean over the region (`gonio.bench.measure.hdr.dark_sensitivity`), and
    two points whose regions overlap move together. Per channel the covariance of brdf from
    it is C[a, b] = sum_k s_k^2 sum over the super-pixels in both (c_a c_b), the regions from the
    plan's geometry (`roi_masks_fast`, as the capture finds them without markers), the darks'
    level from the journalled se_model (:func:`_dark_rate`). Its eigenvectors (scaled by the
    values' brdf_std, :data:`DARK_MODE_MIN`) are the shared inputs; what they leave, and the
    variance as a whole, stays in shot_read's independent line."""
    if not rows or not all("exposures" in r.get("detail", {}) for r in rows):
        return None
    cells = _overlap_cells(rows, settings)
    if cells is None:
        return None
    S, R, area = cells
    cam = settings.get("camera", {})
    noise = NoiseModel(float(cam.get("gain_e_per_dn", 2.0)), float(cam.get("read_noise_e", 3.0)))
    fs = float(2 ** int(cam.get("bits", 14)))
    sat = float(settings.get("capture", {}).get("saturation_fraction", 0.9))
    nan3 = [np.nan] * 3
    t, p, ok = _padded_exposures(rows)
    kk = (t * p).T                                               # (K, N)
    x = np.stack([_detail(rows, f"{k}_mean", nan3) for k in ("sample", "reference")])        # (2, N, 3)
    n = np.stack([_detail(rows, f"{k}_n", nan3) for k in ("sample", "reference")])
    se_model = np.stack([_detail(rows, f"{k}_se_model", nan3) for k in ("sample", "reference")])
    if not np.any(np.isfinite(se_model)):
        return None
    # usable exposures: present and the region's level below saturation (its mean: an estimate)
    usable = ok.T[:, None, :, None] & (np.nan_to_num(x)[None] * kk[:, None, :, None] < sat * fs)   # (K, 2, N, 3)
    kk4 = kk[:, None, :, None]
    t4 = t.T[:, None, :, None]
    rate = _dark_rate(x, n, se_model, t4[..., 0], kk4[..., 0], usable, noise)
    dark_dn = rate * t4                                          # (K, 1, N, 3)
    _, coef = dark_sensitivity(x, kk4, dark_dn, noise, _N_RAW, usable)          # (K, 2, N, 3)
    sigma = np.sqrt((np.maximum(dark_dn, 0.0) / noise.gain + (noise.read_noise / noise.gain) ** 2 + 1.0 / 12.0)
                    / _N_RAW)                                    # a dark value's 1-sigma, DN
    ti = np.array([r.get("theta_i", np.nan) for r in rows], float)
    to = np.array([r.get("theta_o", np.nan) for r in rows], float)
    ref = settings.get("reference", {})
    if "reflectance" in ref:
        model = ReferenceModel(ref)
        f_ref = np.array([model.f_r(a, b) for a, b in zip(ti, to)]).reshape(-1, 3)
    else:
        with np.errstate(invalid="ignore", divide="ignore"):
            f_ref = brdf * x[1] / x[0]
    with np.errstate(invalid="ignore", divide="ignore"):
        # brdf = f_ref x_s / x_r: a dark reading of +1 sigma at one super-pixel of a region
        # lowers that region's mean by coef sigma / n
        alpha_s = -(f_ref / x[1]) * coef[:, 0] * sigma[:, 0] / n[0]          # (K, N, 3)
        alpha_r = (brdf / x[1]) * coef[:, 1] * sigma[:, 0] / n[1]
    alpha_s, alpha_r = np.nan_to_num(alpha_s), np.nan_to_num(alpha_r)
    # the rungs: exposures of one length share one dark frame
    lengths = np.unique(np.round(t[ok], 12))
    SS, SR, RR = (S @ S.T) / area, (S @ R.T) / area, (R @ R.T) / area
    scale = np.where(np.isfinite(brdf_std) & (brdf_std > 0), brdf_std, np.inf)
    values, var = [], np.zeros(brdf.shape)
    for c in range(3):
        G = np.zeros((len(rows), len(rows)))
        for tl in lengths:
            at = np.isclose(t, tl, rtol=1e-9, atol=0.0) & ok                   # (N, K)
            a_s = np.where(at.T, alpha_s[..., c], 0.0).sum(axis=0)             # (N,)
            a_r = np.where(at.T, alpha_r[..., c], 0.0).sum(axis=0)
            G += (np.outer(a_s, a_s) * SS + np.outer(a_s, a_r) * SR + np.outer(a_r, a_s) * SR.T
                  + np.outer(a_r, a_r) * RR)
        Gw = G / np.outer(scale[:, c], scale[:, c])
        lam, vec = np.linalg.eigh(0.5 * (Gw + Gw.T))
        keep = lam >= DARK_MODE_MIN
        modes = vec[:, keep] * np.sqrt(lam[keep]) * np.where(np.isfinite(scale[:, c]), scale[:, c], 0.0)[:, None]
        for m in modes.T:
            v = np.zeros(brdf.shape)
            v[:, c] = m
            values.append(v)
            var[:, c] += m * m
    if not values:
        return None
    return np.array(values), var


def open_beam_components(rows, brdf: np.ndarray, open_beam: dict | None) -> list[Component]:
    """The transmitted points' normalisation (`OpenBeam.to_attrs`, ASTM E2387), as
    ``budget_from_attrs`` reads the attributes (gonio/fitting/uncertainty/budget.py):
    ``open_beam_certificate`` (B, full: brdf x ``open_beam_rel_std``, the attenuator's and the
    beam solid angle's certificates) and ``open_beam_frame`` (B, channel: brdf x
    ``open_beam_frame_rel_u``, the one open-beam frame's scatter and monitor reading, shared by
    every transmitted point); 0 at the reflected points. None without transmitted points."""
    rear = rear_rows(rows)[:, None]
    if not rear.any() or not open_beam:
        return []
    out = []
    rel = float(open_beam.get("open_beam_rel_std", 0.0))
    if rel > 0:
        out.append(Component("open_beam_certificate", np.where(rear, brdf * rel, 0.0), "B", "full",
                             "open_beam_rel_std ([transmission] rel_std: attenuator and beam solid angle)"))
    frame = np.asarray(open_beam.get("open_beam_frame_rel_u", [0.0] * 3), float)
    out.append(Component("open_beam_frame", np.where(rear, brdf * frame[None, :], 0.0), "B", "channel",
                         "open_beam_frame_rel_u (the open-beam frame's scatter and monitor reading)"))
    return out


def certificate(settings, brdf: np.ndarray) -> list[Component]:
    """``reference_certificate``: brdf x the certificate's relative 1-sigma (one per channel
    or one for all); correlation ``full`` unless ``[reference] rel_std_correlation``
    says ``channel``. No component when the certificate states none. Pass 0 for the
    transmitted points: the reference does not normalise them."""
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
    settings hold. Without a calibration, ``[systematics]``'s stray floor and non-linearity
    bounds (gonio.bench.measure.systematics.settings_for_budget), their sources saying so.

    On the rear stop (transmitted points) no reference square is in the frame: the reference
    factor is 0 there; linearity compares the point's level with the open beam's (journalled
    ``open_beam_level``, the ratio f_t is made of); the stray floor, radiance floor / pi per unit
    irradiance as on the front stop (the simulator's model), adds floor / (pi cos theta_i) to
    f_t with nothing to cancel it: its u (the calibrated floor's, which the capture removed as
    on the front stop) or its rectangular [0, floor] root mean square, signed up."""
    out = []
    rear = rear_rows(rows)[:, None]
    uncal = systematics.alignment_table(settings) is not None and all("theta_i" in r for r in rows)
    if uncal:
        settings = systematics.settings_for_budget(settings)
    desc = f" (not calibrated; {systematics.describe(settings)})" if uncal else ""
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
        modes = calibrate.reference_factor_modes(settings, ti, to)
        if modes is not None:
            # f_r = (S / S_ref) rho F / pi: a factor too high by dF moves every value by f_r dF / F,
            # one input per independent direction of the fit's (a, b)
            out.append(Component("reference_factor", np.where(rear, 0.0, brdf)[None] * (modes / factor)[:, :, None],
                                 "B", "full",
                                 "reference factor's fit (gonio calibrate): its two inputs, the eigenvectors of "
                                 "the covariance of (a, b)"))
        else:
            rel = np.asarray(calibrate.u_reference_factor(settings, ti, to), float) / factor
            out.append(Component("reference_factor", np.where(rear, 0.0, brdf * rel[:, None]), "B", "full",
                                 "reference factor table (a certificate's, or a calibration without its "
                                 "covariance); sign taken as common to all points"))
    if float(lin.get("u_gamma", 0.0) or 0.0) > 0:
        # signed: one gamma moves values darker than the reference up and brighter ones down
        u_gamma = float(lin["u_gamma"])
        ref_level = _levels(rows, settings, "reference")
        for k in np.flatnonzero(rear[:, 0]):     # the open beam is what a transmitted point is divided by
            ref_level[k] = np.asarray(rows[k]["detail"].get("open_beam_level") or [0.0] * 3, float)
        rel = linearity_shift_rel(_levels(rows, settings, "sample"), ref_level, u_gamma)
        # a non-linearity known to compress and not linearised: gamma in [0, bound], its mean a correction
        mean = float(lin.get("gamma_mean", 0.0) or 0.0) / u_gamma
        text = ("detector linearity gamma's 1-sigma (gonio calibrate)" if not uncal else
                "detector non-linearity known to compress, gamma in [0, bound] ([systematics] linearity_gamma, "
                "rectangular, nothing linearised): u = bound / sqrt(12) about its mean bound / 2 (input_mean "
                "sqrt(3), which the fit corrects for)" + desc if mean else
                "detector non-linearity bound / sqrt(3) ([systematics] linearity_gamma, rectangular, sign unknown, "
                "nothing linearised)" + desc)
        out.append(Component("linearity", brdf * rel, "B", "full",
                             text + " x (level_reference - level_sample), signed", mean=mean))
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
            out.append(Component("stray_light", np.where(rear, u_floor / (math.pi * cos_i), brdf * rel), "B", "full",
                                 "stray-light floor's u ([stray] u_floor) after its level was removed from both squares"))
        else:
            # the floor's root mean square in [0, floor] (floor / sqrt(3)), signed as a floor moves
            # the ratio: values darker than the reference up, brighter ones down
            rho_ref = model.rho if model is not None else np.ones(3)
            rel = calibrate.stray_shift_rel(np.abs(brdf) * cos_i, rho_ref[None] / math.pi * cos_i, floor / math.sqrt(3.0))
            out.append(Component("stray_light", np.where(rear, floor / math.sqrt(3.0) / (math.pi * cos_i), brdf * rel),
                                 "B", "full",
                                 "stray-light floor in [0, floor] (rectangular; no level stated, nothing corrected)"
                                 + ("; floor from [systematics] stray_floor" + desc if uncal else "")))
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
    :func:`move_history`). Without an [alignment], from ``[systematics]`` (nothing corrected:
    gonio.bench.measure.systematics.alignment_table); empty without either."""
    uncal = systematics.alignment_table(settings)
    if uncal is not None and all(k in r for r in rows for k in ("yaw", "tilt", "azimuth", "lamp")):
        settings, source = {"alignment": uncal}, ("not calibrated: the instrument description's stage zero "
                                                  "offsets, holder tilt, wedge, repeatability and lost motion "
                                                  f"([systematics]; {systematics.describe(settings)})")
    elif isinstance(settings.get("alignment"), dict):
        source = "gonio calibrate's alignment (the fit's covariance, the surveyed lamp zero, the wedge's data sheet)"
    else:
        return {}
    stage = np.array([[r[k] for k in ("yaw", "tilt", "azimuth", "lamp")] for r in rows], float)
    labels, last = move_history(rows)
    u = calibrate.angle_uncertainty(settings, stage, last_dir=last, rear=rear_rows(rows))   # each point's stop
    attrs = {"units": "degree", "angles": "theta_i phi_i theta_o phi_o", "source": source}
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


def budget_variables(rows, settings, brdf: np.ndarray, brdf_std: np.ndarray, extra=(), open_beam=None) -> dict:
    """The budget's dataset variables: ``u_<component>`` for type A, the certificate, the
    calibration's lines (:func:`calibration_components`) and ``extra`` (more :class:`Component`),
    their ``_group`` labels, ``u_combined``, and the angles' shifts (:func:`angle_variables`;
    the fit multiplies them by its model's slope).

    Transmitted points: ``open_beam`` (`OpenBeam.to_attrs`) gives their normalisation's lines
    (:func:`open_beam_components`), the certificate is 0 there and the dark frames' line is
    the reflected points' alone (a transmitted point's dark share stays in shot_read).

    Raises ValueError when a component is malformed or holds NaN where ``brdf`` is finite.
    """
    rear = rear_rows(rows)
    if rear.any():
        front = np.flatnonzero(~rear)
        part = dark_frame([rows[k] for k in front], settings, brdf[front], brdf_std[front]) if len(front) else None
        dark = None
        if part is not None:
            dark = (np.zeros((part[0].shape[0], *brdf.shape)), np.zeros(brdf.shape))
            dark[0][:, front], dark[1][front] = part
    else:
        dark = dark_frame(rows, settings, brdf, brdf_std)
    if dark is not None:
        # the dark inputs carry at most the noise model's share (the type-A lines stay brdf_std)
        shot_model = type_a(rows, brdf, brdf_std)[0].value
        with np.errstate(invalid="ignore", divide="ignore"):
            shrink = np.where(dark[1] > shot_model ** 2, np.sqrt(shot_model ** 2 / dark[1]), 1.0)
        dark = (dark[0] * np.nan_to_num(shrink)[None], dark[1] * np.nan_to_num(shrink) ** 2)
    comps = (type_a(rows, brdf, brdf_std, None if dark is None else dark[1])
             + (certificate(settings, np.where(rear[:, None], 0.0, brdf)) if not rear.all() else [])
             + open_beam_components(rows, brdf, open_beam)
             + calibration_components(rows, settings, brdf) + list(extra))
    seen, out = set(), {}
    total = np.zeros_like(brdf)
    if dark is not None:
        seen.add("dark_frame")
        out["u_dark_frame"] = (("point", "channel", "dark_input"), np.moveaxis(dark[0], 0, -1), {
            "units": "sr^-1", "gum_type": "A", "correlation": "full",
            "source": "the dark frames' noise (one frame a rung, subtracted by every point that uses the rung): "
                      "one input per correlated mode of the regions' overlaps",
            "long_name": "standard uncertainty of brdf from the dark frames (signed: the change for +1 sigma "
                         "of each independent input)"})
        total += dark[1]
    finite = np.isfinite(brdf)
    for c in comps:
        c.check(brdf.shape)
        if c.name in seen:
            raise ValueError(f"budget component {c.name} given twice")
        seen.add(c.name)
        v = np.asarray(c.value, float)
        if not np.all(np.isfinite(v[..., finite])):
            raise ValueError(f"budget component {c.name} is NaN or infinite where brdf is finite")
        corr = c.correlation
        if c.groups is not None:
            g = np.asarray(c.groups, np.int64)
            out[f"u_{c.name}_group"] = (("point",) if g.ndim == 1 else ("point", "channel"), g,
                                        {"long_name": f"labels of the values sharing one {c.name} error"})
            corr = f"group:u_{c.name}_group"
        several = v.ndim == 3            # K independent inputs, each shared by every value
        out[f"u_{c.name}"] = ((("point", "channel", f"{c.name}_input") if several else ("point", "channel")),
                              np.moveaxis(v, 0, -1) if several else v, {
            "units": "sr^-1", "gum_type": c.gum_type, "correlation": corr, "source": c.source,
            "long_name": f"standard uncertainty of brdf from {c.name.replace('_', ' ')}"
                         + (" (signed: the change for +1 sigma of each independent input)" if several else
                            " (signed: the change for +1 sigma of the shared input)" if corr != "none" else ""),
            **({"input_mean": float(c.mean)} if c.mean else {})})
        total += (v * v).sum(axis=0) if several else v * v
    out["u_combined"] = (("point", "channel"), np.sqrt(total), {
        "units": "sr^-1", "budget_format": BUDGET_FORMAT, "components": " ".join(sorted(seen)),
        "long_name": "combined standard uncertainty of brdf (root sum of squares of the u_ components)"})
    out.update(angle_variables(rows, settings))
    return out
