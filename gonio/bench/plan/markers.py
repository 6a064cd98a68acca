"""The holder's ArUco markers or ChArUco board: where the sample and reference squares are in a frame.

The holder carries ArUco markers beside the two squares, or a ChArUco board under them: the
``markers`` entry of the ``[holder]`` settings table, in holder units::

    markers = { dictionary = "DICT_4X4_50", size = 0.12, ids = [0, 1, 2, 3, 4, 5],
                centres = [[-0.49, 0.36], [0.0, 0.36], [0.49, 0.36], ...] }
    markers = { dictionary = "DICT_4X4_50", board = [10, 8], square = 0.125, size = 0.1,
                centre = [0.0, 0.0] }

`find_regions` detects the markers in a frame (OpenCV's aruco module), maps their corners to
the sample plane through the stage geometry (`kinematics.image_to_local`), fits the holder's
pose there (a rotation and a shift, least squares) and returns the super-pixels wholly inside
each square. Where no marker is found, or the fit is poor, the regions come from the geometry
alone (`kinematics.roi_masks`): the fallback, said in ``source``.
"""

# Marker table in full (holder units, in the holder's plane, x from the sample square to the
# reference square, markers upright: their top edge toward +y); the simulated holder
# (gonio/sim/physics/scene.py) renders the same table:
#     [holder]
#     markers = { dictionary = "DICT_4X4_50", size = 0.12, ids = [0, 1, 2, 3, 4, 5],
#                 centres = [[-0.49, 0.36], [0.0, 0.36], [0.49, 0.36],
#                            [-0.49, -0.36], [0.0, -0.36], [0.49, -0.36]] }
# ChArUco board (OpenCV's CharucoBoard: a chessboard whose white squares carry ArUco markers,
# its corners found to sub-pixel precision between two decoded markers): board = the squares
# across and down, square = their side, size = the markers' side (holder units), centre = the
# board's centre on the holder. The board is upright (the top row of OpenCV's board image
# toward +y) and lies under the sample and reference squares, which hide its middle
# (example_board: 10 x 8 squares of 0.125 around the default squares; the two visible rows
# above and below them give 18 corners). The board's object points (OpenCV: origin at the
# top-left corner, x right, y down) map to the holder as centre + (x - W/2, H/2 - y). A corner
# is used only where both markers beside it were decoded (CharucoParameters.minMarkers 2), so
# no corner is interpolated from one marker next to a hidden square.
# The pose is not OpenCV's solvePnP: that is a pinhole camera's pose, and the bench's camera
# is telecentric (orthographic; its intrinsics are the pixel size and image axes of
# docs/interfaces.md), so the matched image points go through that camera's own map to the
# sample plane and the holder's planar shift and turn are fitted there, as for the markers;
# the least squares run over every corner. Where the fit falls back, the holder is assumed
# where the settings put it.
# Corner positions: OpenCV reports a marker's corners on its outermost pixel centres (half a
# pixel inside the true edge on every side); the shrink is symmetric, so the fitted rotation
# and shift, which use the corners' centroid and directions, are unbiased by it.

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from gonio.bench.plan import kinematics
from gonio.core.errors import GonioError

__all__ = [
    "roi_masks_fast",
    "BoardLayout",
    "HolderPose",
    "MarkerLayout",
    "Regions",
    "detect",
    "detect_board",
    "example_board",
    "example_layout",
    "find_regions",
    "fit_pose",
    "layout_of",
    "posed_masks",
]

#: the fit's rms corner residual (holder units, per pixel size) above which the markers are not trusted
MAX_RMS_PIXELS = 1.5
#: the fewest ChArUco corners a pose is fitted to
MIN_BOARD_CORNERS = 4


def example_layout(sample_half: float = 0.25, offset: float = 0.3, size: float = 0.12) -> dict:
    """A ``markers`` table with six 4x4 markers: three above and three below the two squares
    (each on a white margin of one cell, a sixth of ``size``)."""
    y = sample_half + 0.03 + size / 6 + 0.5 * size
    xs = [-(offset + sample_half) + 0.5 * size, 0.0, offset + sample_half - 0.5 * size]
    centres = [[x, y] for x in xs] + [[x, -y] for x in xs]
    return {"dictionary": "DICT_4X4_50", "size": float(size), "ids": list(range(6)), "centres": centres}


def example_board(sample_half: float = 0.25, offset: float = 0.3) -> dict:
    """A ``markers`` table for a ChArUco board under the two squares: 10 x 8 squares of side
    ``sample_half / 2`` (markers 0.8 of it), so a row boundary runs along the squares' top and
    bottom edges and two whole rows show above and below them."""
    sq = 0.5 * sample_half
    nx = 2 * math.ceil((offset + sample_half) / sq)
    return {"dictionary": "DICT_4X4_50", "board": [nx, 8], "square": sq, "size": 0.8 * sq, "centre": [0.0, 0.0]}


@dataclass(frozen=True)
class BoardLayout:
    """A ChArUco board on the holder: dictionary name, squares (nx, ny), square and marker
    sides and centre (holder units)."""

    dictionary: str
    squares: tuple
    square: float
    size: float
    centre: np.ndarray           # (2,)

    def board(self):
        import cv2

        aruco = cv2.aruco
        d = aruco.getPredefinedDictionary(getattr(aruco, self.dictionary))
        return aruco.CharucoBoard(self.squares, self.square, self.size, d)

    def to_holder(self, obj: np.ndarray) -> np.ndarray:
        """OpenCV board object points (n, 3) or (n, 2) -> holder coordinates (n, 2)."""
        obj = np.asarray(obj, float).reshape(-1, np.shape(obj)[-1])
        w, h = self.squares[0] * self.square, self.squares[1] * self.square
        return self.centre + np.stack([obj[:, 0] - 0.5 * w, 0.5 * h - obj[:, 1]], axis=1)


@dataclass(frozen=True)
class MarkerLayout:
    """The markers of the holder: OpenCV dictionary name, side length, ids and centres (holder units)."""

    dictionary: str
    size: float
    ids: tuple
    centres: np.ndarray          # (n, 2)

    def corners(self, marker_id: int) -> np.ndarray:
        """The marker's corners (4, 2) in holder coordinates, OpenCV's order: top-left, top-right,
        bottom-right, bottom-left, for a marker upright on the holder (top toward +y)."""
        c = self.centres[self.ids.index(marker_id)]
        h = 0.5 * self.size
        return c + np.array([[-h, h], [h, h], [h, -h], [-h, -h]])


def layout_of(settings: Mapping) -> MarkerLayout | None:
    """The marker layout of ``settings["holder"]["markers"]``; None where the holder has none.

    Raises
    ------
    GonioError
        The table is malformed (one line naming what to fix).
    """
    table = settings.get("holder", {}).get("markers")
    if table is None:
        return None
    bad = GonioError("[holder] markers must be a table with dictionary (e.g. \"DICT_4X4_50\"), size > 0, "
                     "ids (distinct integers) and centres (one [x, y] per id); fix the settings")
    if not isinstance(table, Mapping):
        raise bad
    if "board" in table:
        return _board_of(table)
    try:
        import cv2

        name = str(table["dictionary"])
        if not (name.startswith("DICT_") and isinstance(getattr(cv2.aruco, name, None), int)):
            raise bad
        size = table["size"]
        ids = tuple(table["ids"])
        centres = np.asarray(table["centres"], dtype=float)
    except (KeyError, TypeError, ValueError):
        raise bad from None
    if (isinstance(size, bool) or not isinstance(size, (int, float)) or not (math.isfinite(size) and size > 0)
            or not ids or len(ids) > 1000 or any(isinstance(i, bool) or not isinstance(i, int) or i < 0 for i in ids)
            or len(set(ids)) != len(ids) or centres.shape != (len(ids), 2) or not np.all(np.isfinite(centres))):
        raise bad
    return MarkerLayout(name, float(size), ids, centres)


def _board_of(table: Mapping) -> BoardLayout:
    bad = GonioError("[holder] markers with a board must have dictionary (e.g. \"DICT_4X4_50\"), board = [nx, ny] "
                     "(integers 3..100), square > size > 0 and centre = [x, y]; fix the settings")

    def number(v) -> float:
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise bad
        return float(v)

    try:
        import cv2

        name = str(table["dictionary"])
        squares = tuple(table["board"])
        square, size = number(table["square"]), number(table["size"])
        centre = np.array([number(v) for v in table.get("centre", (0.0, 0.0))])
    except (KeyError, TypeError, ValueError):
        raise bad from None
    if (not (name.startswith("DICT_") and isinstance(getattr(cv2.aruco, name, None), int)) or len(squares) != 2
            or any(isinstance(n, bool) or not isinstance(n, int) or not 3 <= n <= 100 for n in squares)
            or not 0 < size < square or centre.shape != (2,)):
        raise bad
    layout = BoardLayout(name, squares, square, size, centre)
    n_markers = squares[0] * squares[1] // 2
    if n_markers > cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name)).bytesList.shape[0]:
        raise GonioError(f"[holder] markers: a {squares[0]} x {squares[1]} board needs {n_markers} markers, "
                         f"more than {name} has; choose a larger dictionary or fewer squares")
    return layout


def _to_8bit(image: np.ndarray) -> np.ndarray:
    """A linear image (h, w) scaled to 8 bits: 0 at its 1st percentile, 255 at its 99.5th."""
    img = np.nan_to_num(np.asarray(image, float), nan=0.0, posinf=0.0, neginf=0.0)
    lo, hi = np.percentile(img, [1.0, 99.5])
    if not hi > lo:
        return np.zeros(img.shape, np.uint8)
    return np.clip((img - lo) * (255.0 / (hi - lo)), 0, 255).astype(np.uint8)


def detect(image: np.ndarray, layout: MarkerLayout) -> dict[int, np.ndarray]:
    """Markers of ``layout`` found in ``image`` (h, w), linear: ``{id: corners (4, 2) as (col, row)}``."""
    import cv2

    aruco = cv2.aruco
    dictionary = aruco.getPredefinedDictionary(getattr(aruco, layout.dictionary))
    params = aruco.DetectorParameters()
    params.cornerRefinementMethod = aruco.CORNER_REFINE_SUBPIX
    params.minMarkerPerimeterRate = 0.01       # small markers in a wide frame
    corners, ids, _ = aruco.ArucoDetector(dictionary, params).detectMarkers(_to_8bit(image))
    found = {}
    if ids is None:
        return found
    for c, i in zip(corners, ids.ravel()):
        i = int(i)
        if i in layout.ids and i not in found:
            found[i] = np.asarray(c, float).reshape(4, 2)
    return found


def detect_board(image: np.ndarray, layout: BoardLayout) -> tuple[np.ndarray, np.ndarray]:
    """The board's corners found in ``image`` (h, w), linear: ``(holder_xy (n, 2), image (n, 2)
    as (col, row))``, n = 0 where none; OpenCV's ``CharucoDetector`` and ``matchImagePoints``."""
    import cv2

    aruco = cv2.aruco
    board = layout.board()
    params = aruco.DetectorParameters()
    params.minMarkerPerimeterRate = 0.01       # small markers in a wide frame
    charuco = aruco.CharucoParameters()
    charuco.minMarkers = 2                     # a corner between two decoded markers only
    corners, ids, _, _ = aruco.CharucoDetector(board, charuco, params).detectBoard(_to_8bit(image))
    if ids is None or len(ids) == 0:
        return np.zeros((0, 2)), np.zeros((0, 2))
    obj, img = board.matchImagePoints(corners, ids)
    return layout.to_holder(obj), np.asarray(img, float).reshape(-1, 2)


@dataclass(frozen=True)
class HolderPose:
    """Where the holder sits in the sample plane relative to where the settings put it.

    ``local = R(angle) @ holder + shift``; ``rms`` is the fit's corner residual (holder units),
    ``ids`` the markers it used (a board: the indices of the corners found).
    """

    shift: np.ndarray            # (2,)
    angle_deg: float
    rms: float
    ids: tuple

    def to_holder(self, local: np.ndarray) -> np.ndarray:
        """Sample-plane points (..., 2) -> holder coordinates."""
        a = math.radians(self.angle_deg)
        R = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
        return (np.asarray(local, float) - self.shift) @ R        # R.T applied to row vectors


def fit_pose(holder_xy: np.ndarray, local_xy: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Least-squares rotation and shift with ``local = R @ holder + shift`` (2-D Kabsch).

    Returns ``(shift, angle_deg, rms)``.
    """
    p, q = np.asarray(holder_xy, float), np.asarray(local_xy, float)
    pc, qc = p.mean(0), q.mean(0)
    H = (p - pc).T @ (q - qc)
    a = math.atan2(H[0, 1] - H[1, 0], H[0, 0] + H[1, 1])
    R = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    shift = qc - R @ pc
    rms = float(np.sqrt(np.mean(np.sum((p @ R.T + shift - q) ** 2, axis=1))))
    return shift, math.degrees(a), rms


def posed_masks(stage_deg, settings: Mapping, pose: HolderPose | None, binning: int = 2,
                margin_px: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """As `kinematics.roi_masks`, for the holder at ``pose`` (None: where the settings put it).

    The same test (every corner of a super-pixel's footprint inside the shrunk square), computed
    from the map's affinity: the orthographic camera makes pixel -> holder-plane affine, so each
    of a square's four edges is one linear inequality per super-pixel, with the corners' extreme
    offsets added; two outer sums over the grid replace four corner maps (full-size frames:
    about a tenth of `kinematics.roi_masks`' time, same masks but for ties at rounding level).
    """
    if margin_px is None:
        margin_px = float(settings.get("capture", {}).get("roi_margin_px", 1.0))
    return _posed_masks(stage_deg, settings, pose, binning, (margin_px,))[0]


def _posed_masks(stage_deg, settings: Mapping, pose: HolderPose | None, binning: int,
                 margins_px) -> list[tuple[np.ndarray, np.ndarray]]:
    """`posed_masks` for each margin of ``margins_px`` (pixels), from `_posed_rows`."""
    cam = settings["camera"]
    w = cam["width"] // binning
    cols = np.arange(w)
    return [tuple((cols >= lo[:, None]) & (cols < hi[:, None]) for lo, hi in squares)
            for squares in _posed_rows(stage_deg, settings, pose, binning, margins_px)]


def _first_true(q, h: int, w: int) -> np.ndarray:
    """Per row, the first column j in [0, w] where ``q(j)`` (j: one column per row) is True, ``w``
    where it never is; ``q`` must be False then True along each row (a bisection, ~log2(w) calls)."""
    lo, hi = np.zeros(h, np.int64), np.full(h, w, np.int64)
    while True:
        act = lo < hi
        if not act.any():
            return lo
        mid = (lo + hi) // 2
        t = q(mid)
        hi = np.where(act & t, mid, hi)
        lo = np.where(act & ~t, mid + 1, lo)


def _posed_rows(stage_deg, settings: Mapping, pose: HolderPose | None, binning: int,
                margins_px) -> list[tuple[tuple[np.ndarray, np.ndarray], ...]]:
    """The regions of `posed_masks` as one run of columns per super-pixel row: for each margin of
    ``margins_px`` (pixels), ``((lo, hi) of the sample, (lo, hi) of the reference)``, each (h,)
    ints, the row's region the columns ``lo <= j < hi`` (none where ``hi <= lo``).

    The test of each super-pixel is the grid's (every corner inside the shrunk square): its four
    edge inequalities are evaluated with the very floating-point operations the whole grid took
    (``x = (o + d_row i) + d_col j``, then the corner offset), and each is monotone along a row
    (IEEE rounding is monotone), so a region's row is one run of columns whose ends a bisection
    over the column finds: the same masks as the grid's, bit for bit, from O(h log w) values
    instead of O(h w) (full size: ~0.25 s of float64 grids to a few ms).
    """
    cam, hold = settings["camera"], settings["holder"]
    W, H, s = cam["width"], cam["height"], cam["pixel_size"]
    h, w = H // binning, W // binning

    def plane(rows, cols):
        xy = kinematics.image_to_local(stage_deg, np.asarray(rows, float), np.asarray(cols, float), settings)
        return xy if pose is None else pose.to_holder(xy)

    o = plane(0.0, 0.0)
    d_row = (plane(1.0, 0.0) - o) * binning          # holder-plane step per super-pixel row
    d_col = (plane(0.0, 1.0) - o) * binning
    corners = np.array([plane(dr, dc) - o for dr in (-0.5, binning - 0.5) for dc in (-0.5, binning - 0.5)])
    lo, hi = corners.min(0), corners.max(0)           # extreme corner offsets per coordinate
    i = np.arange(h, dtype=float)
    start = [o[0] + d_row[0] * i, o[1] + d_row[1] * i]   # each row's coordinates at column 0

    def run(k, off, limit, below):
        """Columns of each row where ``start[k] + d_col[k] j + off`` is ``<= limit`` (``below``)
        or ``>= limit``: a prefix (count, "ends") or a suffix (first column, "starts") of the row."""
        b = d_col[k]

        def value(j):
            return (start[k] + b * j.astype(float)) + off

        prefix = (b >= 0) == below                   # the test holds from column 0 on, then fails
        if prefix:
            return "ends", _first_true(lambda j: ~(value(j) <= limit if below else value(j) >= limit), h, w)
        return "starts", _first_true(lambda j: value(j) <= limit if below else value(j) >= limit, h, w)

    off = hold["offset"]
    out = []
    for margin_px in margins_px:
        half = hold["sample_half"] - margin_px * s
        common = [run(1, hi[1], half, True), run(1, lo[1], -half, False)]

        def square(cx):
            cuts = common + [run(0, hi[0], cx + half, True), run(0, lo[0], cx - half, False)]
            first = np.max([c for kind, c in cuts if kind == "starts"] or [np.zeros(h, np.int64)], axis=0)
            end = np.min([c for kind, c in cuts if kind == "ends"] or [np.full(h, w, np.int64)], axis=0)
            return first, end

        out.append((square(-off), square(off)))
    return out


@dataclass(frozen=True)
class Regions:
    """The sample and reference regions of one frame (super-pixel grid) and how they were found."""

    sample: np.ndarray
    reference: np.ndarray
    source: str                  # "markers" or "geometry"
    pose: HolderPose | None
    why: str = ""                # the reason for the fallback, if any


def find_regions(image: np.ndarray, stage_deg, settings: Mapping, binning: int = 2) -> Regions:
    """The regions of interest of a frame, from the holder's markers, else from the geometry.

    Parameters
    ----------
    image : ndarray (H // binning, W // binning)
        A linear image on the super-pixel grid (e.g. the green plane of a decoded RAW frame).
    stage_deg : array_like (4,)
        The stage angles the frame was taken at, degrees.
    """
    layout = layout_of(settings)
    if layout is None:
        sm, rm = kinematics.roi_masks(stage_deg, settings, binning)
        return Regions(sm, rm, "geometry", None, "the holder has no markers in the settings")
    if isinstance(layout, BoardLayout):
        holder, px = detect_board(image, layout)
        ids, none = tuple(range(len(holder))), len(holder) < MIN_BOARD_CORNERS
        why = f"fewer than {MIN_BOARD_CORNERS} board corners found in the frame"
    else:
        found = detect(image, layout)
        ids, none, why = tuple(sorted(found)), not found, "no marker found in the frame"
        if found:
            px = np.concatenate([found[i] for i in ids])            # (col, row) on the super-pixel grid
            holder = np.concatenate([layout.corners(i) for i in ids])
    if none:
        sm, rm = kinematics.roi_masks(stage_deg, settings, binning)
        return Regions(sm, rm, "geometry", None, why)
    rows, cols = binning * px[:, 1] + 0.5 * (binning - 1), binning * px[:, 0] + 0.5 * (binning - 1)
    local = kinematics.image_to_local(stage_deg, rows, cols, settings)
    shift, angle, rms = fit_pose(holder, local)
    limit = MAX_RMS_PIXELS * binning * float(settings["camera"]["pixel_size"]) / max(
        1e-6, abs(kinematics.rotation(stage_deg)[0, 2]))          # foreshortened pixels are longer
    if not (np.isfinite(rms) and rms <= limit):
        sm, rm = kinematics.roi_masks(stage_deg, settings, binning)
        return Regions(sm, rm, "geometry", None, f"the markers do not fit the layout (rms {rms:.3g} > {limit:.3g})")
    pose = HolderPose(shift, angle, rms, ids)
    sm, rm = posed_masks(stage_deg, settings, pose, binning)
    return Regions(sm, rm, "markers", pose)


def roi_masks_fast(stage, settings: Mapping) -> tuple[np.ndarray, np.ndarray]:
    """`kinematics.roi_masks`, exactly, at about `_markers.posed_masks`' cost.

    `posed_masks` finds the same regions from the map's affinity but may decide a super-pixel
    whose corner lies on a square's edge (a tie, common where the pixel grid lines up with the
    squares) the other way at rounding level. So: the super-pixels that `posed_masks` puts
    inside with a margin 1e-3 pixel wider are inside, those it leaves out with one 1e-3 pixel
    narrower are out, and the few in between are decided by `roi_masks`' own corner test. Both
    margins come from one evaluation of the grid's coordinates (`_markers._posed_masks`).
    """
    margin = float(settings.get("capture", {}).get("roi_margin_px", 1.0))
    hold, s = settings["holder"], float(settings["camera"]["pixel_size"])
    half, off = hold["sample_half"] - margin * s, hold["offset"]
    delta = 1e-3
    inner, outer = _posed_masks(stage, settings, None, 2, (margin + delta, margin - delta))
    out = []
    for sure, maybe, cx in zip(inner, outer, (-off, off)):
        i, j = np.nonzero(maybe & ~sure)
        if len(i):
            xy = np.stack([kinematics.image_to_local(stage, 2 * i + dr, 2 * j + dc, settings)
                           for dr in (-0.5, 1.5) for dc in (-0.5, 1.5)], 0)
            ok = np.all((np.abs(xy[..., 0] - cx) <= half) & (np.abs(xy[..., 1]) <= half), axis=0)
            sure = sure.copy()
            sure[i[ok], j[ok]] = True
        out.append(sure)
    return out[0], out[1]
