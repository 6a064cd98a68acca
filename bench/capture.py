"""The capture loop: a session that survives being killed.

`capture` creates a session folder and measures a plan; `resume` finishes one. Per point:
move (in the ordered plan), wait for IDLE, expose with automatic bracketing, read the
monitor at each exposure, merge the bracket into HDR radiance (dark frames subtracted,
saturated values excluded), average the sample and reference regions located from the
geometry, and convert to f_r with the reference:

    f_r = (S_sample / S_ref) * rho_ref / pi

with a 1-sigma propagated from both regions' standard errors. The reference certificate's
own uncertainty is a fully correlated scale error, stored apart (``scale_rel_std``). A
point's journal row is committed only when everything about it succeeded.

Operating behaviour: a rich progress bar (points, ETA, latest f_r); Ctrl-C once finishes the
current point and stops resumably, twice stops the stages and exits; the run pauses itself
(a suspender) while the lamp is off its session-start level by more than
``[lamp] drift_tolerance`` or the meter is silent, and stops resumably with a one-line reason
when that lasts longer than ``suspend_timeout_s``.
"""

from __future__ import annotations

import json
import math
import signal
import threading
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from . import kinematics
from ._camera import RawFrame, SimCamera, decode_raw
from ._files import TMP_PREFIX, remove_orphans, sha256_file
from ._hdr import Exposure, NoiseModel, choose_bracket, ladder, merge
from ._journal import (JOURNAL_FILE, RAW_DIR, SESSION_FILE, Journal, read_session, verify_files, versions,
                       write_session)
from ._ordering import order_moves
from ._scpi import PowerMeter
from ._settings import AXES
from ._zaber import Goniometer, LedSource, ZaberChain
from .errors import CommunicationError, DeviceError, GonioError, SessionError
from .plans import Plan, plan_from_dict, require_reachable

__all__ = ["capture", "resume", "CaptureSummary", "CaptureInterrupted", "Bench", "estop"]


class CaptureInterrupted(GonioError):
    """Ctrl-C pressed twice: the stages were stopped; the session is resumable."""


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
        self.sleep = sleep
        self.chain = self.meter = self.camera = None
        try:
            self.chain = ZaberChain(zaber_url, baudrate, timeout, on_warning=on_warning)
            self.gonio = Goniometer(self.chain, settings, poll_interval_s=poll_interval_s, sleep=sleep)
            self.led = LedSource(self.chain, int(settings.get("lamp", {}).get("device", 2)))
            self.meter = PowerMeter(meter_url, baudrate, timeout)
            self.camera = _open_camera(camera, 30.0)
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        for dev in (self.camera, self.meter, self.chain):
            if dev is not None:
                try:
                    dev.close()
                except Exception:
                    pass


def estop(zaber_url: str, baudrate: int = 115200, n_devices: int = 2) -> int:
    """Send the emergency stop to every device on the chain at once (``/0 0 estop``).

    Returns the number of devices that answered.
    """
    chain = ZaberChain(zaber_url, baudrate, timeout=0.5, retries=0)
    try:
        return len(chain.broadcast("estop", n_devices))
    finally:
        chain.close()


# -- Ctrl-C ----------------------------------------------------------------------------------

class _Interrupts:
    """First SIGINT: ask to stop at the next point boundary; second: KeyboardInterrupt."""

    def __init__(self):
        self.requested = False
        self._old = None

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            self._old = signal.signal(signal.SIGINT, self._handler)
        return self

    def _handler(self, signum, frame):
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True

    def __exit__(self, *exc):
        if self._old is not None:
            signal.signal(signal.SIGINT, self._old)


# -- the measurement of one point ----------------------------------------------------------------

class _Suspended(Exception):
    """The lamp or the meter is not fit to measure; the point must wait and be measured again."""


class _Session:
    """One run over a session folder (shared by `capture` and `resume`)."""

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
        ref = self.settings["reference"]
        self.rho = np.broadcast_to(np.asarray(ref["reflectance"], float), (3,)).copy()
        self.darks: dict[float, RawFrame] = {}
        lamp = self.settings.get("lamp", {})
        self.drift_tol = float(lamp.get("drift_tolerance", 0.2))
        self.bracket_tol = float(lamp.get("bracket_tolerance", 0.02))
        self.suspend_poll = float(lamp.get("suspend_poll_s", 5.0))
        self.suspend_timeout = float(lamp.get("suspend_timeout_s", 120.0))
        self.p_ref = None
        self.results: dict[int, tuple[np.ndarray, np.ndarray]] = {
            r["idx"]: (np.asarray(r["brdf"]), np.asarray(r["brdf_std"])) for r in journal.points()}
        self.reciprocity: list[dict] = []

    # -- instrument preparation ----------------------------------------------------------
    def prepare(self) -> None:
        """Check flags and positions, home if the reference is lost, take missing darks, lamp on."""
        b = self.bench
        flags = b.gonio.connect()
        faults = [f for f in flags if f.startswith("F")]
        if faults:
            b.chain.clear_flags(b.gonio.devices[0])
            flags = b.gonio.flags()
            faults = [f for f in flags if f.startswith("F")]
            if faults:
                from ._zaber import FLAG_MEANINGS
                raise DeviceError("stages report fault(s) " + ", ".join(f"{f} ({FLAG_MEANINGS.get(f, 'fault')})" for f in faults)
                                  + "; clear the cause, then resume the session")
        if any(f in ("WR", "WH") for f in flags):
            self.journal.event("home", f"stages lost their reference ({' '.join(flags)}): homing")
            b.gonio.home()
        b.chain.clear_flags(b.gonio.devices[0])
        b.meter.identify()
        m = self.settings.get("meter", {})
        b.meter.configure(float(m.get("wavelength_nm", 550)), int(m.get("averaging", 10)))
        self._take_darks()
        b.led.set_flux(float(self.settings.get("lamp", {}).get("flux", 1.0)))
        b.led.on()
        self.p_ref = self._p_ref()

    def _p_ref(self) -> float:
        row = self.journal.db.execute(
            "SELECT text FROM events WHERE kind = 'p_ref' ORDER BY id LIMIT 1").fetchone()
        if row is not None:
            return float(row[0])
        p = self.bench.meter.power()
        if not p > 0:
            raise DeviceError(f"the monitor reads {p:g} W with the lamp on; check the LED and the meter, "
                              "then resume the session")
        self.journal.event("p_ref", repr(p))
        return p

    def _take_darks(self) -> None:
        have = self.journal.darks()
        missing = [t for t in self.rungs if float(t) not in have]
        if missing:
            self.bench.led.off()
        for t in self.rungs:
            t = float(t)
            if t in have:
                file, digest = have[t]
                path = self.folder / file
                if not path.is_file() or sha256_file(path) != digest:
                    raise SessionError(f"dark frame {file} is missing or corrupt; the session folder is damaged")
            else:
                file = f"{RAW_DIR}/dark_{t * 1e6:010.0f}us.dng"
                digest = self.bench.camera.expose(t, self.folder / file)
                self.journal.record_dark(t, file, digest)
            self.darks[t] = decode_raw(self.folder / file)

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
    def _expose(self, idx: int, t: float) -> tuple[Exposure, dict]:
        file = f"{RAW_DIR}/p{idx:05d}_{t * 1e6:010.0f}us.dng"
        digest = self.bench.camera.expose(t, self.folder / file)
        p = self._power()
        frame = decode_raw(self.folder / file)
        return Exposure(t, p, frame, self.darks[t]), {"seconds": t, "file": file, "sha256": digest, "power": p}

    def measure(self, idx: int) -> dict:
        """Move to point ``idx``, bracket, merge, calibrate; return the journal row's fields."""
        b = self.bench
        stage = self.stage[idx]
        b.gonio.move_to(dict(zip(AXES, stage)))
        b.sleep(float(self.settings.get("motion", {}).get("settle_s", 0.0)))
        sm, rm = kinematics.roi_masks(stage, self.settings)
        both = sm | rm
        if sm.sum() < 2 or rm.sum() < 2:
            raise GonioError(f"point {idx}: the sample or reference square is not in view; "
                             "remove the point from the plan")
        p_start = self._power()
        taken: dict[float, tuple[Exposure, dict]] = {}
        t = self.probe
        # probe down the ladder until the regions are unsaturated (or the ladder ends)
        while True:
            taken[t] = self._expose(idx, t)
            e = taken[t][0]
            peak = float(e.frame.peak[:, both].max())
            if peak < self.sat * e.frame.full_scale or t <= self.rungs[0]:
                break
            k = int(np.searchsorted(self.rungs, t)) - 3
            t = float(self.rungs[max(0, k)])
        for _ in range(3):
            e = taken[t][0]
            sig = e.frame.signal - e.dark.signal
            peak = float((e.frame.peak - np.maximum(e.dark.signal, 0))[:, both].max())
            low = float(sig[:, both].min())
            bracket = choose_bracket(self.rungs, t, peak, low, e.frame.full_scale, self.noise,
                                     self.sat, self.snr)
            if bracket[0] == t or peak > 0.05 * e.frame.full_scale or bracket[0] in taken:
                break
            t = bracket[0]                      # dim probe: confirm the shortest rung first
            taken[t] = self._expose(idx, t)
        for tb in bracket:
            if tb not in taken:
                taken[tb] = self._expose(idx, tb)
        used = [taken[tb] for tb in sorted(taken)]
        powers = [d["power"] for _, d in used]
        if max(powers) / min(powers) - 1.0 > self.bracket_tol:
            raise _Suspended(f"the lamp changed by {100 * (max(powers) / min(powers) - 1):.1f} % within "
                             f"point {idx}'s bracket (tolerance {100 * self.bracket_tol:g} %)")
        hdr = merge([u[0] for u in used], self.noise, self.sat)
        stats = {}
        saturated = False
        for name, mask in (("sample", sm), ("reference", rm)):
            rad = hdr.radiance[:, mask]
            var = hdr.var[:, mask]
            good = np.isfinite(rad)
            saturated |= bool((~good).any())
            n = good.sum(1)
            mean = np.array([rad[c, good[c]].mean() if n[c] else np.nan for c in range(3)])
            se_emp = np.array([rad[c, good[c]].std(ddof=1) / math.sqrt(n[c]) if n[c] > 1 else np.nan
                               for c in range(3)])
            se_mod = np.array([math.sqrt(var[c, good[c]].sum()) / n[c] if n[c] else np.nan for c in range(3)])
            stats[name] = {"mean": mean, "se": se_emp, "se_model": se_mod, "n": n}
        s, r = stats["sample"], stats["reference"]
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio = s["mean"] / r["mean"]
            brdf = ratio * self.rho / math.pi
            rel = np.sqrt((s["se"] / s["mean"]) ** 2 + (r["se"] / r["mean"]) ** 2)
            std = np.abs(brdf) * rel
        detail = {
            "exposures": [d for _, d in used],
            "p_start": p_start,
            "bracket": bracket,
            **{f"{k}_{q}": [float(v) for v in stats[k][q]] for k in stats for q in ("mean", "se", "se_model", "n")},
        }
        return {"brdf": brdf, "brdf_std": std, "saturated": saturated or not np.all(np.isfinite(brdf)),
                "detail": detail, "stage": stage}

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
    def run(self) -> tuple[int, str]:
        done = self.journal.done()
        todo = [int(i) for i in self.order if int(i) not in done]
        for i in sorted(done):
            r = self._reciprocity(i)
            if r is not None and r["i"] == i:
                self.reciprocity.append(r)
        bar = _ProgressBar(len(self.plan), len(done), self.progress)
        n_new = 0
        stopped = ""
        try:
            for idx in todo:
                if self.stop():
                    stopped = "stopped by Ctrl-C; run the capture again with --resume to finish"
                    break
                while True:
                    try:
                        res = self.measure(idx)
                        break
                    except _Suspended as exc:
                        self._wait_until_fit(str(exc))
                self.journal.record_point(idx, self.plan.angles[idx], res["stage"], res["brdf"],
                                          res["brdf_std"], res["saturated"], res["detail"])
                self.results[idx] = (np.asarray(res["brdf"]), np.asarray(res["brdf_std"]))
                r = self._reciprocity(idx)
                if r is not None:
                    self.reciprocity.append(r)
                n_new += 1
                bar.advance(res["brdf"], r)
        finally:
            bar.close()
        return n_new, stopped


class _ProgressBar:
    """rich progress: points done, ETA, the latest f_r (and reciprocity when a pair closes)."""

    def __init__(self, total: int, done: int, enabled: bool):
        self.p = None
        if not enabled:
            return
        from rich.console import Console
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

        self.p = Progress(TextColumn("capture"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
                          TextColumn("{task.fields[latest]}"), console=Console(stderr=True))
        self.task = self.p.add_task("capture", total=total, completed=done, latest="")
        self.p.start()

    def advance(self, brdf, recip) -> None:
        if self.p is None:
            return
        text = "f_r " + " ".join(f"{v:.4g}" for v in brdf) + " sr^-1"
        if recip is not None:
            text += f"  reciprocity {100 * np.nanmax(np.abs(recip['rel'])):.1f} %"
        self.p.update(self.task, advance=1, latest=text)

    def close(self) -> None:
        if self.p is not None:
            self.p.stop()


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
        import json
        doc["sample_truth"] = {"json": sample_truth if isinstance(sample_truth, str) else json.dumps(sample_truth, sort_keys=True)}
    if meta:
        doc["meta"] = dict(meta)
    return doc


def _run(folder: Path, doc: Mapping, bench: Bench, warnings: list, progress: bool, t0: float) -> CaptureSummary:
    journal = None
    try:
        journal = Journal(folder / JOURNAL_FILE)
        with _Interrupts() as intr:
            sess = _Session(folder, doc, bench, journal, progress, lambda: intr.requested)
            try:
                sess.prepare()
                n_new, stopped = sess.run()
            except KeyboardInterrupt:
                try:
                    bench.gonio.stop()
                finally:
                    journal.event("stop", "Ctrl-C twice: stages stopped")
                raise CaptureInterrupted(f"stopped by Ctrl-C twice; the stages were stopped and the session "
                                         f"is resumable with --resume {folder}") from None
            except GonioError as exc:
                journal.event("stop", str(exc))
                raise
            finally:
                for d, f, m in warnings:
                    journal.event("warning", f"device {d}: {f} {m}")
                journal.event("comm", json.dumps({
                    "zaber_retries": bench.chain.retries_used, "zaber_reconnects": bench.chain.reconnects,
                    "meter_retries": bench.meter.retries_used, "meter_reconnects": bench.meter.reconnects,
                    "camera_retries": getattr(bench.camera, "retries_used", 0)}))
                try:
                    bench.led.off()
                except GonioError:
                    pass
        remove_orphans(folder / RAW_DIR)        # late files of a killed earlier process, if any
        n_done = len(journal.done())
        o = doc["order"]
        return CaptureSummary(folder, len(sess.plan), n_done, n_new, n_done == len(sess.plan), stopped,
                              sess.reciprocity, o["naive_s"], o["ordered_s"], o["bound_s"],
                              time.perf_counter() - t0)
    finally:
        if journal is not None:
            journal.close()
        bench.close()


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
        Unreachable plan, folder already a session, a port that does not open, a fault; the
        session (once written) stays resumable.
    """
    t0 = time.perf_counter()
    folder = Path(session_dir)
    if (folder / SESSION_FILE).exists():
        raise SessionError(f"{folder} already holds a session; resume it with --resume {folder} or choose another --out")
    if folder.exists() and not folder.is_dir():
        raise SessionError(f"{folder} is a file, not a folder; choose another --out")
    if folder.is_dir():
        # a capture killed before its session.toml existed leaves only an empty raw/ and temporary files
        def leftover(p: Path) -> bool:
            if p.is_dir():
                return p.name == RAW_DIR and not any(p.iterdir())
            return p.name.startswith(TMP_PREFIX)
        if not all(leftover(p) for p in folder.iterdir()):
            raise SessionError(f"{folder} is not empty; choose a new folder for the session")
        remove_orphans(folder)
    stage = require_reachable(plan, settings)
    for k, st in enumerate(stage):
        sm, rm = kinematics.roi_masks(st, settings)
        if sm.sum() < 2 or rm.sum() < 2:
            raise GonioError(f"plan {plan.name!r} point {k} {plan.angles[k].tolist()}: the sample or reference "
                             "square is not in the camera's view; remove the point from the plan")
    order = order_moves(stage, settings)
    # open every port before anything is written: a dead port leaves nothing behind
    warnings: list = []
    bench = Bench(settings, zaber_url, meter_url, camera, sleep=sleep, poll_interval_s=poll_interval_s,
                  timeout=timeout, on_warning=lambda d, f, m: warnings.append((d, f, m)))
    try:
        doc = _session_doc(plan, settings, seed, order, zaber_url, meter_url, camera, sample_truth, meta)
        write_session(folder, doc)
        doc = read_session(folder)
    except BaseException:
        bench.close()
        raise
    return _run(folder, doc, bench, warnings, progress, t0)


def resume(session_dir, zaber_url: str | None = None, meter_url: str | None = None, camera=None,
           progress: bool = True, *, sleep: Callable[[float], None] = time.sleep,
           poll_interval_s: float = 0.05, timeout: float = 1.0) -> CaptureSummary:
    """Finish a session: re-check positions and flags (re-home if the reference was lost),
    verify the journalled RAW files, remove orphan temporary files, skip the journalled
    points and measure the rest in the session's order.

    Ports default to those recorded in ``session.toml``.
    """
    t0 = time.perf_counter()
    folder = Path(session_dir)
    doc = read_session(folder)
    remove_orphans(folder / RAW_DIR)
    remove_orphans(folder)
    ports = doc.get("ports", {})
    zaber_url = zaber_url or ports.get("zaber")
    meter_url = meter_url or ports.get("meter")
    if camera is None:
        camera = ports.get("camera")
        if not (isinstance(camera, str) and "://" in camera or isinstance(camera, str) and camera.startswith("/")):
            raise SessionError(f"{folder} was captured with a {camera} camera; give the camera to resume with")
    if not zaber_url or not meter_url:
        raise SessionError(f"{folder}: give the ports to resume on (--port and --meter-port)")
    with Journal(folder / JOURNAL_FILE) as j:
        bad = verify_files(folder, j)
    if bad:
        raise SessionError(f"{len(bad)} journalled RAW file(s) are missing or corrupt (first: {bad[0]}); "
                           "the session folder is damaged")
    warnings: list = []
    bench = Bench(doc["settings"], zaber_url, meter_url, camera, sleep=sleep, poll_interval_s=poll_interval_s,
                  timeout=timeout, on_warning=lambda d, f, m: warnings.append((d, f, m)))
    return _run(folder, doc, bench, warnings, progress, t0)
