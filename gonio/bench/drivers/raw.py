"""RAW decoding to linear values: `decode_raw` and the `RawFrame` it returns.

`decode_raw` opens any RAW rawpy/LibRaw reads (DNG, NEF, CR2, ...) and returns linear,
black-subtracted per-channel planes: ``raw_image_visible`` minus the per-channel black
level, never the gamma-encoded ``postprocess`` output. Where no colour matrix is wanted (a
point's frames), an uncompressed DNG that LibRaw would take as stored is read straight from its
bytes instead, the same values bit for bit (`_dng_direct`).
"""

from __future__ import annotations

import hashlib
import io
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import rawpy
import tifffile

from gonio.core.errors import GonioError

__all__ = ["RawFrame", "decode_raw", "read_verified"]


@dataclass(frozen=True)
class RawFrame:
    """A decoded RAW frame on the 2x2 CFA super-pixel grid.

    Attributes
    ----------
    signal : ndarray (3, h, w) float32
        Black-subtracted DN per channel R, G, B; G is the mean of the two greens (exact in float32).
    peak : ndarray (3, h, w) float32, or None
        Black-subtracted DN of the brightest raw pixel behind each value (for saturation); None
        where decoded without it (dark frames).
    n_raw : ndarray (3,)
        Raw pixels averaged per value (1, 2, 1): variances divide by it.
    black : float
        Black level, DN.
    white : float
        White (clipping) level, DN.
    rgb_cam : ndarray (3, 3) or None
        White-balanced camera RGB -> linear sRGB (D65), from the file's colour matrices as
        LibRaw derives them (rows sum to 1: a neutral stays neutral); None if the file has none.
    """

    signal: np.ndarray
    peak: np.ndarray
    n_raw: np.ndarray
    black: float
    white: float
    rgb_cam: np.ndarray | None = None

    @property
    def full_scale(self) -> float:
        """White minus black, DN: the largest black-subtracted value."""
        return self.white - self.black


def decode_raw(path: str | os.PathLike, *, window: tuple[int, int, int, int] | None = None, peak: bool = True,
               data: bytes | None = None, colour: bool = True) -> RawFrame:
    """Decode a RAW file to linear black-subtracted R, G, B planes (see `RawFrame`).

    Parameters
    ----------
    window : (row0, row1, col0, col1), optional
        Only these super-pixel rows and columns (a crop of the full planes: the same values).
    peak : bool
        Also the brightest raw value behind each value (False: ``peak`` is None; dark frames).
    data : bytes, optional
        The file's bytes, already read (e.g. to check its checksum): not read again.
    colour : bool
        Also the colour matrix (``rgb_cam``). False (a point's frames: only their values are
        used): ``rgb_cam`` is None, and an uncompressed DNG (of 1 MiB or more) whose values LibRaw
        would take unchanged (`_dng_direct`) is read straight from its bytes, window only, without LibRaw
        unpacking the whole sensor (6000 x 4000: ~0.8 s on the reference machine, most of a
        point's decoding): the same values, bit for bit.

    The planes are float32: raw values are integers below 2^16, so black-subtracted values and
    the mean of two greens are exact in float32 (the float64 planes of old held the same numbers).

    Raises
    ------
    GonioError
        The file is missing or not a RAW file rawpy can read.
    """
    path = Path(path)
    if data is None and not path.is_file():
        raise GonioError(f"RAW file {path} is missing; check the session's raw/ folder")
    if not colour:
        if data is None:
            data = path.read_bytes()
        direct = _dng_direct(data) if len(data) >= _DIRECT_MIN_BYTES else None
        if direct is not None:
            return _planes(*direct, window, peak, path)
    try:
        with rawpy.imread(io.BytesIO(data) if data is not None else str(path)) as raw:
            img = raw.raw_image_visible
            sizes = raw.sizes
            pattern = np.asarray(raw.raw_pattern)
            # raw_colors_visible is raw_pattern tiled from the sensor's corner, offset by the margins;
            # only its first 2x2 tile is needed (the whole map costs as much as the decode)
            m = pattern.shape[0]
            colors = np.array([[pattern[(sizes.top_margin + r) % m, (sizes.left_margin + c) % pattern.shape[1]]
                                for c in range(2)] for r in range(2)])
            blacks = np.asarray(raw.black_level_per_channel, float)
            white = float(raw.white_level)
            desc = raw.color_desc.decode("ascii", "replace")
            rgb_cam = np.asarray(raw.color_matrix, float)[:3, :3].copy() if colour else None
            # map LibRaw colour indices to R, G, B through color_desc (e.g. "RGBG")
            chan = np.array([{"R": 0, "G": 1, "B": 2}.get(c, 1) for c in desc[:4].ljust(4, "G")])[colors]
            frame = _planes(img, chan, blacks[colors], white, window, peak, path)
    except (rawpy.LibRawError, OSError, ValueError) as exc:
        raise GonioError(f"cannot decode RAW file {path} ({type(exc).__name__}); "
                         "it is corrupt or not a RAW format") from None
    if rgb_cam is not None and not (np.all(np.isfinite(rgb_cam)) and np.allclose(rgb_cam.sum(1), 1.0, atol=1e-3)):
        rgb_cam = None
    return RawFrame(frame.signal, frame.peak, frame.n_raw, float(np.mean(blacks)), white, rgb_cam)


def _planes(img: np.ndarray, chan: np.ndarray, blacks: np.ndarray, white: float, window, peak: bool,
            path) -> RawFrame:
    """The R, G, B planes of the mosaic ``img`` inside ``window`` (super-pixels): ``chan`` (2, 2)
    is the channel (0, 1, 2) and ``blacks`` (2, 2) the black level of each position of a CFA tile."""
    h, w = img.shape[0] // 2, img.shape[1] // 2
    r0, r1, c0, c1 = window if window is not None else (0, h, 0, w)
    r0, r1, c0, c1 = max(0, r0), min(h, r1), max(0, c0), min(w, c1)
    count = np.zeros(3)
    for k in chan.ravel():
        count[k] += 1
    if np.any(count == 0):
        raise GonioError(f"RAW file {path} has a CFA without R, G and B in a 2x2 tile; "
                         "only Bayer sensors are supported")
    shape = (3, max(0, r1 - r0), max(0, c1 - c0))
    signal = np.empty(shape, np.float32)
    top = np.empty(shape, np.float32) if peak else None
    f32 = np.float32
    # a block of super-pixel rows at a time, each position of the CFA tile written straight into
    # the block's planes while they are in cache (whole-window float32 copies of each position
    # were most of a full-size decode): the same values, every step exact in float32 (integers
    # below 2^17, a halving)
    step = max(1, _DECODE_BLOCK // max(1, shape[2]))
    buf = np.empty((min(step, shape[1]), shape[2]), np.float32)
    for b0 in range(r0, r1, step):
        b1 = min(r1, b0 + step)
        rows = slice(b0 - r0, b1 - r0)
        seen = [False] * 3
        for dr in range(2):
            for dc in range(2):
                k = int(chan[dr, dc])
                raw = img[2 * b0 + dr:2 * b1:2, 2 * c0 + dc:2 * c1:2]
                if not seen[k]:
                    np.subtract(raw, f32(blacks[dr, dc]), out=signal[k, rows], dtype=f32)
                    if peak:
                        top[k, rows] = signal[k, rows]
                    seen[k] = True
                    continue
                plane = np.subtract(raw, f32(blacks[dr, dc]), out=buf[:b1 - b0], dtype=f32)
                signal[k, rows] += plane
                if peak:
                    np.maximum(top[k, rows], plane, out=top[k, rows])
        for k in range(3):
            if count[k] > 1:
                signal[k, rows] /= f32(count[k])          # the two greens' mean (exact: a halving)
    return RawFrame(signal, top, count, float(np.mean(blacks)), float(white), None)


#: values per channel in one block of a decode's rows
_DECODE_BLOCK = 1 << 16

#: below this size LibRaw's whole unpack costs less than parsing the tags with tifffile (~0.5 ms)
_DIRECT_MIN_BYTES = 1 << 20

#: DNG tags under which LibRaw's raw values differ from the stored ones, or the stored image is
#: not the sensor's: linearisation, black-level deltas, active area, masked areas, opcode lists,
#: crops, sub-IFDs (the raw image in a sub-IFD, a preview first). Any of them: LibRaw decodes.
_DNG_NOT_DIRECT = {50712, 50715, 50716, 50719, 50720, 50829, 50830, 51008, 51009, 51022, 330}


def _dng_direct(data: bytes):
    """``(mosaic, chan, blacks, white)`` of an uncompressed, one-image, 16-bit Bayer DNG whose
    values LibRaw takes as stored (one black level, no tag of `_DNG_NOT_DIRECT`): ``mosaic`` a
    view of ``data``, nothing copied; None for anything else (LibRaw decodes it). The simulated
    camera writes such files, and so do some tethering tools."""
    if data[:4] not in (b"II*\x00", b"MM\x00*"):
        return None
    try:
        with tifffile.TiffFile(io.BytesIO(data)) as tf:
            if len(tf.pages) != 1:
                return None
            page = tf.pages[0]
            tags = {t.code: t.value for t in page.tags}
            order = tf.byteorder
            offsets, counts = tuple(page.dataoffsets), tuple(page.databytecounts)
            shape = (int(page.imagelength), int(page.imagewidth))
            plain = (int(page.compression) == 1 and int(page.photometric) == 32803
                     and int(page.samplesperpixel) == 1 and int(page.bitspersample) == 16
                     and page.sampleformat == 1 and int(tags.get(254, 0)) == 0)
    except Exception:                        # tifffile raises its own errors too: LibRaw decides
        return None
    if (not plain or 50706 not in tags or _DNG_NOT_DIRECT & tags.keys() or 50714 not in tags
            or 50717 not in tags or tuple(np.ravel(tags.get(33421, ()))) != (2, 2)):
        return None
    pattern = tags.get(33422, ())
    pattern = np.frombuffer(pattern, np.uint8) if isinstance(pattern, bytes) else np.ravel(pattern)
    black = np.unique(np.ravel(tags[50714]).astype(float))
    white = np.ravel(tags[50717])
    if len(pattern) != 4 or not set(int(c) for c in pattern) <= {0, 1, 2} or len(black) != 1 or len(white) != 1:
        return None
    h, w = shape
    if h % 2 or w % 2:
        return None
    n = h * w * 2
    contiguous = all(o1 == o0 + c0 for o0, c0, o1 in zip(offsets, counts, offsets[1:]))
    if not offsets or not contiguous or sum(counts) != n or offsets[0] + n > len(data):
        return None
    mosaic = np.frombuffer(data, np.dtype(order + "u2"), h * w, offsets[0]).reshape(h, w)
    chan = np.asarray(pattern, int).reshape(2, 2)
    return mosaic, chan, np.full((2, 2), black[0]), float(white[0])


def read_verified(path: str | os.PathLike) -> tuple[bytes, str]:
    """A file's bytes and their SHA-256 (hex), from one read (checksum and decode share it)."""
    with open(path, "rb") as fh:
        data = fh.read()
    return data, hashlib.sha256(data).hexdigest()
