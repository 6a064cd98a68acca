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

from ._hdr import ladder
from .errors import GonioError

__all__ = ["check_sensor", "ReferenceModel", "region_stats", "ProgressBar", "RawEstimate", "raw_estimate",
           "FRAMES_PER_POINT"]

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
    fitted form itself is evaluated (bench/_alignment.reference_factor_model): bilinear
    interpolation of its 20-degree table overstates the convex sin^2 terms between the nodes,
    a one-signed error (2.9e-4 low at 30/30 deg, up to 6e-4 over the quick plan's points; at the
    quick plan's specular peak between nodes it flattened the lobe and biased alpha by about
    +0.1 u_c) that no budget line carries.
    """

    def __init__(self, ref: Mapping):
        self.rho = np.broadcast_to(np.asarray(ref["reflectance"], float), (3,)).copy()
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
            from ._alignment import reference_factor_model
            return float(reference_factor_model(theta_i, theta_o, *self.ab))
        if self.table is None:
            return 1.0
        ti, to, fac = self.table
        rows = np.array([np.interp(theta_o, to, row) for row in fac])
        return float(np.interp(theta_i, ti, rows))

    def f_r(self, theta_i: float, theta_o: float) -> np.ndarray:
        """Reference f_r (3,) in sr^-1."""
        return self.rho / math.pi * self.factor(theta_i, theta_o)


def _sum64(x: np.ndarray) -> float:
    """Sum in float64 of a float32 (or float64) vector, without a float64 copy of it."""
    return float(np.add.reduce(x, dtype=np.float64))


def _ss64(x: np.ndarray, mean: float, block: int = 1 << 18) -> float:
    """Sum of squared deviations from ``mean``, in float64, a block at a time."""
    ss = 0.0
    for i in range(0, x.size, block):
        d = x[i:i + block].astype(np.float64)
        d -= mean
        ss += float(np.dot(d, d))
    return ss


def region_stats(hdr, mask: np.ndarray) -> dict[str, Any]:
    """Per-channel mean of the HDR radiance over ``mask``, its standard error, and counts.

    ``se`` is the empirical standard error of the mean (pixel scatter: shot and read noise and
    the sensor's fixed pattern), ``se_model`` the one the noise model alone predicts. Pixels
    saturated in every exposure (NaN) are left out and counted in ``n_saturated``. Sums are
    float64 whatever the planes' type (float32 from `_hdr.merge`).
    """
    mean, se, se_model = np.full(3, np.nan), np.full(3, np.nan), np.full(3, np.nan)
    n = np.zeros(3, dtype=np.int64)
    bad = 0
    for c in range(3):
        x, v = hdr.radiance[c][mask], hdr.var[c][mask]
        good = np.isfinite(x)
        if not good.all():
            bad += int((~good).sum())
            x, v = x[good], v[good]
        n[c] = x.size
        if n[c]:
            mean[c] = _sum64(x) / n[c]
            se_model[c] = math.sqrt(_sum64(v)) / n[c]
        if n[c] > 1:
            se[c] = math.sqrt(_ss64(x, mean[c]) / (n[c] - 1)) / math.sqrt(n[c])
    return {"mean": mean, "se": se, "se_model": se_model, "n": n, "n_saturated": bad}


class ProgressBar:
    """rich progress: points done, ETA, the latest f_r (and reciprocity when a pair closes)."""

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
