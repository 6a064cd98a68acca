"""One run over a session folder, shared by `gonio.bench.session.capture.capture` and `resume`.

`_Session` prepares the instrument once per session (flags, homing, identification, darks for
every rung, flats, lamp on), then measures the points the journal lacks in the session's order:
per point move, bracket (probe, then the rungs `choose_bracket` picks), merge, reduce the
sample and reference regions, calibrate, journal. The reduction of point k runs in a worker
thread while the stages move to k+1. The suspenders pause the run while the lamp or the meter
is not fit to measure. `gonio.bench.session.capture`'s module notes describe the measurement; the
calibration frames (darks, flats, chart) are `_calframes.CalibrationFrames`'.

A spectral plan's wavelength is set before each point's bracket (`gonio.bench.session.tuning`).
The regions: `roi_masks_fast` (the masks of `kinematics.roi_masks`, mostly from
`_markers.posed_masks`) or, on a holder with markers, `_markers.find_regions` in the probe.
"""

from __future__ import annotations

import contextlib
import json
import math
import sys
import time
from pathlib import Path
from typing import Callable, Mapping

import numpy as np

from gonio.bench.session.calframes import CalibrationFrames
from gonio.core.files import create_exclusive
from gonio.bench.session.rear import RearStop
from gonio.bench.session.tuning import Tuning
from gonio.bench.measure.hdr import Exposure, NoiseModel, choose_bracket, ladder
from gonio.bench.session.journal import RAW_DIR, Journal, preparation_times
from gonio.bench.plan.markers import find_regions, layout_of, roi_masks_fast
from gonio.bench.measure.calpoint import hand_angle_modes, stray_corrected, stray_fraction
from gonio.bench.measure.point import (ProgressBar, ReferenceModel, _runs, check_sensor, merged_region_stats, probe_levels)
from gonio.bench.session.pipeline import Pipeline, _Suspended
from gonio.bench.drivers.rig import Bench
from gonio.bench.settings import AXES
from gonio.bench.drivers import BadDelivery, MoveError, RawFrame, decode_raw, deliver
from gonio.bench.drivers.identify import differences, hardware_note, session_devices
from gonio.bench.drivers.identify import record as record_identification
from gonio.core.errors import CommunicationError, DeviceError, GonioError, SessionError
from gonio.bench.plan.plans import plan_from_dict
from gonio.bench.plan.strategy import strategy_from_doc

__all__ = ["roi_masks_fast"]  # re-exported from _markers (tests and the benchmark patch it here)


class _Session(CalibrationFrames, Tuning, RearStop):
    """One run over a session folder (shared by `capture` and `resume`)."""

    MAX_ATTEMPTS = 5        # measurements of one point interrupted by the lamp before the run stops

    def __init__(self, folder: Path, doc: Mapping, bench: Bench, journal: Journal, progress: bool,
                 stop: Callable[[], bool], *, ident: Mapping | None = None,
                 note: Callable[[str], None] = lambda line: None, operator=None):
        self.folder = folder
        self.doc = doc
        self.settings = doc["settings"]
        self.plan = plan_from_dict(doc["plan"], source=doc["plan"].get("source", ""))
        self.order = np.asarray(doc["order"]["order"], int)
        try:
            self.strategy = hand_angle_modes(strategy_from_doc(doc, self.plan), self.settings, doc["order"]["stage_deg"])
        except ValueError as exc:
            raise SessionError(f"{folder / 'session.toml'}: {exc}") from None
        self.stage = np.asarray(doc["order"]["stage_deg"], float)
        self.bench = bench
        self.journal = journal
        self.progress = progress
        self.stop = stop
        cam, cap = self.settings["camera"], self.settings["capture"]
        self.noise = NoiseModel(float(cam.get("gain_e_per_dn", 2.0)), float(cam.get("read_noise_e", 3.0)))
        self.sat = float(cap["saturation_fraction"])
        self.gamma = float((self.settings.get("linearity") or {}).get("gamma", 0.0))   # gonio calibrate
        self.rungs = ladder(float(cap["exposure_min_s"]), float(cap["exposure_max_s"]))
        self.probe = float(self.rungs[np.argmin(np.abs(np.log(self.rungs / float(cap["probe_s"]))))])
        self.snr = float(cap["noise_floor_snr"])
        self.reference = ReferenceModel(self.settings["reference"])
        # gonio calibrate's stray floor, where it states the level (u_floor present): corrected per point
        stray = self.settings.get("stray") or {}
        self.stray_floor = float(stray.get("floor", 0.0) or 0.0) if "u_floor" in stray else 0.0
        self.darks: dict[float, RawFrame] = {}
        self.gain: np.ndarray | None = None          # flat-field relative gain (3, h, w), None if no flat
        lamp = self.settings.get("lamp", {})
        self.drift_tol = float(lamp.get("drift_tolerance", 0.2))
        self.bracket_tol = float(lamp.get("bracket_tolerance", 0.02))
        self.suspend_poll = float(lamp.get("suspend_poll_s", 5.0))
        self.suspend_timeout = float(lamp.get("suspend_timeout_s", 120.0))
        self.p_ref = None
        rows = journal.points()
        self.results: dict[int, tuple[np.ndarray, np.ndarray]] = {
            r["idx"]: (np.asarray(r["brdf"]), np.asarray(r["brdf_std"])) for r in rows}
        # the RAW files the journalled points name (what a killed run's leftovers are told from)
        self._journalled_files = {e["file"] for r in rows for e in r["detail"].get("exposures", [])}
        self.reciprocity: list[dict] = []
        self.reserved = journal.reserved()
        self._masks_of: dict[tuple, tuple] = {}      # per holder pose (yaw, tilt, azimuth): the regions
        self.layout = layout_of(self.settings)       # the holder's markers, None where it has none
        self._deliveries: dict = {}                  # RAW file name -> Delivery not yet checked and committed
        self.ident = ident                           # a capture's identification, taken before session.toml
        self.note = note                             # says one line (console and summary notes)
        self.exhausted = False                       # the run measured every point its strategy asked for
        self._todo: list[int] | None = None          # the strategy's first points (`_first_todo`)
        # instrument time (the bench's clock): each kept point's, each finished preparation's
        self.clock: Callable[[], float] = getattr(bench, "clock", time.monotonic)
        self.times = {r["idx"]: float(r["detail"]["instrument_s"]) for r in rows
                      if isinstance(r["detail"].get("instrument_s"), (int, float))}
        self.preparations = preparation_times(journal.checked_events()[0])
        self._init_tuning(self.plan, journal)       # a spectral plan's wavelengths (`Tuning`)
        self._init_rear(operator)                   # transmitted points: the rear stop (`RearStop`)

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

    def _fresh_set(self, names: list[str]) -> list[str]:
        """`_fresh` for a set of names, reserved in one journal transaction (a name already
        taken gets `_fresh`'s suffix, one at a time)."""
        files = [f"{RAW_DIR}/{name}" for name in names]
        free = [f for f in files if f not in self.reserved and not (self.folder / f).exists()]
        self.journal.reserve_all(free)
        self.reserved.update(free)
        free = set(free)
        return [f if f in free and create_exclusive(self.folder / f) else self._fresh(name)
                for f, name in zip(files, names)]

    # -- instrument preparation ----------------------------------------------------------
    def _first_todo(self) -> list[int]:
        """The points the strategy asks for before the loop starts (those the journal lacks);
        worked out once (an adaptive strategy fits to choose them)."""
        if self._todo is None:
            self._account()
            done = self.journal.done()
            todo = self._checked(self.strategy.first(set(done)), done, [])
            # a resume past the strategy's first points: it may still want more before the loop starts
            todo.extend(self._checked(self.strategy.more(self.results, tuple(todo)), done, todo))
            self._todo = todo
        return self._todo

    def finished(self) -> bool:
        """Whether the session has nothing left to measure: every point its strategy asks for is
        journalled (a resume of it then moves nothing: issue 40)."""
        return len(self.journal.done()) >= self.strategy.budget or not self._first_todo()

    def prepare(self) -> None:
        """Check flags and positions, home if the reference is lost, take missing darks and
        flats, lamp on; saying what it does (it took ~5 s with a blank screen). Nothing at all
        where the session is `finished`: no device is asked to move, expose or light."""
        if self.finished():
            return
        t0 = self.clock()
        with self._status() as say:
            b = self.bench
            say("checking the camera and the stages")
            check_sensor(b.camera, self.settings)
            flags = b.gonio.connect(clear_faults=True)
            if any(f in ("WR", "WH") for f in flags):
                self.journal.event("home", f"stages lost their reference ({' '.join(flags)}): homing")
                say("homing the stages (they lost their reference)")
                b.gonio.home()
            say("identifying the devices")
            b.meter.identify()
            ident = record_identification(b, self.journal, self.ident)   # *IDN?s, Zaber ids, serials, firmware
            if self.ident is None:
                self._check_hardware(ident)
            m = self.settings.get("meter", {})
            b.meter.configure(float(m.get("wavelength_nm", 550)), int(m.get("averaging", 10)))
            self._take_darks(say)
            self._take_flats(say)
            cm = next(iter(self.darks.values())).rgb_cam
            if cm is not None and self.journal.first_event("rgb_cam") is None:
                self.journal.event("rgb_cam", json.dumps(cm.tolist()))
            say("lamp on, reading the source monitor")
            b.led.set_flux(float(self.settings.get("lamp", {}).get("flux", 1.0)))
            b.led.on()
            self._light_on()                     # the monitor's reference (a spectral plan's at its first point)
            self._take_chart(say)
        # the preparation's instrument time, kept once it finished (a resume's adds to it)
        took, n = max(0.0, self.clock() - t0), len(self.journal.done())
        self.journal.event("instrument_time", json.dumps({"phase": "prepare", "s": took, "points": n}))
        self.preparations.append((n, took))

    def _check_hardware(self, ident: Mapping) -> None:
        """A resume: say (a console line, the summary's notes, a ``hardware`` journal event the
        report shows) where the devices differ from what session.toml's ``[devices]`` records;
        nothing on the same hardware, or for a session.toml from before ``[devices]``."""
        recorded = self.doc.get("devices")
        if not isinstance(recorded, Mapping):
            return
        diffs = differences(recorded, session_devices(ident))
        if diffs:
            line = hardware_note(diffs)
            self.journal.event("hardware", line)
            self.note(line)

    @contextlib.contextmanager
    def _status(self):
        """``say(text)``: one updating status line on a terminal (rich), one line per step when
        stderr is a file or a pipe; nothing without progress output."""
        if not self.progress:
            yield lambda text: None
            return
        from rich.console import Console

        console = Console(stderr=True)
        if not console.is_terminal:
            last = [""]

            def say(text):
                step = text.split(":")[0]
                if step != last[0]:         # one line per step, not per frame
                    last[0] = step
                    print(f"capture: {step}", file=sys.stderr, flush=True)
            yield say
            return
        with console.status("preparing the instrument") as status:
            yield lambda text: status.update(f"capture: {text}")

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
    def _masks(self, stage: np.ndarray, rear: bool = False) -> tuple[np.ndarray, np.ndarray, tuple[int, int, int, int], np.ndarray]:
        """The sample and reference regions at ``stage`` (`roi_masks_fast`: the masks of
        `kinematics.roi_masks`, mostly from the map's affinity) cropped to their bounding box, the box
        (super-pixel rows and columns) that is all a point decodes, merges and reduces, and the
        `_runs` of both regions together. Cached per holder pose: the lamp's angle moves no region
        (`kinematics.rotation` ignores it), so the points that differ only in it share the masks."""
        key = (*(float(v) for v in stage[:3]), rear)       # rear: the sample's region from the rear stop
        if key not in self._masks_of:
            sm, rm = self._rear_regions(stage) if rear else roi_masks_fast(stage, self.settings)
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
        frame = None
        for _ in range(int(getattr(self.bench.camera, "retries", 2)) + 1):
            delivery = deliver(self.bench.camera, t, self.folder / file)   # checked and committed by
            self._deliveries[file] = delivery                             # the point's reduction
            if not decode:
                break
            try:                                 # a probe: decoded now, from the bytes to be checked
                frame = decode_raw(self.folder / file, window=box, data=delivery.read(), colour=False)
                break
            except (GonioError, BadDelivery):    # undecodable: a spoilt file is taken again at once
                if delivery.tmp is None:
                    raise
                try:
                    delivery.finish()
                except BadDelivery:
                    self._deliveries.pop(file)
                    if hasattr(self.bench.camera, "retries_used"):
                        self.bench.camera.retries_used += 1
                    continue
                raise
        else:
            raise DeviceError(f"camera could not deliver {file} (spoilt every time); check the camera and "
                              "disk, then resume the session")
        self.bench.checkpoint()
        p = self._power()
        d = {"seconds": t, "file": file, "sha256": delivery.digest, "power": p}
        if not decode:
            return None, d
        return Exposure(t, p, frame, self._dark(t, box)), d

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
            if goal is None:                     # no move sent ahead (the first point, a retake)
                goal = b.gonio.move_to(target, wait=False)
                if self.layout is None:
                    self._masks(self.stage[idx], bool(self.rear[idx]))  # its regions while the stages move
            b.gonio.finish_move(goal)
        except MoveError as exc:                 # e.g. WL: clear the flags, try once more
            self.journal.event("warning", str(exc))
            b.chain.clear_flags(b.gonio.devices[0])
            b.gonio.move_to(target)
        self._tune(idx)                          # a spectral plan: its wavelength, before its bracket
        b.sleep(float(self.settings.get("motion", {}).get("settle_s", 0.0)))

    def _bracket(self, idx: int, goal: dict | None = None) -> dict:
        """Move to point ``idx`` and take its bracket: what the instrument must do at the point.
        The probe (and a dim probe's confirmation) are decoded here, inside the regions' box, to
        choose the bracket; the other frames are left to `_reduce`."""
        goal = self._to_stop(idx, goal)         # the camera's stop, the open beam (`RearStop`)
        self._arrive(idx, goal)
        stage, rear = self.stage[idx], bool(self.rear[idx])
        regions = None
        if self.layout is None or rear:
            sm, rm, box, runs = self._masks(stage, rear)
        p_start = self._power()
        taken: dict[float, tuple[Exposure | None, dict]] = {}
        t = self.probe
        if self.layout is not None and not rear:   # the regions from the holder's markers, in the probe
            (sm, rm, box), e, d, regions = self._regions_from_markers(idx, stage)
            runs = _runs(sm | rm)
            taken[t] = (e, d)
        levels = {}                             # per exposure: its `probe_levels`, in one pass
        # probe down the ladder until the regions are unsaturated (or the ladder ends)
        while True:
            if t not in taken:
                taken[t] = self._expose(idx, t, box)
            e = taken[t][0]
            levels[t] = probe_levels(e.frame, e.dark, runs)
            if levels[t][0] < self.sat * e.frame.full_scale or t <= self.rungs[0]:
                break
            k = int(np.searchsorted(self.rungs, t)) - 3
            t = float(self.rungs[max(0, k)])
        for _ in range(3):
            e = taken[t][0]
            if t not in levels:
                levels[t] = probe_levels(e.frame, e.dark, runs)
            _, peak, low = levels[t]
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
        deliveries = {d["file"]: self._deliveries.pop(d["file"]) for _, d in used if d["file"] in self._deliveries}
        powers = [d["power"] for _, d in used]
        if max(powers) / min(powers) - 1.0 > self.bracket_tol:
            for dl in deliveries.values():
                dl.discard()
            raise _Suspended(f"the lamp changed by {100 * (max(powers) / min(powers) - 1):.1f} % within "
                             f"point {idx}'s bracket (tolerance {100 * self.bracket_tol:g} %)")
        return {"idx": idx, "stage": stage, "used": used, "p_start": p_start, "bracket": bracket,
                "masks": (sm, rm, box), "regions": regions, "deliveries": deliveries, "tuned": self._tuned(), "rear": rear}

    def _reduce(self, shot: dict) -> dict:
        """Check and commit the point's RAW files (SHA-256 against the camera's, fsync, rename;
        the probes `_bracket` decoded too), decode the others from the bytes checked, merge the
        bracket, reduce the regions, calibrate: the journal row's fields. Touches no device and no journal, so it runs while
        the stages move on; `BadDelivery` (a file spoilt) discards the point's unchecked files."""
        idx, used = shot["idx"], shot["used"]
        sm, rm, box = shot["masks"]
        deliveries = shot.get("deliveries", {})
        exposures = []
        try:
            for e, d in used:
                dl = deliveries.pop(d["file"], None)
                data = None if dl is None else dl.finish()      # probes too: decoded, not yet checked
                if e is None:
                    e = Exposure(d["seconds"], d["power"], decode_raw(self.folder / d["file"], window=box, data=data,
                                                                       colour=False),
                                 self._dark(d["seconds"], box))
                exposures.append(e)
        except BadDelivery:
            for dl in deliveries.values():
                dl.discard()
            raise
        gain = None if self.gain is None else self.gain[:, box[0]:box[1], box[2]:box[3]]
        if shot.get("rear"):                     # a transmitted point: over the open beam (`RearStop`)
            return self._reduce_rear(shot, exposures, gain)
        # merged and reduced a block of rows at a time, each block's region sums taken while it is in cache
        stats = dict(zip(("sample", "reference"),
                         merged_region_stats(exposures, self.noise, (sm, rm), self.sat, self.gamma, gain)))
        del exposures
        saturated = any(st["n_saturated"] for st in stats.values())
        s, r = stats["sample"], stats["reference"]
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio = s["mean"] / r["mean"]
            f_ref = self.reference.f_r(*self.plan.angles[idx, [0, 2]])
            rel = np.sqrt((s["se"] / s["mean"]) ** 2 + (r["se"] / r["mean"]) ** 2)
            q = None
            if self.stray_floor > 0:
                # a calibrated stray floor (gonio calibrate's [stray] level): removed from both squares
                q = stray_fraction(f_ref * math.cos(math.radians(self.plan.angles[idx, 0])), self.stray_floor)
                ratio = stray_corrected(ratio, q)
                rel = rel / np.where(ratio != 0, np.abs(ratio) * (1.0 - q) / np.abs(s["mean"] / r["mean"]), 1.0)
            brdf = ratio * f_ref
            std = np.abs(brdf) * rel
            # a channel without a finite uncertainty (its region left with one unsaturated pixel:
            # no scatter to measure) gives no value, as a region with none does
            brdf = np.where(np.isfinite(std), brdf, np.nan)
        detail = {
            "exposures": [d for _, d in used],
            "p_start": shot["p_start"],
            "bracket": shot["bracket"],
            **{f"{k}_{m}": [float(v) for v in stats[k][m]] for k in stats for m in ("mean", "se", "se_model", "n")},
            "n_saturated": {k: int(stats[k]["n_saturated"]) for k in stats},
        }
        if q is not None:                        # the stray floor's share of the reference's signal, removed
            detail["stray_q"] = [float(v) for v in q]
        if shot.get("regions") is not None:      # a holder with markers: how the regions were found
            detail["regions"] = shot["regions"]
        detail.update(shot.get("tuned") or {})   # a spectral plan: the wavelength read back
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
        """Journal point ``idx`` (its RAW files are complete and fsynced: the camera committed them)
        with its instrument time (``detail["instrument_s"]``, `Pipeline`'s) where measured."""
        self.journal.record_point(idx, self.plan.angles[idx], res["stage"], res["brdf"],
                                  res["brdf_std"], res["saturated"], res["detail"])
        self.results[idx] = (np.asarray(res["brdf"]), np.asarray(res["brdf_std"]))
        if "instrument_s" in res["detail"]:
            self.times[idx] = float(res["detail"]["instrument_s"])
        r = self._reciprocity(idx)
        if r is not None:
            self.reciprocity.append(r)
        bar.advance(res["brdf"], r, quantity="f_t" if bool(self.rear[idx]) else "f_r")

    def _drop_unjournalled_point_files(self) -> None:
        """Delete the point frames (``raw/p*``) an earlier, killed run wrote but never journalled
        (`CalibrationFrames._drop_uncommitted`'s rules); runs before the first point."""
        self._drop_uncommitted("p", self._journalled_files | self.journal.superseded_files())

    def _account(self) -> None:
        """Tell a strategy that counts time (an optional ``account(times, preparations)``) the
        instrument time so far: each kept point's, and each preparation's with the number of
        points kept before it."""
        account = getattr(self.strategy, "account", None)
        if callable(account):
            account(dict(self.times), list(self.preparations))

    def _checked(self, points, done, queued) -> list[int]:
        """The strategy's new points, each a plan point neither done nor queued, within its budget."""
        n, seen, out = len(self.plan), set(done) | set(queued), []
        for p in points:
            i = int(p)
            if not 0 <= i < n:
                raise SessionError(f"plan strategy {self.strategy.name!r} asked for point {i} of a plan of {n}")
            if i not in seen and len(seen) < self.strategy.budget:
                seen.add(i)
                out.append(i)
        return out

    def run(self) -> tuple[int, str]:
        """Measure the points the journal lacks, in the session's order.

        Once point k's bracket is taken, the stages are sent to point k+1 at once, and a worker
        thread checks point k's RAW files against the camera's SHA-256, fsyncs and renames them
        (the probes too: decoded at once to choose the bracket), decodes, merges and reduces
        point k while they move (the main thread meanwhile finds k+1's regions); point k is
        journalled as soon as its reduction is done, still during the move and before k+1's
        bracket, so a point is in the journal only once its row is complete and its RAW files
        checked and committed, and a stop (Ctrl-C once, after the point being journalled; a
        signal, a fault, a full disk) loses at most the point in progress, as before. A file
        found spoilt there sends the stages back: the point is taken again next (at most the
        camera's ``retries`` times). A move sent ahead when the run stops at a point boundary
        is stopped.
        """
        done = self.journal.done()
        if self.finished():
            self.exhausted = True
            self.note(f"the session is finished: all {len(done)} point(s) its plan asks for are measured; "
                      "nothing was moved or exposed (measure points again with --remeasure)")
            for i in sorted(done):
                r = self._reciprocity(i)
                if r is not None and r["i"] == i:
                    self.reciprocity.append(r)
            return 0, ""
        self._drop_unjournalled_point_files()
        todo = list(self._first_todo())
        for i in sorted(done):
            r = self._reciprocity(i)
            if r is not None and r["i"] == i:
                self.reciprocity.append(r)
        bar = ProgressBar(self.strategy.budget, len(done), self.progress)
        pipe = Pipeline(self, todo, bar)
        stopped = ""
        try:
            try:
                for n, idx in enumerate(todo):          # a point taken again is inserted next
                    self.bench.checkpoint()
                    if self.stop():
                        stopped = "stopped by Ctrl-C; run the capture again with --resume to finish"
                        break
                    self._account()
                    todo.extend(self._checked(self.strategy.more(self.results, tuple(todo)), done, todo))
                    pipe.step(n, idx)
                else:
                    self.exhausted = True               # the strategy asked for nothing more
                    if hasattr(self.strategy, "state"):   # why it stopped (budget, target, candidates)
                        self.journal.event("strategy", json.dumps(self.strategy.state(), sort_keys=True,
                                                                  default=str))
                pipe.stop_move_ahead()
            except BaseException:
                pipe.keep_finished()
                raise
        finally:
            pipe.close()
            for dl in self._deliveries.values():      # a bracket cut short: its unchecked files
                dl.discard()
            self._deliveries.clear()
            bar.close()
        return pipe.n_new, stopped
