"""The capture loop: a session that survives being killed.

`capture` creates a session folder and measures a plan; `resume` finishes one.

Once per session: dark frames for every rung of the exposure ladder and, where the camera has
a flat-field source, ``[capture] flat_frames`` flat frames (each set journalled, so a resume
reuses it). Per point: move, settle, expose an automatic bracket, read the monitor, merge it
to HDR radiance, average the sample and reference regions and convert to
``f_r = (S_sample / S_ref) * rho_ref / pi`` with its 1-sigma; the point's journal row is
committed only when everything about it succeeded. Ctrl-C once finishes the current point and
stops resumably, twice stops the stages and exits; lamp drift or a silent meter pauses the run.

This module holds the entry points, the checks before anything is written, the session's
files and how a run stops; `gonio.bench.drivers.rig.Bench` opens the devices together and
`gonio.bench.session.run._Session` is the run itself.
"""

# Calibration frames: the dark frames are taken with the lamp off (the bracketing may use any
# rung); the mean of the flat frames gives each pixel's relative gain (the sensor's response
# non-uniformity).
# Per point: move (in the ordered plan, the shortest way, soft limits checked, the position
# verified), wait for IDLE, settle, expose with automatic bracketing (a probe, then the rungs
# that keep the brightest region pixel below saturation in the shortest exposure and bring
# the darkest to noise_floor_snr in the longest), read the monitor at each exposure, merge the
# bracket into HDR radiance (dark frames subtracted, saturated values excluded, flat-fielded),
# average the sample and reference regions (the super-pixels wholly inside each square, found
# from the holder's markers in the probe where the settings declare them, else from the
# geometry). The 1-sigma comes from both regions' standard errors of the mean (shot, read and
# residual fixed-pattern noise; the monitor cancels in the ratio). The reference certificate's
# own uncertainty is a fully correlated scale error, stored apart (scale_rel_std). Reciprocal
# pairs are compared as they arrive. Once a point's bracket is taken the stages start towards
# the next point, and a worker thread decodes, merges and reduces the point (inside the
# regions' bounding box only) while they move; its row is committed before the next bracket.
# Operation: a rich progress bar (points, ETA, latest f_r). The run pauses itself (a
# suspender) while the lamp is off its session-start level by more than
# [lamp] drift_tolerance, changes within a bracket by more than bracket_tolerance, or the meter
# is silent, and stops resumably with a one-line reason when that lasts longer than
# suspend_timeout_s. A move that falls short (a limit switch) is retried once; faults (a
# stall) stop the run resumably, and a resume clears them and re-homes where the controller
# lost its reference.
# Layout: gonio.bench.session.run._Session does the preparation, the bracket of one point,
# its reduction and the loop; Bench opens the devices (gonio.bench.drivers).

from __future__ import annotations

import json
import math
import sqlite3
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from gonio.core.atomic import is_temporary

from gonio.bench.session import integrity as _integrity
from gonio.core.files import remove_orphans
from gonio.bench.session.journal import (JOURNAL_FILE, LOCK_FILE, RAW_DIR, SESSION_FILE, Journal, SessionLock, read_session, session_text, versions, write_session)
from gonio.bench.measure.point import ReferenceModel, check_sensor, raw_estimate
from gonio.bench.measure.calpoint import hand_angle_modes
from gonio.bench.plan.spectral import SpectralOrder, order_plan
from gonio.core.preflight import (MARGIN, MiB, check_free_space, check_output_dir, disk_full, mount_of, oserror_line)
from gonio.bench.drivers.rig import Bench
from gonio.bench.session.run import _Session
from gonio.bench.settings import default_settings, merge_settings, validate_settings
from gonio.bench.session.signals import Interrupts, StopNow
from gonio.bench.drivers import emergency_stop
from gonio.bench.drivers.identify import identify_bench, session_devices
from gonio.core.errors import GonioError, SessionError
from gonio.bench.plan.plans import Plan, require_reachable
from gonio.bench.plan import kinematics
from gonio.bench.plan.ordering import order_moves, path_time
from gonio.bench.measure.transmission import transmission_settings
from gonio.bench.plan.strategy import strategy_from_doc

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
        Points the plan strategy measures (its budget: every point of a fixed plan).
    n_done : int
        Points journalled now (all runs).
    n_new : int
        Points measured by this call.
    complete : bool
        Every point the strategy asked for is journalled.
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
    plan_stop : str
        Why the plan strategy stopped, where it says (an adaptive plan's budget, time or target).
    instrument_s : float
        The session's instrument time so far, s (every finished preparation and every kept
        point's: dataset.nc's ``instrument_time_s``).
    spectral : str
        A spectral plan's wavelength axis and both orders' estimates (`SpectralOrder.line`).
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
    plan_stop: str = ""
    instrument_s: float = 0.0
    spectral: str = ""

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


estop = emergency_stop        # ``gonio estop --port``: /0 0 estop to every device at once


def _session_doc(plan: Plan, settings: Mapping, seed, order, zaber_url, meter_url, camera,
                 sample_truth, meta, strategy: Mapping, monochromator: str | None = None) -> dict[str, Any]:
    doc = {
        "session": {"created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                    "seed": -1 if seed is None else int(seed), **versions()},
        "ports": {"zaber": str(zaber_url), "meter": str(meter_url),
                  "camera": camera if isinstance(camera, str) else type(camera).__name__,
                  **({"monochromator": str(monochromator)} if monochromator else {})},
        "plan": plan.to_dict(),
        "order": {"order": [int(i) for i in order.order], "stage_deg": order.stage_deg.tolist(),
                  "naive_s": order.naive_s, "ordered_s": order.ordered_s, "bound_s": order.bound_s},
        "settings": dict(settings),
        "strategy": dict(strategy),
    }
    if sample_truth is not None:
        doc["sample_truth"] = {"json": sample_truth if isinstance(sample_truth, str) else json.dumps(sample_truth, sort_keys=True)}
    if meta:
        doc["meta"] = dict(meta)
    return doc


def _run(folder: Path, doc: Mapping, bench: Bench, journal: Journal, lock: SessionLock, warnings: list,
         progress: bool, t0: float, notes: list, *, ident: Mapping | None = None,
         note: Callable[[str], None] | None = None, operator=None) -> CaptureSummary:
    """Measure what the journal lacks. Takes over ``bench``, ``journal`` and ``lock`` (closes them).

    ``ident``: the devices' identification a capture took before writing session.toml (a resume
    identifies them again); ``note``: says a line (a resume on other hardware), else it joins ``notes``;
    ``operator``: who performs the operator's steps (`gonio.bench.session.stops.operator_for`)."""
    try:
        with Interrupts() as intr:
            bench.checkpoint = intr.check
            try:
                sess = _Session(folder, doc, bench, journal, progress, lambda: intr.requested, ident=ident,
                                note=note or notes.append, operator=operator)
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
                    if getattr(bench, "monochromator", None) is not None:     # its shutter closed, as found
                        try:
                            bench.monochromator.shutter(False)
                        except (GonioError, OSError) as exc:
                            _event(journal, "warning", f"could not close the monochromator's shutter ({exc})")
        budget = sess.strategy.budget
        if intr.requested and not stopped and len(journal.done()) < budget:
            stopped = "stopped by a signal; run the capture again with --resume to finish"
        remove_orphans(folder / RAW_DIR)        # late files of a killed earlier process, if any
        n_done = len(journal.done())
        o = doc["order"]
        complete = n_done >= budget or (sess.exhausted and not stopped)
        stop_line = getattr(sess.strategy, "stop_line", None)
        return CaptureSummary(folder, budget, n_done, n_new, complete, stopped,
                              sess.reciprocity, o["naive_s"], o["ordered_s"], o["bound_s"],
                              time.perf_counter() - t0, notes, stop_line() if callable(stop_line) else "",
                              sum(sess.times.values()) + sum(s for _, s in sess.preparations),
                              getattr(SpectralOrder.from_dict(o), "line", str)())
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
    points and the missing calibration frames will write (`gonio.bench.measure.point.raw_estimate`)."""
    chart = settings["capture"].get("colour_chart", False)
    if not isinstance(chart, bool):
        raise GonioError(f"[capture] colour_chart = {chart!r:.40}: it must be true or false")
    if chart and not isinstance(camera, str) and not hasattr(camera, "chart"):
        raise GonioError("[capture] colour_chart = true, but this camera has no chart source; capture the "
                         "ColorChecker yourself and give it to `gonio export --colour-chart`")
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
    return is_temporary(p.name) or p.name == LOCK_FILE       # the one rule for a temporary


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
            timeout: float = 1.0, strategy: Mapping | None = None,
            clock: Callable[[], float] | None = None, monochromator: str | None = None,
            operator=None) -> CaptureSummary:
    """Create a session folder and measure ``plan``.

    Parameters
    ----------
    session_dir : path
        A new (or empty) folder.
    plan : Plan
    settings : dict
        Instrument settings (`gonio.bench.settings.load_settings`).
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
    strategy : dict, optional
        session.toml's ``[strategy]`` table: how the next point is chosen from the plan's
        (`gonio.bench.plan.strategy`); default ``{"name": "fixed"}``, every point in move order.
    clock : callable, optional
        The instrument's clock in seconds, what the journal's instrument time is read from
        (`gonio.bench.drivers.rig.clock_of`: ``time.monotonic``, or the simulated clock whose
        ``advance`` ``sleep`` is).
    monochromator : str, optional
        The monochromator's serial URL (``sim://NAME/monochromator``): opened, identified and
        recorded in ``[ports]`` and ``[devices]``; a spectral plan needs it.
    operator : optional
        Performs the operator's steps of a plan with transmitted points (theta_o > 90: the
        camera to the rear stop, the sample out for the open beam and back;
        `gonio.bench.session.stops`); default: the simulator's twin on a ``sim://`` camera, a
        prompt on a terminal, else a one-line stop saying what to do.

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
    order, spectral = order_plan(plan, stage, settings)        # a spectral plan: its wavelengths checked too
    if spectral and not monochromator:
        raise GonioError("a spectral plan needs the monochromator's port; give it, or a plan without [spectral]")
    strategy = dict(strategy or {"name": "fixed"})
    try:
        budget = hand_angle_modes(strategy_from_doc({"strategy": strategy, "order": {"order": order.order}}, plan), settings, order.stage_deg).budget
    except ValueError as exc:
        raise GonioError(str(exc) + ("; give one of them" if "unknown plan strategy" in str(exc) else "")) from None
    # before any port opens or anything is written: the folder writable, room for the RAW files
    check_output_dir(folder, "session folder (--out)")
    _check_room(folder, settings, min(len(plan), budget), camera, None, f"the RAW files of session {folder}",
                "free some space or give another --out")
    warnings: list = []
    bench_kw = dict(sleep=sleep, poll_interval_s=poll_interval_s, timeout=timeout, clock=clock,
                    on_warning=lambda d, f, m: warnings.append((d, f, m)), monochromator=monochromator)
    doc = _session_doc(plan, settings, seed, order, zaber_url, meter_url, camera, sample_truth, meta, strategy,
                       monochromator)
    doc["order"].update(spectral)
    rear = kinematics.detector_of(plan.angles[:, 2])
    if np.any(rear):       # reflected points first, then transmitted: one camera move between the stops
        transmission_settings(settings)
        for name in ("yaw", "tilt", "azimuth", "lamp"):   # the open beam: every stage at its zero
            lo, hi = (float(v) for v in settings["axes"][name][2:4])
            if not lo <= 0.0 <= hi:
                raise GonioError(f"the plan's transmitted points need the open-beam frame at stage zero, and "
                                 f"[axes] {name} limits [{lo:g}, {hi:g}] exclude it; widen them or drop those points")
        o = np.asarray(doc["order"]["order"], int)
        o = np.concatenate([o[~rear[o]], o[rear[o]]])
        if not spectral and not np.all(rear):    # each stop's points ordered on their own, the rear's from zero
            poses, parts = np.asarray(doc["order"]["stage_deg"], float), []
            for ids, start in ((np.flatnonzero(~rear), None), (np.flatnonzero(rear), np.zeros(4))):
                part = order_moves(poses[ids], settings, start=start)
                poses[ids] = part.stage_deg
                parts.append(ids[part.order])
            doc["order"]["order"], doc["order"]["stage_deg"] = [int(i) for i in np.concatenate(parts)], poses.tolist()
            o = np.concatenate(parts)
        doc["order"]["order"] = [int(i) for i in o]
        # the travel of that order, through the open beam's pose (stage zero) before the first transmitted point
        poses = np.asarray(doc["order"]["stage_deg"], float)[o]
        k = int(np.argmax(rear[o]))
        doc["order"]["ordered_s"] = path_time(np.insert(poses, k, 0.0, axis=0), settings)
    bench, journal, lock, doc, ident = _start_session(folder, doc, (zaber_url, meter_url, camera), bench_kw)
    return _run(folder, doc, bench, journal, lock, warnings, progress, t0, [], ident=ident, operator=operator)


def _with_devices(doc: Mapping, devices: dict) -> dict:
    """``doc`` with its ``[devices]`` table, placed after ``[ports]``."""
    out: dict = {}
    for k, v in doc.items():
        out[k] = v
        if k == "ports":
            out["devices"] = devices
    out.setdefault("devices", devices)
    return out


def _start_session(folder: Path, doc: Mapping, ports: tuple,
                   bench_kw: Mapping) -> tuple[Bench, Journal, SessionLock, dict, dict]:
    """Open every port and identify the devices, then create the folder, take its lock and write
    ``session.toml`` (with the identification as its ``[devices]`` table) and the journal: a dead
    port (or a signal while the ports open) leaves nothing behind, and on any failure what was
    opened is closed and a half-written session.toml removed.

    Returns the bench, the journal, the lock (all three handed to `_run`), the session as read
    back and the identification (`identify.identify_bench`, journalled by the run's preparation).
    """
    settings = doc["settings"]
    lock = journal = bench = None
    try:
        with Interrupts() as pre:               # a signal while the ports open: stop before writing
            bench = Bench(settings, *ports, **bench_kw)
            check_sensor(bench.camera, settings)
            ReferenceModel(settings["reference"])
            ident = identify_bench(bench)         # cheap (a few gets and *IDN?s); cleaned device text
            doc = _with_devices(doc, session_devices(ident))
            text = session_text(doc)
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
        read = read_session(folder)
        try:
            journal = Journal(folder / JOURNAL_FILE)
            journal.record_session(text, read)
        except (OSError, sqlite3.DatabaseError) as exc:
            if not disk_full(exc):
                raise
            # session.toml is written, the journal is not: a resume records it (nothing measured yet)
            raise _environment_stop(folder, read, None, exc) from None
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
    return bench, journal, lock, read, ident


def resume(session_dir, zaber_url: str | None = None, meter_url: str | None = None, camera=None,
           progress: bool = True, *, sleep: Callable[[float], None] = time.sleep,
           poll_interval_s: float = 0.05, timeout: float = 1.0, rebuild_journal: bool = False,
           remeasure: str | None = None, notify: Callable[[str], None] | None = None,
           clock: Callable[[], float] | None = None, monochromator: str | None = None,
           operator=None) -> CaptureSummary:
    """Finish a session: check it is one consistent record (`gonio.bench.session.integrity`), re-check
    positions and flags (re-home if the reference was lost), verify the journalled RAW files,
    remove orphan temporary files, skip the journalled points and measure the rest in the
    session's order.

    Points whose RAW files are missing or corrupt, and the points ``remeasure`` names
    (``"3,7,10-12"``), are measured again (their old rows are kept in ``superseded``);
    calibration frames that are missing or corrupt are taken again. ``rebuild_journal``
    replaces a missing or damaged journal first. Each of these is said in one line to
    ``notify`` and in the summary's ``notes``.

    Ports (the monochromator's too) default to those recorded in ``session.toml``; ``clock`` and
    ``operator`` as `capture`'s (this run's instrument time adds to the time the journal holds; the
    operator is asked again where the camera is before a transmitted point).
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
            monochromator = monochromator or ports.get("monochromator")
            if doc["plan"].get("wavelength_nm") is not None and not monochromator:
                raise SessionError(f"{folder}: the plan is spectral; give the monochromator's port "
                                   "(--monochromator-port) to resume on")
            bench = Bench(doc["settings"], zaber_url, meter_url, camera, sleep=sleep, poll_interval_s=poll_interval_s,
                          timeout=timeout, on_warning=lambda d, f, m: warnings.append((d, f, m)), clock=clock,
                          monochromator=monochromator)
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
    return _run(folder, doc, bench, journal, lock, warnings, progress, t0, notes, note=note, operator=operator)
