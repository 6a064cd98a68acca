"""HDR merge of an exposure bracket into linear relative radiance, with its variance.

Noise model of one black-subtracted raw value ``D`` (DN) holding ``S`` DN of signal (photo
and dark electrons): ``var(D) = S / g + (sigma_read / g)^2 + 1/12``, with ``g`` the gain in
electrons per DN and the last term the quantisation. A value that averages ``n`` raw pixels
(the two greens of a CFA tile) has ``var / n``.

Per exposure k (time ``t_k`` s, monitor reading ``P_k`` W, dark frame ``K_k``):
``x_k = (D_k - K_k) / (t_k P_k)`` with ``var(x_k) = (var(D_k) + var(K_k)) / (t_k P_k)^2``.
The merged radiance is the inverse-variance weighted mean over the exposures where the value
is not saturated (its brightest raw pixel below ``saturation_fraction`` of full scale):
``x = sum(w_k x_k) / sum(w_k)``, ``var(x) = 1 / sum(w_k)``, ``w_k = 1 / var(x_k)``. The
variances are evaluated at the model's prediction ``x t_k P_k`` (a second pass), not at the
noisy measured values, which would bias the weights toward low readings.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ._camera import RawFrame

__all__ = ["NoiseModel", "Exposure", "HdrResult", "merge", "choose_bracket", "ladder", "flat_gain"]


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


def merge(exposures: Sequence[Exposure], noise: NoiseModel, saturation_fraction: float = 0.9) -> HdrResult:
    """Merge a bracket (see the module notes for the formulas)."""
    if not exposures:
        raise ValueError("empty bracket")
    n = exposures[0].frame.n_raw[:, None, None]
    x, ok, scale, dark = [], [], [], []
    for e in exposures:
        k = e.seconds * e.power
        x.append((e.frame.signal - e.dark.signal) / k)
        ok.append(~_saturated(e.frame, saturation_fraction))
        scale.append(k)
        dark.append(np.maximum(e.dark.signal, 0.0))
    x, ok = np.stack(x), np.stack(ok)
    scale = np.asarray(scale)[:, None, None, None]
    dark = np.stack(dark)
    var_dark = noise.var_dn(dark, n)

    def weights(pred):
        var = (noise.var_dn(pred * scale + dark, n) + var_dark) / scale ** 2
        return np.where(ok, 1.0 / var, 0.0)

    # pass 1: weights from the measured values; pass 2: from the merged prediction
    w = weights(np.maximum(x, 0.0))
    wsum = w.sum(0)
    with np.errstate(invalid="ignore", divide="ignore"):
        est = np.where(wsum > 0, (w * x).sum(0) / np.where(wsum > 0, wsum, 1.0), np.nan)
        w = weights(np.maximum(np.nan_to_num(est), 0.0)[None])
        wsum = w.sum(0)
        rad = np.where(wsum > 0, (w * x).sum(0) / np.where(wsum > 0, wsum, 1.0), np.nan)
        var = np.where(wsum > 0, 1.0 / np.where(wsum > 0, wsum, 1.0), np.nan)
    return HdrResult(rad, var, ok.sum(0))


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


def flat_gain(flats: Sequence[RawFrame], dark: RawFrame) -> np.ndarray:
    """Relative gain of each value (3, h, w) from flat-field frames of one exposure time.

    The mean dark-subtracted flat, divided by its mean over the frame per channel: 1 on
    average, the photo-response non-uniformity (PRNU) pixel by pixel. Its own noise is the
    flat's shot noise over ``len(flats)`` frames.
    """
    sig = np.mean([f.signal for f in flats], axis=0) - dark.signal
    return sig / sig.mean(axis=(1, 2), keepdims=True)
