"""``gonio calibrate``: estimate the bench's systematic errors and write a calibration file.

Three procedures, run in this order on one bench (:class:`SimBench` drives the virtual
instrument's physics in this process; a hardware bench offers the same four methods):
:func:`align` (the yaw and tilt zero offsets and the holder's tilt, from specular-peak scans
of a glossy artefact), :func:`linearity` (the integral non-linearity ``gamma``) and
:func:`reference_factor` (the white reference's departure from Lambertian).

:func:`write_calibration` writes values, standard uncertainties, the procedure, the seed and
the versions; its ``[alignment]``, ``[linearity]``, ``[aperture]`` and ``[reference]`` tables
merge into a capture's instrument settings (:func:`merge_calibration`), so its session.toml
records them. The per-point type-B uncertainties they imply (docs/interfaces.md,
"Calibration"): :func:`calibrated_angles`, :func:`angle_uncertainty`,
:func:`u_reference_factor`, :func:`u_linearity_rel`, :func:`u_stray_rel`, :func:`instrument_response`.
"""

# The procedures in detail:
# 1. Alignment: at four azimuths a glossy artefact in the sample slot is scanned across its
#    specular peak, in yaw (tilt stage at 0) and in tilt (yaw at the peak), each scan once
#    upwards and once downwards. The mean of the two passes' peaks is free of backlash; their
#    difference measures it. The peaks fit the yaw and tilt zero offsets and the holder's tilt
#    (gonio.bench.measure.alignment.fit_alignment).
# 2. Linearity: an exposure ladder on the white reference at one pose, monitor-normalised.
# 3. Reference factor: the reference's own signal over a 5 x 5 in-plane grid of
#    (theta_i, theta_o), at the calibrated angles, linearity-corrected and divided by the
#    monitor and cos(theta_i), fits its departure from Lambertian; the file carries the
#    [reference] factor table that gonio.bench.measure.point.ReferenceModel applies.
# The per-point uncertainties are the GUM budget's type-B inputs: calibrated_angles gives the
# angles a point really had, angle_uncertainty their covariance (split into the part shared by
# every point and the part independent per point), instrument_response the source and
# detector solid angles for a forward model of the angular response.

from __future__ import annotations

import io
import math
import time
from pathlib import Path
from typing import Mapping

import numpy as np
from gonio.core.atomic import atomic_open

from gonio.bench.measure import alignment as al
from gonio.bench.plan import kinematics
from gonio.bench.measure.calpoint import (angle_uncertainty, calibrated_angles, dataset_angles, instrument_response, lost_motion, reference_factor_modes, u_linearity_rel, u_reference_factor, u_stray_rel, stray_corrected, stray_fraction, stray_shift_rel)
from gonio.bench.measure.hdr import linearise
from gonio.core.errors import GonioError

__all__ = ["SimBench", "calibrate", "align", "linearity", "reference_factor", "write_calibration",
           "read_calibration", "merge_calibration", "calibrated_angles", "lost_motion", "angle_uncertainty",
           "u_reference_factor", "reference_factor_modes", "u_linearity_rel", "u_stray_rel", "stray_fraction", "stray_corrected",
           "stray_shift_rel", "instrument_response", "dataset_angles",
           "GLOSSY_ARTEFACT", "run_calibration", "summary", "calibrate_cli"]

#: The glossy artefact of the alignment (a rough metal, GGX alpha 0.1: a lobe of about 7 deg
#: FWHM, bright enough for 1/8000 s and wide enough for 0.8 deg steps).
GLOSSY_ARTEFACT = {"model": "roughconductor", "params": {"alpha": 0.1}}
SCAN_LAMP_DEG = 60.0
SCAN_AZIMUTHS = (0.0, 90.0, 180.0, 270.0)
SCAN_HALF_DEG, SCAN_STEP_DEG = 7.0, 1.0
FACTOR_ANGLES = (10.0, 25.0, 40.0, 55.0, 70.0)


class SimBench:
    """The simulated instrument's physics, driven directly (no protocol ports).

    Methods a calibration bench offers: ``move(stage_deg)`` (absolute, the four stages),
    ``frame(exposure_s)`` (black-subtracted DN on the 2x2 super-pixel grid, the mean of the
    tile's R, G, G, B), ``monitor()`` (lamp power, W) and ``full_scale`` (DN). Moves go through
    the stages' physics, so zero offsets, backlash and repeatability act as they do in a
    capture. :class:`DriverBench` offers the same through the bench's drivers.
    """

    def __init__(self, inst):
        self.inst = inst
        inst.home_all()
        inst.lamp.switch(inst.clock.now(), True)
        self.full_scale = float(inst.sensor.white - inst.sensor.black)

    def move(self, stage_deg) -> None:
        inst = self.inst
        t = inst.clock.now()
        ends = []
        for name, deg in zip(kinematics.AXES, stage_deg):
            a = inst.axes[inst.axis_names.index(name)]
            a.move_abs(t, int(round(float(deg) * a.cycle_dist / 360.0)))
            ends.append(a.end_time(t) or t)
        inst.clock.advance(max(ends) - t + 1e-3)

    def frame(self, exposure_s: float) -> np.ndarray:
        import tifffile

        raw = tifffile.imread(io.BytesIO(self.inst.capture(exposure_s))).astype(np.float64) - self.inst.sensor.black
        h, w = raw.shape[0] // 2, raw.shape[1] // 2
        return raw[:2 * h, :2 * w].reshape(h, 2, w, 2).mean(axis=(1, 3))

    def monitor(self, n: int = 10) -> float:
        inst = self.inst
        return float(np.mean([inst.meter.read(inst.lamp.power(inst.clock.now())) for _ in range(n)]))


class DriverBench:
    """A calibration bench on the production drivers (gonio/bench/drivers/rig.Bench: Zaber stages and LED,
    the power meter, the camera): real hardware, or the simulator through its ``sim://`` ports
    (the same bytes). Frames go to ``folder`` as RAW files and are decoded by
    ``drivers.decode_raw``; each move waits ``[motion] settle_s``.
    """

    def __init__(self, rig, settings: Mapping, folder: Path):
        from gonio.bench.drivers import decode_raw

        self.rig, self.folder, self._decode = rig, Path(folder), decode_raw
        self.folder.mkdir(parents=True, exist_ok=True)
        self.settle = float(settings.get("motion", {}).get("settle_s", 0.0))
        flags = rig.gonio.connect(clear_faults=True)
        if any(f in ("WR", "WH") for f in flags):
            rig.gonio.home()
        m = settings.get("meter", {})
        rig.meter.configure(float(m.get("wavelength_nm", 550)), int(m.get("averaging", 10)))
        rig.led.set_flux(float(settings.get("lamp", {}).get("flux", 1.0)))
        rig.led.on()
        self.frames = 0
        self.full_scale = float(self._frame(float(settings["capture"]["exposure_min_s"])).full_scale)

    def move(self, stage_deg) -> None:
        self.rig.gonio.move_to(dict(zip(kinematics.AXES, (float(v) for v in stage_deg))))
        self.rig.sleep(self.settle)

    def _frame(self, exposure_s: float):
        path = self.folder / f"calibration-{self.frames:05d}.dng"
        self.frames += 1
        self.rig.camera.expose(exposure_s, path)
        frame = self._decode(path, peak=False)
        path.unlink()
        return frame

    def frame(self, exposure_s: float) -> np.ndarray:
        r, g, b = self._frame(exposure_s).signal.astype(np.float64)
        return 0.25 * (r + 2.0 * g + b)

    def monitor(self, n: int = 1) -> float:
        return float(np.mean([self.rig.meter.power() for _ in range(n)]))


# ----------------------------------------------------------------------------- measurements
def _squares(bench, stage_deg, settings, exposure):
    """Mean DN of the sample and reference regions (2x2 super-pixels) in one frame."""
    sp = bench.frame(exposure)
    ms, mr = kinematics.roi_masks(np.asarray(stage_deg, float), settings, binning=2)
    if ms.sum() < 4 or mr.sum() < 4:
        raise GonioError(f"calibration pose {list(stage_deg)} does not show both squares; check [holder]")
    return float(sp[ms].mean()), float(sp[mr].mean()), float(sp[ms].max())


def _exposure_for(bench, stage_deg, settings, target=0.6, which=2):
    """Exposure putting region statistic ``which`` (0 sample mean, 1 reference mean, 2 sample
    max) at ``target`` of full scale: probes from ``probe_s``, an eighth of it while saturated."""
    cap = settings["capture"]
    lo, hi = float(cap["exposure_min_s"]), float(cap["exposure_max_s"])
    t = float(cap["probe_s"])
    bench.move(stage_deg)
    for _ in range(12):
        level = _squares(bench, stage_deg, settings, t)[which]
        if level >= 0.9 * bench.full_scale:
            if t <= lo:
                return lo
            t = max(t / 8.0, lo)
            continue
        t_new = float(np.clip(t * target * bench.full_scale / max(level, 1e-9), lo, hi))
        if abs(t_new / t - 1) < 0.3 or t_new in (lo, hi):
            return t_new
        t = t_new
    return t


def _scan(bench, settings, base, axis, xs, exposure, repeat_deg=0.0):
    """Ratio sample/reference along ``axis`` (0 yaw, 1 tilt), one pass up then one down; returns
    ``(centre, u_centre, backlash, u_backlash)`` (deg, gonio/bench/measure/alignment.fit_passes). Every point
    is a move of the scanned stage: each abscissa is uncertain by ``repeat_deg``."""
    out = []
    for order in (xs, xs[::-1]):
        pre = list(base)
        pre[axis] = order[0] - (order[1] - order[0])          # approach the first point in the pass direction
        bench.move(pre)
        ratio = []
        for x in order:
            s = list(base)
            s[axis] = x
            bench.move(s)
            smp, ref, _ = _squares(bench, s, settings, exposure)
            ratio.append(smp / ref)
        out.append(np.asarray(ratio))
    return al.fit_passes(xs, out[0], out[1][::-1], u_x=repeat_deg)


def align(bench, settings: Mapping, lamp_zero_u_deg: float = 0.02, repeat_deg: float = 0.0, progress=None) -> dict:
    """Specular cross-scans at four azimuths; returns the ``[alignment]`` table.

    ``repeat_deg`` (the stages' data sheet): every scan point is a move of the scanned stage, so
    each abscissa is uncertain by it (gonio/bench/measure/alignment.fit_peak's effective variance: the
    flanks, where the centre's information is, are the noisiest points); each peak is fitted to
    the mean of an up and a down pass (:func:`_scan`). The lamp arm is
    positioned once per azimuth: its repeatability moves that azimuth's yaw peak by half of a
    draw, so half of it adds in quadrature to each yaw peak's uncertainty. ``progress``:
    ``progress(done, total, label)`` before the exposure search and each scan (None: silent).
    """
    say = progress if progress is not None else (lambda done, total, label: None)
    steps = 1 + 2 * len(SCAN_AZIMUTHS)
    say(0, steps, "exposure for the scans")
    xs0 = np.arange(-SCAN_HALF_DEG, SCAN_HALF_DEG + 1e-9, SCAN_STEP_DEG)
    L = SCAN_LAMP_DEG
    peaks, back = [], {"yaw": [], "tilt": []}
    t = _exposure_for(bench, [0.5 * L, 0.0, SCAN_AZIMUTHS[0], L], settings)     # the artefact is isotropic
    for k, az in enumerate(SCAN_AZIMUTHS):
        centre = [0.5 * L, 0.0, az, L]
        # the lamp arm reaches L from below at two opposite azimuths and from above at the other
        # two: its backlash is then a parameter of the fit, not a bias of the yaw zero
        side = -1.0 if k % 2 == 0 else 1.0
        bench.move([0.5 * L, 0.0, az, L + side])
        say(1 + 2 * k, steps, f"yaw scan, azimuth {az:g}")
        y, uy, by, uby = _scan(bench, settings, centre, 0, 0.5 * L + xs0, t, repeat_deg)
        y_at = round(y * 2000.0) / 2000.0                           # the microstep grid (720000/rev)
        say(2 + 2 * k, steps, f"tilt scan, azimuth {az:g}")
        tc, utc, bt, ubt = _scan(bench, settings, [y_at, 0.0, az, L], 1, xs0, t, repeat_deg)
        peaks.append({"azimuth": az, "lamp": L, "yaw": y, "u_yaw": math.hypot(uy, 0.5 * repeat_deg), "tilt": tc,
                      "u_tilt": utc,
                      "tilt_scan_at": 0.0, "yaw_scan_at": y_at, "lamp_side": side})
        back["yaw"].append((by, uby))
        back["tilt"].append((bt, ubt))
    fit = al.fit_alignment(peaks, lamp_zero_u_deg)
    cov = np.asarray(fit["cov"])
    table = {name: float(v) for name, v in zip(fit["names"], fit["p"])}
    table.update({f"u_{name}": float(math.sqrt(cov[i, i])) for i, name in enumerate(fit["names"])})
    table["cov_deg2"] = np.asarray(fit["cov_fit"])[:4, :4].tolist()     # the peaks' (the lamp zero: its own term)
    for ax, vals in back.items():
        b = np.array([v for v, _ in vals])
        u = np.array([e for _, e in vals])
        wts = 1.0 / u ** 2
        table[f"backlash_{ax}_deg"] = float(np.sum(wts * b) / np.sum(wts))
        table[f"u_backlash_{ax}_deg"] = float(1.0 / math.sqrt(np.sum(wts)))
    table.update({"lamp_zero_u_deg": float(lamp_zero_u_deg), "chi2": fit["chi2"], "dof": fit["dof"],
                  "peaks": [[p["azimuth"], p["yaw"], p["u_yaw"], p["tilt"], p["u_tilt"]] for p in peaks]})
    return table


def linearity(bench, settings: Mapping, stage_deg=(20.0, 0.0, 0.0, 50.0), rungs: int = 8, frames: int = 6) -> dict:
    """Exposure ladder on the reference square up to 80 % of full scale (shot noise and PRNU keep
    its brightest pixels below saturation); the ``[linearity]`` table.

    Each rung's scatter over its ``frames`` frames (monitor-normalised) feeds one smooth noise
    model ``var = c0 y + c1 y^2`` (shot noise; monitor and lamp noise), fitted over the rungs:
    a standard deviation from a handful of frames alone would weight the fit at random.
    """
    t_top = _exposure_for(bench, stage_deg, settings, target=0.8, which=1)
    ts = t_top * np.geomspace(1.0 / 16.0, 1.0, rungs)
    y, var = [], []
    m0 = bench.monitor()
    for t in ts:
        vals = [_squares(bench, stage_deg, settings, float(t))[1] * m0 / bench.monitor() for _ in range(frames)]
        y.append(np.mean(vals))
        var.append(np.var(vals, ddof=1))
    y, var = np.asarray(y), np.asarray(var)
    c, *_ = np.linalg.lstsq(np.stack([y, y * y], -1) / y[:, None], var / y, rcond=None)
    model = np.maximum(np.stack([y, y * y], -1) @ np.maximum(c, 0.0), (1e-6 * y) ** 2)
    fit = al.fit_linearity(ts, y, np.sqrt(model / frames), bench.full_scale)
    return {"gamma": fit["gamma"], "u_gamma": fit["u_gamma"], "chi2": fit["chi2"], "dof": fit["dof"],
            "exposures_s": ts.tolist()}


def reference_factor(bench, settings: Mapping, cal: Mapping) -> dict:
    """The reference's f_r over a 5 x 5 grid relative to a Lambertian; the ``[reference]`` table."""
    gamma = float(cal.get("linearity", {}).get("gamma", 0.0))
    probe = [FACTOR_ANGLES[0], 0.0, 0.0, 2 * FACTOR_ANGLES[0]]
    t0 = _exposure_for(bench, probe, settings, target=0.5, which=1) * math.cos(math.radians(FACTOR_ANGLES[0]))
    cap = settings["capture"]
    ti, to, y, d = [], [], [], []
    for a_i in FACTOR_ANGLES:
        for a_o in FACTOR_ANGLES:
            stage = [a_o, 0.0, 0.0, a_o + a_i]                  # in plane, lamp on the far side
            t = float(np.clip(t0 / math.cos(math.radians(a_i)), cap["exposure_min_s"], cap["exposure_max_s"]))
            bench.move(stage)
            m = bench.monitor()
            vals = [linearise(_squares(bench, stage, settings, t)[1], gamma, bench.full_scale) for _ in range(2)]
            ang = calibrated_angles(cal, stage)[0]
            sig = np.mean(vals) / (t * m * math.cos(math.radians(ang[0])))
            ti.append(ang[0]), to.append(ang[2]), y.append(sig)
            d.append((vals[0] - vals[1]) / np.mean(vals))
    # one relative noise for the grid, pooled over its repeat pairs (JCGM 100 4.2.8; 25 degrees
    # of freedom): each pair's own |difference| (one degree of freedom) as its weight made the
    # fit's weights follow the noise and its covariance of (a, b) too small to cover the fit.
    # Of the mean of two values: s / sqrt(2), s^2 = mean(d^2) / 2 the variance of one value
    s_rel = max(math.sqrt(float(np.mean(np.square(d))) / 2.0), 2e-4)
    u = np.asarray(y) * s_rel / math.sqrt(2.0)
    # the alignment's shared angle errors move every grid point's incidence, and the signal is
    # divided by its cosine: d ln(signal) = -tan(theta_i) d theta_i per input, the same inputs
    # the capture's budget carries, so the factor's response to each goes with them
    stages = np.array([[a_o, 0.0, 0.0, a_o + a_i] for a_i in FACTOR_ANGLES for a_o in FACTOR_ANGLES])
    per_input = angle_uncertainty(cal, stages)["reference_theta_i_per_input"]      # (M, 7) deg / deg
    shifts = -np.tan(np.radians(np.asarray(ti)))[:, None] * np.radians(per_input)
    fit = al.fit_reference_factor(ti, to, y, u, shifts=shifts)
    return {"factor_theta_i": fit["grid_deg"], "factor_theta_o": fit["grid_deg"], "factor": fit["factor"],
            "u_factor": fit["u_factor"], "factor_a": fit["a"], "factor_b": fit["b"], "factor_cov_ab": fit["cov_ab"],
            "factor_ab_per_deg": fit["ab_shifts"], "factor_chi2": fit["chi2"],
            "factor_dof": fit["dof"]}


# ----------------------------------------------------------------------------- the run and its file
def _sim_bench(settings: Mapping, seed: int):
    """The virtual instrument with the glossy artefact in the sample slot (its faces parallel:
    the sample's wedge is switched off for it; every other drawn error is the session's)."""
    import gonio.sim

    errors = settings.get("errors")
    spec = {"preset": errors} if isinstance(errors, str) else dict(errors or {})
    spec["alignment"] = {**dict(spec.get("alignment", {})), "wedge_deg": 0.0}
    s = {**settings, "errors": spec}
    reference = {"model": "diffuse", "params": {"reflectance": settings["reference"]["reflectance"]}}
    try:
        inst = gonio.sim.Instrument(s, sample=GLOSSY_ARTEFACT, reference=reference, seed=seed)
    except (ValueError, KeyError) as exc:
        raise GonioError(f"cannot build the simulated instrument: {exc}") from None
    model = gonio.sim.error_model(errors)
    specs = {"repeat_deg": model.stages.repeat_deg, "wedge_u_deg": model.alignment.wedge_deg,
             "source_half_deg": model.aperture.source_half_deg,
             "detector_half_deg": model.aperture.detector_half_deg, "stray_floor": model.stray.floor,
             "errors": model.to_dict()}
    return SimBench(inst), specs


def calibrate(settings: Mapping, *, seed: int, bench=None, specs: Mapping | None = None,
              lamp_zero_u_deg: float = 0.02, sim: bool | None = None, progress=None) -> dict:
    """Run the three procedures; return the calibration document (tables of plain values).

    ``bench`` None: the simulated instrument built from ``settings`` (its ``[errors]``) and
    ``seed``. ``specs``: data-sheet values the procedures cannot measure (``repeat_deg``,
    ``wedge_u_deg``, ``source_half_deg``, ``detector_half_deg``, ``stray_floor``, ``stray_u_floor``: the
    floor's level, from a dark-sample or beam-dump reading, and its u); with the
    simulator they come from its error model, on hardware from ``[calibration]`` of the settings.
    ``sim``: what the file records (default: ``bench`` is None). ``progress``:
    ``progress(done, total, label)`` before each scan and procedure (None: silent).
    """
    from gonio.bench.session.journal import versions

    t0 = time.perf_counter()
    sim = bench is None if sim is None else bool(sim)
    if bench is None:
        bench, specs = _sim_bench(settings, seed)
        try:
            return calibrate(settings, seed=seed, bench=bench, specs=specs, lamp_zero_u_deg=lamp_zero_u_deg, sim=sim,
                             progress=progress)
        finally:
            bench.inst.release()       # its Mitsuba scene now, not when a cyclic collection finds it
    specs = dict(specs if specs is not None else settings.get("calibration", {}))
    cal = {"calibration": {
        "procedure": (f"specular cross-scans (yaw, tilt; up and down; {SCAN_STEP_DEG} deg steps over "
                      f"+-{SCAN_HALF_DEG} deg) of a glossy artefact ({GLOSSY_ARTEFACT['model']} alpha "
                      f"{GLOSSY_ARTEFACT['params']['alpha']}) at azimuths {list(SCAN_AZIMUTHS)}, lamp "
                      f"{SCAN_LAMP_DEG} deg; exposure ladder on the reference; the reference over a "
                      f"{len(FACTOR_ANGLES)}x{len(FACTOR_ANGLES)} in-plane grid"),
        "seed": int(seed), "sim": sim, "versions": versions()}}
    if "errors" in specs:
        cal["calibration"]["errors"] = specs.pop("errors")
    steps = 3 + 2 * len(SCAN_AZIMUTHS)          # the exposure, the scans, linearity, the reference grid
    say = progress if progress is not None else (lambda done, total, label: None)
    a = align(bench, settings, lamp_zero_u_deg, float(specs.get("repeat_deg", 0.0)),
              progress=lambda done, total, label: say(done, steps, label))
    a["repeat_deg"] = float(specs.get("repeat_deg", 0.0))
    a["wedge_u_deg"] = float(specs.get("wedge_u_deg", 0.0))
    cal["alignment"] = a
    say(steps - 2, steps, "exposure ladder (linearity)")
    cal["linearity"] = linearity(bench, settings)
    say(steps - 1, steps, "reference over its grid")
    cal["reference"] = reference_factor(bench, settings, cal)
    say(steps, steps, "done")
    cal["aperture"] = {"source_half_deg": float(specs.get("source_half_deg", 0.0)),
                       "detector_half_deg": float(specs.get("detector_half_deg", 0.0)),
                       "profile": "uniform disk"}
    # the floor's level and its u (a dark-sample reading or the data sheet): the capture removes
    # it from both squares (gonio/bench/session/run.py, stray_corrected) and the budget carries u_floor;
    # the simulator's floor is its setting, not drawn, so its u is 0
    cal["stray"] = {"floor": float(specs.get("stray_floor", 0.0)), "u_floor": float(specs.get("stray_u_floor", 0.0))}
    cal["calibration"]["wall_s"] = round(time.perf_counter() - t0, 3)
    return cal


def write_calibration(path: Path, cal: Mapping) -> Path:
    """Write the calibration document as TOML (atomically; read back before it is renamed)."""
    from gonio.bench.session.journal import session_text

    text = "# gonio calibration file (gonio calibrate): values, standard uncertainties (u_*), procedure, seed\n"
    text += session_text(cal)
    with atomic_open(path, "w") as fh:
        fh.write(text)
    return Path(path)


_CAL_TABLES = ("alignment", "linearity", "reference", "aperture", "stray")


def read_calibration(path: Path) -> dict:
    """Read a calibration file; GonioError (one line) if it is not one."""
    from gonio.core.tomlfile import read_toml

    try:
        doc = read_toml(path, "calibration file")
    except GonioError as exc:
        if not Path(path).is_file():
            raise
        raise GonioError(f"{path} is not a calibration TOML file ({' '.join(str(exc).split())[:160]}); "
                         "give the file `gonio calibrate` wrote") from None
    if not isinstance(doc.get("calibration"), dict) or not isinstance(doc.get("alignment"), dict):
        raise GonioError(f"{path} has no [calibration] and [alignment] tables; give the file `gonio calibrate` wrote")
    for key in ("yaw_zero_deg", "tilt_zero_deg", "holder_tilt_x_deg", "holder_tilt_y_deg"):
        v = doc["alignment"].get(key)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or abs(v) > 10:
            raise GonioError(f"{path}: [alignment] {key} is missing or not a finite angle within 10 deg")
    return doc


def merge_calibration(settings: Mapping, cal: Mapping) -> dict:
    """Settings with the calibration's tables merged in (the reference's factor table replaces
    the settings'; the certificate's reflectance and rel_std stay)."""
    out = {k: (dict(v) if isinstance(v, Mapping) else v) for k, v in settings.items()}
    for key in _CAL_TABLES:
        if key in cal:
            out[key] = {**dict(out.get(key, {})), **dict(cal[key])}
    out["calibration"] = {**dict(out.get("calibration", {})),
                          **{k: v for k, v in cal["calibration"].items() if k != "versions"}}
    return out


def run_calibration(settings: Mapping, *, sim: bool, seed: int, port=None, meter_port=None, camera=None,
                    progress=None) -> dict:
    """The three procedures through the production drivers; returns the calibration document.

    ``sim``: against the simulated instrument of ``settings`` (its ``[errors]``) and ``seed`` over
    its ``sim://`` ports (the bytes a real bench gets); otherwise on hardware at ``port``,
    ``meter_port`` and ``camera`` (a URL or a camera object), with the glossy artefact mounted and
    the data-sheet values in ``[calibration]``. Nothing is written but scratch RAW files.
    ``progress``: as :func:`calibrate`'s.
    """
    import tempfile

    from gonio.bench.drivers.rig import Bench

    inst = None
    if sim:
        physics, specs = _sim_bench(settings, seed)
        inst = physics.inst.register(f"gonio-calibrate-{id(physics):x}")
        urls, sleep = (inst.url("zaber"), inst.url("meter"), inst.url("camera")), inst.clock.advance
    else:
        specs, urls, sleep = None, (port, meter_port, camera), time.sleep
    try:
        rig = Bench(settings, *urls, sleep=sleep)
        try:
            with tempfile.TemporaryDirectory(prefix="gonio-calibrate-") as scratch:
                return calibrate(settings, seed=seed, bench=DriverBench(rig, settings, Path(scratch)), specs=specs,
                                 sim=sim, progress=progress)
        finally:
            try:
                rig.led.off()
            finally:
                rig.close()
    finally:
        if inst is not None:
            inst.unregister()


def summary(cal: Mapping) -> str:
    """One line: the zero offsets, the holder tilt and gamma with their standard uncertainties."""
    a = cal["alignment"]
    return (f"yaw zero {a['yaw_zero_deg']:+.4f} +- {a['u_yaw_zero_deg']:.4f} deg, tilt zero "
            f"{a['tilt_zero_deg']:+.4f} +- {a['u_tilt_zero_deg']:.4f} deg, holder tilt ({a['holder_tilt_x_deg']:+.4f}, "
            f"{a['holder_tilt_y_deg']:+.4f}) +- ({a['u_holder_tilt_x_deg']:.4f}, {a['u_holder_tilt_y_deg']:.4f}) deg; "
            f"gamma {cal['linearity']['gamma']:.5f} +- {cal['linearity']['u_gamma']:.5f}")


def calibrate_cli(out: Path, *, sim: bool, settings, errors, seed: int, port=None, meter_port=None,
                  camera=None, progress=None, say=print) -> int:
    """``gonio calibrate``: refuse bad input in one line before anything is written.

    ``--sim`` runs the procedures through the production drivers against the simulator's
    ``sim://`` ports (the bytes a real bench gets); ``--port``/``--meter-port``/``--camera`` run
    them on hardware, with the glossy artefact mounted in the sample slot and the data-sheet
    values (``repeat_deg``, ``wedge_u_deg``, ``source_half_deg``, ``detector_half_deg``,
    ``stray_floor``) in the settings' ``[calibration]`` table. ``camera``: a URL or a camera
    object (``session_runner._camera`` builds one from the command line's spec). ``progress``:
    as :func:`calibrate`'s; ``say``: prints the result's line (the command line's wraps it on a
    terminal).
    """
    from gonio.core.preflight import check_output_file
    from gonio.bench.settings import load_settings

    if sim == bool(port):
        raise GonioError("calibrate needs --sim (the simulated instrument) or --port, --meter-port and --camera")
    if not sim and (not meter_port or not camera):
        raise GonioError("a hardware calibration needs --port, --meter-port and --camera")
    if not sim and errors is not None:
        raise GonioError("--errors sets the simulated instrument's errors; use it with --sim")
    s = settings if isinstance(settings, dict) else load_settings(settings)
    if errors is not None:
        old = s.get("errors")
        s["errors"] = {**({} if not isinstance(old, dict) else old), "preset": errors}
    check_output_file(out, "calibration file")
    cal = run_calibration(s, sim=sim, seed=seed, port=port, meter_port=meter_port, camera=camera, progress=progress)
    write_calibration(out, cal)
    say(f"wrote {out}: {summary(cal)}; {cal['calibration']['wall_s']:.1f} s")
    return 0


def with_errors_and_calibration(settings_d: dict, *, sim: bool, seed: int, errors, calibration) -> dict:
    """``--errors PRESET`` into ``[errors]`` (simulator only), ``--calibration CAL.toml`` merged
    (gonio/bench/calibrate); a calibration of the simulator made for another seed or error model is
    refused (the virtual instrument's errors come from them)."""
    if errors is not None:
        if not sim:
            raise GonioError("--errors sets the simulated instrument's errors; use it with --sim")
        old = settings_d.get("errors")
        settings_d = {**settings_d, "errors": {**(old if isinstance(old, dict) else {}), "preset": errors}}
    if sim and settings_d.get("errors") is not None:
        import gonio.sim

        try:
            gonio.sim.error_model(settings_d["errors"])
        except ValueError as exc:
            raise GonioError(f"settings: {exc}") from None
    if calibration is None:
        return settings_d
    cal = read_calibration(Path(calibration))
    made = cal["calibration"]
    if bool(made.get("sim")) != bool(sim):
        raise GonioError(f"{calibration} calibrated {'the simulated' if made.get('sim') else 'a real'} instrument; "
                         f"use it with {'--sim' if made.get('sim') else 'the hardware ports'}")
    if sim:
        import gonio.sim

        if int(made.get("seed", -1)) != int(seed):
            raise GonioError(f"{calibration} calibrated the simulated instrument of seed {made.get('seed')}; capture "
                             f"with --seed {made.get('seed')} (its errors come from the seed) or calibrate again")
        if made.get("errors") != gonio.sim.error_model(settings_d.get("errors")).to_dict():
            raise GonioError(f"{calibration} calibrated another error model ([calibration.errors] preset "
                             f"{(made.get('errors') or {}).get('preset')!r}); give the same --errors / [errors]")
    return merge_calibration(settings_d, cal)
