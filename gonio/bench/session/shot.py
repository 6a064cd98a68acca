"""``gonio shot``: one bracketed exposure at a pose (see `operator`).

The bracket is chosen as a capture chooses it for one point: a probe at ``[capture] probe_s``
(down the ladder while the regions saturate), then `choose_bracket`. The regions come from
the holder's markers where it has them (`_markers.find_regions`), else from the geometry.
After the bracket the LED is switched off and a dark frame is taken per exposure time the merge
uses (a saturated probe is kept, marked unmerged, and gets none); the LED stays off at the end
(and after any failure). Files, in a new folder: ``shot_<us>us.dng``,
``dark_<us>us.dng``, ``preview.png`` (the HDR merge, tone-mapped, sample region outlined in
green, reference in blue) and ``shot.json``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
from PIL import Image

from gonio.core.atomic import atomic_open

from gonio.bench.plan import markers as _markers
from gonio.bench.plan import kinematics
from gonio.core.files import atomic_write_text, create_exclusive
from gonio.bench.measure.hdr import Exposure, NoiseModel, choose_bracket, ladder, merge
from gonio.bench.measure.point import ReferenceModel, check_sensor, region_stats
from gonio.bench.session.operate import move, open_camera, require_homed, where
from gonio.bench.settings import AXES
from gonio.bench.drivers import Goniometer, LedSource, PowerMeter, ZaberChain, decode_raw
from gonio.bench.drivers import identify as _identify
from gonio.core.errors import GonioError

__all__ = ["take_shot", "write_preview"]


def _green(frame_signal: np.ndarray) -> np.ndarray:
    return np.asarray(frame_signal[1], float)


def _expose(camera, out: Path, name: str, seconds: float):
    path = out / name
    if not create_exclusive(path):
        raise GonioError(f"{path} appeared while the shot was taken; give a new --out folder")
    digest = camera.expose(seconds, path)
    return path, digest


def write_preview(path: Path, radiance: np.ndarray, sample: np.ndarray, reference: np.ndarray) -> None:
    """The HDR radiance (3, h, w) as an 8-bit sRGB PNG, the reference's 99th percentile at 0.9,
    the regions' outlines drawn (sample green, reference blue); written atomically."""
    rad = np.nan_to_num(np.moveaxis(np.asarray(radiance, float), 0, -1), nan=0.0, posinf=0.0, neginf=0.0)
    ref = rad[reference] if reference.any() else rad.reshape(-1, 3)
    scale = float(np.percentile(ref, 99)) if ref.size else 0.0
    x = np.clip(rad * (0.9 / scale if scale > 0 else 0.0), 0.0, 1.0)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    img = (srgb * 255 + 0.5).astype(np.uint8)
    for mask, colour in ((sample, (0, 255, 0)), (reference, (0, 96, 255))):
        m = np.asarray(mask, bool)
        inner = m.copy()
        inner[1:, :] &= m[:-1, :]
        inner[:-1, :] &= m[1:, :]
        inner[:, 1:] &= m[:, :-1]
        inner[:, :-1] &= m[:, 1:]
        img[m & ~inner] = colour
    with atomic_open(path, "wb") as fh:              # the one atomic writer
        Image.fromarray(img).save(fh, format="PNG")


def take_shot(args, settings, stage, out: Path) -> str:
    """Move (if ``stage`` is given), bracket, dark frames, merge, write; return the summary line."""
    flux = args.flux if args.flux is not None else float(settings.get("lamp", {}).get("flux", 1.0))
    chain = meter = camera = led = None
    try:
        chain = ZaberChain(args.port, args.baud, 1.0)
        gonio = Goniometer(chain, settings, poll_interval_s=0.05)
        gonio.connect()
        led = LedSource(chain, int(settings.get("lamp", {}).get("device", 2)))
        meter = PowerMeter.from_settings(args.meter_port, settings, args.baud, 1.0)
        camera = open_camera(args.camera)
        check_sensor(camera, settings)
        if stage is not None:
            move(gonio, stage, args.port)
        else:
            require_homed(gonio, args.port)          # the pose (and the regions) need a reference
        pos = gonio.positions()
        stage = np.array([pos[n] for n in AXES])
        m = settings.get("meter", {})
        meter.configure(float(m.get("wavelength_nm", 550)), int(m.get("averaging", 10)))
        out.mkdir(parents=True, exist_ok=True)
        led.set_flux(flux)
        led.on()
        taken, used = _bracket(camera, meter, out, stage, settings)
        led.off()
        darks = {}
        for tb in used:                            # a dark per exposure the merge uses, not per probe
            path, digest = _expose(camera, out, f"dark_{tb * 1e6:010.0f}us.dng", tb)
            darks[tb] = {"seconds": tb, "file": path.name, "sha256": digest, "frame": decode_raw(path)}
        hdr = merge([Exposure(tb, taken[tb]["power"], taken[tb]["frame"], darks[tb]["frame"]) for tb in used],
                    _noise(settings), float(settings["capture"]["saturation_fraction"]))
        regions = _markers.find_regions(np.nan_to_num(hdr.radiance[1]), stage, settings)
        stats = {"sample": region_stats(hdr, regions.sample), "reference": region_stats(hdr, regions.reference)}
        angles = kinematics.forward_angles(stage)
        with np.errstate(invalid="ignore", divide="ignore"):
            f_r = (stats["sample"]["mean"] / stats["reference"]["mean"]
                   * ReferenceModel(settings["reference"]).f_r(angles[0], angles[2]))
        write_preview(out / "preview.png", hdr.radiance, regions.sample, regions.reference)
        ident = {"zaber": [chain.identify(d) for d in sorted({a.device for a in gonio.axes.values()} | {led.device})],
                 "meter": _identify.clean(meter.identify()), "camera": _identify.camera_text(camera)}
        doc = _shot_doc(stage, angles, flux, taken, used, darks, regions, stats, f_r, ident)
        atomic_write_text(out / "shot.json", json.dumps(doc, indent=1, allow_nan=False) + "\n")
        where_ = where(gonio)
    finally:
        if led is not None:
            try:
                led.off()
            except Exception:            # noqa: BLE001 - the port may be the reason we are here
                pass
        for dev in (camera, meter, chain):
            if dev is not None:
                try:
                    dev.close()
                except Exception:        # noqa: BLE001
                    pass
    src = "markers" if regions.source == "markers" else f"geometry ({regions.why})"
    unused = sorted(set(taken) - set(used))
    probes = (f" (and {len(unused)} saturated probe{'s' if len(unused) != 1 else ''} "
              f"{', '.join(f'{x:g}' for x in unused)} s, not merged)" if unused else "")
    return (f"shot: {len(used)} exposure{'s' if len(used) != 1 else ''} {', '.join(f'{x:g}' for x in used)} s"
            f"{probes} and {len(darks)} dark{'s' if len(darks) != 1 else ''} in {out}; "
            f"regions from {src}; f_r ~ " + " ".join(f"{v:.4g}" for v in f_r) + f" sr^-1 at {where_}")


def _noise(settings) -> NoiseModel:
    cam_s = settings["camera"]
    return NoiseModel(float(cam_s.get("gain_e_per_dn", 2.0)), float(cam_s.get("read_noise_e", 3.0)))


def _bracket(camera, meter, out: Path, stage, settings) -> tuple[dict[float, dict], list[float]]:
    """The exposures of the shot, LED on: a probe at ``[capture] probe_s``, down the ladder while
    the regions saturate, then the rungs `choose_bracket` picks. Returns every exposure taken
    (by its seconds) and the ones the merge uses."""
    cap = settings["capture"]
    sat = float(cap["saturation_fraction"])
    rungs = ladder(float(cap["exposure_min_s"]), float(cap["exposure_max_s"]))
    taken: dict[float, dict] = {}

    def shoot(t: float) -> dict:
        path, digest = _expose(camera, out, f"shot_{t * 1e6:010.0f}us.dng", t)
        taken[t] = {"seconds": t, "file": path.name, "sha256": digest, "power": meter.power(),
                    "frame": decode_raw(path)}
        return taken[t]

    t = float(rungs[np.argmin(np.abs(np.log(rungs / float(cap["probe_s"]))))])
    while True:                               # down the ladder until the regions are unsaturated
        f = shoot(t)["frame"]
        regions = _markers.find_regions(_green(f.signal), stage, settings)
        both = regions.sample | regions.reference
        if not both.any():
            raise GonioError("neither the sample nor the reference square is in view at this pose; "
                             "give another --stage/--angles")
        peak = float(f.peak[:, both].max())
        if peak < sat * f.full_scale or t <= rungs[0]:
            break
        t = float(rungs[max(0, int(np.searchsorted(rungs, t)) - 3)])
    low = float(max(f.signal[:, both].min(), 1.0))
    bracket = choose_bracket(rungs, t, peak, low, f.full_scale, _noise(settings), sat, float(cap["noise_floor_snr"]))
    for tb in bracket:
        if tb not in taken:
            shoot(tb)
    return taken, sorted(set(bracket) | {t})


def _shot_doc(stage, angles, flux, taken, used, darks, regions, stats, f_r, ident) -> dict:
    """``shot.json``: the pose, the files and their checksums, the regions, the means, f_r."""
    pose = regions.pose
    return {
        "stage_deg": dict(zip(AXES, map(float, stage))),
        "angles_deg": dict(zip(("theta_i", "phi_i", "theta_o", "phi_o"), map(float, angles))),
        "flux": flux,
        "exposures": [{**{k: v for k, v in taken[tb].items() if k != "frame"}, "merged": tb in used}
                      for tb in sorted(taken)],
        "bracket": used,
        "darks": [{k: v for k, v in darks[tb].items() if k != "frame"} for tb in sorted(darks)],
        "regions": {"source": regions.source, "why": regions.why,
                    "pixels": {"sample": int(regions.sample.sum()), "reference": int(regions.reference.sum())},
                    "holder_pose": None if pose is None else {
                        "shift": [float(v) for v in pose.shift], "angle_deg": float(pose.angle_deg),
                        "rms": float(pose.rms), "marker_ids": list(pose.ids)}},
        "mean": {k: [_num(v) for v in stats[k]["mean"]] for k in stats},
        "f_r_estimate": [_num(v) for v in f_r],
        "identification": ident,
    }


def _num(v: float):
    return float(v) if math.isfinite(v) else None
