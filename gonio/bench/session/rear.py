"""A session's transmitted points: the detector arm's rear stop and the open beam (issue 37).

`RearStop` is the part of `run._Session` that measures a plan's points with theta_o > 90. Before
the first of them the operator moves the camera to the rear stop; once per session the sample
comes out of the holder for the open-beam frame (ASTM E2387: lamp on and settled, the lamp
straight behind the empty aperture, the longest rung that keeps it below saturation, dark
subtracted, flat-fielded, per unit monitor power: `OpenBeam`) and goes back. Each step is an
``operator`` journal event (`gonio.bench.session.stops`: who performs it), the frame a
calibration frame (kind ``open_beam``) with its digest, its rate an ``open_beam`` event, so a
killed session resumes on the right stop, neither retakes nor loses the frame, and asks the
operator again where the camera and the sample are. A transmitted point is the sample region
alone (`kinematics.roi_masks(..., rear=True)`) merged like any other, per unit monitor power:
f_t = (S_t / S_open) a / (Omega cos theta_i) (`transmission.btdf`); its monitor reading does
not cancel as the reference square's does, so its scatter joins the point's own uncertainty.
"""

from __future__ import annotations

import json
import math

import numpy as np

from gonio.bench.measure.hdr import Exposure
from gonio.bench.measure.point import _runs, merged_region_stats, probe_levels
from gonio.bench.measure.transmission import OpenBeam, btdf, journalled_open_beam, transmission_settings
from gonio.bench.plan import kinematics
from gonio.bench.session.stops import STEPS, operator_for
from gonio.bench.settings import AXES
from gonio.core.errors import DeviceError, GonioError

OPEN_BEAM_FRAME = "open_beam:000"
#: the open beam's brightest aperture pixel stays below this fraction of the saturation level
OPEN_BEAM_HEADROOM = 0.7
#: monitor readings that measure the lamp's settling and the meter's scatter before the open beam
MONITOR_READINGS = 8


class RearStop:
    """The rear stop of one session (a mixin of `run._Session`)."""

    def _init_rear(self, operator=None) -> None:
        self.rear = np.asarray(kinematics.detector_of(self.plan.angles[:, 2]), bool).reshape(-1)
        self._operator_given = operator
        self._operator = None
        self._confirmed: dict[str, str] = {}        # what the operator confirmed in this run
        self.open_beam: OpenBeam | None = None
        self.open_beam_info: dict = {}
        self._state = {"stop": "front", "sample": "in"}
        if self.rear.any():
            self._state = {w: self._journalled(w) for w in self._state}
            transmission_settings(self.settings)    # a malformed [transmission]: one line, before any move
            self.open_beam, self.open_beam_info = self._journalled_open_beam()

    # -- the journal ------------------------------------------------------------------------
    def _journalled(self, what: str) -> str:
        """The last state the operator's steps left (``stop``: front at first; ``sample``: in)."""
        state = {"stop": "front", "sample": "in"}[what]
        for _, kind, text in self.journal.events():
            if kind == "operator":
                step = json.loads(text).get("step")
                if step in STEPS and STEPS[step][1][0] == what:
                    state = STEPS[step][1][1]
        return state

    def _journalled_open_beam(self) -> tuple[OpenBeam | None, dict]:
        """The session's open beam (`transmission.journalled_open_beam`: a frame found damaged is
        forgotten by the resume's repair, and taken again)."""
        return journalled_open_beam(self.journal.events(), self.journal.frames("open_beam"), self.settings)

    def _step(self, step: str) -> None:
        """Ask the operator for ``step`` (the simulator's twin does it), then journal it."""
        if self._operator is None:
            self._operator = operator_for(self.bench, self.folder, self._operator_given)
        self._operator.perform(step)
        self.journal.event("operator", json.dumps({"step": step, "by": self._operator.name}))
        what, value = STEPS[step][1]
        self._confirmed[what] = self._state[what] = value

    # -- before a point ----------------------------------------------------------------------
    def _to_stop(self, idx: int, goal):
        """The camera on point ``idx``'s stop (the open beam taken first for the rear one) and the
        sample in the holder, asking the operator for what this run has not confirmed; returns
        the move sent ahead (None where the stages had to go elsewhere meanwhile). A session
        whose journal never left the front stop asks nothing: a reflection plan is as before."""
        want = "rear" if self.rear[idx] else "front"
        if self._state["sample"] == "in" and (want == "front" or self.open_beam is not None) and (
                self._confirmed.get("stop") == want or (want == "front" == self._state["stop"]
                                                        and "stop" not in self._confirmed)):
            return goal
        if goal is not None:                     # the stages finish the move sent ahead first
            self.bench.gonio.finish_move(goal)
            goal = None
        if self._confirmed.get("stop") != want:
            self._step(f"{want}_stop")
        if want == "rear" and self.open_beam is None:
            self._take_open_beam()
        if self._state["sample"] == "out":
            self._step("sample_in")
        return goal

    # -- the open beam -------------------------------------------------------------------------
    def _monitor(self) -> tuple[float, float]:
        """`MONITOR_READINGS` readings, the lamp settled: their mean (W) and one reading's relative
        scatter; waits (`_wait_until_fit`'s poll and timeout) while they spread by more than
        [lamp] bracket_tolerance."""
        for _ in range(max(1, math.ceil(self.suspend_timeout / self.suspend_poll)) + 1):
            r = np.array([self._power() for _ in range(MONITOR_READINGS)])
            rel = float(r.std(ddof=1) / r.mean())
            if (r.max() - r.min()) / r.mean() <= self.bracket_tol:
                return float(r.mean()), rel
            self.journal.event("pause", f"the lamp is settling ({100 * rel:.2f} % scatter): waiting for the open beam")
            self.bench.sleep(self.suspend_poll)
        raise DeviceError(f"the lamp did not settle within {self.suspend_timeout:g} s for the open beam; check the LED, "
                          "then resume the session")

    def _open_frame(self, t: float):
        self.bench.checkpoint()
        file = self._fresh(f"open_beam_{t * 1e6:010.0f}us.dng")
        digest = self.bench.camera.expose(t, self.folder / file)
        return file, digest, self._load(file, digest)

    def _take_open_beam(self) -> None:
        """The open-beam frame at the stages' zero (the lamp straight behind the aperture, seen
        from the rear stop), once per session; `GonioError` (nothing journalled) without signal."""
        b = self.bench
        stage = np.zeros(4)
        b.gonio.move_to(dict(zip(AXES, (float(v) for v in stage))))
        b.sleep(float(self.settings.get("motion", {}).get("settle_s", 0.0)))
        if self._confirmed.get("sample") != "out":
            self._step("sample_out")
        p, p_rel = self._monitor()              # the lamp on and settled, before any frame is written
        aperture = kinematics.roi_masks(stage, self.settings, rear=True)[0]
        runs = _runs(aperture)
        rungs, t, tried = self.rungs, float(self.probe), {}
        while True:                              # down from the probe while saturated, then the longest safe rung
            file, digest, frame = tried.get(t) or self._open_frame(t)
            tried[t] = (file, digest, frame)
            peak, over, _ = probe_levels(frame, self.darks[t], runs)
            k = int(np.searchsorted(rungs, t))
            if peak >= self.sat * frame.full_scale and k > 0:
                t = float(rungs[max(0, k - 3)])
                continue
            fits = rungs[rungs * max(over, 1e-9) / t <= OPEN_BEAM_HEADROOM * self.sat * frame.full_scale]
            best = float(fits[-1]) if len(fits) else float(rungs[0])
            if best in tried or best == t:
                t = t if peak < self.sat * frame.full_scale else best
                break
            t = best
        file, digest, frame = tried[t]
        st = merged_region_stats([Exposure(t, p, frame, self.darks[t])], self.noise, (aperture,), self.sat, self.gamma,
                                 self.gain)[0]
        self._drop_uncommitted("open_beam_", {file})        # the tries not kept
        mean, se = np.asarray(st["mean"], float), np.asarray(st["se"], float)
        if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(se)) and np.all(mean > self.snr * se)):
            (self.folder / file).unlink(missing_ok=True)
            raise GonioError(f"the open beam has no signal through the aperture (mean {np.round(mean, 3).tolist()} "
                             f"+- {np.round(se, 3).tolist()} DN/(s W)): check the lamp, the attenuator and that the "
                             f"sample is out, then resume with `gonio capture --resume {self.folder}`")
        # the frame's scatter and its monitor reading's (the mean of the readings), per channel
        u = np.hypot(se, mean * p_rel / math.sqrt(MONITOR_READINGS))
        level = (mean * t * p / frame.full_scale).tolist()
        info = {"file": file, "sha256": digest, "seconds": t, "power": p, "monitor_rel_u": p_rel,
                "rate": mean.tolist(), "rate_u": u.tolist(), "level": level, "n": int(np.max(st["n"])),
                "stage": stage.tolist()}
        self.journal.event("open_beam", json.dumps(info))        # first: a frame without it is taken again
        self.journal.record_frame(OPEN_BEAM_FRAME, "open_beam", t, file, digest)
        self.open_beam, self.open_beam_info = self._journalled_open_beam()

    # -- a transmitted point ---------------------------------------------------------------------
    def _rear_regions(self, stage) -> tuple[np.ndarray, np.ndarray]:
        """The sample region seen from the rear stop, and an empty reference region (the open beam
        normalises transmission, not the reference square)."""
        sm = kinematics.roi_masks(stage, self.settings, rear=True)[0]
        return sm, np.zeros_like(sm)

    def _reduce_rear(self, shot: dict, exposures: list, gain) -> dict:
        """`_reduce` of a transmitted point: f_t and its 1-sigma from the sample region's rate."""
        idx = shot["idx"]
        sm = shot["masks"][0]
        s = merged_region_stats(exposures, self.noise, (sm,), self.sat, self.gamma, gain)[0]
        ti = float(self.plan.angles[idx, 0])
        p_rel = float(self.open_beam_info.get("monitor_rel_u", 0.0))
        mean = np.asarray(s["mean"], float)
        with np.errstate(invalid="ignore", divide="ignore"):
            u = np.hypot(np.asarray(s["se"], float), mean * p_rel)
            f, fu = (v[0] for v in btdf(mean[None], u[None], self.open_beam, [ti]))
            if self.stray_floor > 0:             # the calibrated floor, as the front stop's: floor / pi per irradiance
                f = f - self.stray_floor / (math.pi * math.cos(math.radians(ti)))
            f = np.where(np.isfinite(fu), f, np.nan)
        detail = {"exposures": [d for _, d in shot["used"]], "p_start": shot["p_start"], "bracket": shot["bracket"],
                  **{f"sample_{m}": [float(v) for v in s[m]] for m in ("mean", "se", "se_model", "n")},
                  "n_saturated": {"sample": int(s["n_saturated"])}, "stop": "rear", "monitor_rel_u": p_rel,
                  "open_beam_level": self.open_beam_info.get("level"), "open_beam_sha256": self.open_beam_info.get("sha256")}
        detail.update(shot.get("tuned") or {})
        return {"brdf": f, "brdf_std": fu, "saturated": bool(s["n_saturated"]) or not np.all(np.isfinite(f)),
                "detail": detail, "stage": shot["stage"]}
