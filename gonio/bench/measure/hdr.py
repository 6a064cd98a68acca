"""HDR merge of an exposure bracket into linear relative radiance, with its variance.

Noise model of one black-subtracted raw value ``D`` (DN) holding ``S`` DN of signal:
``var(D) = S / g + (sigma_read / g)^2 + 1/12`` (``g`` the gain in electrons per DN, the last
term the quantisation); a value that averages ``n`` raw pixels has ``var / n``. Per exposure
k (time ``t_k`` s, monitor reading ``P_k`` W, dark frame ``K_k``):
``x_k = (D_k - K_k) / (t_k P_k)``. The merged radiance is the inverse-variance weighted mean
over the exposures where the value is not saturated (its brightest raw pixel below
``saturation_fraction`` of full scale), ``var(x) = 1 / sum(w_k)``, with the variances
evaluated at the model's prediction ``x t_k P_k`` (a second pass).

With a calibrated detector non-linearity ``gamma`` (``[linearity]`` of a calibration:
``D = L (1 - gamma L / FS)`` for the linear value ``L``, ``FS`` the full scale), each value and
its dark are linearised first; ``gamma = 0`` (the default) leaves them untouched.
"""

# Details: S counts photo and dark electrons; n = 2 for the two greens of a CFA tile.
# var(x_k) = (var(D_k) + var(K_k)) / (t_k P_k)^2; x = sum(w_k x_k) / sum(w_k), w_k = 1 / var(x_k).
# The variances are evaluated at the prediction, not at the noisy measured values, which would
# bias the weights toward low readings. For the same reason the dark's level in them is the
# dark frame's mean over the block of rows (per channel), not each value's own dark: a value's
# dark noise enters x_k with the opposite sign, so weights from it favoured the exposures whose
# dark read low, and a region at zero signal merged to +0.1 of its pixels' standard deviation
# (1.7 standard errors of a 300-value region's mean: the dark points of a glossy gold capture
# sat at z = +1.5 and its fit at chi2/dof 1.33-1.54). The dark frame itself, one a rung, is
# shared by every point that subtracts it: its noise is a correlated line of the budget
# (`dark_sensitivity`; gonio/bench/dataset/budget.py). Linearisation (gamma from gonio calibrate):
# L = FS (1 - sqrt(1 - 4 gamma D / FS)) / (2 gamma).

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Iterable, Sequence

import numpy as np

from gonio.core.channels import CHANNELS
from gonio.bench.drivers.camera import RawFrame

__all__ = ["NoiseModel", "Exposure", "HdrResult", "merge", "merge_blocks", "linearise", "choose_bracket", "ladder",
           "flat_gain", "dark_sensitivity"]


@dataclass(frozen=True)
class NoiseModel:
    """Sensor noise: gain (electrons per DN) and read noise (electrons rms)."""

    gain: float = 2.0
    read_noise: float = 3.0

    def var_dn(self, signal_dn, n_raw=1.0):
        """Variance (DN^2) of a black-subtracted value holding ``signal_dn`` DN, averaged over ``n_raw`` pixels."""
        s = np.maximum(np.asarray(signal_dn, float), 0.0)
        return (s / self.gain + (self.read_noise / self.gain) ** 2 + 1.0 / 12.0) / n_raw

    def dn_for_snr(self, snr: float) -> float:
        """Signal (DN, one raw pixel) whose shot + read noise gives signal-to-noise ``snr``."""
        a = 1.0 / self.gain
        b = (self.read_noise / self.gain) ** 2 + 1.0 / 12.0
        # S^2 = snr^2 (a S + b)
        q = snr * snr
        return 0.5 * (q * a + np.sqrt((q * a) ** 2 + 4 * q * b))


@dataclass(frozen=True)
class Exposure:
    """One frame of a bracket: exposure time (s), monitor reading (W), the decoded frame and its dark."""

    seconds: float
    power: float
    frame: RawFrame
    dark: RawFrame


@dataclass(frozen=True)
class HdrResult:
    """Merged radiance (relative: DN per s per W) and its variance, per channel and super-pixel.

    Attributes
    ----------
    radiance, var : ndarray (3, h, w)
    n_used : ndarray of int (3, h, w)
        Unsaturated exposures that went into each value (0: saturated in all; radiance NaN).
    """

    radiance: np.ndarray
    var: np.ndarray
    n_used: np.ndarray

    def flat_fielded(self, gain: np.ndarray | None) -> "HdrResult":
        """Divide out each pixel's relative gain (3, h, w) from a flat field (PRNU); None: unchanged."""
        if gain is None:
            return self
        return HdrResult(self.radiance / gain, self.var / gain ** 2, self.n_used)


def _saturated(frame: RawFrame, saturation_fraction: float) -> np.ndarray:
    return frame.peak >= saturation_fraction * frame.full_scale


_BLOCK = 1 << 16          # values per channel in one block of rows: the block's arrays stay in cache


def linearise(dn, gamma: float, full_scale: float):
    """Invert the integral non-linearity ``D = L (1 - gamma L / FS)`` (module notes); dtype kept."""
    if not gamma:
        return dn
    dn = np.asarray(dn)
    g, fs = dn.dtype.type(gamma), dn.dtype.type(full_scale)
    root = np.sqrt(np.maximum(dn.dtype.type(1.0) - dn.dtype.type(4.0) * g * dn / fs, dn.dtype.type(0.0)))
    return (dn.dtype.type(1.0) - root) * fs / (dn.dtype.type(2.0) * g)


def merge(exposures: Sequence[Exposure], noise: NoiseModel, saturation_fraction: float = 0.9,
          gamma: float = 0.0) -> HdrResult:
    """Merge a bracket (see the module notes for the formulas; ``gamma``: the calibrated
    non-linearity, 0 for none).

    Float32, in blocks of rows: both weighting passes of a block run while it is in cache, and
    no (exposures, 3, h, w) stack is built (the float64 stacks of old took 5 x the memory and
    4 x the time at 6000 x 4000, for the same values to float32 rounding, ~1e-7 relative).
    """
    if not exposures:
        raise ValueError("empty bracket")
    _, h, w = exposures[0].frame.signal.shape
    rad = np.empty((CHANNELS, h, w), np.float32)
    var = np.empty((CHANNELS, h, w), np.float32)
    n_used = np.empty((CHANNELS, h, w), np.int64)

    def keep(k, rows, rad_b, var_b, used_b):
        rad[:, rows], var[:, rows], n_used[:, rows] = rad_b, var_b, used_b

    merge_blocks(exposures, noise, keep, saturation_fraction, gamma, count_used=True)
    return HdrResult(rad, var, n_used)


def merge_blocks(exposures: Sequence[Exposure], noise: NoiseModel, consume, saturation_fraction: float = 0.9,
                 gamma: float = 0.0, gain: np.ndarray | None = None, count_used: bool = False) -> int:
    """The merge of `merge`, handed over a block of rows at a time: ``consume(k, rows, radiance,
    var, n_used)`` for the ``k``-th block (``rows`` a slice; the planes (3, rows, w) float32, the
    block's own, valid only during the call; ``n_used`` None unless ``count_used``), from this
    thread or, for a large bracket, the merge's helper thread (blocks in no set order: ``consume``
    keeps each block's result by ``k``). ``gain``: a flat field (3, h, w) divided out of each block
    as `HdrResult.flat_fielded` divides it out of the whole, the same values. Returns the number
    of blocks.

    A point's reduction consumes each block while it is in cache (`_measure.merged_region_stats`)
    instead of reading the merged planes again (at 6000 x 4000, 3 x 6 M values each).
    """
    if not exposures:
        raise ValueError("empty bracket")
    f32 = np.float32
    n = np.asarray(exposures[0].frame.n_raw, f32)[:, None, None]
    _, h, w = exposures[0].frame.signal.shape
    inv_g = f32(1.0 / noise.gain)
    floor = f32((noise.read_noise / noise.gain) ** 2 + 1.0 / 12.0)
    scale = [f32(e.seconds * e.power) for e in exposures]
    limit = [np.float64(saturation_fraction * e.frame.full_scale) for e in exposures]   # compared exactly
    step = max(1, _BLOCK // max(1, w))

    def block(k, r0):
        rows = slice(r0, min(h, r0 + step))
        x, inv_ok, dark, var_dark = [], [], [], []
        used = None
        for e, kk, lim in zip(exposures, scale, limit):
            sig, dk = e.frame.signal[:, rows], e.dark.signal[:, rows]
            if gamma:
                fs = e.frame.full_scale
                sig, dk = linearise(sig, gamma, fs), linearise(dk, gamma, fs)
            x.append((sig - dk) / kk)
            ok = e.frame.peak[:, rows] < lim
            if count_used:
                used = ok.astype(np.int64) if used is None else used + ok
            inv_ok.append(ok)
            # the dark's level in the weights is its mean over the block (per channel), not each
            # value's own dark: a value's dark noise is in x_k with the opposite sign, so weights
            # from it favour the exposures whose dark read low, a positive bias at low signal
            # (module notes)
            d = np.maximum(dk.mean(axis=(1, 2), dtype=np.float64, keepdims=True), 0.0).astype(f32)
            dark.append(d)
            var_dark.append((d * inv_g + floor) / n)

        def accumulate(pred):
            wsum = wx = None
            for xk, ok, d, vd, kk in zip(x, inv_ok, dark, var_dark, scale):
                s = pred(xk) * kk + d                 # model signal, DN (>= 0)
                v = ((s * inv_g + floor) / n + vd) / (kk * kk)
                wk = np.where(ok, f32(1.0) / v, f32(0.0))
                if wsum is None:
                    wsum, wx = wk, wk * xk
                else:
                    wsum += wk
                    wx += wk * xk
            return wsum, wx

        with np.errstate(invalid="ignore", divide="ignore"):
            # pass 1: weights from the measured values; pass 2: from the merged prediction
            wsum, wx = accumulate(lambda xk: np.maximum(xk, f32(0.0)))
            est = np.where(wsum > 0, wx / np.where(wsum > 0, wsum, f32(1.0)), f32(0.0))
            est = np.maximum(est, f32(0.0))
            wsum, wx = accumulate(lambda xk: est)
            good = wsum > 0
            safe = np.where(good, wsum, f32(1.0))
            rad = np.where(good, wx / safe, f32(np.nan))
            var = np.where(good, f32(1.0) / safe, f32(np.nan))
            if gain is not None:
                g = gain[:, rows]
                rad, var = rad / g, var / g ** 2
        consume(k, rows, rad, var, used)

    def blocks(starts):
        for k, r0 in starts:
            block(k, r0)

    starts = list(enumerate(range(0, h, step)))
    if len(starts) > 1 and 3 * h * w * len(exposures) >= _PARALLEL and _helpers() > 0:
        # the blocks are independent (each writes its own rows): the lower half in a helper
        # thread, the upper here; numpy lets go of the GIL in each block's arithmetic, so the
        # merge of a full-size point takes both cores, as the capture's worker thread has them
        # while the stages move (the main thread waits for it then). The same values.
        half = len(starts) // 2
        lower = _pool().submit(blocks, starts[:half])
        try:
            blocks(starts[half:])
        finally:
            lower.result()
    else:
        blocks(starts)
    return len(starts)


_PARALLEL = 1 << 21       # values (channels x pixels x exposures) from which a merge takes two threads
_pool_of: list = []
_pool_lock = threading.Lock()


def _helpers() -> int:
    """Helper threads a large merge may use: one where the machine has two or more cores."""
    return 1 if (os.cpu_count() or 1) >= 2 else 0


def _pool() -> ThreadPoolExecutor:
    """The merge's helper thread, started at the first large merge, shared by all."""
    with _pool_lock:
        if not _pool_of:
            _pool_of.append(ThreadPoolExecutor(1, thread_name_prefix="gonio-merge"))
        return _pool_of[0]


def dark_sensitivity(x, scales, dark_dn, noise: NoiseModel, n_raw=1.0, usable=None) -> tuple[np.ndarray, np.ndarray]:
    """What the merge makes of a value's darks: (var, coef) for merged radiance ``x`` (DN per s
    per W, shape S), exposures of ``scales`` t_k P_k (K, or (K,) + S), darks of level
    ``dark_dn`` (DN, broadcast to (K,) + S) and ``usable`` (K,) + S (unsaturated; default all).

    ``var`` (S) is the merge's variance of the value (`merge_blocks`' second pass at the
    prediction x); ``coef`` ((K,) + S) = w_k / (sum_j w_j t_k P_k), minus the change of the
    merged value per DN of exposure k's dark frame: a dark frame's noise (variance
    ``(dark/g + (sigma_read/g)^2 + 1/12) / n_raw`` a value) moves every value that subtracts it,
    in every point that uses it (gonio/bench/dataset/budget.py carries it as a shared line)."""
    kk = np.asarray(scales, float)
    x = np.maximum(np.asarray(x, float), 0.0)
    kk = kk.reshape(kk.shape + (1,) * (x.ndim + 1 - kk.ndim)) if kk.ndim == 1 else kk
    d = np.maximum(np.asarray(dark_dn, float), 0.0)
    floor = (noise.read_noise / noise.gain) ** 2 + 1.0 / 12.0
    v_dark = (d / noise.gain + floor) / n_raw
    v = ((x * kk + d) / noise.gain + floor) / n_raw + v_dark
    w = kk * kk / v
    if usable is not None:
        w = np.where(usable, w, 0.0)
    wsum = w.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        var = np.where(wsum > 0, 1.0 / wsum, np.nan)
        coef = np.where(wsum > 0, w / (wsum * kk), 0.0)
    return var, coef


def ladder(t_min: float, t_max: float) -> np.ndarray:
    """Exposure times t_min * 2^k up to t_max (s): the rungs the bracketing may use."""
    k = int(np.floor(np.log2(t_max / t_min) + 1e-9))
    return t_min * 2.0 ** np.arange(k + 1)


def choose_bracket(rungs: np.ndarray, t_probe: float, peak_dn: float, low_dn: float, full_scale: float,
                   noise: NoiseModel, saturation_fraction: float = 0.9, snr: float = 20.0,
                   step: int = 2) -> list[float]:
    """The exposures to take, from one unsaturated probe frame.

    Parameters
    ----------
    rungs : ndarray
        The ladder (s), ascending.
    t_probe : float
        Probe exposure (s), a rung.
    peak_dn, low_dn : float
        Brightest raw value and darkest super-pixel signal (black-subtracted DN, dark-corrected)
        in the regions of interest, in the probe.
    full_scale : float
        White minus black, DN.
    step : int
        Take every ``step``-th rung between the shortest and the longest (2: factors of 4).

    Returns
    -------
    list of float
        Ascending exposure times: the shortest keeps the brightest value below
        ``0.8 * saturation_fraction`` of full scale; the longest brings the darkest to the
        signal-to-noise ``snr`` (or is the last rung that keeps the darkest unsaturated).
    """
    rate_hi = max(peak_dn, 1e-9) / t_probe              # DN/s of the brightest value
    rate_lo = max(low_dn, 1e-9) / t_probe
    t_short_max = 0.8 * saturation_fraction * full_scale / rate_hi
    i_short = int(np.searchsorted(rungs, t_short_max, side="right")) - 1
    i_short = max(0, i_short)
    need = noise.dn_for_snr(snr)
    t_long_min = need / rate_lo
    t_long_cap = 0.8 * saturation_fraction * full_scale / rate_lo   # darkest must stay unsaturated
    i_long = int(np.searchsorted(rungs, t_long_min, side="left"))
    i_cap = int(np.searchsorted(rungs, t_long_cap, side="right")) - 1
    i_long = max(i_short, min(i_long, i_cap, len(rungs) - 1))
    idx = list(range(i_short, i_long + 1, step))
    if idx[-1] != i_long:
        idx.append(i_long)
    return [float(rungs[i]) for i in idx]


def flat_gain(flats: Iterable[RawFrame], dark: RawFrame) -> np.ndarray:
    """Relative gain of each value (3, h, w) from flat-field frames of one exposure time.

    The mean dark-subtracted flat, divided by its mean over the frame per channel: 1 on
    average, the photo-response non-uniformity (PRNU) pixel by pixel. Its own noise is the
    flat's shot noise over ``len(flats)`` frames.
    """
    sig = np.zeros(np.shape(dark.signal))
    n = 0
    for f in flats:                       # summed in float64, one frame at a time (any iterable)
        sig += f.signal
        n += 1
    sig /= n
    sig -= dark.signal
    return (sig / sig.mean(axis=(1, 2), keepdims=True)).astype(np.float32)
