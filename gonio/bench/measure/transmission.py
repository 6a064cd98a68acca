"""Transmission measurements normalised by the open beam (ASTM E2387).

The camera on the detector arm's rear stop reads the radiance L_t the sample transmits; the
open-beam frame (the sample out of the holder, the lamp straight behind its empty aperture,
through an attenuator of transmittance a) reads the lamp itself, E a / Omega_beam: the beam's
irradiance at the sample over its solid angle. As signal rates S = (DN - dark) / (t P), per
unit of the lamp monitor's power P (lamp drift cancels),

    f_t(wi, wo) = L_t / (E cos theta_i) = (S_t / S_open) a / (Omega_beam cos theta_i).

`OpenBeam` is that calibration, recorded in the dataset's attributes as the reference's
certificate is; a and Omega_beam come from ``[transmission]`` (their certificates' relative
uncertainties: a scale common to every transmitted point). The session takes the open beam and
the points on the rear stop (gonio/bench/session/rear.py); `journalled_open_beam` reads it back.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping

import numpy as np

from gonio.core.errors import GonioError

__all__ = ["OpenBeam", "transmission_settings", "open_beam_rate", "journalled_open_beam", "btdf"]

_DEFAULTS = {"open_beam_attenuation": 1e-3, "beam_solid_angle_sr": 1e-3, "rel_std": 0.01}


def transmission_settings(settings: Mapping) -> dict:
    """``[transmission]``: open_beam_attenuation (a), beam_solid_angle_sr (Omega_beam) and
    rel_std (their combined relative standard uncertainty, >= 0: 0 where they are exactly
    known, as in the simulator); GonioError naming the key otherwise."""
    tr = {**_DEFAULTS, **dict(settings.get("transmission") or {})}
    for key in _DEFAULTS:
        v = tr[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) \
                or (v < 0 if key == "rel_std" else v <= 0) or (key == "open_beam_attenuation" and v > 1):
            raise GonioError(f"[transmission] {key} must be a finite number > 0 (rel_std >= 0; <= 1 for the "
                             "attenuation); fix the settings")
    if tr["beam_solid_angle_sr"] > 2 * math.pi:
        raise GonioError("[transmission] beam_solid_angle_sr must be at most 2 pi sr; fix the settings")
    return tr


@dataclass(frozen=True)
class OpenBeam:
    """The open-beam calibration: the lamp's signal rate through the aperture and what scales it."""

    rate: np.ndarray            # (C,) DN per second per W of monitor power
    rate_u: np.ndarray          # (C,) its standard error
    attenuation: float
    beam_sr: float
    rel_std: float              # a and Omega_beam's combined relative standard uncertainty (type B)

    @property
    def radiance_scale(self) -> float:
        """a / Omega_beam: the open beam's radiance per unit irradiance at the sample, sr^-1."""
        return self.attenuation / self.beam_sr

    def to_attrs(self) -> dict:
        """The dataset attributes (NetCDF-friendly: numbers and lists of numbers): the budget's
        two type-B lines for transmission, ``open_beam_rel_std`` (the certificate, every channel
        alike) and ``open_beam_frame_rel_u`` (the open-beam frame's own relative error per channel:
        its pixels' scatter and its monitor reading, one error shared by every point)."""
        return {"open_beam_rate": [float(v) for v in self.rate], "open_beam_rate_u": [float(v) for v in self.rate_u],
                "open_beam_attenuation": self.attenuation, "beam_solid_angle_sr": self.beam_sr,
                "open_beam_rel_std": self.rel_std,
                "open_beam_frame_rel_u": [float(v) for v in self.rate_u / self.rate],
                "transmission_normalisation": "open beam (ASTM E2387)"}


def open_beam_rate(signal_dn: np.ndarray, exposure_s: float, power_w: float, settings: Mapping,
                   power_rel_u: float = 0.0) -> OpenBeam:
    """`OpenBeam` from the aperture's dark-subtracted pixel values (n, C) at one exposure and the
    monitor's power (W) with its relative standard error."""
    x = np.asarray(signal_dn, dtype=float)
    if x.ndim != 2 or x.shape[0] < 2 or not np.all(np.isfinite(x)):
        raise GonioError("open beam: need at least 2 finite aperture pixels per channel")
    if not (exposure_s > 0 and power_w > 0 and math.isfinite(exposure_s) and math.isfinite(power_w)):
        raise GonioError("open beam: the exposure and the monitor power must be finite and > 0 (is the lamp on?)")
    tr = transmission_settings(settings)
    k = 1.0 / (exposure_s * power_w)
    mean = x.mean(0)
    if np.any(mean <= 0):
        raise GonioError("open beam: no signal through the aperture; check the lamp and the beam's path")
    u = np.hypot(x.std(0, ddof=1) / math.sqrt(x.shape[0]), float(power_rel_u) * mean)
    return OpenBeam(mean * k, u * k, float(tr["open_beam_attenuation"]),
                    float(tr["beam_solid_angle_sr"]), float(tr["rel_std"]))


def journalled_open_beam(events, frames: Mapping, settings: Mapping) -> tuple[OpenBeam | None, dict]:
    """A session's open beam (gonio/bench/session/rear.py): the last ``open_beam`` journal event
    (``events``: (time, kind, text)) whose frame ``frames`` (the journal's kind ``open_beam``
    calibration frames, ``{name: (seconds, file, sha256)}``) still holds with its digest; (None,
    {}) without one."""
    import json

    held = {f: d for _, f, d in frames.values()}
    found = None
    for _, kind, text in events:
        if kind == "open_beam":
            info = json.loads(text)
            if held.get(info.get("file")) == info.get("sha256"):
                found = info
    if found is None:
        return None, {}
    tr = transmission_settings(settings)
    return OpenBeam(np.asarray(found["rate"], float), np.asarray(found["rate_u"], float),
                    float(tr["open_beam_attenuation"]), float(tr["beam_solid_angle_sr"]), float(tr["rel_std"])), found


def btdf(rate, rate_u, ob: OpenBeam, theta_i_deg) -> tuple[np.ndarray, np.ndarray]:
    """f_t and its standard uncertainty from the sample's signal rate (N, C) (module docstring):
    each point's own; the open beam's error is one scale shared by every point (a fit that
    took it as independent errors would average it away), carried by the budget
    (`OpenBeam.to_attrs`), as the certificate is."""
    rate, rate_u = np.atleast_2d(rate), np.atleast_2d(rate_u)
    c = np.cos(np.radians(np.asarray(theta_i_deg, float)))[:, None]
    k = ob.radiance_scale / (ob.rate * c)
    return rate * k, rate_u * k
