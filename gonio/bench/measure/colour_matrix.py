"""Camera RGB -> linear sRGB and CIE XYZ: the colour matrix, where it comes from, and its uncertainty.

The bench's f_r is white-balanced camera RGB by construction (sample and reference share the
illumination and the reference is spectrally flat). One 3x3 ``srgb_from_cam`` (rows sum to 1,
a neutral stays neutral) then gives linear sRGB (D65), Mitsuba's rendering space, and the
IEC 61966-2-1 matrix gives XYZ. Its source, recorded in ``dataset.nc``, is ``"dng"`` (the RAW
file's ColorMatrix1, Adobe DNG 1.4 chapter 6; uncertainty not assessed) or ``"chart"`` (a
least-squares fit to an X-Rite ColorChecker, 24 patches, in the holder's chart slot; its
uncertainty makes the budget's "colour matrix" line, fully correlated across points). Every
point's f_r in sRGB takes its 1-sigma and the channel-to-channel covariance from the camera's
independent channel noise: ``cov = S diag(sigma^2) S^T`` (JCGM 100:2008 5.1.2).

References: Cheung, V., Westland, S., Connah, D., Ripamonti, C. (2004), Coloration Technology
120(1), 19-25; IEC 61966-2-1:1999, sRGB.
"""

# White balance: the per-channel ratio of sample and reference removes the lamp's and the
# sensor's channel gains.
# "dng": with ColorMatrix1 CM (XYZ -> camera for CalibrationIlluminant1 = D65) and M =
# colour-science's linear sRGB -> XYZ, C = CM M maps sRGB to raw camera RGB; normalising its
# rows to sum 1 white-balances it (the D65 white's raw response is C's row sums, which
# AsShotNeutral must equal), and srgb_from_cam = (diag(1 / C 1) C)^-1 (the algebra of dcraw's
# cam_xyz_coeff, read here from the tags exactly instead of through LibRaw's rounded
# color_matrix). A maker's matrix states no uncertainty.
# "chart": the chart is found by OpenCV contrib's cv2.mcc detector in frames large enough for
# it, else read from the slot's declared geometry CHART_BOX. The 3x3 from raw camera RGB is
# the least-squares fit to the patches' reference linear sRGB (colour-science
# matrix_colour_correction, Cheung 2004, 3 terms; reference values
# CCS_COLOURCHECKERS["ColorChecker24 - After November 2014"], D50, adapted to D65 with
# Bradford); the raw response of a perfect white is the one it maps to (1, 1, 1), which
# white-balances it (rows sum to 1). Its uncertainty has two parts: the estimate's, row c's
# covariance s_c^2 (X^T X)^-1 (ordinary least squares, s_c^2 the residual variance on 24 - 3
# degrees of freedom), and the prediction's, each channel's residual RMS relative to the
# patches' luminance (a 3x3 cannot map every spectrum right: it is the larger part).
# What the fit's diagonal weights leave out of the sRGB covariance is stated in the fit file.
# Cheung et al. (2004): "A comparative study of the characterisation of colour cameras by
# means of neural networks and polynomial transforms."

from __future__ import annotations

import dataclasses
import io
import os

import numpy as np

from gonio.core.errors import GonioError

__all__ = ["CHART_BOX", "CHART_BORDER", "CHART_GRID", "COLOUR_SPACES", "ColourMatrix", "SRGB_TO_XYZ", "chart_patches", "find_chart",
           "chart_reference_srgb", "colour_matrix_components", "colour_matrix_uncertainty", "convert",
           "matrix_from_chart", "matrix_from_chart_dng", "matrix_from_dng", "matrix_from_libraw"]

#: The spaces a dataset's f_r can be fitted in: linear sRGB (D65), CIE XYZ (D65), camera RGB.
COLOUR_SPACES = ("srgb", "xyz", "camera")
#: Linear sRGB -> CIE XYZ (D65) as IEC 61966-2-1 publishes it.
SRGB_TO_XYZ = np.array([[0.4124, 0.3576, 0.1805], [0.2126, 0.7152, 0.0722], [0.0193, 0.1192, 0.9505]])
#: The ColorChecker edition whose reference values the chart fit uses.
CHART_REFERENCE = "ColorChecker24 - After November 2014"
#: Index of the chart's white patch (19 of 24, "white 9.5"): it must be lit for a fit.
CHART_WHITE = 18


@dataclasses.dataclass(frozen=True)
class ColourMatrix:
    """White-balanced camera RGB -> linear sRGB, with its source and uncertainty.

    Attributes
    ----------
    srgb_from_cam : ndarray (3, 3)
    source : str
        ``"dng"``, ``"libraw"`` (LibRaw's rounded ``color_matrix``) or ``"chart"``.
    cov : ndarray (3, 3, 3) or None
        ``cov[c]``: covariance of row c's three elements (chart fits); None: not assessed.
    residual_rms : float or None
        Chart fit: RMS of the patch residuals in linear sRGB.
    prediction_rel : ndarray (3,) or None
        Chart fit: RMS of the patch residuals relative to each patch's luminance, per output
        channel: how far the one 3x3 misses a surface's colour (metamerism, the Luther
        condition), the prediction part of the uncertainty (it dominates the estimation part).
    found_by : str or None
        Chart fit: ``"mcc"`` (OpenCV's detector) or ``"slot"`` (the slot's geometry).
    """

    srgb_from_cam: np.ndarray
    source: str
    cov: np.ndarray | None = None
    residual_rms: float | None = None
    prediction_rel: np.ndarray | None = None
    found_by: str | None = None

    def describe(self) -> dict:
        """JSON-ready record for the dataset's attributes."""
        return {"source": self.source, "srgb_from_cam": np.round(self.srgb_from_cam, 12).tolist(),
                "row_cov": None if self.cov is None else self.cov.tolist(),
                "residual_rms": self.residual_rms,
                "prediction_rel": None if self.prediction_rel is None else self.prediction_rel.tolist(),
                "chart_found_by": self.found_by,
                "uncertainty": "row covariance of the chart fit" if self.cov is not None else "not assessed"}


def _srgb_to_xyz_cs() -> np.ndarray:
    import colour

    return np.asarray(colour.RGB_COLOURSPACES["sRGB"].matrix_RGB_to_XYZ, float)


def _check(m: np.ndarray, what: str) -> np.ndarray:
    m = np.asarray(m, float)
    if m.shape != (3, 3) or not np.all(np.isfinite(m)) or not np.linalg.cond(m) < 1e8:
        raise GonioError(f"{what}: the colour matrix is not an invertible 3x3 ({m.tolist()}); "
                         "the colour tags or the chart capture are broken")
    return m


def matrix_from_dng(path: str | os.PathLike | None = None, data: bytes | None = None) -> ColourMatrix | None:
    """The DNG's ColorMatrix1 as camera -> sRGB (module notes); None if the file declares none,
    or declares the identity-free placeholder of a file without colour data."""
    import tifffile

    try:
        with tifffile.TiffFile(io.BytesIO(data) if data is not None else path) as tif:
            tags = tif.pages[0].tags
            cm, illum = tags.get(50721), tags.get(50778)
            if cm is None:
                return None
            values = np.asarray(cm.value, float).reshape(-1)
    except (OSError, ValueError, tifffile.TiffFileError) as exc:
        raise GonioError(f"cannot read the colour tags of {path or 'the RAW file'} ({type(exc).__name__})") from None
    if values.size == 18:                                     # (numerator, denominator) pairs
        values = values[0::2] / values[1::2]
    if values.size != 9:
        raise GonioError(f"{path or 'RAW file'}: ColorMatrix1 holds {values.size} values, not 9 (a 3-colour sensor)")
    if illum is not None and int(np.ravel(illum.value)[0]) not in (21, 0):
        raise GonioError(f"{path or 'RAW file'}: ColorMatrix1 is calibrated for illuminant "
                         f"{int(np.ravel(illum.value)[0])}, not D65 (21); calibrate with a ColorChecker capture")
    c = _check(values.reshape(3, 3), str(path)) @ _srgb_to_xyz_cs()
    rows = c.sum(1)
    if np.any(rows <= 0):
        raise GonioError(f"{path or 'RAW file'}: ColorMatrix1 maps white to a non-positive camera response")
    return ColourMatrix(np.linalg.inv(c / rows[:, None]), "dng")


def matrix_from_libraw(rgb_cam) -> ColourMatrix:
    """LibRaw's ``color_matrix`` (as the capture journalled it) when the DNG cannot be read."""
    return ColourMatrix(_check(rgb_cam, "journalled rgb_cam"), "libraw")


def chart_reference_srgb() -> np.ndarray:
    """The 24 ColorChecker patches' reference linear sRGB (D65), shape (24, 3)."""
    import colour

    cc = colour.CCS_COLOURCHECKERS[CHART_REFERENCE]
    xyz = colour.xyY_to_XYZ(np.array(list(cc.data.values()), float))
    cat = colour.adaptation.matrix_chromatic_adaptation_VonKries(
        colour.xy_to_XYZ(cc.illuminant),
        colour.xy_to_XYZ(colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"]), transform="Bradford")
    return xyz @ (np.linalg.inv(_srgb_to_xyz_cs()) @ cat).T


#: The holder's ColorChecker slot in the camera frame (fractions: left, top, right, bottom), its
#: patch grid (rows, columns) and the black border of each grid cell (fraction of the cell);
#: gonio/sim/physics/colour.py renders the chart by the same declared geometry.
CHART_BOX = (0.1, 0.1, 0.9, 0.9)
CHART_GRID = (4, 6)
CHART_BORDER = 0.15


def chart_patches(planes, box=CHART_BOX, grid=CHART_GRID, border=CHART_BORDER) -> np.ndarray:
    """Mean camera RGB (24, 3) of each patch of a chart image (3, h, w), from the chart's known
    geometry in its slot: the central part of each patch (a further quarter of the cell inside
    its border), in reading order. OpenCV's ``cv2.mcc`` detector needs patches of tens of
    pixels; the slot's geometry serves the simulator's small frames."""
    planes = np.asarray(planes, float)
    _, h, w = planes.shape
    rows, cols = grid
    x0, y0, x1, y1 = box
    ch, cw = (y1 - y0) * h / rows, (x1 - x0) * w / cols
    inset = border + 0.25 * (1 - 2 * border)
    out = np.empty((rows * cols, 3))
    for k in range(rows * cols):
        r, c = divmod(k, cols)
        top, left = y0 * h + r * ch, x0 * w + c * cw
        r0, r1 = int(np.ceil(top + inset * ch - 0.5)), int(np.floor(top + (1 - inset) * ch - 0.5)) + 1
        c0, c1 = int(np.ceil(left + inset * cw - 0.5)), int(np.floor(left + (1 - inset) * cw - 0.5)) + 1
        if r1 <= r0 or c1 <= c0:
            raise GonioError(f"the chart's patches are under one pixel in a {w} x {h} frame; "
                             "capture it with a larger frame")
        out[k] = planes[:, r0:r1, c0:c1].mean(axis=(1, 2))
    return out


#: Frames at least this many super-pixels high (and wide) are searched with OpenCV's ``cv2.mcc``
#: ColorChecker detector first; smaller ones (the simulator's default 32 x 24) are read from the slot.
MCC_MIN_PX = 200


def find_chart(planes) -> tuple[np.ndarray, str]:
    """The chart's 24 patch means (24, 3) and how they were found: ``"mcc"`` (OpenCV contrib's
    Macbeth-chart detector, its box mapped onto the 6 x 4 grid by a homography; of the box's
    corner orders the one whose fit leaves the smallest residual), else ``"slot"``
    (:func:`chart_patches`, the slot's declared geometry)."""
    planes = np.asarray(planes, float)
    if min(planes.shape[1:]) >= MCC_MIN_PX:
        found = _mcc_patches(planes)
        if found is not None:
            return found, "mcc"
    return chart_patches(planes), "slot"


def _mcc_patches(planes):
    import cv2

    img = np.clip(planes / max(float(np.percentile(planes, 99.5)), 1e-12), 0, 1).transpose(1, 2, 0)
    bgr = np.ascontiguousarray((255 * img ** (1 / 2.2))[..., ::-1] + 0.5).astype(np.uint8)
    det = cv2.mcc.CCheckerDetector_create()
    det.setColorChartType(cv2.mcc.MCC24)
    if not det.process(bgr, 1):
        return None
    box = np.asarray(det.getBestColorChecker().getBox(), np.float32).reshape(4, 2)
    rows, cols = CHART_GRID
    unit = np.float32([[0, 0], [cols, 0], [cols, rows], [0, rows]])
    centres = np.float32([[[c + 0.5, r + 0.5]] for r in range(rows) for c in range(cols)])
    best = None
    for corners in [np.roll(box, -k, axis=0) for k in range(4)] + [np.roll(box[::-1], -k, axis=0) for k in range(4)]:
        pts = cv2.perspectiveTransform(centres, cv2.getPerspectiveTransform(unit, corners))[:, 0]
        half = max(1, int(0.15 * np.linalg.norm(corners[1] - corners[0]) / cols))
        if np.any(pts < half) or np.any(pts[:, 0] >= planes.shape[2] - half) or np.any(pts[:, 1] >= planes.shape[1] - half):
            continue
        patches = np.array([planes[:, int(y) - half:int(y) + half + 1, int(x) - half:int(x) + half + 1].mean(axis=(1, 2))
                            for x, y in pts])
        try:
            rms = matrix_from_chart(patches).residual_rms
        except GonioError:
            continue
        if best is None or rms < best[0]:
            best = (rms, patches)
    return None if best is None else best[1]


def matrix_from_chart_dng(path: str | os.PathLike) -> ColourMatrix:
    """:func:`matrix_from_chart` on a RAW capture of the chart in its slot (black-subtracted,
    decoded by the camera driver's ``decode_raw``)."""
    from gonio.bench.drivers.camera import decode_raw

    if not os.path.isfile(path):
        raise GonioError(f"colour chart capture {path} does not exist; give the chart's RAW file (--colour-chart)")
    frame = decode_raw(path, peak=True)
    if np.any(frame.peak >= frame.full_scale):
        raise GonioError(f"{path}: the chart capture is saturated; capture it with a shorter exposure")
    patches, how = find_chart(frame.signal)
    return dataclasses.replace(matrix_from_chart(patches), found_by=how)


def matrix_from_chart(patches_cam) -> ColourMatrix:
    """Fit camera -> sRGB to a ColorChecker capture (module notes).

    Parameters
    ----------
    patches_cam : (24, 3) array
        Each patch's mean raw camera RGB (black-subtracted, any common scale), in the chart's
        reading order (dark skin first, black last).
    """
    import colour

    x = np.asarray(patches_cam, float)
    if x.shape != (24, 3) or not np.all(np.isfinite(x)) or np.any(x[CHART_WHITE] <= 0):
        raise GonioError(f"a ColorChecker capture needs 24 finite patch means with a lit white patch, "
                         f"got shape {x.shape}; check the chart's pose and exposure")
    ref = chart_reference_srgb()
    m_raw = np.asarray(colour.characterisation.matrix_colour_correction(x, ref, method="Cheung 2004", terms=3), float)
    white = np.linalg.solve(_check(m_raw, "chart fit"), np.ones(3))     # raw of a perfect white
    if np.any(white <= 0):
        raise GonioError("the chart fit maps white to a non-positive camera response; check the chart capture")
    xw = x / white                                    # white-balanced camera RGB of the patches
    m = m_raw * white                                 # rows sum to 1: white stays white
    resid = ref - xw @ m.T
    inv = np.linalg.inv(xw.T @ xw)
    cov = np.array([(resid[:, c] @ resid[:, c]) / (len(x) - 3) * inv for c in range(3)])
    lum = ref @ SRGB_TO_XYZ[1]
    pred = np.sqrt(np.mean((resid / lum[:, None]) ** 2, axis=0))
    return ColourMatrix(m, "chart", cov, float(np.sqrt(np.mean(resid ** 2))), pred)


def convert(f_cam, sd_cam, matrix: ColourMatrix, space: str):
    """f_r (N, 3) and its 1-sigma from white-balanced camera RGB into ``space``.

    Returns ``(f, sd, cov)``: values, 1-sigma and the (N, 3, 3) channel covariance from the
    camera's independent channel noise (``S diag(sigma^2) S^T``).
    """
    if space not in COLOUR_SPACES:
        raise ValueError(f"unknown colour space {space!r}; one of {', '.join(COLOUR_SPACES)}")
    f_cam, sd_cam = np.asarray(f_cam, float), np.asarray(sd_cam, float)
    s = {"camera": np.eye(3), "srgb": matrix.srgb_from_cam, "xyz": SRGB_TO_XYZ @ matrix.srgb_from_cam}[space]
    cov = np.einsum("ij,nj,kj->nik", s, sd_cam ** 2, s)
    return f_cam @ s.T, np.sqrt(np.einsum("nii->ni", cov)), cov


def colour_matrix_components(f_cam, matrix: ColourMatrix, space: str = "srgb") -> list[np.ndarray]:
    """The colour matrix's budget lines: signed (N, 3) arrays, one per independent input.

    The chart fit's nine elements are, per output row, correlated with each other; the
    eigenvectors of each row's covariance are independent inputs; so is each output channel's
    prediction error (``prediction_rel`` times the value). Each array is the change
    of f_r (in ``space``) when one of them moves by +1 standard uncertainty (JCGM 100 5.1.3),
    shared by every point (a fully correlated component: one matrix serves the session).
    Empty when the matrix's uncertainty is not assessed (``"dng"``, ``"libraw"``) or
    ``space`` is ``"camera"``.
    """
    if matrix.cov is None or space == "camera":
        return []
    f_cam = np.asarray(f_cam, float)
    out = []
    for c in range(3):
        lam, vec = np.linalg.eigh(matrix.cov[c])
        for k in range(3):
            d_row = np.sqrt(max(lam[k], 0.0)) * vec[:, k]       # one input's +1 sigma move of row c
            d_srgb = np.zeros(f_cam.shape)
            d_srgb[:, c] = f_cam @ d_row
            out.append(d_srgb @ SRGB_TO_XYZ.T if space == "xyz" else d_srgb)
    if matrix.prediction_rel is not None:          # the 3x3's miss of a surface's colour, per channel
        f_srgb = f_cam @ matrix.srgb_from_cam.T
        for c in range(3):
            d_srgb = np.zeros(f_cam.shape)
            d_srgb[:, c] = f_srgb[:, c] * matrix.prediction_rel[c]
            out.append(d_srgb @ SRGB_TO_XYZ.T if space == "xyz" else d_srgb)
    return out


def colour_matrix_uncertainty(f_cam, matrix: ColourMatrix, space: str = "srgb") -> np.ndarray:
    """Each value's standard uncertainty (N, 3) from the colour matrix: the root sum of squares
    of :func:`colour_matrix_components` (zeros where not assessed). Correlation: full (the
    same matrix for every point)."""
    parts = colour_matrix_components(f_cam, matrix, space)
    f_cam = np.asarray(f_cam, float)
    if not parts:
        return np.zeros(f_cam.shape)
    return np.sqrt(np.sum(np.square(parts), axis=0))
