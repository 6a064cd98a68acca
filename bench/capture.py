"""The capture loop: a session that survives being killed.

`capture` creates a session folder and measures a plan; `resume` finishes one.

Once per session, before the first point (each set journalled, so a resume reuses it): dark
frames with the lamp off for every rung of the exposure ladder (the bracketing may use any of
them), and, where the camera has a flat-field source, ``[capture] flat_frames`` flat frames
whose mean gives each pixel's relative gain (the sensor's response non-uniformity).

Per point: move (in the ordered plan, the shortest way, soft limits checked, the position
verified), wait for IDLE, settle, expose with automatic bracketing (a probe, then the rungs
that keep the brightest region pixel below saturation in the shortest exposure and bring the
darkest to ``noise_floor_snr`` in the longest), read the monitor at each exposure, merge the
bracket into HDR radiance (dark frames subtracted, saturated values excluded, flat-fielded),
average the sample and reference regions (the super-pixels wholly inside each square, found
from the holder's markers in the probe where the settings declare them, else from the
geometry), and convert to f_r with the reference:

    f_r = (S_sample / S_ref) * rho_ref / pi

with a 1-sigma from both regions' standard errors of the mean (shot, read and residual
fixed-pattern noise; the monitor cancels in the ratio). The reference certificate's own
uncertainty is a fully correlated scale error, stored apart (``scale_rel_std``). A point's
journal row is committed only when everything about it succeeded; reciprocal pairs are
compared as they arrive. Once a point's bracket is taken the stages start towards the next
point, and a worker thread decodes, merges and reduces the point (inside the regions' bounding
box only) while they move; its row is committed before the next bracket starts.

Operating behaviour: a rich progress bar (points, ETA, latest f_r); Ctrl-C once finishes the
current point and stops resumably, twice stops the stages and exits; the run pauses itself
(a suspender) while the lamp is off its session-start level by more than
``[lamp] drift_tolerance``, changes within a bracket by more than ``bracket_tolerance``, or
the meter is silent, and stops resumably with a one-line reason when that lasts longer than
``suspend_timeout_s``. A move that falls short (a limit switch) is retried once; faults
(a stall) stop the run resumably, and a resume clears them and re-homes where the controller
lost its reference.
"""

from __future__ import annotations

import json
import math
import sqlite3
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from ._files import TMP_PREFIX, create_exclusive, remove_orphans
from . import _integrity, kinematics
from ._hdr import Exposure, NoiseModel, choose_bracket, flat_gain, ladder, merge
from ._markers import find_regions, layout_of, posed_masks
from ._journal import (JOURNAL_FILE, LOCK_FILE, RAW_DIR, SESSION_FILE, Journal, SessionLock,
                       read_session, session_text, versions, write_session)
from ._measure import ProgressBar, ReferenceModel, check_sensor, raw_estimate, region_stats
from ._preflight import _MARGIN as MARGIN, MiB, check_free_space, check_output_dir, disk_full, mount_of, oserror_line
from ._ordering import order_moves
from ._signals import Interrupts, StopNow
from ._settings import AXES, default_settings, merge_settings, validate_settings
from .drivers import (Goniometer, LedSource, MoveError, PowerMeter, RawFrame, SimCamera, ZaberChain, decode_raw,
                      emergency_stop, read_verified)
from .drivers.identify import record as record_identification
from .errors import CommunicationError, DeviceError, GonioError, SessionError
from .plans import Plan, plan_from_dict, require_reachable

__all__ = ["capture", "resume", "CaptureSummary", "CaptureInterrupted", "StopNow", "Bench", "estop"]


class CaptureInterrupted(GonioError):
    """Ctrl-C pressed twice, or SIGTERM / SIGHUP: the stages were stopped; the session is resumable."""


class DiskFull(SessionError):
    """The disk filled during a capture (a RAW file, the journal, a session file): the stages were
    stopped, the LED switched off; the session is consistent and resumable once space is freed."""


@dataclass
class CaptureSummary:
    """What a capture (or resume) did.

    Attributes
    ----------
    session_dir : Path
    n_points : int
        Points in the plan.
    n_done : int
        Points journalled now (all runs).
    n_new : int
        Points measured by this call.
    complete : bool
        Every point is journalled.
    stopped : str
        Why the run stopped early ("" if it did not).
    reciprocity : list of dict
        Per reciprocal pair measured: ``i``, ``j``, ``rel`` (relative difference per channel),
        ``z`` (difference over its 1-sigma per channel).
    move_naive_s, move_ordered_s, move_bound_s : float
        Planned stage travel time: plan order, ordered, lower bound (s).
    wall_s : float
        Wall time of this call, s.
    notes : list of str
        One line per recovery a resume made (journal rebuilt, points measured again).
    """

    session_dir: Path
    n_points: int
    n_done: int
    n_new: int
    complete: bool
    stopped: str = ""
    reciprocity: list = field(default_factory=list)
    move_naive_s: float = 0.0
    move_ordered_s: float = 0.0
    move_bound_s: float = 0.0
    wall_s: float = 0.0
    notes: list = field(default_factory=list)

    @property
    def per_point_s(self) -> float:
        """Wall time per point measured by this call, s (NaN if none)."""
        return self.wall_s / self.n_new if self.n_new else math.nan

    @property
    def reciprocity_error(self) -> float:
        """Median over pairs and channels of |f_a - f_b| / mean(f_a, f_b) (NaN without pairs)."""
        if not self.reciprocity:
            return math.nan
        return float(np.median(np.abs([r["rel"] for r in self.reciprocity])))


def _open_camera(camera, timeout: float):
    if isinstance(camera, str):
        return SimCamera(camera, timeout=timeout)
    if not hasattr(camera, "expose"):
        raise GonioError(f"camera {camera!r} is neither a URL nor a camera object; give a camera URL")
    return camera


class Bench:
    """The instrument's drivers, opened together (closed together on failure).

    Parameters
    ----------
    settings : dict
    zaber_url, meter_url : str
        Serial URLs of the Zaber chain and of the power meter.
    camera : str or camera object
        A camera URL (`SimCamera`) or an object with ``expose(seconds, path)``.
    sleep : callable
        Called with seconds to wait (settling, polling); ``time.sleep`` on hardware; a
        simulated clock's ``advance`` in tests.
    """

    def __init__(self, settings: Mapping, zaber_url: str, meter_url: str, camera, *,
                 sleep: Callable[[float], None] = time.sleep, poll_interval_s: float = 0.05,
                 timeout: float = 1.0, baudrate: int = 115200, on_warning=None):
        self.settings = settings
        self._sleep = sleep
        self.checkpoint: Callable[[], None] = lambda: None    # a run's safe point: may raise StopNow
        self.chain = self.meter = self.camera = None
        try:
            self.chain = ZaberChain(zaber_url, baudrate, timeout, on_warning=on_warning)
            self.gonio = Goniometer(self.chain, settings, poll_interval_s=poll_interval_s, sleep=self.sleep)
            self.led = LedSource(self.chain, int(settings.get("lamp", {}).get("device", 2)))
            self.meter = PowerMeter(meter_url, baudrate, timeout)
            self.camera = _open_camera(camera, 30.0)
        except BaseException:
            self.close()
            raise

    def sleep(self, seconds: float) -> None:
        """Wait (a stage poll, a settle, a pause): a safe point to stop at."""
        self.checkpoint()
        self._sleep(seconds)
        self.checkpoint()

    def close(self) -> None:
        for dev in (self.camera, self.meter, self.chain):
            if dev is not None:
                try:
                    dev.close()
                except Exception:
                    pass


estop = emergency_stop        # ``gonio estop --port``: /0 0 estop to every device at once


# -- the measurement of one point ----------------------------------------------------------------

def roi_masks_fast(stage, settings: Mapping) -> tuple[np.ndarray, np.ndarray]:
    """`kinematics.roi_masks`, exactly, at about `_markers.posed_masks`' cost.

    `posed_masks` finds the same regions from the map's affinity but may decide a super-pixel
    whose corner lies on a square's edge (a tie, common where the pixel grid lines up with the
    squares) the other way at rounding level. So: the super-pixels that `posed_masks` puts
    inside with a margin 1e-3 pixel wider are inside, those it leaves out with one 1e-3 pixel
    narrower are out, and the few in between are decided by `roi_masks`' own corner test.
    """
    margin = float(settings.get("capture", {}).get("roi_margin_px", 1.0))
    hold, s = settings["holder"], float(settings["camera"]["pixel_size"])
    half, off = hold["sample_half"] - margin * s, hold["offset"]
    delta = 1e-3
    inner = posed_masks(stage, settings, None, margin_px=margin + delta)
    outer = posed_masks(stage, settings, None, margin_px=margin - delta)
    out = []
    for sure, maybe, cx in zip(inner, outer, (-off, off)):
        i, j = np.nonzero(maybe & ~sure)
        if len(i):
            xy = np.stack([kinematics.image_to_local(stage, 2 * i + dr, 2 * j + dc, settings)
                           for dr in (-0.5, 1.5) for dc in (-0.5, 1.5)], 0)
            ok = np.all((np.abs(xy[..., 0] - cx) <= half) & (np.abs(xy[..., 1]) <= half), axis=0)
            sure = sure.copy()
            sure[i[ok], j[ok]] = True
        out.append(sure)
    return out[0], out[1]


def _runs(mask: np.ndarray) -> np.ndarray:
    """Where the runs of True in ``mask`` (read row by row) start and end, alternately."""
    edges = np.flatnonzero(np.diff(np.concatenate(([0], mask.ravel().view(np.int8), [0]))))
    return edges[:-1] if len(edges) and edges[-1] == mask.size else edges


def _extreme(ufunc, planes: np.ndarray, runs: np.ndarray) -> float:
    """``ufunc`` (np.maximum, np.minimum) over the values of every plane inside a mask given by its
    `_runs`: the same value as ``planes[:, mask].max()``, without copying the regions out."""
    if not len(runs):
        raise ValueError("no value in the regions")
    flat = planes.reshape(planes.shape[0], -1)
    return float(ufunc.reduce(ufunc.reduceat(flat, runs, axis=1)[:, 0::2], axis=None))


class _Suspended(Exception):
    """The lamp or the meter is not fit to measure; the point must wait and be measured again."""


class _Session:
    """One run over a session folder (shared by `capture` and `resume`)."""

    MAX_ATTEMPTS = 5        # measurements of one point interrupted by the lamp before the run stops

    def __init__(self, folder: Path, doc: Mapping, bench: Bench, journal: Journal, progress: bool,
                 stop: Callable[[], bool]):
        self.folder = folder
        self.doc = doc
        self.settings = doc["settings"]
        self.plan = plan_from_dict(doc["plan"], source=doc["plan"].get("source", ""))
        self.order = np.asarray(doc["order"]["order"], int)
        self.stage = np.asarray(doc["order"]["stage_deg"], float)
        self.bench = bench
        self.journal = journal
        self.progress = progress
        self.stop = stop
        cam, cap = self.settings["camera"], self.settings["capture"]
        self.noise = NoiseModel(float(cam.get("gain_e_per_dn", 2.0)), float(cam.get("read_noise_e", 3.0)))
        self.sat = float(cap["saturation_fraction"])
        self.rungs = ladder(float(cap["exposure_min_s"]), float(cap["exposure_max_s"]))
        self.probe = float(self.rungs[np.argmin(np.abs(np.log(self.rungs / float(cap["probe_s"]))))])
        self.snr = float(cap["noise_floor_snr"])
        self.reference = ReferenceModel(self.settings["reference"])
        self.darks: dict[float, RawFrame] = {}
        self.gain: np.ndarray | None = None          # flat-field relative gain (3, h, w), None if no flat
        lamp = self.settings.get("lamp", {})
        self.drift_tol = float(lamp.get("drift_tolerance", 0.2))
        self.bracket_tol = float(lamp.get("bracket_tolerance", 0.02))
        self.suspend_poll = float(lamp.get("suspend_poll_s", 5.0))
        self.suspend_timeout = float(lamp.get("suspend_timeout_s", 120.0))
        self.p_ref = None
        self.results: dict[int, tuple[np.ndarray, np.ndarray]] = {
            r["idx"]: (np.asarray(r["brdf"]), np.asarray(r["brdf_std"])) for r in journal.points()}
        self.reciprocity: list[dict] = []
        self.reserved = journal.reserved()
        self._masks_of: dict[tuple, tuple] = {}      # per pose: the regions (the plan revisits none, a retry does)
        self.layout = layout_of(self.settings)       # the holder's markers, None where it has none

    def _fresh(self, name: str) -> str:
        """A RAW file name (``raw/NAME``) never used in this session, reserved in the journal and
        created empty with O_EXCL before the camera writes it (its rename replaces the placeholder):
        an existing RAW file is never overwritten, and every file in raw/ is one the journal names."""
        stem, dot, ext = name.rpartition(".")
        k = 0
        while True:
            file = f"{RAW_DIR}/{name}" if k == 0 else f"{RAW_DIR}/{stem}_{k}{dot}{ext}"
            k += 1
            if file in self.reserved or (self.folder / file).exists():
                continue
            self.journal.reserve(file)
            self.reserved.add(file)
            if create_exclusive(self.folder / file):
                return file

    # -- instrument preparation ----------------------------------------------------------
    def prepare(self) -> None:
        """Check flags and positions, home if the reference is lost, take missing darks and
        flats, lamp on."""
        b = self.bench
        check_sensor(b.camera, self.settings)
        flags = b.gonio.connect(clear_faults=True)
        if any(f in ("WR", "WH") for f in flags):
            self.journal.event("home", f"stages lost their reference ({' '.join(flags)}): homing")
            b.gonio.home()
        b.meter.identify()
        record_identification(b, self.journal)     # every device's *IDN?, Zaber id, serial, firmware
        m = self.settings.get("meter", {})
        b.meter.configure(float(m.get("wavelength_nm", 550)), int(m.get("averaging", 10)))
        self._take_darks()
        self._take_flats()
        cm = next(iter(self.darks.values())).rgb_cam
        if cm is not None and self.journal.first_event("rgb_cam") is None:
            self.journal.event("rgb_cam", json.dumps(cm.tolist()))
        b.led.set_flux(float(self.settings.get("lamp", {}).get("flux", 1.0)))
        b.led.on()
        self.p_ref = self._p_ref()

    def _p_ref(self) -> float:
        known = self.journal.first_event("p_ref")       # a resumed session keeps its reference
        if known is not None:
            return float(known)
        p = self.bench.meter.power()
        if not p > 0:
            raise DeviceError(f"the monitor reads {p:g} W with the lamp on; check the LED and the meter, "
                              "then resume the session")
        self.journal.event("p_ref", repr(p))
        return p

    def _load(self, file: str, digest: str, peak: bool = True) -> RawFrame:
        """A calibration frame, its checksum checked and decoded from one read."""
        path = self.folder / file
        try:
            data, got = read_verified(path) if path.is_file() else (b"", "")
        except OSError:
            data, got = b"", ""
        if got != digest:
            raise SessionError(f"calibration frame {file} is missing or corrupt; the session folder is damaged")
        return decode_raw(path, data=data, peak=peak)

    def _take_darks(self) -> None:
        """Dark frames (lamp off) for every rung of the exposure ladder, journalled once per session."""
        have = {v[0]: v for v in self.journal.frames("dark").values()}
        if any(float(t) not in have for t in self.rungs):
            self.bench.led.off()
        for t in map(float, self.rungs):
            if t in have:
                _, file, digest = have[t]
            else:
                self.bench.checkpoint()
                file = self._fresh(f"dark_{t * 1e6:010.0f}us.dng")
                digest = self.bench.camera.expose(t, self.folder / file)
                self.journal.record_frame(f"dark:{t!r}", "dark", t, file, digest)
            self.darks[t] = self._load(file, digest, peak=False)     # signal only: what a dark is used for

    def _take_flats(self) -> None:
        """Flat-field frames for the PRNU correction (cameras with a ``flat`` source only).

        The exposure is the longest rung that keeps the flat below 60 % of full scale, found
        from probe frames; ``[capture] flat_frames`` frames are averaged. An incomplete set
        (a crash while taking it) is taken again whole. Whether a session has a flat field is
        decided once, when it starts.
        """
        cam = self.bench.camera
        n = int(self.settings["capture"].get("flat_frames", 16))
        if self.journal.first_event("no_flat") is not None:
            return                               # decided when the session started: keep it so
        have = self.journal.frames("flat")
        if len(have) != n or n < 1:              # none yet, or a crash while taking them (or none wanted)
            self.journal.forget_frames("flat")
            if not hasattr(cam, "flat") or n < 1:
                self.journal.event("no_flat", "no flat-field source: pixel response non-uniformity not corrected")
                return
            t = self._flat_exposure(cam)
            for k in range(n):
                self.bench.checkpoint()
                file = self._fresh(f"flat_{k:03d}.dng")
                self.journal.record_frame(f"flat:{k:03d}", "flat", t, file, cam.flat(t, self.folder / file))
            have = self.journal.frames("flat")
        t = next(iter(have.values()))[0]
        self.gain = flat_gain((self._load(f, d, peak=False) for _, f, d in have.values()), self.darks[t])

    def _flat_exposure(self, cam) -> float:
        probe = self.folder / RAW_DIR / f"{TMP_PREFIX}flat-probe.dng"
        t = self.probe
        try:
            for _ in range(len(self.rungs)):
                cam.flat(t, probe)
                f = decode_raw(probe)
                level = float(np.percentile(f.peak - self.darks[t].signal, 99.9)) / f.full_scale
                i = int(np.searchsorted(self.rungs, t))
                if level >= self.sat and i > 0:
                    t = float(self.rungs[max(0, i - 3)])
                    continue
                fits = self.rungs[self.rungs * max(level, 1e-6) / t <= 0.6]
                return float(fits[-1]) if len(fits) else float(self.rungs[0])
            return t
        finally:
            probe.unlink(missing_ok=True)

    # -- suspenders -----------------------------------------------------------------------
    def _power(self) -> float:
        """One monitor reading; `_Suspended` if the meter is silent or the lamp is off its level."""
        try:
            p = self.bench.meter.power()
        except CommunicationError as exc:
            raise _Suspended(f"the power meter is silent ({exc})") from None
        if not abs(p / self.p_ref - 1.0) <= self.drift_tol:
            raise _Suspended(f"the lamp monitor reads {p:.4g} W, {100 * (p / self.p_ref - 1):+.0f} % from its "
                             f"session-start {self.p_ref:.4g} W (tolerance {100 * self.drift_tol:g} %)")
        return p

    def _wait_until_fit(self, why: str) -> None:
        """Pause: poll the monitor until it is fit again; `GonioError` after the timeout."""
        self.journal.event("pause", why)
        n = max(1, math.ceil(self.suspend_timeout / self.suspend_poll))
        for _ in range(n):
            self.bench.sleep(self.suspend_poll)
            try:
                self._power()
            except _Suspended as exc:
                why = str(exc)
                continue
            self.journal.event("resume", "monitor back within tolerance")
            return
        raise DeviceError(f"paused {self.suspend_timeout:g} s and {why}; fix the lamp or the meter, "
                          "then resume the session")

    # -- one point -----------------------------------------------------------------------
    def _masks(self, stage: np.ndarray) -> tuple[np.ndarray, np.ndarray, tuple[int, int, int, int], np.ndarray]:
        """The sample and reference regions at ``stage`` (`roi_masks_fast`: the masks of
        `kinematics.roi_masks`, mostly from the map's affinity) cropped to their bounding box, the box
        (super-pixel rows and columns) that is all a point decodes, merges and reduces, and the
        `_runs` of both regions together."""
        key = tuple(float(v) for v in stage)
        if key not in self._masks_of:
            sm, rm = roi_masks_fast(stage, self.settings)
            both = sm | rm
            rows, cols = np.flatnonzero(both.any(1)), np.flatnonzero(both.any(0))
            if len(rows):
                box = (int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1)
            else:                                # no region in view: the whole frame, as before
                box = (0, sm.shape[0], 0, sm.shape[1])
            win = np.s_[box[0]:box[1], box[2]:box[3]]
            while len(self._masks_of) > 1:       # this pose and the next are all a run needs
                self._masks_of.pop(next(iter(self._masks_of)))
            self._masks_of[key] = (sm[win], rm[win], box, _runs(both[win]))
        return self._masks_of[key]

    def _dark(self, t: float, box) -> RawFrame:
        d = self.darks[t]
        if box is None:
            return d
        return RawFrame(d.signal[:, box[0]:box[1], box[2]:box[3]], None, d.n_raw, d.black, d.white, d.rgb_cam)

    def _expose(self, idx: int, t: float, box, decode: bool = True) -> tuple[Exposure | None, dict]:
        """One exposure of point ``idx``: its RAW file, the monitor reading, and (``decode``) its
        frame inside ``box`` (else decoded later, by the point's reduction)."""
        self.bench.checkpoint()
        file = self._fresh(f"p{idx:05d}_{t * 1e6:010.0f}us.dng")
        digest = self.bench.camera.expose(t, self.folder / file)
        self.bench.checkpoint()
        p = self._power()
        d = {"seconds": t, "file": file, "sha256": digest, "power": p}
        if not decode:
            return None, d
        return Exposure(t, p, decode_raw(self.folder / file, window=box), self._dark(t, box)), d

    def _regions_from_markers(self, idx: int, stage) -> tuple[tuple, Exposure, dict, dict]:
        """The first probe of a point on a holder with markers: decoded whole, the regions found
        from the markers in it (`_markers.find_regions`; the geometry's where none fit), the frame
        then cropped to their box like any other."""
        e, d = self._expose(idx, self.probe, None)
        sig = e.frame.signal[1] - e.dark.signal[1]
        found = find_regions(np.asarray(sig, float), stage, self.settings)
        sm, rm = found.sample, found.reference
        both = sm | rm
        rows, cols = np.flatnonzero(both.any(1)), np.flatnonzero(both.any(0))
        box = ((int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1) if len(rows)
               else (0, sm.shape[0], 0, sm.shape[1]))
        win = np.s_[box[0]:box[1], box[2]:box[3]]
        f = e.frame
        e = Exposure(e.seconds, e.power, RawFrame(f.signal[(slice(None), *win)].copy(), f.peak[(slice(None), *win)].copy(), f.n_raw, f.black,
                                                  f.white, f.rgb_cam), self._dark(e.seconds, box))
        info = {"source": found.source, "why": found.why}
        if found.pose is not None:
            info.update(shift_m=[float(v) for v in found.pose.shift], angle_deg=float(found.pose.angle_deg),
                        rms_m=float(found.pose.rms), ids=[int(i) for i in found.pose.ids])
        return (sm[win], rm[win], box), e, d, info

    def _start_move(self, idx: int) -> dict:
        """Send the stages towards point ``idx`` and return at once (they move on the controller)."""
        return self.bench.gonio.move_to(dict(zip(AXES, self.stage[idx])), wait=False)

    def _arrive(self, idx: int, goal: dict | None) -> None:
        """Finish the move to point ``idx`` (``goal``: the one `_start_move` sent; None: move now),
        then settle."""
        b = self.bench
        target = dict(zip(AXES, self.stage[idx]))
        try:
            if goal is None:
                b.gonio.move_to(target)
            else:
                b.gonio.finish_move(goal)
        except MoveError as exc:                 # e.g. WL: clear the flags, try once more
            self.journal.event("warning", str(exc))
            b.chain.clear_flags(b.gonio.devices[0])
            b.gonio.move_to(target)
        b.sleep(float(self.settings.get("motion", {}).get("settle_s", 0.0)))

    def _bracket(self, idx: int, goal: dict | None = None) -> dict:
        """Move to point ``idx`` and take its bracket: what the instrument must do at the point.
        The probe (and a dim probe's confirmation) are decoded here, inside the regions' box, to
        choose the bracket; the other frames are left to `_reduce`."""
        self._arrive(idx, goal)
        stage = self.stage[idx]
        regions = None
        if self.layout is None:
            sm, rm, box, runs = self._masks(stage)
        p_start = self._power()
        taken: dict[float, tuple[Exposure | None, dict]] = {}
        t = self.probe
        if self.layout is not None:             # the regions from the holder's markers, in the probe
            (sm, rm, box), e, d, regions = self._regions_from_markers(idx, stage)
            runs = _runs(sm | rm)
            taken[t] = (e, d)
        # probe down the ladder until the regions are unsaturated (or the ladder ends)
        while True:
            if t not in taken:
                taken[t] = self._expose(idx, t, box)
            e = taken[t][0]
            peak = _extreme(np.maximum, e.frame.peak, runs)
            if peak < self.sat * e.frame.full_scale or t <= self.rungs[0]:
                break
            k = int(np.searchsorted(self.rungs, t)) - 3
            t = float(self.rungs[max(0, k)])
        for _ in range(3):
            e = taken[t][0]
            peak = _extreme(np.maximum, e.frame.peak - np.maximum(e.dark.signal, 0), runs)
            low = _extreme(np.minimum, e.frame.signal - e.dark.signal, runs)
            bracket = choose_bracket(self.rungs, t, peak, low, e.frame.full_scale, self.noise,
                                     self.sat, self.snr)
            if bracket[0] == t or peak > 0.05 * e.frame.full_scale or bracket[0] in taken:
                break
            t = bracket[0]                      # dim probe: confirm the shortest rung first
            taken[t] = self._expose(idx, t, box)
        for tb in bracket:
            if tb not in taken:
                taken[tb] = self._expose(idx, tb, box, decode=False)
        used = [taken[tb] for tb in sorted(taken)]
        powers = [d["power"] for _, d in used]
        if max(powers) / min(powers) - 1.0 > self.bracket_tol:
            raise _Suspended(f"the lamp changed by {100 * (max(powers) / min(powers) - 1):.1f} % within "
                             f"point {idx}'s bracket (tolerance {100 * self.bracket_tol:g} %)")
        return {"idx": idx, "stage": stage, "used": used, "p_start": p_start, "bracket": bracket,
                "masks": (sm, rm, box), "regions": regions}

    def _reduce(self, shot: dict) -> dict:
        """Decode what `_bracket` left, merge the bracket, reduce the regions, calibrate: the journal
        row's fields. Touches no device and no journal, so it runs while the stages move on."""
        idx, used = shot["idx"], shot["used"]
        sm, rm, box = shot["masks"]
        exposures = [e if e is not None else
                     Exposure(d["seconds"], d["power"], decode_raw(self.folder / d["file"], window=box),
                              self._dark(d["seconds"], box))
                     for e, d in used]
        gain = None if self.gain is None else self.gain[:, box[0]:box[1], box[2]:box[3]]
        hdr = merge(exposures, self.noise, self.sat).flat_fielded(gain)
        del exposures
        stats = {"sample": region_stats(hdr, sm), "reference": region_stats(hdr, rm)}
        saturated = any(st["n_saturated"] for st in stats.values())
        s, r = stats["sample"], stats["reference"]
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio = s["mean"] / r["mean"]
            brdf = ratio * self.reference.f_r(*self.plan.angles[idx, [0, 2]])
            rel = np.sqrt((s["se"] / s["mean"]) ** 2 + (r["se"] / r["mean"]) ** 2)
            std = np.abs(brdf) * rel
        detail = {
            "exposures": [d for _, d in used],
            "p_start": shot["p_start"],
            "bracket": shot["bracket"],
            **{f"{k}_{q}": [float(v) for v in stats[k][q]] for k in stats for q in ("mean", "se", "se_model", "n")},
            "n_saturated": {k: int(stats[k]["n_saturated"]) for k in stats},
        }
        if shot.get("regions") is not None:      # a holder with markers: how the regions were found
            detail["regions"] = shot["regions"]
        return {"brdf": brdf, "brdf_std": std, "saturated": saturated or not np.all(np.isfinite(brdf)),
                "detail": detail, "stage": shot["stage"]}

    def measure(self, idx: int) -> dict:
        """Move to point ``idx``, bracket, merge, calibrate; return the journal row's fields (one
        point, start to end: `run` overlaps the reduction with the next move instead)."""
        return self._reduce(self._bracket(idx))

    def _reciprocity(self, idx: int) -> dict | None:
        j = int(self.plan.partner[idx])
        if j < 0 or j not in self.results or idx not in self.results:
            return None
        (fa, sa), (fb, sb) = self.results[idx], self.results[j]
        with np.errstate(invalid="ignore", divide="ignore"):
            rel = (fa - fb) / (0.5 * (fa + fb))
            z = (fa - fb) / np.sqrt(sa ** 2 + sb ** 2)
        return {"i": min(idx, j), "j": max(idx, j), "rel": rel.tolist(), "z": z.tolist()}

    # -- the loop ------------------------------------------------------------------------
    def _commit(self, idx: int, res: dict, bar: ProgressBar) -> None:
        """Journal point ``idx`` (its RAW files are complete and fsynced: the camera committed them)."""
        self.journal.record_point(idx, self.plan.angles[idx], res["stage"], res["brdf"],
                                  res["brdf_std"], res["saturated"], res["detail"])
        self.results[idx] = (np.asarray(res["brdf"]), np.asarray(res["brdf_std"]))
        r = self._reciprocity(idx)
        if r is not None:
            self.reciprocity.append(r)
        bar.advance(res["brdf"], r)

    def run(self) -> tuple[int, str]:
        """Measure the points the journal lacks, in the session's order.

        Once point k's bracket is taken, the stages are sent to point k+1 at once, and a worker
        thread decodes, merges and reduces point k while they move (the main thread meanwhile
        finds k+1's regions); point k is journalled as soon as its reduction is done, still
        during the move and before k+1's bracket, so a point is in the journal only once its
        row is complete and its RAW files committed, and a stop (Ctrl-C once, after the point
        being journalled; a signal, a fault, a full disk) loses at most the point in progress,
        as before. A move sent ahead when the run stops at a point boundary is stopped.
        """
        done = self.journal.done()
        todo = [int(i) for i in self.order if int(i) not in done]
        for i in sorted(done):
            r = self._reciprocity(i)
            if r is not None and r["i"] == i:
                self.reciprocity.append(r)
        bar = ProgressBar(len(self.plan), len(done), self.progress)
        n_new = 0
        stopped = ""
        pending = None                   # (idx, future of its reduction): not yet journalled
        goal = None                      # the move sent ahead to todo[n], not yet waited for
        pool = ThreadPoolExecutor(1, thread_name_prefix="gonio-reduce")

        def commit_pending() -> None:
            nonlocal pending, n_new
            if pending is not None:
                idx, fut = pending
                res = fut.result()
                pending = None
                self._commit(idx, res, bar)
                n_new += 1

        try:
            try:
                for n, idx in enumerate(todo):
                    self.bench.checkpoint()
                    if self.stop():
                        stopped = "stopped by Ctrl-C; run the capture again with --resume to finish"
                        break
                    for attempt in range(self.MAX_ATTEMPTS):
                        try:
                            shot = self._bracket(idx, goal)
                            break
                        except _Suspended as exc:
                            goal = None
                            why = str(exc)
                            self._wait_until_fit(why)
                    else:
                        raise DeviceError(f"point {idx} failed {self.MAX_ATTEMPTS} times ({why}); "
                                          "check the lamp, then resume the session")
                    goal = None
                    ahead = todo[n + 1] if n + 1 < len(todo) and not self.stop() else None
                    if ahead is not None:
                        goal = self._start_move(ahead)         # the stages move while the host works
                    pending = (idx, pool.submit(self._reduce, shot))
                    del shot
                    if ahead is not None:
                        self._masks(self.stage[ahead])         # the next regions, during the move
                    commit_pending()                           # point k, still during the move
                if goal is not None:                           # stopped with a move sent ahead
                    goal = None
                    self.bench.gonio.stop()
            except BaseException:
                # what stops the run keeps a point whose reduction finished (its data is complete)
                if pending is not None:
                    try:
                        commit_pending()
                    except Exception:
                        pass
                raise
        finally:
            pool.shutdown(wait=True, cancel_futures=True)
            bar.close()
        return n_new, stopped


def _session_doc(plan: Plan, settings: Mapping, seed, order, zaber_url, meter_url, camera,
                 sample_truth, meta) -> dict[str, Any]:
    doc = {
        "session": {"created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                    "seed": -1 if seed is None else int(seed), **versions()},
        "ports": {"zaber": str(zaber_url), "meter": str(meter_url),
                  "camera": camera if isinstance(camera, str) else type(camera).__name__},
        "plan": plan.to_dict(),
        "order": {"order": [int(i) for i in order.order], "stage_deg": order.stage_deg.tolist(),
                  "naive_s": order.naive_s, "ordered_s": order.ordered_s, "bound_s": order.bound_s},
        "settings": dict(settings),
    }
    if sample_truth is not None:
        doc["sample_truth"] = {"json": sample_truth if isinstance(sample_truth, str) else json.dumps(sample_truth, sort_keys=True)}
    if meta:
        doc["meta"] = dict(meta)
    return doc


def _run(folder: Path, doc: Mapping, bench: Bench, journal: Journal, lock: SessionLock, warnings: list,
         progress: bool, t0: float, notes: list) -> CaptureSummary:
    """Measure what the journal lacks. Takes over ``bench``, ``journal`` and ``lock`` (closes them)."""
    try:
        with Interrupts() as intr:
            bench.checkpoint = intr.check
            try:
                sess = _Session(folder, doc, bench, journal, progress, lambda: intr.requested)
                sess.prepare()
                n_new, stopped = sess.run()
            except StopNow as exc:
                intr.stopping = True
                why = "stopped by Ctrl-C twice" if exc.why == "Ctrl-C twice" else f"stopped by {exc.why}"
                try:
                    bench.gonio.stop()
                finally:
                    _event(journal, "stop", f"{why}: stages stopped")
                raise CaptureInterrupted(f"{why}; the stages were stopped, the LED switched off and the session "
                                         f"is resumable with `gonio capture --resume {folder}`") from None
            except GonioError as exc:
                _event(journal, "stop", str(exc))
                exc.session_dir = folder          # the session stays resumable (exit status 3)
                raise
            except (OSError, sqlite3.DatabaseError) as exc:     # disk full, or another environment error
                if not isinstance(exc, OSError) and not disk_full(exc):
                    raise
                intr.deferred = True
                try:
                    bench.gonio.stop()
                except (GonioError, OSError):
                    pass
                err = _environment_stop(folder, doc, journal, exc)
                _event(journal, "stop", f"{err}: stages stopped")
                remove_orphans(folder / RAW_DIR)    # a half-written RAW file of this run (.tmp-*, *.part)
                raise err from None
            finally:
                intr.deferred = True              # a signal now only sets the flag: clean up first
                bench.checkpoint = lambda: None
                try:
                    for d, f, m in warnings:
                        _event(journal, "warning", f"device {d}: {f} {m}")
                    _event(journal, "comm", json.dumps({
                        "zaber_retries": bench.chain.retries_used, "zaber_reconnects": bench.chain.reconnects,
                        "meter_retries": bench.meter.retries_used, "meter_reconnects": bench.meter.reconnects,
                        "camera_retries": getattr(bench.camera, "retries_used", 0)}))
                finally:                          # the LED goes off whatever the journal does
                    try:
                        bench.led.off()
                        _event(journal, "lamp", "LED off")
                    except (GonioError, OSError) as exc:
                        _event(journal, "warning", f"could not switch the LED off ({exc}); switch it off by hand")
        if intr.requested and not stopped and len(journal.done()) < len(sess.plan):
            stopped = "stopped by a signal; run the capture again with --resume to finish"
        remove_orphans(folder / RAW_DIR)        # late files of a killed earlier process, if any
        n_done = len(journal.done())
        o = doc["order"]
        return CaptureSummary(folder, len(sess.plan), n_done, n_new, n_done == len(sess.plan), stopped,
                              sess.reciprocity, o["naive_s"], o["ordered_s"], o["bound_s"],
                              time.perf_counter() - t0, notes)
    finally:
        journal.close()
        bench.close()
        lock.__exit__()


def _event(journal: Journal, kind: str, text: str) -> None:
    """Journal an event; on a full disk (the journal cannot grow) it is dropped, so the clean-up
    (stages stopped, LED off) still runs and the reason for the stop is still said."""
    try:
        journal.event(kind, text)
    except (OSError, sqlite3.DatabaseError) as exc:
        if not disk_full(exc):
            raise


def _has_flat(camera) -> bool:
    """Whether ``camera`` has a flat-field source (a camera URL is a `SimCamera`, which has one)."""
    if isinstance(camera, str):
        return "://" in camera or camera.startswith("/")
    return hasattr(camera, "flat")


def _check_room(folder: Path, settings: Mapping, points: int, camera, journal: Journal | None, what: str,
                hint: str) -> None:
    """Refuse (one line) unless the disk holding ``folder`` has room for the RAW files ``points``
    points and the missing calibration frames will write (`gonio.bench._measure.raw_estimate`)."""
    est = raw_estimate(settings, points, has_flat=_has_flat(camera), journal=journal)
    if est.frames:
        check_free_space(folder, est.bytes, est.describe(what), hint)


def _environment_stop(folder: Path, doc: Mapping, journal: Journal | None, exc: BaseException) -> SessionError:
    """The one line for an environment error during a run (disk full: which disk, how much to free,
    how to resume), as a resumable stop (``session_dir`` set: exit status 3)."""
    n = len(doc["plan"]["points"])
    try:
        done = len(journal.done()) if journal is not None else 0
    except sqlite3.Error:
        done = None
    state = (f"{done}/{n} points are measured and the session is consistent" if done is not None
             else "the session is consistent")
    resume = f"`gonio capture --resume {folder}`"
    if disk_full(exc):
        name = getattr(exc, "filename", None)
        where = Path(name) if name else folder / (JOURNAL_FILE if isinstance(exc, sqlite3.Error) else RAW_DIR)
        shown = where
        for base in (folder, folder.resolve()):
            try:
                shown = where.relative_to(base)
                break
            except ValueError:
                pass
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        left = n - done if done is not None else n
        try:
            est = raw_estimate(doc["settings"], left, has_flat=True, journal=journal)
            if not est.frames:
                raise ValueError
            need = f"free at least {(est.bytes + MARGIN) / MiB:.0f} MiB for the {left} point(s) left, then resume"
        except Exception:                         # the estimate is a courtesy: never hide the stop
            need = "free some space, then resume"
        err = DiskFull(f"the disk at {mount_of(where)} is full ({reason}) while writing {shown}; the capture "
                       f"stopped, {state}; {need} with {resume}")
    else:
        err = SessionError(f"{oserror_line(exc)}; the capture stopped, {state}; fix it, then resume with {resume}")
    err.session_dir = folder
    return err


def _leftover(p: Path) -> bool:
    """What a capture stopped before its session.toml existed may leave (an empty folder otherwise)."""
    if p.is_dir():
        return p.name == RAW_DIR and not any(p.iterdir())
    return p.name.startswith(TMP_PREFIX) or p.name == LOCK_FILE


def _check_new_folder(folder: Path) -> None:
    if (folder / SESSION_FILE).exists():
        raise SessionError(f"{folder} already holds a session; resume it with --resume {folder} or choose another --out")
    if folder.exists() and not folder.is_dir():
        raise SessionError(f"{folder} is a file, not a folder; choose another --out")
    if folder.is_dir() and not all(_leftover(p) for p in folder.iterdir()):
        raise SessionError(f"{folder} is not empty; choose a new folder for the session")


def capture(session_dir, plan: Plan, settings: Mapping, zaber_url: str, meter_url: str, camera,
            seed: int | None = None, progress: bool = True, *, sample_truth=None, meta: Mapping | None = None,
            sleep: Callable[[float], None] = time.sleep, poll_interval_s: float = 0.05,
            timeout: float = 1.0) -> CaptureSummary:
    """Create a session folder and measure ``plan``.

    Parameters
    ----------
    session_dir : path
        A new (or empty) folder.
    plan : Plan
    settings : dict
        Instrument settings (`gonio.bench._settings.load_settings`).
    zaber_url, meter_url : str
        Serial URLs (``sim://NAME/zaber``, ``/dev/ttyUSB0``, a pty path).
    camera : str or camera object
        Camera URL (``sim://NAME/camera``) or an object with ``expose(seconds, path)``.
    seed : int, optional
        Recorded in the session (the simulator's seed in simulated sessions).
    progress : bool
        Show a rich progress bar on stderr.
    sample_truth : dict or str, optional
        The simulated sample's spec (recorded as JSON; simulated sessions only).
    meta : dict, optional
        Extra scalars for ``session.toml``'s ``[meta]`` table (e.g. how to rebuild a simulator).
    sleep : callable
        Waits (settling, polling, pauses): ``time.sleep`` on hardware, a simulated clock's
        ``advance`` against the simulator.

    Returns
    -------
    CaptureSummary

    Raises
    ------
    GonioError
        Unreachable plan, folder already a session (or in use by another capture), a port that
        does not open, a fault; the session (once written) stays resumable.
    """
    t0 = time.perf_counter()
    folder = Path(session_dir)
    settings = validate_settings(merge_settings(default_settings(), settings))   # tables left out keep their defaults
    _check_new_folder(folder)
    stage = require_reachable(plan, settings)
    order = order_moves(stage, settings)
    # before any port opens or anything is written: the folder writable, room for the RAW files
    check_output_dir(folder, "session folder (--out)")
    _check_room(folder, settings, len(plan), camera, None, f"the RAW files of session {folder}",
                "free some space or give another --out")
    # open every port before anything is written: a dead port leaves nothing behind
    warnings: list = []
    lock = journal = bench = None
    try:
        with Interrupts() as pre:               # a signal while the ports open: stop before writing
            bench = Bench(settings, zaber_url, meter_url, camera, sleep=sleep, poll_interval_s=poll_interval_s,
                          timeout=timeout, on_warning=lambda d, f, m: warnings.append((d, f, m)))
            check_sensor(bench.camera, settings)
            ReferenceModel(settings["reference"])
            text = session_text(_session_doc(plan, settings, seed, order, zaber_url, meter_url, camera,
                                             sample_truth, meta))
            try:
                folder.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise SessionError(f"cannot create session folder {folder} ({exc.strerror}); "
                                   "choose another --out") from None
            lock = SessionLock(folder).__enter__()  # before anything else is written: one capture per folder
            _check_new_folder(folder)               # again, now that no other capture can write here
        if pre.requested:
            raise CaptureInterrupted(f"stopped by {pre.stop or 'Ctrl-C'} before the capture started; no session "
                                     "was written")
        remove_orphans(folder)
        write_session(folder, text)             # once: never replaces an existing session.toml
        doc = read_session(folder)
        try:
            journal = Journal(folder / JOURNAL_FILE)
            journal.record_session(text, doc)
        except (OSError, sqlite3.DatabaseError) as exc:
            if not disk_full(exc):
                raise
            # session.toml is written, the journal is not: a resume records it (nothing measured yet)
            raise _environment_stop(folder, doc, None, exc) from None
    except BaseException:
        if journal is not None:
            journal.close()
        if bench is not None:
            bench.close()
        if lock is not None:
            if not (folder / SESSION_FILE).exists():
                try:
                    remove_orphans(folder)       # e.g. a session.toml half-written on a full disk
                except OSError:
                    pass
            lock.__exit__()
        raise
    return _run(folder, doc, bench, journal, lock, warnings, progress, t0, [])


def resume(session_dir, zaber_url: str | None = None, meter_url: str | None = None, camera=None,
           progress: bool = True, *, sleep: Callable[[float], None] = time.sleep,
           poll_interval_s: float = 0.05, timeout: float = 1.0, rebuild_journal: bool = False,
           remeasure: str | None = None, notify: Callable[[str], None] | None = None) -> CaptureSummary:
    """Finish a session: check it is one consistent record (`gonio.bench._integrity`), re-check
    positions and flags (re-home if the reference was lost), verify the journalled RAW files,
    remove orphan temporary files, skip the journalled points and measure the rest in the
    session's order.

    Points whose RAW files are missing or corrupt, and the points ``remeasure`` names
    (``"3,7,10-12"``), are measured again (their old rows are kept in ``superseded``);
    calibration frames that are missing or corrupt are taken again. ``rebuild_journal``
    replaces a missing or damaged journal first. Each of these is said in one line to
    ``notify`` and in the summary's ``notes``.

    Ports default to those recorded in ``session.toml``.
    """
    t0 = time.perf_counter()
    folder = Path(session_dir)
    notes: list[str] = []

    def note(line: str) -> None:
        notes.append(line)
        if notify is not None:
            notify(line)

    _integrity.load_session(folder)             # not a session: say so before taking its lock
    lock = SessionLock(folder).__enter__()      # not while another process measures into it
    journal = bench = None
    try:
        with Interrupts() as pre:               # checks and repairs finish whole; a signal stops after them
            data, doc, why = _integrity.load_session(folder)
            want = None
            if remeasure and doc is not None and isinstance(doc.get("plan"), Mapping):
                want = _integrity.parse_points(remeasure, len(doc["plan"].get("points", [])))   # before any write
            if rebuild_journal:
                note(_integrity.rebuild_journal(folder, data, doc, why))
            journal = _integrity.open_journal(folder, data, doc, why)
            # before a repair or a measurement writes: the folder writable, room for what is left
            left = (set(range(len(doc["plan"]["points"]))) - journal.done()) | set(want or ())
            check_output_dir(folder, "session folder")
            _check_room(folder, doc["settings"], len(left),
                        camera if camera is not None else doc.get("ports", {}).get("camera"), journal,
                        f"the {len(left)} point(s) left to measure in {folder}",
                        f"free some space, then resume with `gonio capture --resume {folder}`")
            remove_orphans(folder / RAW_DIR)
            remove_orphans(folder)
            _integrity.repair(folder, journal, want, note)
            ports = doc.get("ports", {})
            zaber_url = zaber_url or ports.get("zaber")
            meter_url = meter_url or ports.get("meter")
            if camera is None:
                camera = ports.get("camera")
                if not (isinstance(camera, str) and ("://" in camera or camera.startswith("/"))):
                    raise SessionError(f"{folder} was captured with a {camera} camera; give the camera to resume with")
            if not zaber_url or not meter_url:
                raise SessionError(f"{folder}: give the ports to resume on (--port and --meter-port)")
            warnings: list = []
            bench = Bench(doc["settings"], zaber_url, meter_url, camera, sleep=sleep, poll_interval_s=poll_interval_s,
                          timeout=timeout, on_warning=lambda d, f, m: warnings.append((d, f, m)))
        if pre.requested:
            raise CaptureInterrupted(f"stopped by {pre.stop or 'Ctrl-C'} before measuring; the session is resumable "
                                     f"with `gonio capture --resume {folder}`")
    except BaseException:
        if journal is not None:
            journal.close()
        if bench is not None:
            bench.close()
        lock.__exit__()
        raise
    return _run(folder, doc, bench, journal, lock, warnings, progress, t0, notes)
