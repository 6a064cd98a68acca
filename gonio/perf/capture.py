"""``gonio bench capture``: the capture pipeline's time per point against the instrument's own.

A capture of a few points (the quick plan's first) runs on the simulated instrument, in real
time, twice: with the default camera and with a real camera's size (`SENSOR_SIZES` ``24mp``:
6000 x 4000, 14-bit RGGB, the same field of view); exposures 1/500 s to 1/16 s (6 rungs), one flat-field frame. Per point (a
cycle: from the start of its move to the start of the next) it reports the **lower bound**
(stage motion plus ``settle_s``, and the exposures: a bench can go no faster), the cycle's
**wall** time less the simulator's own computing (``proj``: the point on hardware; ``host =
proj - bound``: what the host adds), where the host's time goes (RAW decoding, HDR merge with
the region statistics, region masks, the worker's ``reduce``, the run's ``tail``), **CPU
seconds** (``host``, ``crit``, ``lag``, per phase), the **idle-machine bound** ``(bound + crit
+ lag) / bound`` and ``peak MiB``. The simulator renders only while the worker is idle, and
the benchmark only measures: it wraps the pipeline's functions with timers for the run and
restores them; the last lines say each camera's ratio against issue 40's target (1.1x the
bound). Each figure's definition: the comment below.
"""

# Definitions (per point, in the same run):
# * lower bound: what the instrument itself needs: the stages' motion (the simulated stages' own
#   time from the move command to standstill, plus settle_s) and the exposures.
# * wall: the wall time of the cycle; sim: the simulator's own computing in it (rendering, sensor
#   noise, DNG encoding, the simulated camera hashing and writing its file: what a real camera
#   and its tethering do on their side), which is taken out: proj = wall - sim is what the point
#   would take on hardware and host = proj - bound what the host adds to the bound (protocol,
#   seeing the standstill, the probe's decoding, the client's checksum check, fsync and rename of
#   each RAW file, and whatever of the reduction the move does not hide).
# * where the host's time goes: RAW decoding, HDR merge with the region statistics (one pass:
#   each block of merged rows is reduced while in cache), region masks (per point, whichever
#   thread ran them), and reduce, the worker thread's time per point (decode, merge and
#   statistics of point k while the stages move to k+1); tail, the last point's reduction and
#   journal row after its bracket (once a run: no move hides it; not in the per-point means).
# * CPU seconds (the machine is shared: wall times grow with its load, CPU times much less):
#   host every host thread's CPU in the cycle (the process's, less what it spent while the
#   simulator computed with the worker idle; the simulated devices' protocol handling stays in,
#   an overestimate); crit the main thread's from the stages' standstill being seen to the next
#   move, less the simulator's: the host work no motion hides; lag the wall time from the
#   standstill to its being seen (the stages' alert, then one confirming poll:
#   gonio.bench.drivers.zaber.ZaberChain.wait_idle); and each phase's CPU, the merge's helper
#   thread included.
# * idle-machine bound (bound + crit + lag) / bound: valid where every point's other host CPU
#   (host - crit, serialised on one core) is below its motion, so the move hides it; on an idle
#   machine the critical path's wall is its CPU, and the standstill is seen no later than on the
#   loaded one (lag as measured). With the simulator the waiting read itself costs host CPU
#   (sim:// reads wait in 1 ms steps in this process; a serial port's read blocks in the kernel).
# * peak MiB: the process's peak resident memory after the camera's run.
#
# To keep the accounting honest, the simulator renders a frame only once the worker is idle: the
# worker may overlap the stage motion and the exposures, never the simulator's computing, which
# a real bench does not have. The session takes a dark frame per rung and keeps each decoded,
# signal only, float32 (size at full frame: docs/performance.md, gonio.perf.capture).

from __future__ import annotations

import contextlib
import math
import resource
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import gonio.sim
from gonio.sim.physics.sensor import SENSOR_SIZES, camera_table, sensor_size

from gonio.bench.settings import default_settings, merge_settings
from gonio.bench.session.capture import capture
from gonio.core.errors import GonioError
from gonio.bench.plan.plans import Plan, load_plan

__all__ = ["run", "run_cli", "PointTimes"]

_PHASES = ("decode", "merge", "masks")


@dataclass
class PointTimes:
    """Seconds of one point's cycle (its move's start to the next's): wall, the simulator's
    computing, the bound (motion, exposure), and the phases that ran meanwhile; and CPU seconds
    (see the module notes): ``host_cpu`` every host thread's, ``crit_cpu`` the main thread's from
    the stages' standstill being seen to the next move (the part no motion hides), ``lag`` the
    wall seconds from the standstill to its being seen, ``cpu`` each phase's."""

    wall: float = 0.0
    sim_cpu: float = 0.0
    motion: float = 0.0
    exposure: float = 0.0
    phases: dict = field(default_factory=lambda: dict.fromkeys(_PHASES, 0.0))
    reduce: float = 0.0
    host_cpu: float = 0.0
    crit_cpu: float = 0.0
    lag: float = 0.0
    cpu: dict = field(default_factory=lambda: dict.fromkeys(_PHASES, 0.0))

    @property
    def bound(self) -> float:
        return self.motion + self.exposure

    @property
    def host(self) -> float:
        return self.wall - self.sim_cpu - self.bound


@contextlib.contextmanager
def _patched(targets):
    """Replace ``obj.name`` by ``make(obj.name)`` for each ``(obj, name, make)``; restore on exit
    (an attribute the object only inherited is deleted again)."""
    patches = []
    try:
        for obj, name, make in targets:
            old = getattr(obj, name)
            patches.append((obj, name, old, name in vars(obj)))
            setattr(obj, name, make(old))
        yield
    finally:
        for obj, name, old, own in reversed(patches):
            if own:
                setattr(obj, name, old)
            else:
                delattr(obj, name)


class _Meter:
    """Timers wrapped around the pipeline's functions for one run (restored afterwards)."""

    _SUMS = ("motion", "sim_cpu", "exposure", "reduce", "sim_proc", "crit", "lag")

    def __init__(self, inst, settle_s: float = 0.0):
        self.inst = inst
        self.settle = settle_s
        self.lock = threading.Lock()
        self.idle = threading.Condition(self.lock)
        self.busy = 0                       # reductions running in the worker
        self.sim_cpu = self.exposure = 0.0
        self.sim_cpu_port = 0.0
        self.phases = dict.fromkeys(_PHASES, 0.0)
        self.cpu = dict.fromkeys(_PHASES, 0.0)
        self.reduce = 0.0
        self.motion = 0.0                   # the stages' own time of the moves sent, s
        self.sim_proc = 0.0                 # process CPU while the simulator computed (the worker idle)
        self.sim_main = 0.0                 # the main thread's CPU in the simulator
        self.crit = self.lag = 0.0
        self.seen: tuple | None = None      # (main thread CPU, sim_main) when a standstill was seen
        self.helper = None                  # the merge's helper thread's CPU clock
        self.marks: list[dict] = []         # the sums at each move's start
        self.end: dict | None = None        # the same after the last bracket
        self.run_end: float = 0.0

    def _mark(self) -> dict:
        """The sums now (on the main thread: a move's start, a bracket's end)."""
        with self.lock:
            if self.seen is not None:       # the main thread's work since the standstill was seen
                tt, sim = self.seen
                self.crit += time.thread_time() - tt - (self.sim_main - sim)
                self.seen = None
            return {"wall": time.perf_counter(), "proc": time.process_time(), "phases": dict(self.phases),
                    "cpu": dict(self.cpu), **{k: getattr(self, k) for k in self._SUMS}}

    def _motion_left(self) -> float:
        """Seconds until the simulated stages stand still (0 when idle)."""
        t = self.inst.clock.now()
        ends = [e for e in (a.end_time(t) for a in self.inst.axes) if e is not None]
        return max(ends) - t if ends else 0.0

    def _helper_cpu(self) -> float:
        return time.clock_gettime(self.helper) if self.helper is not None else 0.0

    # -- timers wrapped around the pipeline's functions (each takes the original, returns the wrapper)
    def _phase(self, key):
        def make(fn):
            def timed(*a, **kw):
                t, c, hc = time.perf_counter(), time.thread_time(), self._helper_cpu()
                try:
                    return fn(*a, **kw)
                finally:
                    extra = self._helper_cpu() - hc if key == "merge" else 0.0   # the merge's second thread
                    with self.lock:
                        self.phases[key] += time.perf_counter() - t
                        self.cpu[key] += time.thread_time() - c + extra
            return timed
        return make

    def _sim_capture(self, fn):
        def timed(seconds, *a, **kw):
            with self.idle:                          # the worker never hides in the simulator's computing
                while self.busy:
                    self.idle.wait()
            t = time.perf_counter()
            try:
                return fn(seconds, *a, **kw)         # renders, then lets the exposure pass (real time)
            finally:
                cpu = max(0.0, time.perf_counter() - t - seconds)
                with self.lock:
                    self.sim_cpu += cpu
                    self.sim_cpu_port += cpu         # camera_port counts the rest of the command
                    self.exposure += seconds
                cache = self.inst._radiance          # keep one full-size render, not 16
                while len(cache) > 1:
                    cache.popitem(last=False)
        return timed

    def _camera_port(self, fn):                      # fn: the port's bound method
        def timed(*a, **kw):
            with self.idle:                          # the process's CPU meanwhile is the simulator's
                while self.busy:
                    self.idle.wait()
            t, e = time.perf_counter(), self.exposure
            pc, tc = time.process_time(), time.thread_time()
            try:
                return fn(*a, **kw)                  # render (timed by _sim_capture), encode, hash, write
            finally:
                with self.lock:
                    inner = self.sim_cpu_port
                    self.sim_cpu += max(0.0, time.perf_counter() - t - (self.exposure - e) - inner)
                    self.sim_cpu_port = 0.0
                    self.sim_proc += time.process_time() - pc
                    self.sim_main += time.thread_time() - tc
        return timed

    def _finish_move(self, fn):
        def timed(gonio, goal, *a, **kw):
            standstill = time.perf_counter() + self._motion_left()
            try:
                return fn(gonio, goal, *a, **kw)
            finally:
                with self.lock:
                    self.lag += max(0.0, time.perf_counter() - standstill)
                    self.seen = (time.thread_time(), self.sim_main)
        return timed

    def _move(self, fn):
        def timed(gonio, target, *a, wait=True, **kw):
            self.marks.append(self._mark())          # a point's cycle starts with its move
            goal = fn(gonio, target, *a, wait=False, **kw)
            with self.lock:
                self.motion += self._motion_left() + self.settle
            if wait:
                gonio.finish_move(goal)
            return goal
        return timed

    def _bracket(self, fn):
        def timed(sess, idx, *a, **kw):
            try:
                return fn(sess, idx, *a, **kw)
            finally:
                self.end = self._mark()
        return timed

    def _reduce(self, fn):
        def timed(sess, shot):
            with self.lock:
                self.busy += 1
            t = time.perf_counter()
            try:
                return fn(sess, shot)
            finally:
                with self.idle:
                    self.reduce += time.perf_counter() - t
                    self.busy -= 1
                    self.idle.notify_all()
        return timed

    def _run(self, fn):
        def timed(sess):
            try:
                return fn(sess)
            finally:
                self.run_end = time.perf_counter()
        return timed

    @contextlib.contextmanager
    def installed(self):
        """The timers in place for the ``with`` block; the originals restored after it."""
        from gonio.bench.session import run as capture              # the run's module: its names are patched
        from gonio.bench.drivers import stages as _zaber

        targets = [(capture, "decode_raw", self._phase("decode")), (capture, "roi_masks_fast", self._phase("masks")),
                   (capture, "merged_region_stats", self._phase("merge")),
                   (_zaber.Goniometer, "move_to", self._move), (_zaber.Goniometer, "finish_move", self._finish_move),
                   (capture._Session, "_bracket", self._bracket),
                   (capture._Session, "_reduce", self._reduce), (capture._Session, "run", self._run),
                   (self.inst, "capture", self._sim_capture), (self.inst.camera, "_expose", self._camera_port)]
        from gonio.bench.measure import hdr as _hdr

        if _hdr._helpers() > 0:                    # the merge's helper thread: its CPU clock
            self.helper = time.pthread_getcpuclockid(_hdr._pool().submit(threading.get_ident).result())
        with _patched(targets):
            yield self

    def points(self) -> tuple[list[PointTimes], float]:
        """The points' cycles (the last one to the end of its bracket) and the tail after it."""
        marks = [*self.marks, self.end]
        pts = []
        for m0, m1 in zip(marks, marks[1:]):
            d = {k: m1[k] - m0[k] for k in ("wall", "proc", *self._SUMS)}
            pts.append(PointTimes(d["wall"], d["sim_cpu"], d["motion"], d["exposure"],
                                  {k: m1["phases"][k] - m0["phases"][k] for k in _PHASES}, d["reduce"],
                                  d["proc"] - d["sim_proc"], d["crit"], d["lag"],
                                  {k: m1["cpu"][k] - m0["cpu"][k] for k in _PHASES}))
        last = self.end
        tail = self.run_end - last["wall"]
        if pts:                                    # what ran after the last bracket belongs to the last point
            p = pts[-1]
            for k in _PHASES:
                p.phases[k] += self.phases[k] - last["phases"][k]
                p.cpu[k] += self.cpu[k] - last["cpu"][k]
            p.reduce += self.reduce - last["reduce"]
        return pts, tail


def _one(width: int, height: int, n_points: int, seed: int, folder: Path) -> tuple[list[PointTimes], float]:
    base = default_settings()
    settings = merge_settings(base, {
        "camera": camera_table(f"{width}x{height}", base["camera"]),
        "capture": {"exposure_min_s": 1 / 500, "exposure_max_s": 1 / 16, "probe_s": 1 / 125, "flat_frames": 1},
    })
    quick = load_plan("quick")
    plan = Plan(f"bench-{n_points}", quick.angles[:n_points], source="quick")
    sample = {"model": "diffuse", "params": {"reflectance": 0.5}}
    ref = {"model": "diffuse", "params": {"reflectance": float(settings["reference"]["reflectance"])}}
    inst = gonio.sim.Instrument(settings, sample=sample, reference=ref, seed=seed, clock="real",
                                spp=1 if width * height > 1_000_000 else 4)
    inst.register(f"bench-capture-{width}x{height}-{id(inst):x}")
    meter = _Meter(inst, float(settings.get("motion", {}).get("settle_s", 0.0)))
    try:
        with meter.installed():
            capture(folder, plan, settings, inst.url("zaber"), inst.url("meter"), inst.url("camera"), seed=seed,
                    progress=False, sample_truth=sample, sleep=time.sleep)
    finally:
        inst.unregister()
    return meter.points()


def _peak_mib() -> float:
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return rss / (1 << 20) if sys.platform == "darwin" else rss / 1024


#: issue 40's target: a point at most this many times the motion + exposure bound
TARGET_RATIO = 1.1


def run(n_points: int = 3, full: tuple[int, int] | None = SENSOR_SIZES["24mp"][:2], seed: int = 0,
        out=print) -> list[dict]:
    """Run the benchmark, print the table, return its rows."""
    cams = [(64, 48)] + ([full] if full else [])
    rows = []
    for w, h in cams:
        with tempfile.TemporaryDirectory(prefix="gonio-bench-capture-") as tmp:
            pts, tail = _one(w, h, n_points, seed, Path(tmp) / "session")
        n = len(pts)
        mean = lambda f: sum(f(p) for p in pts) / n          # noqa: E731
        row = {"camera": f"{w}x{h}", "points": n, "motion_s": mean(lambda p: p.motion),
               "exposure_s": mean(lambda p: p.exposure), "bound_s": mean(lambda p: p.bound),
               "wall_s": mean(lambda p: p.wall), "sim_s": mean(lambda p: p.sim_cpu),
               "host_s": mean(lambda p: p.host), **{k + "_s": mean(lambda p, k=k: p.phases[k]) for k in _PHASES},
               "reduce_s": mean(lambda p: p.reduce), "tail_s": tail, "peak_mib": _peak_mib(),
               "host_cpu_s": mean(lambda p: p.host_cpu), "crit_cpu_s": mean(lambda p: p.crit_cpu),
               "lag_s": mean(lambda p: p.lag), **{k + "_cpu_s": mean(lambda p, k=k: p.cpu[k]) for k in _PHASES}}
        row["projected_s"] = row["bound_s"] + row["host_s"]
        row["ratio"] = row["projected_s"] / row["bound_s"] if row["bound_s"] > 0 else math.nan
        # an idle machine: the critical path's CPU, the standstill seen by its alert (lag as measured);
        # valid only where every point's work during its move (all threads, serialised) fits in the motion
        fits = all(p.host_cpu - p.crit_cpu < p.motion for p in pts)
        row["idle_ratio"] = ((row["bound_s"] + row["crit_cpu_s"] + row["lag_s"]) / row["bound_s"]
                             if fits and row["bound_s"] > 0 else None)    # None: no bound can be stated
        rows.append(row)
    head = (f"{'camera':>10} {'pts':>3} {'motion':>7} {'expose':>7} {'bound':>7} {'wall':>7} {'sim':>7} "
            f"{'host':>7} {'decode':>7} {'merge+st':>8} {'masks':>7} {'proj/bound':>10} {'reduce':>7} "
            f"{'tail':>7} {'peak MiB':>8}")
    out("capture pipeline, seconds per point (the simulator in real time; bound = the stages' own motion + "
        "settling + exposures; wall = a point's move start to the next's; sim = the simulator's computing in it; "
        "host = wall - sim - bound; proj = bound + host; reduce = the worker's decode, merge and statistics "
        "of the point, overlapping the next move; tail = the last point's reduction, after its bracket, once a run)")
    out(head)
    for r in rows:
        out(f"{r['camera']:>10} {r['points']:>3} {r['motion_s']:7.3f} {r['exposure_s']:7.3f} {r['bound_s']:7.3f} "
            f"{r['wall_s']:7.3f} {r['sim_s']:7.3f} {r['host_s']:7.3f} {r['decode_s']:7.3f} {r['merge_s']:8.3f} "
            f"{r['masks_s']:7.3f} {r['ratio']:9.3f}x {r['reduce_s']:7.3f} {r['tail_s']:7.3f} "
            f"{r['peak_mib']:8.0f}")
    out("CPU seconds per point (host = every host thread, the simulator's computing taken out; crit = the main "
        "thread from the stages' standstill being seen to the next move, what no motion hides; lag = wall from "
        "the standstill to its being seen; decode, merge+st (both threads), masks: the phases; idle <= "
        "(bound + crit + lag) / bound, where each point's other host CPU < its motion)")
    out(f"{'camera':>10} {'host':>7} {'crit':>7} {'lag':>7} {'decode':>7} {'merge+st':>8} {'masks':>7} {'idle<=':>8}")
    for r in rows:
        out(f"{r['camera']:>10} {r['host_cpu_s']:7.3f} {r['crit_cpu_s']:7.3f} {r['lag_s']:7.3f} "
            f"{r['decode_cpu_s']:7.3f} "
            f"{r['merge_cpu_s']:8.3f} {r['masks_cpu_s']:7.3f} "
            + (f"{r['idle_ratio']:7.3f}x" if r["idle_ratio"] is not None else "     n/a"))
    if any(r["idle_ratio"] is None for r in rows):
        out("n/a: a point's work beside the critical path took more CPU than its move, so no idle-machine bound follows")
    for r in rows:
        verdict = "met" if r["ratio"] <= TARGET_RATIO else "NOT met"
        out(f"{r['camera']}: {r['projected_s']:.3f} s per point against the motion + exposure bound "
            f"{r['bound_s']:.3f} s = {r['ratio']:.3f}x (target <= {TARGET_RATIO:g}x: {verdict}); "
            f"peak memory {r['peak_mib']:.0f} MiB")
    return rows


def run_cli(args) -> int:
    if not 1 <= args.points <= 20:
        raise GonioError(f"--points {args.points}: give 1 to 20 points")
    full = None
    if not args.skip_full:
        try:
            w, h, _ = sensor_size(args.full_size)
        except ValueError:
            raise GonioError(f"--full-size {args.full_size!r}: give 24mp or WIDTHxHEIGHT, even, 16 to 12000 pixels, "
                             "e.g. 6000x4000") from None
        full = (w, h)
    run(args.points, full)
    return 0
