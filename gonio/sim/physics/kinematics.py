"""Forward kinematics of the simulated gonioreflectometer (docs/interfaces.md section 3).

The simulator's physical truth: stage angles -> sample orientation -> (wi, wo) in the sample
frame, and the camera's image axes expressed in the sample frame. bench/ keeps its own
(inverse) model; tests compare the two. The rear detector arm (transmission) holds the camera
on the far side, at -c looking along +c with the same image up: wo and image right flip sign.
"""

from __future__ import annotations

import numpy as np

__all__ = ["rot_z", "rot_y", "sample_rotation", "forward", "B", "DETECTORS"]

#: Columns: local x -> lab Y, local y -> lab Z, local z -> lab X.
B = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])

CAMERA = np.array([1.0, 0.0, 0.0])     # lab direction from the sample centre to the camera
IMAGE_RIGHT = np.array([0.0, 1.0, 0.0])
IMAGE_UP = np.array([0.0, 0.0, 1.0])
#: The detector arm's two stops: the camera's lab direction (from the sample centre) and its image right.
DETECTORS = {"front": (CAMERA, IMAGE_RIGHT), "rear": (-CAMERA, -IMAGE_RIGHT)}


def rot_z(a: float) -> np.ndarray:
    """Right-handed rotation about lab Z by ``a`` radians."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rot_y(a: float) -> np.ndarray:
    """Right-handed rotation about lab Y by ``a`` radians."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def sample_rotation(yaw: float, tilt: float, azimuth: float) -> np.ndarray:
    """``R = Rz(yaw) Ry(tilt) B Rz(azimuth)``; columns are the local axes in the lab (radians in)."""
    return rot_z(yaw) @ rot_y(tilt) @ B @ rot_z(azimuth)


def forward(yaw: float, tilt: float, azimuth: float, lamp: float, detector: str = "front") -> dict:
    """Directions in the sample frame for stage angles in radians, the camera on the detector
    arm's ``front`` (reflection) or ``rear`` (transmission) stop.

    Returns
    -------
    dict
        ``wi`` (to the lamp), ``wo`` (to the camera), ``right`` and ``up`` (the image axes),
        each a unit 3-vector in the sample's local frame; ``R`` the 3x3 orientation.
    """
    try:
        cam, right = DETECTORS[detector]
    except KeyError:
        raise ValueError(f"detector must be 'front' or 'rear', not {str(detector)[:20]!r}") from None
    R = sample_rotation(yaw, tilt, azimuth)
    light = np.array([np.cos(lamp), np.sin(lamp), 0.0])
    return {"wi": R.T @ light, "wo": R.T @ cam, "right": R.T @ right,
            "up": R.T @ IMAGE_UP, "R": R}
