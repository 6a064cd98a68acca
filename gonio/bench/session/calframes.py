"""The calibration frames of a session: darks, the flat field, the colour chart.

`CalibrationFrames` is the part of `_session._Session` that takes them once per session
(``prepare``) and reads them back on a resume: dark frames for every rung of the exposure
ladder, the flat field as one unit (its names reserved together, each frame checked as it
comes, one file-system sync and one journal transaction for the set), and one frame of the
ColorChecker. It uses the session's ``folder``, ``bench``, ``journal``, ``settings``,
``rungs``, ``probe``, ``sat``, ``darks`` and its RAW name reservation (``_fresh``,
``_fresh_set``).
"""

from __future__ import annotations

import numpy as np

from gonio.core.files import TMP_PREFIX, is_tiff, make_durable
from gonio.bench.measure.hdr import flat_gain
from gonio.bench.session.journal import RAW_DIR
from gonio.bench.drivers import BadDelivery, RawFrame, decode_raw, read_verified
from gonio.core.errors import GonioError, SessionError


class CalibrationFrames:
    """Darks, flats and the chart of one session (a mixin of `_session._Session`)."""

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

    def _take_darks(self, say=lambda text: None) -> None:
        """Dark frames (lamp off) for every rung of the exposure ladder, journalled once per session."""
        have = {v[0]: v for v in self.journal.frames("dark").values()}
        self._drop_uncommitted("dark_", {v[1] for v in have.values()})
        if any(float(t) not in have for t in self.rungs):
            self.bench.led.off()
        for k, t in enumerate(map(float, self.rungs)):
            if t in have:
                _, file, digest = have[t]
            else:
                say(f"dark frames, lamp off: {k + 1} of {len(self.rungs)} ({t:g} s)")
                self.bench.checkpoint()
                file = self._fresh(f"dark_{t * 1e6:010.0f}us.dng")
                digest = self.bench.camera.expose(t, self.folder / file)
                self.journal.record_frame(f"dark:{t!r}", "dark", t, file, digest)
            self.darks[t] = self._load(file, digest, peak=False)     # signal only: what a dark is used for

    def _take_flats(self, say=lambda text: None) -> None:
        """Flat-field frames for the PRNU correction (cameras with a ``flat`` source only).

        The exposure is the longest rung that keeps the flat below 60 % of full scale, found
        from probe frames; ``[capture] flat_frames`` frames are averaged. An incomplete set
        (a crash while taking it) is taken again whole. Whether a session has a flat field is
        decided once, when it starts.

        The set is one unit (:meth:`_take_flat_set`): its names reserved in one journal
        transaction, each frame checked and renamed as it comes, averaged from the bytes
        checked, then all made durable with one file-system sync and journalled in one
        transaction. A frame at a time (two fsyncs and two journal commits a frame) the
        default 512 frames cost ~4 s of a quick session's ~6 s on this machine's disk, for a
        durability that the retake of an incomplete set never used. The frames of an incomplete
        set are deleted before it is taken again (a kill left up to ``flat_frames - 1`` of them).
        """
        cam = self.bench.camera
        n = int(self.settings["capture"].get("flat_frames", 16))
        if self.journal.first_event("no_flat") is not None:
            return                               # decided when the session started: keep it so
        have = self.journal.frames("flat")
        if len(have) != n or n < 1:              # none yet, or a crash while taking them (or none wanted)
            self.journal.forget_frames("flat")
            self._drop_uncommitted("flat_", set())   # the frames a killed run took of its set
            if not hasattr(cam, "flat") or n < 1:
                self.journal.event("no_flat", "no flat-field source: pixel response non-uniformity not corrected")
                return
            say("flat-field frames: finding the exposure")
            self.gain = self._take_flat_set(cam, self._flat_exposure(cam), n, say)
            return
        t = next(iter(have.values()))[0]
        say(f"averaging the {len(have)} flat-field frames")
        self.gain = flat_gain((self._load(f, d, peak=False) for _, f, d in have.values()), self.darks[t])

    def _take_flat_set(self, cam, t: float, n: int, say) -> np.ndarray:
        """Take, average, make durable and journal ``n`` flat frames of ``t`` s; the gain."""
        files = self._fresh_set([f"flat_{k:03d}.dng" for k in range(n)])
        take = getattr(cam, "flat_deferred", None)
        rows = []

        def frames():
            for k, file in enumerate(files):
                say(f"flat-field frames: {k + 1} of {n} ({t:g} s each)")
                self.bench.checkpoint()
                path = self.folder / file
                data = None
                if take is not None:
                    delivery = take(t, path)
                    try:
                        data = delivery.finish(durable=False)     # checked, renamed; synced below
                    except BadDelivery as exc:                    # spoilt: taken again, checked
                        if hasattr(cam, "retries_used"):
                            cam.retries_used += 1
                        self.journal.event("warning", f"flat-field frame {k + 1}: {exc}; taking it again")
                if data is None:        # no deferred delivery, or a spoilt one: checked and committed
                    digest = cam.flat(t, path)
                    frame = self._load(file, digest, peak=False)
                else:
                    digest, frame = delivery.digest, decode_raw(path, data=data, peak=False)
                rows.append((f"flat:{k:03d}", "flat", t, file, digest))
                yield frame

        gain = flat_gain(frames(), self.darks[t])
        make_durable([self.folder / file for file in files])
        self.journal.record_frames(rows)
        return gain

    def _drop_uncommitted(self, prefix: str, committed: set) -> None:
        """Delete the RAW files ``raw/PREFIX*`` a killed run reserved and wrote but never
        committed (not in ``committed``): they are taken again under new names. Only DNGs (any
        other file is someone else's) and never after a journal rebuild. Called before any is
        taken, holding the session lock; a kill between two deletions leaves the rest to the
        next run."""
        if self.journal.first_event("rebuild") is not None:
            return                 # a rebuild keeps every RAW file it could not place
        for file in sorted(self.reserved):
            if file.startswith(f"{RAW_DIR}/{prefix}") and file not in committed and is_tiff(self.folder / file):
                (self.folder / file).unlink(missing_ok=True)

    def _take_chart(self, say=lambda text: None) -> None:
        """One frame of the ColorChecker in the holder's chart slot, lamp on (``[capture]
        colour_chart = true`` and a camera with a ``chart`` source): export fits the colour
        matrix to it (gonio/bench/measure/colour_matrix.py). The longest rung from the probe down that does
        not saturate; journalled once per session."""
        cam = self.bench.camera
        if not self.settings["capture"].get("colour_chart", False) or self.journal.frames("chart"):
            return
        if not hasattr(cam, "chart"):
            raise GonioError("[capture] colour_chart = true, but this camera has no chart source; "
                             "capture the ColorChecker yourself and give it to `gonio export --colour-chart`")
        say("colour chart: one frame of the ColorChecker")
        for t in self.rungs[self.rungs <= self.probe][::-1]:
            file = self._fresh("colour_chart.dng")
            digest = cam.chart(float(t), self.folder / file)
            frame = decode_raw(self.folder / file)
            if float(frame.peak.max()) < self.sat * frame.full_scale or t <= self.rungs[0]:
                self.journal.record_frame("chart:000", "chart", float(t), file, digest)
                return                    # (a saturated try stays in raw/, reserved, unused)

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
