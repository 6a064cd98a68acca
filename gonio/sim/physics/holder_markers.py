"""ArUco markers or a ChArUco board printed on the simulated holder, as Mitsuba shapes.

The layout is the ``markers`` entry of the ``[holder]`` settings table (the table the bench
reads, gonio/bench/plan/markers.py): an OpenCV dictionary name (``DICT_4X4_50``), the side
length, the ids and their centres (holder units; markers upright, top edge toward +y). Each
marker is a ``rectangle`` just above the dark holder plate (below the squares) whose diffuse
reflectance is its bitmap (OpenCV's ``generateImageMarker``) on a one-cell white margin, black
0.03, white 0.8, nearest-filtered so the cells stay sharp. ``board = [nx, ny]`` makes it a
ChArUco board: the image of OpenCV's ``CharucoBoard((nx, ny), square, size, dictionary)``
(``generateImage``, non-legacy) on a quarter-square white margin, centred at ``centre``,
upright, one rectangle below the sample and reference squares, which hide its middle.

``holder_pose`` ``(dx, dy, angle_deg)`` is where the holder really sits in the sample plane,
relative to the settings (off centre or turned): the squares and markers move with it, the plate
is uniform. The simulator's truth, for tests of marker-based region finding; the bench lacks it.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["MARKER_BLACK", "MARKER_WHITE", "board_bitmap", "holder_transform", "marker_bitmap", "marker_shapes"]

MARKER_BLACK = 0.03
MARKER_WHITE = 0.8
_MARKER_DROP = 1e-4          # between the squares (z = 0) and the plate (z = -2e-4)
_CELL_PIXELS = 8             # bitmap pixels per marker cell
_SQUARE_PIXELS = 64          # bitmap pixels per ChArUco square


def marker_bitmap(dictionary: str, marker_id: int) -> tuple[np.ndarray, float]:
    """The marker's reflectance (n, n), row 0 at its top: OpenCV's marker (one-cell black
    border) on a one-cell white margin, the quiet zone a detector needs on a dark plate.

    Returns the bitmap and its side relative to the marker's (black border to black border).
    """
    import cv2

    aruco = cv2.aruco
    d = aruco.getPredefinedDictionary(getattr(aruco, dictionary))
    cells = d.markerSize + 2
    img = aruco.generateImageMarker(d, int(marker_id), cells * _CELL_PIXELS)
    img = np.pad(img, _CELL_PIXELS, constant_values=255)
    return np.where(img > 127, MARKER_WHITE, MARKER_BLACK), (cells + 2) / cells


def board_bitmap(board) -> tuple[np.ndarray, tuple[float, float]]:
    """The board's reflectance (rows, cols), row 0 at its top, with a quarter-square white
    margin; returns it and its (width, height) in holder units."""
    import cv2

    nx, ny = (int(v) for v in board["board"])
    aruco = cv2.aruco
    d = aruco.getPredefinedDictionary(getattr(aruco, str(board["dictionary"])))
    b = aruco.CharucoBoard((nx, ny), float(board["square"]), float(board["size"]), d)
    img = b.generateImage((nx * _SQUARE_PIXELS, ny * _SQUARE_PIXELS), marginSize=0, borderBits=1)
    pad = _SQUARE_PIXELS // 4
    img = np.pad(img, pad, constant_values=255)
    grow = 1.0 + 2.0 * pad / _SQUARE_PIXELS                   # squares, margin included
    sq = float(board["square"])
    return np.where(img > 127, MARKER_WHITE, MARKER_BLACK), ((nx - 1 + grow) * sq, (ny - 1 + grow) * sq)


def _textured(refl: np.ndarray, mi) -> dict:
    # Mitsuba's rectangle maps v = 0 to its -y edge and a bitmap's row 0 to v = 0: flip the
    # rows so the print's top lies toward +y (as printed, seen from the +z side)
    rgb = np.repeat(refl[::-1, :, None], 3, axis=2).astype(np.float32)
    return {"type": "diffuse",
            "reflectance": {"type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(rgb)),
                            "filter_type": "nearest", "raw": True, "wrap_mode": "clamp"}}


def holder_transform(T, holder_pose):
    """The Mitsuba transform that puts the holder at A ``markers`` table with ``board = [nx, ny]`` is a ChArUco board instead (gonio/bench/plan/markers.py
describes the layout): OpenCV's ``CharucoBoard((nx, ny), square, size, dictionary)``
image (``generateImage``, OpenCV's current, non-legacy pattern) on a quarter-square white
margin, centred at ``centre`` and upright (its image's top row toward +y), one rectangle below
the sample and reference squares, which hide the board's middle.

``holder_pose`` ``(dx, dy, angle_deg)``."""
    dx, dy, ang = (float(v) for v in (holder_pose or (0.0, 0.0, 0.0)))
    if not all(math.isfinite(v) for v in (dx, dy, ang)):
        raise ValueError("holder_pose must be three finite numbers (dx, dy, angle_deg)")
    return T().translate([dx, dy, 0.0]) @ T().rotate([0.0, 0.0, 1.0], ang)


def marker_shapes(markers, holder_pose, mi) -> dict:
    """Scene-dict entries ``marker<ID>`` (or ``charuco``) for the layout ``markers`` (None: none)."""
    if not markers:
        return {}
    T = mi.ScalarTransform4f
    pose = holder_transform(T, holder_pose)
    if "board" in markers:
        refl, (w, h) = board_bitmap(markers)
        cx, cy = (float(v) for v in markers.get("centre", (0.0, 0.0)))
        return {"charuco": {"type": "rectangle", "bsdf": _textured(refl, mi),
                            "to_world": pose @ T().translate([cx, cy, -_MARKER_DROP]) @ T().scale([0.5 * w, 0.5 * h, 1.0])}}
    size = float(markers["size"])
    ids = [int(i) for i in markers["ids"]]
    centres = np.asarray(markers["centres"], float).reshape(len(ids), 2)
    out = {}
    for mid, (cx, cy) in zip(ids, centres):
        refl, grow = marker_bitmap(str(markers["dictionary"]), mid)
        out[f"marker{mid}"] = {
            "type": "rectangle", "bsdf": _textured(refl, mi),
            "to_world": pose @ T().translate([float(cx), float(cy), -_MARKER_DROP]) @ T().scale([0.5 * size * grow, 0.5 * size * grow, 1.0]),
        }
    return out
