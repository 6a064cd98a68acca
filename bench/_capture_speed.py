"""``gonio bench capture``: the capture pipeline's time per point against the instrument's own.

A capture of a few points runs on the simulated instrument (instant clock) twice: with the
default camera and with a full-size one (6000 x 4000, 14-bit RGGB, the same field of view).
Per point it measures, in the same run:

* the **lower bound**: the simulated time the instrument itself needs, stage motion (with
  settling and the protocol's polls) plus the exposures; a bench can go no faster;
* the **host time**: wall time of the point minus the simulator's own computing (rendering,
  sensor noise, DNG encoding: what a real camera does in its own hardware), split into RAW
  decoding, HDR merge, region masks and statistics, and the rest (protocol, checksums,
  journal);
* the **projection**: bound + host time, what the point would take on hardware, and its ratio
  to the bound.

The capture loop (bench/capture.py) is sequential: a point's frames are decoded as they
arrive, merged and reduced after the bracket, and only then does the next move start. No
work of one point overlaps the next move, so the projection adds the host time to the bound
in full; the table says how much of it an overlap could hide (the part shorter than the next
move). The benchmark only measures: it wraps the pipeline's functions with timers for the run
and restores them.

Settings of the run (both cameras): exposures 1/500 s to 1/16 s (6 rungs: the session takes a
dark frame per rung and keeps each decoded, 288 MB at full size), one flat-field frame (0 is not accepted by the capture), the quick
plan's first points.
"""

from __future__ import annotations

import contextlib
import math
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from .errors import GonioError

__all__ = ["run", "run_cli", "PointTimes"]

_PHASES = ("decode", "merge", "masks", "stats")


@dataclass
class PointTimes:
    """Seconds per point: wall, the simulator's computing, the bound (motion, exposure) and phases."""

    wall: float = 0.0
    sim_cpu: float = 0.0
    motion: float = 0.0
    exposure: float = 0.0
    phases: dict = field(default_factory=lambda: dict.fromkeys(_PHASES, 0.0))
    mask_calls: list = field(default_factory=list)
    masks_affine: float = 0.0     # the same masks through _markers.posed_masks, timed after the run

    @property
    def bound(self) -> float:
        return self.motion + self.exposure

    @property
    def host(self) -> float:
        return self.wall - self.sim_cpu


class _Meter:
    """Timers wrapped around the pipeline's functions for one run (restored afterwards)."""

    def __init__(self, inst):
        self.inst = inst
        self.current: PointTimes | None = None
        self.points: list[PointTimes] = []
        self.exposure_sim = 0.0

    @contextlib.contextmanager
    def installed(self):
        from . import capture, kinematics

        patches = []

        def patch(obj, name, make):
            old = getattr(obj, name)
            patches.append((obj, name, old, name in vars(obj)))
            setattr(obj, name, make(old))

        def phase(key):
            def make(fn):
                def timed(*a, **kw):
                    if key == "masks" and self.current is not None:
                        self.current.mask_calls.append((a, kw))
                    t = time.perf_counter()
                    try:
                        return fn(*a, **kw)
                    finally:
                        if self.current is not None:
                            self.current.phases[key] += time.perf_counter() - t
                return timed
            return make

        def sim_capture(fn):
            def timed(seconds, *a, **kw):
                t, c = time.perf_counter(), self.inst.clock.now()
                try:
                    return fn(seconds, *a, **kw)
                finally:
                    if self.current is not None:
                        self.current.sim_cpu += time.perf_counter() - t
                        self.current.exposure += self.inst.clock.now() - c
                    cache = self.inst._radiance          # keep one full-size render, not 16
                    while len(cache) > 1:
                        cache.popitem(last=False)
            return timed

        def measure(fn):
            def timed(sess, idx):
                self.current = PointTimes()
                t, c = time.perf_counter(), self.inst.clock.now()
                try:
                    return fn(sess, idx)
                finally:
                    p, self.current = self.current, None
                    p.wall = time.perf_counter() - t
                    p.motion = self.inst.clock.now() - c - p.exposure
                    self.points.append(p)
            return timed

        patch(capture, "decode_raw", phase("decode"))
        patch(capture, "merge", phase("merge"))
        patch(capture, "region_stats", phase("stats"))
        patch(kinematics, "roi_masks", phase("masks"))
        patch(capture._Session, "measure", measure)
        patch(self.inst, "capture", sim_capture)
        try:
            yield self
        finally:
            for obj, name, old, own in reversed(patches):
                if own:
                    setattr(obj, name, old)
                else:
                    delattr(obj, name)


def _one(width: int, height: int, n_points: int, seed: int, folder: Path) -> list[PointTimes]:
    import gonio.sim

    from .capture import capture
    from ._settings import default_settings, merge_settings
    from .plans import Plan, load_plan

    base = default_settings()
    px = float(base["camera"]["pixel_size"]) * base["camera"]["width"] / width
    settings = merge_settings(base, {
        "camera": {"width": width, "height": height, "pixel_size": px},
        "capture": {"exposure_min_s": 1 / 500, "exposure_max_s": 1 / 16, "probe_s": 1 / 125, "flat_frames": 1},
    })
    quick = load_plan("quick")
    plan = Plan(f"bench-{n_points}", quick.angles[:n_points], source="quick")
    sample = {"model": "diffuse", "params": {"reflectance": 0.5}}
    ref = {"model": "diffuse", "params": {"reflectance": float(settings["reference"]["reflectance"])}}
    inst = gonio.sim.Instrument(settings, sample=sample, reference=ref, seed=seed, clock="instant",
                                spp=1 if width * height > 1_000_000 else 4)
    inst.register(f"bench-capture-{width}x{height}-{id(inst):x}")
    meter = _Meter(inst)
    try:
        with meter.installed():
            capture(folder, plan, settings, inst.url("zaber"), inst.url("meter"), inst.url("camera"), seed=seed,
                    progress=False, sample_truth=sample, sleep=inst.clock.advance)
    finally:
        inst.unregister()
    from ._markers import posed_masks

    for p in meter.points:                 # the same masks from the map's affinity, for comparison
        for a, kw in p.mask_calls:
            t = time.perf_counter()
            posed_masks(a[0], a[1], None, *a[2:], **kw)
            p.masks_affine += time.perf_counter() - t
    return meter.points


def run(n_points: int = 3, full: tuple[int, int] | None = (6000, 4000), seed: int = 0, out=print) -> list[dict]:
    """Run the benchmark, print the table, return its rows."""
    cams = [(64, 48)] + ([full] if full else [])
    rows = []
    for w, h in cams:
        with tempfile.TemporaryDirectory(prefix="gonio-bench-capture-") as tmp:
            pts = _one(w, h, n_points, seed, Path(tmp) / "session")
        n = len(pts)
        mean = lambda f: sum(f(p) for p in pts) / n          # noqa: E731
        row = {"camera": f"{w}x{h}", "points": n, "motion_s": mean(lambda p: p.motion),
               "exposure_s": mean(lambda p: p.exposure), "bound_s": mean(lambda p: p.bound),
               "wall_s": mean(lambda p: p.wall), "sim_s": mean(lambda p: p.sim_cpu),
               "host_s": mean(lambda p: p.host), **{k + "_s": mean(lambda p, k=k: p.phases[k]) for k in _PHASES}}
        row["projected_s"] = row["bound_s"] + row["host_s"]
        row["ratio"] = row["projected_s"] / row["bound_s"] if row["bound_s"] > 0 else math.nan
        # with the reduction of point k overlapping the move to k+1, only what outlasts the move stays
        compute = sum(row[k + "_s"] for k in ("merge", "masks", "stats"))
        row["overlap_ratio"] = (row["bound_s"] + row["host_s"] - min(compute, row["motion_s"])) / row["bound_s"]
        row["masks_affine_s"] = mean(lambda p: p.masks_affine)
        row["affine_ratio"] = (row["projected_s"] - row["masks_s"] + row["masks_affine_s"]) / row["bound_s"]
        rows.append(row)
    head = (f"{'camera':>10} {'pts':>3} {'motion':>7} {'expose':>7} {'bound':>7} {'wall':>7} {'sim':>7} "
            f"{'host':>7} {'decode':>7} {'merge':>7} {'masks':>7} {'stats':>7} {'proj/bound':>10} {'overlapped':>10} "
            f"{'masks*':>7} {'proj*/bound':>11}")
    out("capture pipeline, seconds per point (bound = stage motion + exposures, simulated time; "
        "host = wall - simulator's computing; proj = bound + host; the loop is sequential: nothing "
        "overlaps the next move, 'overlapped' is what overlapping merge, masks and stats with it could reach; "
        "masks* = the same masks through _markers.posed_masks, timed after the run, proj* = proj with them)")
    out(head)
    for r in rows:
        out(f"{r['camera']:>10} {r['points']:>3} {r['motion_s']:7.3f} {r['exposure_s']:7.3f} {r['bound_s']:7.3f} "
            f"{r['wall_s']:7.3f} {r['sim_s']:7.3f} {r['host_s']:7.3f} {r['decode_s']:7.3f} {r['merge_s']:7.3f} "
            f"{r['masks_s']:7.3f} {r['stats_s']:7.3f} {r['ratio']:9.3f}x {r['overlap_ratio']:9.3f}x "
            f"{r['masks_affine_s']:7.3f} {r['affine_ratio']:10.3f}x")
    return rows


def run_cli(args) -> int:
    if not 1 <= args.points <= 20:
        raise GonioError(f"--points {args.points}: give 1 to 20 points")
    full = None
    if not args.skip_full:
        try:
            w, h = (int(v) for v in str(args.full_size).lower().split("x"))
        except ValueError:
            w = h = 0
        if not (16 <= w <= 12000 and 16 <= h <= 12000 and w % 2 == 0 and h % 2 == 0):
            raise GonioError(f"--full-size {args.full_size!r}: give WIDTHxHEIGHT, even, 16 to 12000 pixels, "
                             "e.g. 6000x4000")
        full = (w, h)
    run(args.points, full)
    return 0
