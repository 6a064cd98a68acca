"""Kinematics of the default 4-axis gonioreflectometer (docs/interfaces.md section 3).

Lab frame: +Z up, the camera along ``c = (1, 0, 0)`` from the sample centre, the lamp arm at
angle L about lab Z: ``l(L) = (cos L, sin L, 0)``. The sample's orientation is
``R = Rz(yaw) @ Ry(tilt) @ B @ Rz(azimuth)`` with ``B = [[0,0,1],[1,0,0],[0,1,0]]``; in the
sample's local frame ``wi = R.T @ l(L)`` and ``wo = R.T @ c``.

Stage angles are given as arrays whose last axis holds ``(yaw, tilt, azimuth, lamp)`` in
degrees (the order of `AXES`). Direction angles (theta, phi) are in degrees at this module's
public surface (plans and files use degrees); vectors are unit, float64. The inverse (stage
angles from directions) is in closed form, with the lamp on the +Y side (L in (0, 180)).
Transmission (theta_o in (90, 180]) puts the camera on the detector arm's rear stop, at -c
(image right -Y): the pose is the one that shows the front camera -wo (`detector_of`).
"""

# The inverse, in closed form. The sample normal in the lab is
# n = R e_z = (cos(tilt) cos(yaw), cos(tilt) sin(yaw), -sin(tilt)), so n.c = n_x = cos(theta_o),
# n.l = n_x cos L + n_y sin L = cos(theta_i) and, since (l x c).n = -sin L n_z equals the
# local (wi x wo)_z = sin(theta_i) sin(theta_o) sin(phi_o - phi_i),
# n_z = sin(theta_i) sin(theta_o) sin(phi_i - phi_o) / sin L. With L = arccos(wi.wo) in
# (0, 180) (the lamp on the +Y side; the mirror solution -L, -n_y, -n_z exists too):
# yaw = atan2(n_y, n_x), tilt = -asin(n_z), and the azimuth is the difference between the
# azimuth of wo (or of wi, whichever is farther from the normal) in the pre-azimuth frame
# Rz(yaw) Ry(tilt) B and in the sample frame.

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping

import numpy as np

from gonio.core import geometry
from gonio.core.sides import REFLECTION_ONLY, Side

from gonio.bench.settings import AXES

__all__ = [
    "AXES",
    "B",
    "rotation",
    "forward",
    "forward_angles",
    "inverse",
    "directions",
    "angles_of",
    "reachable",
    "Reachability",
    "detector_of",
]

B = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
_C = np.array([1.0, 0.0, 0.0])
MIN_ROI_PIXELS = 4      # super-pixels each region of interest needs for a mean and its standard error


def _rz(a):
    c, s = np.cos(a), np.sin(a)
    z, o = np.zeros_like(a), np.ones_like(a)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)


def _ry(a):
    c, s = np.cos(a), np.sin(a)
    z, o = np.zeros_like(a), np.ones_like(a)
    return np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2)


def rotation(stage_deg) -> np.ndarray:
    """Sample orientation ``R`` (..., 3, 3): columns are the local axes in lab coordinates.

    Parameters
    ----------
    stage_deg : array_like (..., 4)
        ``(yaw, tilt, azimuth, lamp)`` in degrees (the lamp is ignored).
    """
    s = np.radians(np.asarray(stage_deg, dtype=float))
    return _rz(s[..., 0]) @ _ry(s[..., 1]) @ B @ _rz(s[..., 2])


def detector_of(theta_o) -> np.ndarray:
    """The detector arm's stop for each theta_o (deg): True (rear) where it lies on the
    transmission side (theta_o > 90), False (front) otherwise."""
    return np.asarray(theta_o, float) > 90.0


def forward(stage_deg, rear=False) -> tuple[np.ndarray, np.ndarray]:
    """Stage angles -> local directions.

    Parameters
    ----------
    stage_deg : array_like (..., 4)
        ``(yaw, tilt, azimuth, lamp)``, degrees.
    rear : bool or array of bool (...)
        The camera on the rear stop (transmission): ``wo`` flips.

    Returns
    -------
    wi, wo : ndarray (..., 3)
        Unit vectors in the sample's local frame toward the lamp and the camera.
    """
    s = np.asarray(stage_deg, dtype=float)
    R = rotation(s)
    L = np.radians(s[..., 3])
    lamp = np.stack([np.cos(L), np.sin(L), np.zeros_like(L)], -1)
    Rt = np.swapaxes(R, -1, -2)
    wi = (Rt @ lamp[..., None])[..., 0]
    wo = Rt @ _C
    wo = np.where(np.asarray(rear, bool)[..., None], -wo, wo)
    return wi, wo


def angles_of(w) -> tuple[np.ndarray, np.ndarray]:
    """Unit vectors (..., 3) -> (theta, phi) in degrees, phi in [-180, 180)."""
    theta, phi = geometry.angles_deg(w)
    return theta, _wrap(phi)


def directions(theta_deg, phi_deg) -> np.ndarray:
    """(theta, phi) in degrees -> unit vectors (..., 3) in the local frame."""
    return geometry.directions_deg(theta_deg, phi_deg)


def forward_angles(stage_deg, rear=False) -> np.ndarray:
    """Stage angles (..., 4) -> ``(theta_i, phi_i, theta_o, phi_o)`` (..., 4) in degrees."""
    wi, wo = forward(stage_deg, rear)
    ti, pi_ = angles_of(wi)
    to, po = angles_of(wo)
    return np.stack([ti, pi_, to, po], -1)


def _wrap(deg):
    """Wrap degrees to [-180, 180)."""
    return (np.asarray(deg, float) + 180.0) % 360.0 - 180.0


def inverse(theta_i, phi_i, theta_o, phi_o) -> np.ndarray:
    """Direction angles (degrees) -> stage angles ``(yaw, tilt, azimuth, lamp)`` (..., 4), degrees.

    Closed form (module docstring); the lamp arm on the +Y side (L in (0, 180)). Geometries
    with ``wi = wo`` (L = 0: the lamp would sit on the camera) give NaN; `reachable` says why.
    theta_o > 90 (transmission, the rear detector): the pose that shows the front stop -wo.
    """
    rear = detector_of(theta_o)
    theta_o = np.where(rear, 180.0 - np.asarray(theta_o, float), theta_o)
    phi_o = np.where(rear, np.asarray(phi_o, float) + 180.0, phi_o)
    ti, pi_, to, po = np.broadcast_arrays(*(np.radians(np.asarray(a, float)) for a in (theta_i, phi_i, theta_o, phi_o)))
    wi = directions(np.degrees(ti), np.degrees(pi_))
    wo = directions(np.degrees(to), np.degrees(po))
    cosL = np.clip(np.sum(wi * wo, -1), -1.0, 1.0)
    L = np.arccos(cosL)
    sinL = np.sin(L)
    with np.errstate(divide="ignore", invalid="ignore"):
        nx = np.cos(to)
        ny = (np.cos(ti) - nx * cosL) / sinL
        nz = np.sin(ti) * np.sin(to) * np.sin(pi_ - po) / sinL
    yaw = np.arctan2(ny, nx)
    tilt = -np.arcsin(np.clip(nz, -1.0, 1.0))
    # pre-azimuth frame P = Rz(yaw) Ry(tilt) B; local = Rz(az).T @ (P.T @ lab)
    P = _rz(yaw) @ _ry(tilt) @ B
    Pt = np.swapaxes(P, -1, -2)
    wo_pre = Pt @ _C
    lamp = np.stack([cosL, sinL, np.zeros_like(L)], -1)
    wi_pre = (Pt @ lamp[..., None])[..., 0]
    use_wo = np.sin(to) >= np.sin(ti)
    pre = np.where(use_wo[..., None], wo_pre, wi_pre)
    phi_loc = np.where(use_wo, po, pi_)
    az = np.arctan2(pre[..., 1], pre[..., 0]) - phi_loc
    out = np.degrees(np.stack([yaw, tilt, az, L], -1))
    out[..., 2] = _wrap(out[..., 2])
    bad = ~np.isfinite(out).all(-1) | (sinL < 1e-12)
    out[bad] = np.nan
    # straight through: the lamp on the front axis, L = 0, where the closed form is 0 / 0 (at
    # sin L = 1e-8 from rounding it put a 40 deg point at normal incidence)
    through = rear & (sinL < 1e-6) & (cosL > 0.0)
    if np.any(through):                               # one pose of the family: tilt 0, yaw theta_i
        yaw0 = np.where(through, ti, 0.0)
        P0 = _rz(yaw0) @ B
        wi0 = np.swapaxes(P0, -1, -2) @ _C
        az0 = np.degrees(np.arctan2(wi0[..., 1], wi0[..., 0]) - pi_)
        alt = np.stack([np.degrees(yaw0), np.zeros_like(yaw0), _wrap(az0), np.zeros_like(yaw0)], -1)
        out[through] = alt[through]
    return out


@dataclass(frozen=True)
class Reachability:
    """Why a configuration can or cannot be reached.

    Attributes
    ----------
    ok : ndarray of bool (N,)
    reason : list of str
        ``""`` where reachable, else a short phrase (e.g. ``"lamp in front of the camera (L = 3.0 deg < 6 deg)"``).
    stage_deg : ndarray (N, 4)
        The inverse solution (NaN where none).
    """

    ok: np.ndarray
    reason: list
    stage_deg: np.ndarray


def reachable(theta_i, phi_i, theta_o, phi_o, settings: Mapping, masks=None, sides=REFLECTION_ONLY) -> Reachability:
    """Check direction angles (degrees) against the instrument's geometry and limits.

    Reasons, in the order checked: not finite; below the horizon or at grazing (theta_i outside
    [0, 90), theta_o outside ``sides``' ranges: [0, 90), and (90, 180] with transmission);
    lamp in front of the camera (L <
    ``lamp_block_deg``, or 180 - L on the rear stop); an axis outside its limits
    (after choosing the equivalent azimuth inside the limits); fewer than `MIN_ROI_PIXELS`
    super-pixels of the sample or reference square in view (the sample's alone from the rear: the
    open beam normalises transmission, not the reference). ``masks(stage, settings)`` gives
    the two regions (default :func:`roi_masks`; a plan's check uses the capture's own
    ``_markers.roi_masks_fast``, the same masks at a fraction of the cost on a large sensor).
    """
    masks = roi_masks if masks is None else masks
    through = Side.TRANSMIT in tuple(sides)
    ti, pi_, to, po = (np.atleast_1d(np.asarray(a, float)) for a in (theta_i, phi_i, theta_o, phi_o))
    ti, pi_, to, po = np.broadcast_arrays(ti, pi_, to, po)
    stage = inverse(ti, pi_, to, po)
    axes = settings["axes"]
    block = float(axes["lamp_block_deg"])
    n = ti.shape[0]
    ok = np.ones(n, bool)
    reasons = [""] * n
    for k in range(n):
        a = (ti[k], pi_[k], to[k], po[k])
        if not all(math.isfinite(x) for x in a):
            reasons[k] = "angle is not a finite number"
        elif not (0.0 <= ti[k] < 90.0 and (0.0 <= to[k] < 90.0 or (through and 90.0 < to[k] <= 180.0))):
            reasons[k] = ("below the horizon or grazing (theta must be in [0, 90) deg"
                          + (", theta_o also (90, 180])" if through else ")"))
        else:
            rear = bool(detector_of(to[k]))
            L = stage[k, 3]
            Lc = 180.0 - L if rear else L           # the lamp's angle from the camera in use
            if not math.isfinite(L) or Lc < block:
                Ls = 0.0 if not math.isfinite(L) else Lc
                reasons[k] = f"lamp in front of the camera (L = {Ls:.1f} deg < {block:g} deg)"
            else:
                for j, name in enumerate(AXES):
                    lo, hi = float(axes[name][2]), float(axes[name][3])
                    v = stage[k, j]
                    if name == "azimuth" and hi - lo >= 360.0 - 1e-9:
                        continue
                    if not (lo - 1e-9 <= v <= hi + 1e-9):
                        reasons[k] = f"{name} = {v:.1f} deg outside its limits [{lo:g}, {hi:g}]"
                        break
                if not reasons[k] and "camera" in settings and "holder" in settings:
                    sm, rm = masks(stage[k], settings)      # from the rear: the same regions mirrored
                    if min(sm.sum(), MIN_ROI_PIXELS if rear else rm.sum()) < MIN_ROI_PIXELS:
                        reasons[k] = "the sample or reference square is out of the camera's view"
        ok[k] = reasons[k] == ""
    return Reachability(ok, reasons, stage)


def image_to_local(stage_deg, rows, cols, settings: Mapping, rear: bool = False) -> np.ndarray:
    """Where camera pixels see the sample plane, in the sample's local frame.

    Parameters
    ----------
    stage_deg : array_like (4,)
        ``(yaw, tilt, azimuth, lamp)``, degrees.
    rows, cols : array_like
        Pixel coordinates (row 0 at the top; fractional values allowed: -0.5 is a pixel's edge).
    settings : dict
        ``camera`` table: ``width``, ``height``, ``pixel_size`` (holder units per pixel).

    Returns
    -------
    ndarray (..., 2)
        Local (x, y) in holder units of the points the pixels see (orthographic camera along
        -c, docs/interfaces.md section 3; from the rear stop along +c, image right -Y).
    """
    cam = settings["camera"]
    W, H, s = cam["width"], cam["height"], cam["pixel_size"]
    rows, cols = np.broadcast_arrays(np.asarray(rows, float), np.asarray(cols, float))
    R = rotation(stage_deg)
    n = R[:, 2]
    p = np.stack([np.zeros_like(rows), (cols - (W - 1) / 2) * s * (-1.0 if rear else 1.0), -(rows - (H - 1) / 2) * s], -1)
    t = (p @ n) / n[0]
    q = p - t[..., None] * _C
    return (q @ R)[..., :2]


def roi_masks(stage_deg, settings: Mapping, binning: int = 2, margin_px: float | None = None, rear: bool = False):
    """Pixels (on the ``binning`` x ``binning`` super-pixel grid) that lie wholly inside each square.

    A super-pixel belongs to a region when all four corners of its footprint on the sample
    plane lie inside the holder square shrunk by ``margin_px`` raw pixels (``roi_margin_px``
    of ``[capture]`` by default): the region is located from the geometry alone, and it stays
    inside the square however grazing the view.

    Returns
    -------
    sample, reference : ndarray of bool (H // binning, W // binning)
    """
    cam, hold = settings["camera"], settings["holder"]
    W, H, s = cam["width"], cam["height"], cam["pixel_size"]
    if margin_px is None:
        margin_px = float(settings.get("capture", {}).get("roi_margin_px", 1.0))
    h, w = H // binning, W // binning
    i, j = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    corners = []
    for dr in (-0.5, binning - 0.5):
        for dc in (-0.5, binning - 0.5):
            corners.append(image_to_local(stage_deg, binning * i + dr, binning * j + dc, settings, rear))
    xy = np.stack(corners, 0)                        # (4, h, w, 2)
    half = hold["sample_half"] - margin_px * s
    off = hold["offset"]

    def inside(cx):
        return np.all((np.abs(xy[..., 0] - cx) <= half) & (np.abs(xy[..., 1]) <= half), axis=0)

    return inside(-off), inside(off)
