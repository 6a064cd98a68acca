"""The point pipeline of one run: bracket point k, send the stages to k+1, reduce k meanwhile.

`_Session.run` walks the points the journal lacks; `Pipeline` holds what lives between two
points of that walk: the point whose reduction runs in the worker thread (not yet
journalled), the move sent ahead, and how often each point's files were taken again. A
point is journalled only once its reduction is done and its RAW files checked and committed.
A point's instrument time (the bench's clock, journalled as ``detail["instrument_s"]``) runs from
the end of the previous bracket of the run (or the run's start) to the end of its own: the move
sent ahead, settling, its exposures and monitor readings, any pause, and whatever the host kept
the stages waiting for; a bracket taken again after a spoilt file adds to it.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

from gonio.bench.drivers import BadDelivery
from gonio.core.errors import DeviceError


class _Suspended(Exception):
    """The lamp or the meter is not fit to measure: wait, then take the point again."""


class Pipeline:
    """One run's point pipeline over a `_Session` (see the module notes)."""

    def __init__(self, session, todo: list, bar):
        self.session = session
        self.todo = todo                 # taken again points are inserted next
        self.bar = bar
        self.pending = None              # (idx, future of its reduction): not yet journalled
        self.goal = None                 # the move sent ahead, not yet waited for
        self.retakes: dict[int, int] = {}
        self.n_new = 0
        self.pool = ThreadPoolExecutor(1, thread_name_prefix="gonio-reduce")
        self.clock = session.clock
        self.mark = self.clock()         # the end of the last bracket (the run's start at first)
        self.spent: dict[int, float] = {}   # instrument time per point not yet journalled, s

    def step(self, n: int, idx: int) -> None:
        """Bracket point ``idx`` (the ``n``-th of ``todo``), send the stages on, reduce it."""
        s = self.session
        shot = self._bracket(idx)
        now = self.clock()
        self.spent[idx] = self.spent.get(idx, 0.0) + max(0.0, now - self.mark)
        self.mark = now
        ahead = self.todo[n + 1] if n + 1 < len(self.todo) and not s.stop() else None
        if ahead is not None:
            self.goal = s._start_move(ahead)          # the stages move while the host works
        self.pending = (idx, self.pool.submit(s._reduce, shot))
        del shot
        if ahead is not None:
            s._masks(s.stage[ahead], bool(s.rear[ahead]))   # the next regions, during the move
        try:
            self.commit_pending()                      # point k, still during the move
        except BadDelivery as exc:
            self._retake(n, idx, exc)

    def _bracket(self, idx: int) -> dict:
        """The bracket of ``idx``, waiting out a lamp or meter not fit to measure."""
        s = self.session
        why = ""
        for _ in range(s.MAX_ATTEMPTS):
            try:
                shot = s._bracket(idx, self.goal)
                break
            except _Suspended as exc:
                self.goal = None
                why = str(exc)
                s._wait_until_fit(why)
        else:
            raise DeviceError(f"point {idx} failed {s.MAX_ATTEMPTS} times ({why}); "
                              "check the lamp, then resume the session")
        self.goal = None
        return shot

    def commit_pending(self) -> None:
        """Journal the point whose reduction is pending (waiting for it)."""
        if self.pending is not None:
            idx, fut = self.pending
            self.pending = None
            res = fut.result()
            res["detail"]["instrument_s"] = self.spent.pop(idx, 0.0)
            self.session._commit(idx, res, self.bar)
            self.n_new += 1

    def _retake(self, n: int, idx: int, exc: BadDelivery) -> None:
        """A RAW file of point ``idx`` failed its check after the stages left: take it again next."""
        s = self.session
        self.retakes[idx] = self.retakes.get(idx, 0) + 1
        cam = s.bench.camera
        if hasattr(cam, "retries_used"):
            cam.retries_used += 1
        if self.retakes[idx] > getattr(cam, "retries", 2):
            raise DeviceError(f"camera could not deliver point {idx}'s files ({exc}); "
                              "check the camera and disk, then resume the session") from None
        s.journal.event("warning", f"point {idx}: {exc}; taking it again")
        if self.goal is not None:                      # let the move sent ahead end, then go back
            s.bench.gonio.finish_move(self.goal)
            self.goal = None
        self.todo.insert(n + 1, idx)

    def stop_move_ahead(self) -> None:
        """Stopped at a point boundary with a move sent ahead: stop the stages."""
        if self.goal is not None:
            self.goal = None
            self.session.bench.gonio.stop()

    def keep_finished(self) -> None:
        """What stops the run keeps a point whose reduction finished (its data is complete)."""
        if self.pending is not None:
            try:
                self.commit_pending()
            except Exception:
                pass

    def close(self) -> None:
        self.pool.shutdown(wait=True, cancel_futures=True)
