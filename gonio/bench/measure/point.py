"""Pieces of one point's measurement: the sensor check, the reference's f_r, region statistics,
the disk space a capture needs, and the progress bar."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn
from rich.table import Column

from gonio.core.channels import CHANNELS
from gonio.bench.measure.hdr import ladder, merge_blocks
from gonio.core.errors import GonioError

__all__ = ["check_sensor", "ReferenceModel", "region_stats", "merged_region_stats", "probe_levels", "ProgressBar",
           "RawEstimate", "raw_estimate", "FRAMES_PER_POINT"]

#: RAW frames per point assumed before a session has measured one: the probe and a bracket of three
#: rungs (a 16:1 range at factors of 4; the simulated plans take 1 to 3). Once points are measured,
#: the session's own mean (plus a quarter) is used instead. An estimate, not a bound: a capture
#: that outgrows it stops resumably when the disk fills.
FRAMES_PER_POINT = 4
_BLOCK = 4096
_JOURNAL_PER_POINT = 8 << 10       # a point's row (its detail JSON) and its share of the WAL
_JOURNAL_PER_FRAME = 512           # a RAW file's reserved name, a calibration row


def frame_bytes(settings: Mapping) -> int:
    """Bytes one RAW frame takes on disk, from ``[camera]``: width x height samples of
    ceil(bits / 8) bytes (an uncompressed DNG; compressed RAW files are smaller), a header and
    preview allowance of 5 % (at least 4 KiB), rounded up to 4 KiB blocks."""
    cam = settings["camera"]
    data = int(cam["width"]) * int(cam["height"]) * ((int(cam.get("bits", 16)) + 7) // 8)
    size = data + max(_BLOCK, data // 20)
    return -(-size // _BLOCK) * _BLOCK


@dataclass(frozen=True)
class RawEstimate:
    """What a capture (or what is left of one) will write: points, frames, bytes."""

    points: int
    per_point: int
    calibration: int              # dark and flat-field frames still to take
    frame_bytes: int

    @property
    def frames(self) -> int:
        return self.points * self.per_point + self.calibration

    @property
    def bytes(self) -> int:
        return (self.frames * (self.frame_bytes + _JOURNAL_PER_FRAME) + self.points * _JOURNAL_PER_POINT)

    def describe(self, what: str) -> str:
        return (f"{what} ({self.points} point(s) x ~{self.per_point} RAW frames + {self.calibration} dark/flat "
                f"frames, ~{self.frame_bytes / 1024:.0f} KiB each)")


def raw_estimate(settings: Mapping, points: int, *, has_flat: bool, journal=None) -> RawEstimate:
    """The RAW files still to write for ``points`` points: their exposures (`FRAMES_PER_POINT`, or
    the session's own mean once ``journal`` holds measured points), the dark frames of every rung
    of the exposure ladder not yet journalled, and ``[capture] flat_frames`` flat frames (and the
    probe that sets their exposure) where the camera has a flat-field source and the session has
    not yet taken them (or decided it has none)."""
    cap = settings["capture"]
    rungs = [float(t) for t in ladder(float(cap["exposure_min_s"]), float(cap["exposure_max_s"]))]
    n_flat = int(cap.get("flat_frames", 16))
    per_point, darks = FRAMES_PER_POINT, len(rungs)
    flats = n_flat + 1 if has_flat and n_flat >= 1 else 0
    if journal is not None:
        have = {float(v[0]) for v in journal.frames("dark").values()}
        darks = sum(t not in have for t in rungs)
        if journal.first_event("no_flat") is not None or len(journal.frames("flat")) == n_flat:
            flats = 0
        counts = [len(r["detail"].get("exposures", [])) for r in journal.points()]
        if counts:
            per_point = max(1, math.ceil(1.25 * sum(counts) / len(counts)))
    return RawEstimate(int(points), per_point, darks + flats, frame_bytes(settings))


def check_sensor(camera, settings: Mapping) -> None:
    """The regions of interest come from ``[camera]``: the camera must have that many pixels."""
    sensor = getattr(camera, "sensor", None)
    cam = settings["camera"]
    if sensor is not None and (sensor.width, sensor.height) != (cam["width"], cam["height"]):
        raise GonioError(f"the camera reports {sensor.width}x{sensor.height} pixels but the settings say "
                         f"{cam['width']}x{cam['height']}; fix [camera] width/height in the settings")


class ReferenceModel:
    """f_r of the reference (sr^-1, per channel): ``rho / pi`` times its non-Lambertian factor.

    Settings (``[reference]``): ``reflectance`` (a number or one per channel), and optionally
    ``factor_theta_i``, ``factor_theta_o`` (degrees, ascending) and ``factor`` (a table, rows
    over theta_i, columns over theta_o) from the certificate: the reference's f_r relative to
    a Lambertian of the same reflectance, interpolated bilinearly (clamped at the edges).
    Where the table came from gonio calibrate's fit (``factor_a``, ``factor_b`` present) the
    fitted form itself is evaluated (gonio/bench/measure/alignment.reference_factor_model): bilinear
    interpolation of its 20-degree table overstates the convex sin^2 terms between the nodes,
    a one-signed error (2.9e-4 low at 30/30 deg, up to 6e-4 over the quick plan's points; at the
    quick plan's specular peak between nodes it flattened the lobe and biased alpha by about
    +0.1 u_c) that no budget line carries.
    """

    def __init__(self, ref: Mapping):
        self.rho = np.broadcast_to(np.asarray(ref["reflectance"], float), (CHANNELS,)).copy()
        self.table = None
        if "factor" in ref:
            ti = np.asarray(ref.get("factor_theta_i", []), float)
            to = np.asarray(ref.get("factor_theta_o", []), float)
            fac = np.asarray(ref["factor"], float)
            if (fac.shape != (len(ti), len(to)) or len(ti) < 1 or len(to) < 1 or not np.all(np.isfinite(fac))
                    or np.any(np.diff(ti) <= 0) or np.any(np.diff(to) <= 0) or np.any(fac <= 0)):
                raise GonioError("[reference] factor must be a positive len(factor_theta_i) x len(factor_theta_o) "
                                 "table over ascending angles; fix the settings")
            self.table = (ti, to, fac)
        self.ab = None
        if "factor_a" in ref or "factor_b" in ref:
            ab = [ref.get("factor_a"), ref.get("factor_b")]
            if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in ab):
                raise GonioError("[reference] factor_a and factor_b must both be finite numbers (gonio calibrate's "
                                 "fit); fix the settings or remove both")
            self.ab = (float(ab[0]), float(ab[1]))

    def factor(self, theta_i: float, theta_o: float) -> float:
        """The non-Lambertian factor at (theta_i, theta_o) in degrees (1 without a table)."""
        if self.ab is not None:
            from gonio.bench.measure.alignment import reference_factor_model
            return float(reference_factor_model(theta_i, theta_o, *self.ab))
        if self.table is None:
            return 1.0
        ti, to, fac = self.table
        rows = np.array([np.interp(theta_o, to, row) for row in fac])
        return float(np.interp(theta_i, ti, rows))

    def f_r(self, theta_i: float, theta_o: float) -> np.ndarray:
        """Reference f_r (3,) in sr^-1."""
        return self.rho / math.pi * self.factor(theta_i, theta_o)


def _sums(radiance: np.ndarray, var: np.ndarray, mask: np.ndarray) -> tuple:
    """One block's share of `region_stats` over ``mask`` (rows, w): per channel the count of
    finite values, their float64 sum, their sum of squared deviations from their own mean, and
    the float64 sum of their variances (3,) each; and the count of values left out (NaN)."""
    x, v = radiance[:, mask], var[:, mask]                      # (3, k), the region's values
    n, s, m2, sv = (np.zeros(CHANNELS, np.int64), np.zeros(CHANNELS), np.zeros(CHANNELS), np.zeros(CHANNELS))
    good = np.isfinite(x)
    bad = 0 if good.all() else int((~good).sum())
    for c in range(3):
        xc, vc = (x[c], v[c]) if not bad else (x[c][good[c]], v[c][good[c]])
        n[c] = xc.size
        if n[c]:
            s[c] = np.add.reduce(xc, dtype=np.float64)
            d = xc.astype(np.float64)
            d -= s[c] / n[c]
            # numpy's own reduction, not BLAS: a multithreaded ddot woke its threads for every
            # block (tens of thousands of values), 12x this sum's cost on 2 busy cores (issue 40)
            m2[c] = np.einsum("i,i->", d, d)
            sv[c] = np.add.reduce(vc, dtype=np.float64)
    return n, s, m2, sv, bad


def _combined(parts) -> dict[str, Any]:
    """`region_stats`' result from the `_sums` of the blocks that tile the region (in any fixed
    order). The squared deviations combine as in Chan, Golub & LeVeque, "Algorithms for computing
    the sample variance" (Am. Stat. 37, 1983), eq. 1.5b for many parts: ``M2 = sum_b [M2_b +
    n_b (mean_b - mean)^2]``, exact in exact arithmetic, every term >= 0 (no cancellation)."""
    n = np.sum([p[0] for p in parts], axis=0)
    total = np.sum([p[1] for p in parts], axis=0)
    sv = np.sum([p[3] for p in parts], axis=0)
    mean, se, se_model = np.full(CHANNELS, np.nan), np.full(CHANNELS, np.nan), np.full(CHANNELS, np.nan)
    m2 = np.zeros(CHANNELS)
    some = n > 0
    mean[some] = total[some] / n[some]
    for nb, sb, m2b, _, _ in parts:
        has = nb > 0
        dev = np.where(has, sb / np.where(has, nb, 1) - np.where(some, mean, 0.0), 0.0)
        m2 += np.where(has, m2b + nb * dev * dev, 0.0)
    se_model[some] = np.sqrt(sv[some]) / n[some]
    many = n > 1
    se[many] = np.sqrt(m2[many] / (n[many] - 1)) / np.sqrt(n[many])
    return {"mean": mean, "se": se, "se_model": se_model, "n": n, "n_saturated": int(sum(p[4] for p in parts))}


def region_stats(hdr, mask: np.ndarray) -> dict[str, Any]:
    """Per-channel mean of the HDR radiance over ``mask``, its standard error, and counts.

    ``se`` is the empirical standard error of the mean (pixel scatter: shot and read noise and
    the sensor's fixed pattern), ``se_model`` the one the noise model alone predicts. Pixels
    saturated in every exposure (NaN) are left out and counted in ``n_saturated``. Sums are
    float64 whatever the planes' type (float32 from `_hdr.merge`).
    """
    return _combined([_sums(hdr.radiance, hdr.var, mask)])


def merged_region_stats(exposures, noise, masks, saturation_fraction: float = 0.9, gamma: float = 0.0,
                        gain: np.ndarray | None = None) -> list[dict[str, Any]]:
    """`region_stats` of each mask of ``masks`` over ``merge(exposures, ...).flat_fielded(gain)``,
    accumulated inside the merge's row blocks (`_hdr.merge_blocks`) while each block is in cache:
    no merged plane is kept and none is read again. The same counts; means and standard errors
    equal the two-pass ones to float64 rounding (the sums are grouped by block, `_combined`).
    """
    parts: dict[int, list] = {}

    def consume(k, rows, rad, var, _):
        parts[k] = [_sums(rad, var, m[rows]) for m in masks]

    n_blocks = merge_blocks(exposures, noise, consume, saturation_fraction, gamma, gain=gain)
    return [_combined([parts[k][r] for k in range(n_blocks)]) for r in range(len(masks))]


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


_PROBE_BLOCK = 1 << 17         # values per channel in one block of a probe's rows


def probe_levels(frame, dark, runs: np.ndarray) -> tuple[float, float, float]:
    """What a probe tells the bracketing, over the regions given by their `_runs`: the brightest
    raw value, the brightest raw value over its dark (``peak - max(dark, 0)``) and the darkest
    dark-subtracted value (``signal - dark``): the values of `_extreme` over the whole planes,
    computed a block of rows at a time (no frame-sized temporary: at 6000 x 4000 the two
    differences were 72 MB arrays each, most of their cost the fresh pages).

    Raises
    ------
    ValueError
        The regions are empty.
    """
    if not len(runs):
        raise ValueError("no value in the regions")
    _, h, w = frame.signal.shape
    starts = runs[0::2]
    ends = np.append(runs[1::2], h * w) if len(runs) % 2 else runs[1::2]
    step = max(1, _PROBE_BLOCK // max(1, w))
    out = [-np.inf, -np.inf, np.inf]
    for r0 in range(0, h, step):
        rows = slice(r0, min(h, r0 + step))
        lo, hi = r0 * w, rows.stop * w
        k0, k1 = np.searchsorted(ends, lo, "right"), np.searchsorted(starts, hi, "left")
        if k1 <= k0:
            continue
        cut = np.empty(2 * (k1 - k0), np.int64)           # the runs inside the block, from its start
        cut[0::2] = np.maximum(starts[k0:k1], lo) - lo
        cut[1::2] = np.minimum(ends[k0:k1], hi) - lo
        if cut[-1] == hi - lo:
            cut = cut[:-1]
        peak, sig, dk = frame.peak[:, rows], frame.signal[:, rows], dark.signal[:, rows]
        out[0] = max(out[0], _extreme(np.maximum, peak, cut))
        out[1] = max(out[1], _extreme(np.maximum, peak - np.maximum(dk, 0), cut))
        out[2] = min(out[2], _extreme(np.minimum, sig - dk, cut))
    return out[0], out[1], out[2]


class ProgressBar:
    """rich progress: points done, ETA, the latest value (f_r, or f_t for a transmitted point)
    and reciprocity when a pair closes."""

    def __init__(self, total: int, done: int, enabled: bool, console=None):
        self.p = None
        if not enabled:
            return
        # the count and the ETA keep their width (an 80-column terminal showed "0:00:…"); the
        # bar and the latest value give way, the latter cut at its end
        self.p = Progress(TextColumn("capture"), BarColumn(bar_width=None, table_column=Column(ratio=1, min_width=8)),
                          MofNCompleteColumn(table_column=Column(no_wrap=True, min_width=2 * len(str(total)) + 1)),
                          TimeRemainingColumn(table_column=Column(no_wrap=True, min_width=7)),
                          TextColumn("{task.fields[latest]}", table_column=Column(ratio=1, no_wrap=True,
                                                                                 overflow="ellipsis")),
                          console=console or Console(stderr=True))
        self.task = self.p.add_task("capture", total=total, completed=done, latest="")
        self.p.start()

    def advance(self, brdf, recip, quantity: str = "f_r") -> None:
        if self.p is None:
            return
        text = f"{quantity} " + " ".join(f"{v:.4g}" for v in brdf) + " sr^-1"
        if recip is not None:
            text += f"  reciprocity {100 * np.nanmax(np.abs(recip['rel'])):.1f} %"
        self.p.update(self.task, advance=1, latest=text)

    def close(self) -> None:
        if self.p is not None:
            self.p.stop()
