"""Pieces of one point's measurement: the sensor check, the reference's f_r, region statistics,
and the progress bar."""

from __future__ import annotations

import math
from typing import Any, Mapping

import numpy as np

from .errors import GonioError

__all__ = ["check_sensor", "ReferenceModel", "region_stats", "ProgressBar"]


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

    def factor(self, theta_i: float, theta_o: float) -> float:
        """The non-Lambertian factor at (theta_i, theta_o) in degrees (1 without a table)."""
        if self.table is None:
            return 1.0
        ti, to, fac = self.table
        rows = np.array([np.interp(theta_o, to, row) for row in fac])
        return float(np.interp(theta_i, ti, rows))

    def f_r(self, theta_i: float, theta_o: float) -> np.ndarray:
        """Reference f_r (3,) in sr^-1."""
        return self.rho / math.pi * self.factor(theta_i, theta_o)


def region_stats(hdr, mask: np.ndarray) -> dict[str, Any]:
    """Per-channel mean of the HDR radiance over ``mask``, its standard error, and counts.

    ``se`` is the empirical standard error of the mean (pixel scatter: shot and read noise and
    the sensor's fixed pattern), ``se_model`` the one the noise model alone predicts. Pixels
    saturated in every exposure (NaN) are left out and counted in ``n_saturated``.
    """
    rad, var = hdr.radiance[:, mask], hdr.var[:, mask]
    good = np.isfinite(rad)
    n = good.sum(1)
    mean, se, se_model = np.full(3, np.nan), np.full(3, np.nan), np.full(3, np.nan)
    for c in range(3):
        x = rad[c, good[c]]
        if n[c]:
            mean[c] = x.mean()
            se_model[c] = math.sqrt(var[c, good[c]].sum()) / n[c]
        if n[c] > 1:
            se[c] = x.std(ddof=1) / math.sqrt(n[c])
    return {"mean": mean, "se": se, "se_model": se_model, "n": n, "n_saturated": int((~good).sum())}


class ProgressBar:
    """rich progress: points done, ETA, the latest f_r (and reciprocity when a pair closes)."""

    def __init__(self, total: int, done: int, enabled: bool):
        self.p = None
        if not enabled:
            return
        from rich.console import Console
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

        self.p = Progress(TextColumn("capture"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
                          TextColumn("{task.fields[latest]}"), console=Console(stderr=True))
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
